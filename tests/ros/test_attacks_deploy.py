"""Attacks on a deployed team, through `htlm launch deploy --robots sim` (the entry point users run: the world
observing the agents' free clock, five agents, five simulated robots and their stand-in operation, over real DDS),
by a stranger on the team's ROS domain with its own rclpy node. Each test checks that the attack happened (the
records went out and every reader acknowledged them), that the counter naming it grew by exactly what was sent, and
that the team was not harmed: the launch goes on without a restart, every agent acts at every step of the episodes
around the attack, as in the episodes before it, and no episode counts an agent absent.

Two launched teams, each attacked in several ways at once (the attacks touch different tables and counters):

- without a key: about 70 far-future, well-formed actions per agent on /htlm/action and observations on every
  agent's robot topic (more than the 64 steps any per-step table keeps); a NaN and an out-of-map goal pose to a
  simulated robot;
- with a team key: the signed `stopped` announcement of an earlier run whose directory had the same name, and a
  signed announcement of the team's own run with sequence number 2^53; an unsigned goal pose (in the map) and a NaN
  one.

Slow: a team of 14 processes and two or three 15 s episodes each."""

from __future__ import annotations

import json
import math
import os
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.signing import Signer
from support.ros import Launcher, alive_with, read_json

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]

AGENTS = [f"agent{i}" for i in range(1, 6)]
PERIOD, HORIZON = 0.5, 30
AHEAD = 70
"""Far-future records per agent and topic: more than the 64 steps a per-step table keeps."""
KEY = "a-team-key-only-the-team-knows-0123"
DEPLOY = (
    *("deploy", "--robots", "sim", "--policy", "greedy", "--episodes", "0", "--period", str(PERIOD)),
    *("--world-param", "diagnostics_period=0.2", "--agent-param", "diagnostics_period=0.2"),
    *("--robot-param", "diagnostics_period=0.2", "--trainer-param", "diagnostics_period=0.2"),
)


@dataclass
class Attacked:
    """A deployed team after its attacks: what went out, the last /diagnostics of every node, the odometry seen."""

    team: Launcher
    sent: dict[str, Any]
    diag: dict[str, dict[str, str]]
    odometry: dict[str, dict[str, Any]]
    attacked_in: int
    """The episode in progress when the attacks were sent."""


def _key_file(where: Path) -> Path:
    where.mkdir(parents=True, exist_ok=True)
    f = where / "team.key"
    f.write_text(KEY + "\n")
    f.chmod(0o600)
    return f


def _diag(team: Launcher) -> dict[str, dict[str, str]]:
    f = team.tmp / "diag.json"
    return {k.removeprefix("htlm: "): v for k, v in read_json(f).items()} if f.exists() else {}


def _count(team: Launcher, node: str, counter: str) -> int:
    return int(_diag(team).get(node, {}).get(counter, 0))


def _episodes_logged(team: Launcher) -> int:
    """Episodes every agent has logged."""
    return min(len(team.agent_episodes(a)) for a in AGENTS)


def _start(where: Path, *extra: str) -> Launcher:
    team = Launcher(where, *DEPLOY, *extra)
    team.helper("diag", "--out", str(where / "diag.json"))
    team.helper("odometry", "--out", str(where / "odometry.json"))
    # a control: every agent logs the team's first episode (acting at every step, see _unharmed)
    team.wait_for(lambda: _episodes_logged(team) >= 1, 120, "every agent to log episode 0")
    return team


def _send(
    team: Launcher, name: str, source: dict[str, list[str]], subscribers: dict[str, int], qos: str = "events"
) -> Any:
    """Publish the records of `source` ({topic: [texts]}) with the `send` helper, every topic matched with all its
    readers first (`subscribers`, per topic: a record published before a reader matched would never reach it);
    returns its report once every reader acknowledged them."""
    src = team.tmp / f"{name}.json"
    src.write_text(json.dumps(source))
    out = team.tmp / f"{name}-sent.json"
    h = team.helper(
        "send", "--out", str(out), "--topics", ",".join(source), "--source", str(src), "--qos", qos,
        "--subscribers", json.dumps(subscribers),
    )  # fmt: skip
    assert h.wait(timeout=90) == 0, (team.tmp / f"helper-{len(team.helpers) - 1}-send.log").read_text()[-2000:]
    got = read_json(out)
    assert all(got["matched"][t] >= subscribers[t] for t in source), f"{name}: readers not matched: {got}"
    assert got["acked"] == dict.fromkeys(source, True), f"{name}: not every reader acknowledged every record: {got}"
    assert got["sent"] == {t: len(v) for t, v in source.items()}, got
    return got


