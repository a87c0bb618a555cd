"""`htlm launch --record` over real DDS: the run's bag (RUN/recording, rosbag2 in MCAP storage) read back with the
reference MCAP reader, every message decoded with the schema the file holds, and counted against what the team
published: the world's episode log, its counters of received actions and readies, the step records."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from htlm_agent.experiments.episode_plot import read_episode
from htlm_agent.experiments.recording import episode_log, recorded_topics
from htlm_world.scenario import builtin
from support.ros import next_domain

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

SC = builtin()
AGENTS = [a.name for a in SC.agents]


def _launch(run: Path, *args: str, timeout: float = 200) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "htlm_agent.cli", "launch", *args, "--domain-id", str(next_domain())]
        + ["--run-dir", str(run), "--record", "--json", "--quiet"],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def _read(bag: Path) -> dict[str, list[tuple[Any, Any]]]:
    """Every message of the bag's MCAP file, decoded by mcap_ros2 from the schema stored with it: topic -> [(decoded
    message, channel)], after checking the encodings and that each topic has the type of the topic table."""
    types = {t.name: t.msg_type for t in recorded_topics(AGENTS)}
    (mcap,) = bag.glob("*.mcap")
    out: dict[str, list[tuple[Any, Any]]] = {}
    with mcap.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        for c in summary.channels.values():
            schema = summary.schemas[c.schema_id]
            assert (c.message_encoding, schema.encoding, schema.name) == ("cdr", "ros2msg", types[c.topic]), c.topic
            assert "offered_qos_profiles" in c.metadata, c.topic  # what `ros2 bag play` publishes with
        assert set(types) == {c.topic for c in summary.channels.values()}  # every topic has its channel
        for _, channel, _, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((decoded, channel))
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert (meta["version"], meta["storage_identifier"]) == (9, "mcap")
    counted = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counted == {t: len(out.get(t, [])) for t in types}
    return out


def _records(msgs: dict[str, list[tuple[Any, Any]]], topic: str) -> list[dict[str, Any]]:
    return [json.loads(m.data) for m, _ in msgs.get(topic, [])]


def _world_counter(run: Path, name: str) -> int:
    m = re.search(rf"received/{name} (\d+)", (run / "logs" / "world.log").read_text())
    assert m is not None, f"the world logged no received/{name}"
    return int(m.group(1))


def _watch_replay(run: Path) -> str:
    """The final snapshot of `htlm watch --replay RUN --speed 0 --once` (no ROS involved)."""
    r = subprocess.run(
        [sys.executable, "-m", "htlm_agent.cli", "watch", "--replay", str(run), "--speed", "0", "--once"]
        + ["--width", "200"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout


def test_a_recorded_evaluation_holds_every_message_the_team_published(tmp_path: Path) -> None:
    run = tmp_path / "run"
    episodes, h, n = 3, SC.horizon, len(AGENTS)
    _launch(run, "evaluate", "--policy", "greedy", "--episodes", str(episodes), "--batch", "1")
    msgs = _read(run / "recording")
    print({t: len(v) for t, v in sorted(msgs.items())})
    world = [json.loads(x) for x in (run / "world.jsonl").read_text().splitlines()]
    assert len(world) == episodes

    metrics = _records(msgs, "/htlm/episode_metrics")
    assert [{k: v for k, v in r.items() if k not in ("schema", "v")} for r in metrics] == [w["metrics"] for w in world]
    steps = _records(msgs, "/htlm/step")
    applied = Counter((r["episode"], r["step"]) for r in steps if r["phase"] == "step")
    assert applied == Counter({(e, t): 1 for e in range(episodes) for t in range(1, h + 1)})
    assert sorted(r["episode"] for r in steps if r["phase"] == "end") == list(range(episodes))
    assert len(msgs["/htlm/ground_truth"]) == episodes * h
    assert episode_log(run / "recording") == world  # levels, assignments, observations and metrics, step by step
    for agent in AGENTS:
        assert len(msgs[f"/htlm/{agent}/observation"]) == episodes * h, agent
        beliefs = _records(msgs, f"/htlm/{agent}/belief")
        assert (beliefs[-1]["episode"], beliefs[-1]["step"]) == (episodes - 1, h), agent  # its last one too
        assert msgs[f"/htlm/{agent}/goal_pose"][-1][0].header.frame_id == "map"
    # an agent's writers reach the recorder once the two processes have discovered each other: on a loaded machine
    # an agent's first steps may precede that (11 steps of one agent's broadcasts once, in a full `make test`); from
    # then on every record is there, once
    every = [(e, t) for e in range(episodes) for t in range(1, h + 1)]
    for topic in ("/htlm/broadcast", "/htlm/action"):
        got = Counter((r["agent"], r["episode"], r["step"]) for r in _records(msgs, topic))
        for k in range(n):
            mine = sorted((e, t) for (a, e, t) in got if a == k)
            assert mine and mine == every[every.index(mine[0]) :], (topic, k, mine[:3])
            assert mine[0][0] == 0, f"{topic}: agent {k} recorded from episode {mine[0][0]} only"
        if topic == "/htlm/broadcast":
            assert all(c == 1 for c in got.values()), topic
    # the world may have received more actions (an agent answers the first begin again until the world has its answer)
    assert len(_records(msgs, "/htlm/action")) <= _world_counter(run, "action")
    assert _world_counter(run, "ready") == n * episodes
    readies = Counter((r["agent"], r["episode"]) for r in _records(msgs, "/htlm/ready"))  # the same limit as above
    assert all(c == 1 for c in readies.values())
    for k in range(n):
        mine = sorted(e for (a, e) in readies if a == k)
        assert mine == list(range(mine[0], episodes)) and mine[0] <= 1, (k, mine)
    assert _records(msgs, "/htlm/scenario")[-1]["state"] == "stopped"
    # `htlm watch --replay` shows the recording as the live view shows the team: the finished episodes' metrics
    view = _watch_replay(run)
    mean = sum(w["metrics"]["completion"] for w in world) / episodes
    assert f"{episodes} episodes finished  completion {mean:.2f}" in view, view
    assert "[stopped]" in view and f"episode {episodes - 1}  step {h}/{h}" in view, view
    assert re.search(r"watch: \d+ records received, 0 rejected", view), view
    markers = [m for m, _ in msgs["/htlm/markers"]]
    assert markers and all(mk.header.frame_id == "map" for m in markers for mk in m.markers)
    shown = read_episode(run / "recording", 1)  # `htlm show RUN/recording`
    assert shown.levels.tolist() == world[1]["levels"] and shown.actions.tolist() == world[1]["actions"]


@pytest.mark.slow  # CI budget: the default run keeps the recorded evaluation; this one with -m slow
def test_a_recorded_deployment_holds_the_robots_odometry_and_goal_poses(tmp_path: Path) -> None:
    run = tmp_path / "run"
    args = ["deploy", "--policy", "greedy", "--robots", "sim", "--episodes", "1", "--period", "0.25"]
    _launch(run, *args)
    msgs = _read(run / "recording")
    print({t: len(v) for t, v in sorted(msgs.items())})
    world = [json.loads(x) for x in (run / "world.jsonl").read_text().splitlines()]
    assert len(world) == 1 and len(msgs["/htlm/episode_metrics"]) == 1
    severity = _records(msgs, "/htlm/severity")  # the robots' stand-in operation, one record per step on its clock
    assert sorted(r["step"] for r in severity) == list(range(1, SC.horizon + 1))
    for agent in AGENTS:
        odom = [m for m, _ in msgs[f"/htlm/{agent}/odom"]]
        assert len(odom) > 10 and all(o.header.frame_id == "map" for o in odom), agent
        goals = [m for m, _ in msgs[f"/htlm/{agent}/goal_pose"]]
        assert goals and goals[-1].header.frame_id == "map", agent
    sites = set(SC.site_positions)  # every goal is a site of the scenario
    assert all((g.pose.position.x, g.pose.position.y) in sites for a in AGENTS for g, _ in msgs[f"/htlm/{a}/goal_pose"])
