"""Several agents in one process (`htlm launch --agents-per-process`), through `htlm launch` over real DDS: the
composed team is the same team on the graph (node names, topics, services, parameters), runs the same evaluation as
a process per agent, and, when one of its processes is SIGKILLed, the launcher restarts it and every agent it hosted
rejoins while the other agents miss no step. The grouping rule and the command lines are tested without ROS in
tests/test_compose.py."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.settings import Settings
from htlm_world.clock import StepClock
from htlm_world.scenario import builtin
from support.ros import HTLM, Launcher, alive_with, next_domain, read_json

pytestmark = [pytest.mark.ros]

AGENTS = [f"agent{i}" for i in range(1, 6)]
# generous deadlines: on a loaded machine a slow step must not turn into an absent agent (which would change the
# run); when every agent answers, no deadline is ever waited for
PATIENT = ("--world-param", "act_deadline=10.0", "--world-param", "update_deadline=10.0")
PATIENT += ("--agent-param", "broadcast_timeout=5.0")


def _evaluate(run: Path, per: int) -> dict[str, Any]:
    r = subprocess.run(
        [HTLM, "launch", "evaluate", "--policy", "greedy", "--seed", "7", "--episodes", "6", "--batch", "2",
         "--agents-per-process", str(per), *PATIENT, "--domain-id", str(next_domain()), "--run-dir", str(run),
         "--json", "--quiet"],
        capture_output=True,
        text=True,
        timeout=150,
        check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    assert alive_with(str(run)) == []
    summary: dict[str, Any] = json.loads(r.stdout.strip().splitlines()[-1])
    return summary


def _lines(path: Path) -> list[dict[str, Any]]:
    """The JSON lines of an agent's episode log without the run id (it names the run directory)."""
    return [{k: v for k, v in json.loads(x).items() if k != "run"} for x in path.read_text().splitlines()]


def _episodes(run: Path) -> list[dict[str, Any]]:
    """The world's episode log without what differs between any two runs (the run id, the wall-clock seconds)."""
    out = []
    for line in (run / "world.jsonl").read_text().splitlines():
        e = json.loads(line)
        e.pop("run", None)
        for k in ("run", "seconds"):
            e["metrics"].pop(k, None)
        out.append(e)
    return out


@pytest.mark.timeout(330)
def test_a_composed_team_evaluates_exactly_as_a_process_per_agent(tmp_path: Path) -> None:
    composed = _evaluate(tmp_path / "composed", 3)
    logs = sorted(p.name for p in (tmp_path / "composed" / "logs").iterdir())
    assert logs == ["agent1+agent2+agent3.log", "agent4+agent5.log", "trainer.log", "world.log"]
    hosting = (tmp_path / "composed" / "logs" / "agent4+agent5.log").read_text()
    assert "hosting 2 agents in one process: htlm_agent4, htlm_agent5" in hosting
    for a in AGENTS:  # every hosted agent logs its episodes into its own file, as its own process would
        assert len(_lines(tmp_path / "composed" / f"{a}.jsonl")) == 6  # one line per episode
    alone = _evaluate(tmp_path / "alone", 1)
    assert sorted(p.name for p in (tmp_path / "alone" / "logs").iterdir()) == sorted(
        [f"{a}.log" for a in AGENTS] + ["trainer.log", "world.log"]
    )
    assert composed["episodes"] == alone["episodes"] == 6
    assert composed["absent_agent_steps"] == alone["absent_agent_steps"] == 0
    # the same seed and greedy agents: the same trajectories, levels, actions and observations, episode by episode
    assert _episodes(tmp_path / "composed") == _episodes(tmp_path / "alone")
    for k in ("completion_mean", "failure_rate", "unused_fraction_mean"):
        assert composed[k] == alone[k], k
    for a in AGENTS:  # and every agent's own log: its assignments, broadcast levels and rewards
        assert _lines(tmp_path / "composed" / f"{a}.jsonl") == _lines(tmp_path / "alone" / f"{a}.jsonl"), a


@pytest.mark.slow  # CI budget: the default run keeps the composed evaluation and graph; this one with -m slow
@pytest.mark.timeout(300)
def test_a_composed_team_trains_exactly_the_networks_of_htlm_train(ros_team: Any, tmp_path: Path) -> None:
    """Training with agents 1-3 and 4-5 in two processes (the agents act with the trainer's weights, the world paces
    the steps by the trainer's progress) ends with the Q-networks of the in-process `htlm train`, bit for bit, as a
    process per agent does (tests/ros/test_training_equivalence.py)."""
    import numpy as np

    from htlm_agent.learning.run import train

    sc, episodes, learner = builtin(), 64, {"envs": 32, "learning_starts": 300, "batch_size": 32}
    learner |= {"validate_every": 0, "select_best": False}
    settings = Settings.from_dict(
        Settings.with_preset({**learner, "episodes": episodes, "seed": 0, "eval_episodes": 0})
    )
    train(sc, settings, tmp_path / "inproc", progress=False, tensorboard=False, evaluate_at_end=False)
    ref = load_checkpoint(tmp_path / "inproc" / "checkpoint")
    team = ros_team(
        scenario=sc, mode="train", policy="auto", episodes=episodes, batch=32, seed=0, learner=learner,
        agents_per_process=3,
    )  # fmt: skip
    team.start()
    assert sorted(team.procs) == ["agent1+agent2+agent3", "agent4+agent5", "trainer", "world"]
    assert team.wait("world", 150) == 0
    codes = team.wait_all(60)
    assert codes == dict.fromkeys(codes, 0), codes
    eps = team.world_episodes()
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(episodes))
    assert all(sum(w["metrics"]["absent"]) == 0 for w in eps), "every agent acted in every step"
    got = load_checkpoint(team.run_dir / "trainer" / "checkpoint")
    assert got.episodes_done == ref.episodes_done == episodes
    for i, (a, b) in enumerate(zip(ref.weights, got.weights, strict=True)):
        for j, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"agent {i} tensor {j} differs"