def _settled(value: Any, want: Any, seconds: float = 10.0) -> Any:
    """`value()` once it equals `want`, or its last value after `seconds` (counters of two topics reach
    /diagnostics a moment apart)."""
    end = time.monotonic() + seconds
    while (got := value()) != want and time.monotonic() < end:
        time.sleep(0.1)
    return got


def _goal_poses(team: Launcher, agent: str, goals: list[list[Any]]) -> None:
    out = team.tmp / f"goal_pose-{agent}.json"
    h = team.helper("goal_pose", "--out", str(out), "--agent", agent, "--goals", json.dumps(goals))
    assert h.wait(timeout=60) == 0
    got = read_json(out)
    running = "running" if team.popen.poll() is None else f"exited with {team.popen.returncode}"
    assert got["matched"] >= 1, (
        f"no robot of {agent} read the goal poses (the launch {running}); the launcher said:\n{team.said()[-3000:]}"
    )
    assert got["sent"] == len(goals), got


def _finish(team: Launcher, attacked_in: int, sent: dict[str, Any]) -> Attacked:
    """Wait for the episode of the attacks and one more to be logged by every agent, give /diagnostics a moment,
    then stop the team with Ctrl-C (exit code 130, no process left, none restarted)."""
    team.wait_for(
        lambda: _episodes_logged(team) >= attacked_in + 2,
        60 + 3 * HORIZON * PERIOD,
        f"every agent to log episodes {attacked_in} and {attacked_in + 1} (the attacked one and the next)",
    )
    time.sleep(1.5)  # the operation reports every second
    diag = _diag(team)
    odom = read_json(team.tmp / "odometry.json")
    os.kill(team.popen.pid, signal.SIGINT)
    assert team.popen.wait(timeout=60) == 130, team.said()[-3000:]
    assert alive_with(str(team.run)) == [], "orphaned processes"
    said = team.said()
    assert "restarting it" not in said, f"a process of the team died under the attack:\n{said[-3000:]}"
    return Attacked(team, sent, diag, odom, attacked_in)


def _unharmed(a: Attacked) -> dict[str, Any]:
    """The team acted as it does unattacked: every agent at every step of every episode up to the one after the
    attack (the episodes before it are the control), the world counted no agent absent, every robot's odometry
    stayed finite and kept coming. Returns what was compared."""
    last = a.attacked_in + 1
    missed = {
        ag: {x["episode"]: [t + 1 for t, yes in enumerate(x["acted"]) if not yes] for x in a.team.agent_episodes(ag)}
        for ag in AGENTS
    }
    for ag in AGENTS:
        assert sorted(missed[ag])[: last + 1] == list(range(last + 1)), f"{ag} logged episodes {sorted(missed[ag])}"
    bad = {ag: {e: m for e, m in missed[ag].items() if m and e <= last} for ag in AGENTS}
    assert not any(bad.values()), f"steps an agent did not act at (agent: episode: steps): {bad}"
    world = {w["metrics"]["episode"]: w["metrics"]["absent"] for w in a.team.jsonl("world")}
    assert all(e in world for e in range(last + 1)), f"the world logged episodes {sorted(world)}"
    assert all(sum(world[e]) == 0 for e in range(last + 1)), f"agents absent (episode: per agent): {world}"
    assert all(o["nonfinite"] == 0 and o["count"] > 0 for o in a.odometry.values()), a.odometry
    return {"episodes": last + 1, "steps_acted_per_agent": (last + 1) * HORIZON}


