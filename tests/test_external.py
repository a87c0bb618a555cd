"""The external operation without ROS: the world's side (it applies and observes nothing, takes the levels an
outside source reports, knows the metrics only then), the agent's pairing of step records with its robot's
observations, and the robots' cores (driving, arrival, the stand-in operation, sensing)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from htlm_agent.mind.deploy import DeployObservations
from htlm_world.episode import DeployEpisode
from htlm_world.model import Model
from htlm_world.protocol import LockstepSettings, WorldProtocol, world_protocol
from htlm_world.robots import (
    Drive,
    Sensing,
    StandInOperation,
    action_distance,
    arrival_period,
    longest_drive,
    odometry_due,
    site_distance,
)
from htlm_world.scenario import builtin, load


def _external(episodes: int = 1) -> WorldProtocol:
    sc = builtin().replace(horizon=3)
    s = LockstepSettings(episodes=episodes, clock="free", period=0.1, operation="external", run_id="x", mode="deploy")
    return world_protocol(sc, s)


def _run_steps(proto: WorldProtocol, now: float) -> tuple[float, list[tuple[str, dict]]]:  # type: ignore[type-arg]
    """Begin (every agent answers with action 0/2/...), then let the free clock apply every step."""
    out = proto.start(now).publish
    n = proto.scenario.n_agents
    for k in range(n):
        out += proto.on_action({"agent": k, "episode": 0, "step": 1, "actions": [4]}, now).publish
    for _ in range(40):
        now += 0.05
        out += proto.tick(now).publish
    return now, out


def test_the_external_world_publishes_no_observation_and_announces_the_operation() -> None:
    proto = _external()
    _now, out = _run_steps(proto, 0.0)
    kinds = [k for k, _ in out]
    assert "observation" not in kinds and "ground_truth" not in kinds
    assert kinds.count("step") >= 3  # begin and the applied steps
    sc = next(f for k, f in out if k == "scenario")
    assert sc["operation"] == "external" and sc["clock"] == "free" and sc["period"] == 0.1


def test_metrics_are_unknown_without_a_severity_source() -> None:
    proto = _external()
    _now, out = _run_steps(proto, 0.0)
    (m,) = [f for k, f in out if k == "episode_metrics"]
    assert m["severity"] == "unknown" and m["completion"] == -1 and m["unused_fraction"] == -1.0


def test_reported_levels_become_ground_truth_and_metrics() -> None:
    sc = builtin().replace(horizon=3)
    model = Model.build(sc)
    ep = DeployEpisode(sc, model, episode=0, started=0.0)
    for _t in range(3):
        ep.step({k: np.array([4]) for k in range(sc.n_agents)})
    assert ep.report_levels(1, np.array([3, 4, 4, 4])) and ep.report_levels(2, np.array([0, 0, 0, 0]))
    assert not ep.report_levels(4, np.array([0, 0, 0, 0])), "a step that did not happen"
    assert ep.metrics(1.0)[0]["severity"] == "unknown"  # step 3 missing
    ep.report_levels(3, np.array([0, 0, 0, 0]))
    (m,) = ep.metrics(1.0)
    assert m["severity"] == "reported" and m["completion"] == 2 and not m["failed"]
    ep.report_observation(1, 2, 3)
    traj = ep.trajectory()
    assert traj["levels"][2] == [0, 0, 0, 0] and traj["observations"][1][1] == 3 and traj["observations"][0][1] == -1


def test_the_protocol_takes_severity_of_the_current_episode_only() -> None:
    proto = _external(episodes=2)
    proto.start(0.0)
    for k in range(proto.scenario.n_agents):
        proto.on_action({"agent": k, "episode": 0, "step": 1, "actions": [4]}, 0.0)
    proto.tick(0.05)
    proto.tick(0.16)  # step 1 applied
    eff = proto.on_severity({"episode": 0, "step": 1, "levels": [[3, 4, 4, 4]]}, 0.2)
    (gt,) = [f for k, f in eff.publish if k == "ground_truth"]
    assert gt["levels"] == [[3, 4, 4, 4]] and gt["actions"] == [[4, 4, 4, 4, 4]]
    assert proto.on_severity({"episode": 5, "step": 1, "levels": [[0, 0, 0, 0]]}, 0.2).drops == [("severity", "future")]
    assert proto.on_severity({"episode": 0, "step": 3, "levels": [[0, 0, 0, 0]]}, 0.2).drops == [("severity", "future")]


def test_a_simulated_world_drops_severity_records() -> None:
    proto = world_protocol(builtin(), LockstepSettings(run_id="x"))
    proto.start(0.0)
    assert proto.on_severity({"episode": 0, "step": 1, "levels": [[0, 0, 0, 0]]}, 0.0).drops == [
        ("severity", "simulated")
    ]


def test_observations_pair_step_records_with_the_robots_observations() -> None:
    ext = DeployObservations()
    assert ext.on_robot(0, 1, [3]) == []  # ahead of the world's step record: kept
    (ob,) = ext.on_step(0, 1, [0, 1], now=0.0, wait=0.1)
    assert (ob.episode, ob.step, ob.levels, ob.acted) == (0, 1, [3], [0, 1])
    assert ext.on_step(0, 2, [0], now=1.0, wait=0.1) == []
    assert ext.next_deadline() == pytest.approx(1.1)
    assert ext.due(1.05) == []
    (ob,) = ext.due(1.2)
    assert ob.levels == [-1] and ext.missing == 1  # no observation: the belief predicts
    assert ext.on_robot(0, 2, [2]) == [] and ext.late == 1
    assert ext.on_step(0, 1, [0], now=2.0, wait=0.1) == [], "a repeated step record"


def test_a_robot_drives_to_its_goal_at_its_speed_and_stops_there() -> None:
    d = Drive(0.0, 0.0, speed=10.0, goal=(30.0, 40.0))
    vx, vy = d.advance(1.0)
    assert (round(d.x, 9), round(d.y, 9)) == (6.0, 8.0) and (round(vx, 9), round(vy, 9)) == (6.0, 8.0)
    for _ in range(10):
        d.advance(1.0)
    assert (d.x, d.y) == (30.0, 40.0) and d.advance(1.0) == (0.0, 0.0)
    assert Drive(1.0, 2.0, speed=0.0, goal=(50.0, 0.0)).advance(5.0) == (0.0, 0.0)


def test_a_robot_publishes_its_odometry_while_it_drives_and_once_a_second_standing_still() -> None:
    d, sent, was, times = Drive(0.0, 0.0, speed=10.0, goal=(3.0, 4.0)), -math.inf, False, []
    for tick in range(60):  # 3 s at 20 Hz: it drives 5 m in 0.5 s, then stands
        moving = d.advance(0.05) != (0.0, 0.0)
        if odometry_due(moving, was, tick * 0.05 - sent):
            sent, was = tick * 0.05, moving
            times.append(tick)
    stop = next(i for i in range(len(times)) if times[i + 1] != times[i] + 1)
    assert 10 <= stop <= 11 and times[: stop + 1] == list(range(stop + 1))  # every update while it drives, and one
    assert times[stop + 1 :] == [stop + 20, stop + 40] and (d.x, d.y) == (3.0, 4.0)  # after; then once a second


def test_the_arrival_period_lets_a_robot_drive_the_farthest_way_within_a_step() -> None:
    sc = load("facility-20")
    metres, a, b = longest_drive(sc)
    assert {sc.sites[a].name, sc.sites[b].name} == {"zone1", "zone8"} and metres == pytest.approx(math.hypot(120, 40))
    period = arrival_period(sc, 20.0)
    assert metres / 20.0 + 0.5 <= period <= metres / 20.0 * 1.1 + 0.6 and round(period * 10) == period * 10
    assert arrival_period(sc, 200.0) < period  # faster robots, shorter steps
    assert arrival_period(sc, 0.0) == 0.5  # a robot that does not move: the margin alone


def test_arrival_is_the_distance_to_the_site_of_the_action() -> None:
    sc = builtin()
    model = Model.build(sc)
    assert site_distance(sc, 1, 47.0, 4.0) == pytest.approx(5.0)
    task_at_site2 = int(np.flatnonzero(model.action_site[: sc.n_tasks] == 1)[0])
    assert action_distance(model, task_at_site2, 50.0, 0.0) == 0.0


def test_a_robot_on_its_way_adds_nothing_to_its_task() -> None:
    sc = builtin()
    model = Model.build(sc)
    everyone_on_task0 = np.zeros(sc.n_agents, dtype=np.int64)
    away = StandInOperation(sc, model, seed=1, episode=0)
    there = StandInOperation(sc, model, seed=1, episode=0)
    for _ in range(6):
        a = away.step(everyone_on_task0, np.zeros(sc.n_agents, dtype=bool))
        b = there.step(everyone_on_task0, np.ones(sc.n_agents, dtype=bool))
    assert b[0] < a[0], (a, b)


def test_sensing_is_the_model_observation_with_its_own_stream() -> None:
    model = Model.build(builtin())
    one = [Sensing(model, 0, 3, 1).observe(0, 2) for _ in range(1)]
    again = Sensing(model, 0, 3, 1)
    assert one == [again.observe(0, 2)]
    draws = [again.observe(0, 2) for _ in range(400)]
    assert 0.5 < draws.count(2) / len(draws) < 1.0 and set(draws) <= set(range(model.scenario.levels))


def test_an_agent_whose_robot_is_on_its_way_counts_its_assignment_as_idle() -> None:
    from htlm_agent.mind.agent import AgentMind
    from htlm_agent.session.builtin import builtin_policy

    sc = builtin()
    model = Model.build(sc)
    policy, _eps = builtin_policy(sc, "greedy", 0)
    there, away = AgentMind(sc, 0, 1, policy), AgentMind(sc, 0, 1, policy)
    (_t, a), (_t2, a2) = there.begin(0).action, away.begin(0).action  # type: ignore[misc]
    assert int(a[0]) < sc.n_tasks and a.tolist() == a2.tolist(), "greedy works on a task at step 1"
    b_there = there.observe(0, 1, [-1], [0], worked=True).broadcast
    b_away = away.observe(0, 1, [-1], [0], worked=False).broadcast
    assert b_there is not None and b_away is not None
    assert b_there[1].tolist() == a.tolist()
    assert b_away[1].tolist() == model.idle_action(a).tolist(), "teammates hear it idle at that site"
    assert away.prev.tolist() == a.tolist(), "the assignment stands (the robot is on its way)"
    assert not np.allclose(there.marg, away.marg), "its belief predicts no work on the task"