def _graph(launcher: Any, where: Path, per: int, robots: bool = False) -> dict[str, Any]:
    team: Launcher = launcher(
        *("deploy", "--policy", "greedy", "--episodes", "0", "--period", "0.5", "--agents-per-process", str(per)),
        *(("--robots", "sim") if robots else ()),
        where=where,
    )
    out = where / "graph.json"
    nodes = [f"htlm_robot_{a}" for a in AGENTS] if robots else [f"htlm_{a}" for a in AGENTS]
    params = ["--params", "agent,goal_topic"] if robots else []
    helper = team.helper("graph", "--out", str(out), "--nodes", ",".join(nodes), *params)
    team.wait_for(lambda: helper.poll() is not None, 120, "the graph helper to see every agent's node")
    assert helper.returncode == 0, (where / "helper-0-graph.log").read_text()
    got: dict[str, Any] = read_json(out)
    os.kill(team.popen.pid, signal.SIGINT)  # Ctrl-C: every process stops cleanly, the composed ones too
    assert team.popen.wait(timeout=60) == 130, team.said()[-3000:]
    assert alive_with(str(team.run)) == [], "orphaned processes"
    return got


@pytest.mark.slow  # CI budget: the default run keeps the composed evaluation; this one with -m slow
@pytest.mark.timeout(300)
def test_on_the_graph_a_composed_agent_is_the_node_its_own_process_would_be(launcher: Any, tmp_path: Path) -> None:
    composed = _graph(launcher, tmp_path / "composed", 3)
    alone = _graph(launcher, tmp_path / "alone", 1)
    assert set(composed) == {f"htlm_{a}" for a in AGENTS}
    for a in AGENTS:
        node = composed[f"htlm_{a}"]
        assert node["parameters"] == {"agent": a, "policy": "greedy"}
        assert ["/htlm/broadcast", ["std_msgs/msg/String"]] in node["publishers"]
        assert [f"/htlm/{a}/observation", ["std_msgs/msg/String"]] in node["subscriptions"]
        assert [f"/htlm_{a}/get_parameters", ["rcl_interfaces/srv/GetParameters"]] in node["services"]
    assert composed == alone


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_on_the_graph_a_composed_robot_is_the_node_its_own_process_would_be(launcher: Any, tmp_path: Path) -> None:
    composed = _graph(launcher, tmp_path / "composed", 3, robots=True)
    alone = _graph(launcher, tmp_path / "alone", 1, robots=True)
    assert set(composed) == {f"htlm_robot_{a}" for a in AGENTS}
    for a in AGENTS:
        node = composed[f"htlm_robot_{a}"]
        assert node["parameters"] == {"agent": a, "goal_topic": ""}
        assert [f"/htlm/{a}/odom", ["nav_msgs/msg/Odometry"]] in node["publishers"]
        assert [f"/htlm/{a}/goal_pose", ["geometry_msgs/msg/PoseStamped"]] in node["subscriptions"]
    assert composed == alone


