"""The seam to real robot stacks, with real processes over real DDS: an external-operation world (it keeps the
free clock, the assignments and the logs, and simulates nothing), agents acting from a trained checkpoint and
taking their robot's arrival from its odometry, a simulated robot per agent (follows the goal pose, publishes
odometry, observes its task only when at the task's site) and the robots' stand-in operation (the true levels).

The team completes its mission with travel taking real steps; a robot that never arrives leaves its agent
observing nothing and the team finishes without it."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(150), pytest.mark.slow]  # 13 processes each: CI budget

CHECKPOINT = Path(__file__).resolve().parents[1] / "data" / "policy_heterogeneous_seed0"
"""The five Q-networks of `htlm train --seed 0` (default budget; agents.pt and meta.json of its checkpoint)."""
PERIOD = 0.25
SPEED = 25.0  # m/s: the two sites are 50 m apart, 2 s = 8 steps of travel


def _team(ros_team: Any, episodes: int, **kw: Any) -> Any:
    return ros_team(
        mode="deploy",
        policy="checkpoint",
        checkpoint=str(CHECKPOINT),
        episodes=episodes,
        seed=5,
        robots="sim",
        period=PERIOD,
        robot_params={"speed": SPEED},
        world_params={"begin_deadline": 5.0},
        agent_params={"broadcast_timeout": 0.1},
        **kw,
    )


def _names(team: Any) -> list[str]:
    return ["world", "operation", *(a.name for a in team.cfg.scenario.agents)]


def test_external_world_with_simulated_robots_completes_the_mission_with_travel(ros_team: Any) -> None:
    team = _team(ros_team, episodes=2)
    robots = [f"robot_{a.name}" for a in team.cfg.scenario.agents]
    team.start(*_names(team), *robots)  # no trainer: deploy
    assert team.wait("world", 120) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    sc = team.cfg.scenario
    eps = team.world_episodes()
    assert [e["metrics"]["episode"] for e in eps] == [0, 1]
    for e in eps:
        m = e["metrics"]
        assert m["severity"] == "reported", m  # the stand-in operation reported every level
        assert not m["failed"] and m["completion"] < sc.horizon, m  # the team completed its mission
        assert all(lv is not None for lv in e["levels"]) and e["levels"][m["completion"]] == [0] * sc.n_tasks
    # travel takes real steps: an agent works on a task at the other site for steps before its robot observes it
    travel = sum(
        a < sc.n_tasks and o == -1
        for e in eps
        for acts, obs in zip(e["actions"], e["observations"], strict=True)
        for a, o in zip(acts, obs, strict=True)
    )
    assert travel >= 3, f"only {travel} working agent-steps without an observation"
    observed = sum(o >= 0 for e in eps for row in e["observations"] for o in row)
    assert observed > 20, "the robots observed their tasks once there"
    log = team.log("agent1") + team.log("agent2") + team.log("agent3")
    assert "robot on its way to site" in log and "robot at site" in log, log[-2000:]
    ops = re.search(r"robot_steps_on_the_way (\d+)", team.log("operation"))
    assert ops is not None and int(ops.group(1)) >= travel, team.log("operation")[-1500:]
    print(
        f"completion {[e['metrics']['completion'] for e in eps]}, {travel} working agent-steps on the way, "
        f"{observed} observations from the robots"
    )


def test_a_robot_that_never_arrives_observes_nothing_and_the_team_finishes_without_it(ros_team: Any) -> None:
    team = _team(ros_team, episodes=1)
    sc = team.cfg.scenario
    stuck = "agent3"  # a fire fighter (fire 2, rescue 0): the others must do its work
    others = [f"robot_{a.name}" for a in sc.agents if a.name != stuck]
    diag = team.tmp / "diag.json"
    team.helper("diag", "--out", str(diag))
    team.start(*_names(team), *others)
    team.cfg.robot_params = {"speed": 0.0, "start": "25.0,40.0"}  # parked away from every site, never moves
    team.start(f"robot_{stuck}")
    assert team.wait("world", 120) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    (e,) = team.world_episodes()
    k = [a.name for a in sc.agents].index(stuck)
    assert all(row[k] == -1 for row in e["observations"]), "the stuck robot observed something"
    assert any(row[k] < sc.n_tasks for row in e["actions"]), "its agent was assigned a task"
    m = e["metrics"]
    assert m["severity"] == "reported" and not m["failed"] and m["completion"] < sc.horizon, m
    status = json.loads(diag.read_text())
    st = next(v for name, v in status.items() if name == f"htlm: {stuck}")
    assert st["arrived"] == "no" and float(st["distance_to_site"]) > 40.0, st
    print(
        f"completion {m['completion']} without {stuck}; its diagnostics: arrived {st['arrived']}, "
        f"{st['distance_to_site']} m from its site"
    )


def test_robots_that_drive_at_their_speeds_keep_the_operations_step(ros_team: Any, tmp_path: Path) -> None:
    """An operation with travel (docs/model.md, Travel) deployed on simulated robots at its own step: every robot
    drives at its agent's speed, the launch takes the operation's step as its period, the finish-time auction
    completes the mission, and the drives the world records take about the steps the model gives them."""
    import yaml

    from htlm_world.metrics import drives
    from htlm_world.scenario import builtin, from_dict
    from htlm_world.travel import TravelState

    base = builtin()
    spec = [{"name": a.name, **a.capabilities} for a in base.agents]
    spec[0]["speed"] = 200.0  # agent1 crosses in one step, the others in three (50 m, 20 m a step)
    sc = from_dict({"step_seconds": 0.5, "speed": 40.0, "agents": spec}, "<travel>")
    (path := tmp_path / "travel.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    team = ros_team(
        mode="deploy",
        policy="auction",
        episodes=1,
        seed=3,
        robots="sim",
        period=sc.step_seconds,
        scenario=sc,
        scenario_file=str(path),
        world_params={"begin_deadline": 5.0},
        agent_params={"broadcast_timeout": 0.1},
    )
    team.start(*_names(team), *(f"robot_{a.name}" for a in sc.agents))
    assert team.wait("world", 120) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    (e,) = team.world_episodes()
    m = e["metrics"]
    assert m["severity"] == "reported" and not m["failed"] and m["completion"] < sc.horizon, m
    assert "robot of agent1 at (0, 0), 200 m/s" in team.log("robot_agent1"), team.log("robot_agent1")[-800:]
    assert "40 m/s" in team.log("robot_agent2")
    actions = np.array(e["actions"])[:, None, :]  # (h, 1, N)
    _, model_way = drives(sc, actions)
    state = TravelState(sc, 1)
    for a in actions:
        state.step(a)
    robot_way = np.array(
        [
            [a < sc.n_tasks and o == -1 for a, o in zip(acts, obs, strict=True)]
            for acts, obs in zip(e["actions"], e["observations"], strict=True)
        ]
    ).sum(axis=0)
    print(
        f"completion {m['completion']}; steps on the way by the model {model_way[0].tolist()}, "
        f"working steps without an observation on the robots {robot_way.tolist()}, drives {state.moves[0].tolist()}"
    )
    assert model_way.sum() > 0, "nobody drove"
    # a robot leaves when its agent decides, before its step begins, and is seen at the instant its observation is due:
    # each drive ends within about a step of what the model counts, either way
    assert (np.abs(robot_way - model_way[0]) <= 2 * state.moves[0]).all(), (robot_way, model_way, state.moves)
