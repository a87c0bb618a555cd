"""Lockstep training over bad links gives the networks of `htlm train` bit for bit: the world,
the trainer and every agent in a network namespace of its own, joined by the user-space switch of tests/ros/links.py
(this kernel has no netem), each started as docs/ros.md says for several hosts (`team.sh train --only NAME
--discovery subnet`, DDS on UDP). Every agent's link loses 5 % of the frames it sends and delays them by 100 ms; the
world's and the trainer's links are clean (the delay and loss are on the agents' egress: an agent's records reach
everyone 100 ms late, and 5 % of its datagrams, DDS's acknowledgements included, are lost on the way). The same run
then goes again in the same namespaces with every link clean, so the cost of the bad links is measured in one run
(printed: wall times and their ratio; never asserted).

Nobody may be counted absent for the lockstep to stay exact, so every deadline that would give up on an agent or
a record is raised far above what a lost datagram costs to recover; the deadlines cost nothing while everyone
answers (docs/ros.md, Node parameters)."""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.settings import Settings
from htlm_msgs_py.qos import FASTDDS_PROFILE
from htlm_world.scenario import builtin
from support.ros import next_domain, wait_team

from .links import LinkEmulator

pytestmark = [pytest.mark.ros, pytest.mark.timeout(600)]

HOSTS = ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]
AGENTS = HOSTS[2:]
LOSS, DELAY = 0.05, 0.1
LEARNER = {
    "learner": "paper",
    "envs": 4,
    "learning_starts": 60,
    "batch_size": 16,
    "validate_every": 0,
    "select_best": False,
}
EPISODES, SEED = 8, 0
"""The benchmark's budget: two batches of four episodes, 60 lockstep steps, the learner updating from step 15 on (the
test trains one batch)."""
# far above the recovery of a lost datagram (Fast DDS's heartbeat period, 3 s by default, or an agent's resend)
WORLD = {"act_deadline": 60.0, "update_deadline": 60.0, "begin_deadline": 60.0, "trainer_deadline": 120.0}
TRAINER = {"round_deadline": 60.0}
AGENT = {"broadcast_timeout": 30.0, "discovery_grace": 60.0, "stop_timeout": 60.0}
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def emu(links: Callable[..., LinkEmulator]) -> LinkEmulator:
    return links(HOSTS, seed=SEED)


def writer_profile(path: Path, heartbeat: float) -> Path:
    """The launch's Fast DDS profile (htlm_msgs_py's fastdds.xml) with reliable writers' periodic heartbeat every
    `heartbeat` seconds instead of its 0.1 s (Fast DDS's own default is 3 s). A reader asks for a lost sample again
    only when a heartbeat (or a later sample) shows it the gap, so this period bounds the recovery of the last sample
    of a burst, which in the lockstep is nearly every sample."""
    ns, nanos = divmod(round(heartbeat * 1e9), 10**9)
    text = FASTDDS_PROFILE.read_text()
    ours = "<heartbeatPeriod>\n        <sec>0</sec>\n        <nanosec>100000000</nanosec>\n      </heartbeatPeriod>"
    assert ours in text, f"{FASTDDS_PROFILE} no longer sets the heartbeat period as this test expects"
    path.write_text(text.replace(ours, f"<heartbeatPeriod><sec>{ns}</sec><nanosec>{nanos}</nanosec></heartbeatPeriod>"))
    return path


def _team(emu: LinkEmulator, run: Path, episodes: int, profile: Path | None) -> float:
    """Train with every process in its namespace (the team of the module's docstring) on a domain of its own; its
    wall time, start-up and exit included. Every process must exit 0 (else the failure shows the world's output and
    every log's tail)."""
    script = str(ROOT / "launch_scripts" / "team.sh")
    args = ["train", "--seed", str(SEED), "--episodes", str(episodes), "--batch", str(LEARNER["envs"])]
    args += ["--eval-episodes", "0", "--timeout", "500", "--domain-id", str(next_domain())]
    args += [x for k, v in LEARNER.items() for x in ("--set", f"{k}={json.dumps(v)}")]
    for opt, params in (("--world-param", WORLD), ("--trainer-param", TRAINER), ("--agent-param", AGENT)):
        args += [x for k, v in params.items() for x in (opt, f"{k}={v}")]
    env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    if profile is not None:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
    t0 = time.monotonic()
    procs = {}
    for name in HOSTS:
        cmd = ["ip", "netns", "exec", emu.ns[name], script, *args, "--only", name, "--discovery", "subnet"]
        cmd += ["--run-dir", str(run), "--quiet"]
        procs[name] = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    wait_team(procs, run, 550)
    return time.monotonic() - t0