# ----- without a key: far-future records, bad goals ------------------------------------------------------------


def _far_ahead(run: str) -> dict[str, list[str]]:
    """AHEAD well-formed actions per agent and AHEAD observations on every agent's robot topic, for steps about
    1000 episodes ahead of the run (valid episode and step numbers, each key distinct)."""
    keys = [(1000 + i // HORIZON, 1 + i % HORIZON) for i in range(AHEAD)]
    actions = [
        S.encode(S.ACTION, {"run": run, "agent": k, "episode": e, "step": t, "actions": [3], "before": []})
        for e, t in keys
        for k in range(len(AGENTS))
    ]
    out = {topics.ACTION: actions}
    for k, ag in enumerate(AGENTS):
        fields = {"run": run, "agent": k, "tasks": [0], "levels": [0], "acted": [k]}
        out[topics.observation(ag)] = [S.encode(S.OBSERVATION, {**fields, "episode": e, "step": t}) for e, t in keys]
    return out


@pytest.fixture(scope="module")
def unkeyed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Attacked]:
    where = tmp_path_factory.mktemp("unkeyed")
    team = _start(where)
    try:
        attacked_in = _episodes_logged(team)
        ahead = _far_ahead(team.run_id())
        # /htlm/action: the world, the operation and five robots; a robot topic: its agent and the world
        readers = {t: 7 if t == topics.ACTION else 2 for t in ahead}
        sent = {"ahead": _send(team, "ahead", ahead, readers)}
        _goal_poses(team, "agent1", [["nan", 0.0], [1e6, 0.0], ["inf", "-inf"]])
        sent["goal_pose"] = 3
        yield _finish(team, attacked_in, sent)
    finally:
        team.stop()


def test_far_future_records_are_rejected_as_future_and_evict_nothing(unkeyed: Attacked) -> None:
    a = unkeyed
    assert a.sent["ahead"]["sent"][topics.ACTION] == AHEAD * len(AGENTS)
    got = {
        "world": int(a.diag["world"].get("rejected/action/future", 0)),
        "operation": int(a.diag["operation"].get("rejected/action/future", 0)),
        **{f"robot {ag}": int(a.diag[f"robot {ag}"].get("rejected/action/future", 0)) for ag in AGENTS},
        **{ag: int(a.diag[ag].get("rejected/observation/future", 0)) for ag in AGENTS},
    }
    want = {
        "world": AHEAD * len(AGENTS),
        "operation": AHEAD * len(AGENTS),
        **{f"robot {ag}": AHEAD for ag in AGENTS},  # each robot reads its own agent's actions
        **dict.fromkeys(AGENTS, AHEAD),
    }
    assert got == want, f"far-future records counted as future (node: counted) {got}, sent {want}"
    seen = _unharmed(a)
    print(f"far-future records sent {want}; counted as future {got}; unharmed: {seen}")


def test_a_nan_or_out_of_map_goal_pose_is_rejected_and_the_robot_stays_finite(unkeyed: Attacked) -> None:
    a = unkeyed
    robot = a.diag["robot agent1"]
    assert int(robot.get("rejected/goal_pose/range", 0)) == a.sent["goal_pose"] == 3, robot
    assert all(math.isfinite(float(robot[v])) for v in ("x", "y")), robot
    assert a.odometry["agent1"]["nonfinite"] == 0, a.odometry["agent1"]
    seen = _unharmed(a)
    print(f"robot agent1 after 3 bad goal poses: {robot}; odometry {a.odometry['agent1']}; unharmed: {seen}")


# ----- with a key: an earlier run's stop, a forged sequence number, unsigned goals ------------------------------


def _earlier_stop(where: Path, key: Path) -> str:
    """The signed `stopped` announcement of an earlier run launched into a directory of the same name (RUN is
    `run` in both), recorded from /htlm/scenario as any participant of its domain could."""
    earlier = Launcher(
        where,
        *("evaluate", "--policy", "greedy", "--episodes", "8", "--batch", "1", "--key-file", str(key)),
    )
    try:
        rec = where / "scenario.json"
        earlier.helper("record", "--out", str(rec), "--topic", "scenario")
        assert earlier.popen.wait(timeout=120) == 0, earlier.said()[-3000:]
        time.sleep(0.5)
        earlier.helpers[0].send_signal(signal.SIGTERM)
        earlier.helpers[0].wait(timeout=10)
        stops = [x for x in read_json(rec) if json.loads(x)["state"] == "stopped"]
        assert stops, f"the earlier run's stop was not recorded: {read_json(rec)}"
        return str(stops[-1])
    finally:
        earlier.stop()


FORGED_GOAL = (-37.0, 21.0)
"""An unsigned goal in the map, at no site."""
SCENARIO_READERS = ["trainer", "operation", *AGENTS, *(f"robot {ag}" for ag in AGENTS)]


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Attacked]:
    base = tmp_path_factory.mktemp("keyed")
    key = _key_file(base)
    stop = _earlier_stop(base / "earlier", key)
    where = base / "later"
    team = _start(where, "--key-file", str(key))
    try:
        earlier_run = json.loads(stop)["run"]
        # the same directory name, another run
        assert earlier_run != team.run_id() and earlier_run.startswith("run-") and team.run_id().startswith("run-")
        rec = where / "scenario.json"
        recorder = team.helper("record", "--out", str(rec), "--topic", "scenario")
        team.wait_for(lambda: rec.exists() and read_json(rec), 30, "the team's announcement (recorded)")
        recorder.send_signal(signal.SIGTERM)
        recorder.wait(timeout=10)
        ours = {k: v for k, v in json.loads(read_json(rec)[-1]).items() if k not in ("schema", "v", "sig")}
        signer = Signer(KEY.encode())
        forged = S.encode(S.SCENARIO, {**ours, "seq": S.SEQ_MAX, "state": "stopped"}, signer)
        attacked_in = _episodes_logged(team)
        readers = {topics.SCENARIO: len(SCENARIO_READERS)}
        sent = {"scenario": _send(team, "scenario", {topics.SCENARIO: [stop, forged]}, readers, "state")}
        _goal_poses(team, "agent2", [list(FORGED_GOAL), ["nan", "nan"]])
        sent["goal_pose"] = 2
        # the agent's own goal poses are unsigned too (a robot stack without the key follows them): the robot ignores
        # every one, and follows the signed twin the agent sends beside each (arrived/goal)
        robot = "robot agent2"
        sent["ignored_beside_twins"] = _settled(
            lambda: _count(team, robot, "ignored/goal_pose/unsigned") - _count(team, robot, "arrived/goal"), 2
        )
        yield _finish(team, attacked_in, sent)
    finally:
        team.stop()