PERIOD = 0.5


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_a_killed_composed_process_is_restarted_and_its_agents_rejoin(launcher: Any) -> None:
    """A deployed team (an external operation: the agents keep the step clock), agents 1-3 in one process and 4-5
    in another: the first is SIGKILLed; the launcher restarts
    it, each of its three agents joins the team's clock again and acts at every step from then on, and agents 4 and
    5 act at every step throughout."""
    team = launcher(
        *("deploy", "--operation", "external", "--policy", "greedy", "--episodes", "0", "--period", str(PERIOD)),
        *("--agents-per-process", "3", "--respawn-delay", "0.5", "--agent-param", "broadcast_timeout=0.2"),
    )
    proc, hosted = "agent1+agent2+agent3", ["agent1", "agent2", "agent3"]
    f = team.run / "agent1.run.json"
    team.wait_for(lambda: f.exists() and json.loads(f.read_text())["epoch"] > 0, 120, "the team's epoch (agent1)")
    rec = json.loads(f.read_text())
    horizon = rec["scenario"]["horizon"]
    clock = StepClock(rec["epoch"], PERIOD, horizon, 0, 0)
    now = lambda: clock.last(time.time())  # noqa: E731  # the step index in progress on the team's clock
    i = now() + 4
    team.wait_for(lambda: now() >= i, 60 + i * PERIOD, f"step index {i} (before the kill)")
    pid = team.pid("agent2")  # the process whose command line names agent2's parameters file: the composed one
    assert pid == team.pid("agent1") == team.pid("agent3") != team.pid("agent4")
    start, said = len(team.log(proc)), len(team.said())
    os.kill(pid, signal.SIGKILL)
    killed_at, t_kill = now(), time.time()
    restarted = team.wait_for(
        lambda: re.search(rf"{re.escape(proc)} restarted \(pid (\d+)", team.said()[said:]),
        30,
        f"the launcher to restart {proc}",
    )
    assert f"{proc} exited with -9; restarting it" in team.said()[said:] and int(restarted.group(1)) != pid
    rejoined = {}
    for a in hosted:
        m = team.wait_for(
            lambda a=a: re.search(
                rf"\[htlm_{a}\]: joined the team's clock at episode (\d+) step (\d+)", team.log(proc)[start:]
            ),
            60,
            f"{a} to log that it joined the team's clock again",
        )
        rejoined[a] = clock.index(int(m.group(1)), int(m.group(2)))
    seconds = round(time.time() - t_kill, 2)
    last = max(rejoined.values()) // horizon
    for a in AGENTS:
        team.wait_for(
            lambda a=a: any(x["episode"] > last for x in team.agent_episodes(a)),
            60 + 2 * horizon * PERIOD,
            f"{a} to log episode {last + 1}",
        )
    os.kill(team.popen.pid, signal.SIGINT)
    assert team.popen.wait(timeout=60) == 130, team.said()[-3000:]
    assert alive_with(str(team.run)) == [], "orphaned processes"
    assert f"restarts: {proc} 1" in team.said()
    missed = {}
    for a in AGENTS:
        acted = {
            clock.index(x["episode"], t + 1)
            for x in team.agent_episodes(a)
            for t, yes in enumerate(x["acted"])
            if yes and x["episode"] <= last + 1
        }
        missed[a] = sorted(set(range((last + 2) * horizon)) - acted)
    assert not missed["agent4"] and not missed["agent5"], missed
    for a in hosted:  # down from the kill to its rejoin, at every step after
        assert missed[a] and max(missed[a]) < rejoined[a], (a, rejoined[a], missed[a])
    print(
        f"killed at step index {killed_at}; rejoined at {json.dumps(rejoined)}; {seconds} s from the kill to the "
        f"last rejoin line; agents 4 and 5 missed 0 steps in {last + 2} episodes"
    )


@pytest.mark.timeout(60)
def test_a_bad_parameter_of_one_hosted_agent_stops_the_process_with_2_naming_it(tmp_path: Path) -> None:
    """As an agent process of its own would: exit 2, nothing started, the reason on stderr, naming the node."""
    import sys

    from htlm_agent.ros.launch import LaunchConfig, ros_env, write_params

    good = write_params(tmp_path / "agent1.yaml", {"agent": "agent1", "policy": "greedy"})
    bad = write_params(tmp_path / "agent2.yaml", {"agent": "agent2", "policy": "cleverest"})
    env = ros_env(LaunchConfig(mode="evaluate", scenario=builtin(), domain_id=next_domain()))
    cmd = [sys.executable, "-m", "htlm_agent.ros.agents_node", f"htlm_agent1={good}", f"htlm_agent2={bad}"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=50, check=False)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "agents_node: htlm_agent2: policy" in r.stderr and "cleverest" in r.stderr, r.stderr
    r = subprocess.run(cmd[:3] + ["agent1.yaml"], env=env, capture_output=True, text=True, timeout=50, check=False)
    assert r.returncode == 2 and "expected NODE=PARAMETERS_FILE" in r.stderr, r.stderr


@pytest.mark.timeout(150)
def test_a_fatal_error_of_one_hosted_agent_stops_its_process_and_the_launch_with_2(tmp_path: Path) -> None:
    """facility-20 (20 agents, two processes of 10: the default on 2 cores) with a policy its agents refuse once the
    run is announced (QMDP: the optimum is too large to compute): the process exits 2, naming the agent and the
    reason, and the launch stops with 2 as it would for one agent."""
    run = tmp_path / "qmdp"
    r = subprocess.run(
        [HTLM, "launch", "evaluate", "--scenario", "facility-20", "--policy", "qmdp", "--episodes", "1", "--batch",
         "1", "--agents-per-process", "10", "--domain-id", str(next_domain()), "--run-dir", str(run), "--json",
         "--quiet"],
        capture_output=True,
        text=True,
        timeout=140,
        check=False,
    )  # fmt: skip
    assert r.returncode == 2, r.stdout + r.stderr
    said = re.search(r"htlm launch: (\S+) exited with 2 \(bad parameters or store\): fatal in htlm_(\w+): ", r.stderr)
    assert said is not None, r.stderr
    assert said.group(1) in {p.stem for p in (run / "logs").iterdir()} and "policy qmdp" in r.stderr
    assert alive_with(str(run)) == []