def _same_networks(run: Path, ref: Any, episodes: int) -> None:
    eps = [json.loads(x) for x in (run / "world.jsonl").read_text().splitlines()]
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(episodes)), f"{run.name}: episodes ran once"
    absent = [w["metrics"]["absent"] for w in eps]
    assert all(sum(a) == 0 for a in absent), f"{run.name}: an agent was counted absent: {absent}"
    got = load_checkpoint(run / "trainer" / "checkpoint")
    assert got.episodes_done == ref.episodes_done == episodes
    assert len(got.weights) == len(ref.weights) == len(AGENTS)
    for i, (a, b) in enumerate(zip(ref.weights, got.weights, strict=True)):
        assert len(a) == len(b)
        for j, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"{run.name}: agent {i} tensor {j} differs"


def bad_then_clean(
    emu: LinkEmulator, tmp: Path, episodes: int = EPISODES, heartbeats: tuple[float | None, ...] = (None,)
) -> dict[str, Any]:
    """`htlm train` in process, then the team over bad links once per heartbeat period (None: the launch's profile
    as it is), then over clean links in the same namespaces; every run must end with the in-process networks and
    nobody absent. Returns each run's wall time and the frames the agents' links sent and lost."""
    from htlm_agent.learning.run import train

    settings = Settings.from_dict({**LEARNER, "episodes": episodes, "seed": SEED, "eval_episodes": 0})
    train(builtin(), settings, tmp / "inproc", progress=False, tensorboard=False, evaluate_at_end=False)
    ref = load_checkpoint(tmp / "inproc" / "checkpoint")
    runs: dict[str, Any] = {}
    for hb in (*heartbeats, "clean"):
        name = "clean" if hb == "clean" else "bad" if hb is None else f"bad_heartbeat_{hb:g}s"
        for a in AGENTS:
            emu.set_link(a, **({} if hb == "clean" else {"loss": LOSS, "delay": DELAY}))
        profile = writer_profile(tmp / f"{name}.xml", hb) if isinstance(hb, float) else None
        before = emu.counters()
        seconds = _team(emu, tmp / name, episodes, profile)
        after = emu.counters()
        _same_networks(tmp / name, ref, episodes)
        runs[name] = {
            "seconds": round(seconds, 1),
            "agent_frames_sent": sum(after[a].sent - before[a].sent for a in AGENTS),
            "agent_frames_lost": sum(after[a].lost - before[a].lost for a in AGENTS),
        }
    for r in runs.values():
        r["vs_clean"] = round(r["seconds"] / runs["clean"]["seconds"], 2)
    return {
        "episodes": episodes,
        "batch": LEARNER["envs"],
        "steps": -(-episodes // LEARNER["envs"]) * builtin().horizon,
        **runs,
    }


@pytest.mark.slow  # two training runs of seven processes (CI budget: about 2 min)
def test_lockstep_training_over_lossy_delayed_links_gives_the_networks_of_htlm_train(
    emu: LinkEmulator, tmp_path: Path
) -> None:
    r = bad_then_clean(emu, tmp_path, episodes=4)
    for name, run in r.items():
        if name.startswith("bad"):
            share = run["agent_frames_lost"] / run["agent_frames_sent"]
            assert 0.03 < share < 0.07, f"{name}: the agents' links lost {share:.3f} of their frames, not about 5 %"
    print(f"training over the agents' bad links ({LOSS:.0%} loss, {DELAY * 1000:.0f} ms), networks equal: {r}")