def test_an_earlier_runs_stop_and_a_huge_sequence_number_do_not_stop_the_team(keyed: Attacked) -> None:
    a = keyed
    counted = {
        n: (int(a.diag[n].get("rejected/scenario/other_run", 0)), int(a.diag[n].get("rejected/scenario/future", 0)))
        for n in SCENARIO_READERS
    }
    assert counted == dict.fromkeys(SCENARIO_READERS, (1, 1)), f"(other_run, future) per reader: {counted}"
    seen = _unharmed(a)
    print(f"the earlier run's stop and seq 2^53: (other_run, future) counted {counted}; unharmed: {seen}")


def test_with_a_key_an_unsigned_goal_pose_is_ignored(keyed: Attacked) -> None:
    a = keyed
    robot = a.diag["robot agent2"]
    # every goal pose was ignored: the agent's own (one beside each signed twin it sent) and the stranger's two
    assert a.sent["ignored_beside_twins"] == a.sent["goal_pose"] == 2, robot
    assert robot.get("goal") != "{:g},{:g}".format(*FORGED_GOAL), f"robot agent2 took the unsigned goal: {robot}"
    assert a.odometry["agent2"]["nonfinite"] == 0, a.odometry["agent2"]
    seen = _unharmed(a)
    print(f"robot agent2 after 2 unsigned goal poses: {robot}; unharmed: {seen}")
