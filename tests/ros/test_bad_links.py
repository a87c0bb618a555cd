"""Lockstep training over bad links gives the networks of `htlm train` bit for bit (issue 20, bad links): the world,
the trainer and every agent in a network namespace of its own, joined by the user-space switch of tests/ros/links.py
(this kernel has no netem), each started as the README says for several hosts (`team.sh train --only NAME
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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.settings import Settings
from htlm_world.scenario import builtin

from .conftest import next_domain
from .links import LinkEmulator, unavailable
from .test_netns import _wait_team

pytestmark = [pytest.mark.ros, pytest.mark.timeout(600)]

HOSTS = ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]
AGENTS = HOSTS[2:]
LOSS, DELAY = 0.05, 0.1
LEARNER = {"envs": 4, "learning_starts": 60, "batch_size": 16, "validate_every": 0, "select_best": False}
EPISODES, SEED = 8, 0
"""Two batches of four episodes: 60 lockstep steps, the learner updating from the middle of the first batch."""
# far above the recovery of a lost datagram (Fast DDS's heartbeat period, 3 s by default, or an agent's resend)
WORLD = {"act_deadline": 60.0, "update_deadline": 60.0, "begin_deadline": 60.0, "trainer_deadline": 120.0}
TRAINER = {"round_deadline": 60.0}
AGENT = {"broadcast_timeout": 30.0, "discovery_grace": 60.0, "stop_timeout": 60.0}
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def emu() -> Iterator[LinkEmulator]:
    why = unavailable()
    if why:
        pytest.skip(why)
    e = LinkEmulator(HOSTS, tag=next_domain(), seed=SEED)
    try:
        e.up()
    except OSError as err:
        pytest.skip(f"cannot make the link emulator here: {err}")
    yield e
    e.down()


def _team(emu: LinkEmulator, run: Path, domain: int) -> float:
    """Train with every process in its namespace (the team of the module's docstring); its wall time, start-up and
    exit included. Every process must exit 0 (else the failure shows the world's output and every log's tail)."""
    script = str(ROOT / "launch_scripts" / "team.sh")
    args = ["train", "--seed", str(SEED), "--episodes", str(EPISODES), "--batch", str(LEARNER["envs"])]
    args += ["--eval-episodes", "0", "--timeout", "400"]
    args += [x for k, v in LEARNER.items() for x in ("--set", f"{k}={json.dumps(v)}")]
    for opt, params in (("--world-param", WORLD), ("--trainer-param", TRAINER), ("--agent-param", AGENT)):
        args += [x for k, v in params.items() for x in (opt, f"{k}={v}")]
    env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    t0 = time.monotonic()
    procs = {}
    for name in HOSTS:
        cmd = ["ip", "netns", "exec", emu.ns[name], script, *args, "--only", name, "--discovery", "subnet"]
        cmd += ["--domain-id", str(domain), "--run-dir", str(run), "--quiet"]
        procs[name] = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    _wait_team(procs, run, 450)
    return time.monotonic() - t0


def _same_networks(run: Path, ref: Any) -> None:
    eps = [json.loads(x) for x in (run / "world.jsonl").read_text().splitlines()]
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(EPISODES)), "every episode ran once"
    absent = [w["metrics"]["absent"] for w in eps]
    assert all(sum(a) == 0 for a in absent), f"an agent was counted absent: {absent}"
    got = load_checkpoint(run / "trainer" / "checkpoint")
    assert got.episodes_done == ref.episodes_done == EPISODES
    assert len(got.weights) == len(ref.weights) == len(AGENTS)
    for i, (a, b) in enumerate(zip(ref.weights, got.weights, strict=True)):
        assert len(a) == len(b)
        for j, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"{run.name}: agent {i} tensor {j} differs"


def bad_then_clean(emu: LinkEmulator, tmp: Path) -> dict[str, Any]:
    """`htlm train` in process, then the team over bad links, then over clean links in the same namespaces; both
    must end with the in-process networks and nobody absent. Returns the wall times, their ratio and the frames the
    agents' links lost."""
    from htlm_agent.experiments.train import train

    settings = Settings.from_dict({**LEARNER, "episodes": EPISODES, "seed": SEED, "eval_episodes": 0})
    train(builtin(), settings, tmp / "inproc", progress=False, tensorboard=False, evaluate_at_end=False)
    ref = load_checkpoint(tmp / "inproc" / "checkpoint")

    for a in AGENTS:
        emu.set_link(a, loss=LOSS, delay=DELAY)
    before = emu.counters()
    bad = _team(emu, tmp / "bad", emu.tag)
    after = emu.counters()
    _same_networks(tmp / "bad", ref)
    sent = sum(after[a].sent - before[a].sent for a in AGENTS)
    lost = sum(after[a].lost - before[a].lost for a in AGENTS)

    for a in AGENTS:
        emu.set_link(a)
    clean = _team(emu, tmp / "clean", next_domain())
    _same_networks(tmp / "clean", ref)
    return {
        "episodes": EPISODES,
        "batch": LEARNER["envs"],
        "bad_s": round(bad, 1),
        "clean_s": round(clean, 1),
        "ratio": round(bad / clean, 2),
        "agent_frames_sent": sent,
        "agent_frames_lost": lost,
        "networks_equal": True,
    }


@pytest.mark.slow  # two training runs of seven processes (about N s)
def test_lockstep_training_over_lossy_delayed_links_gives_the_networks_of_htlm_train(
    emu: LinkEmulator, tmp_path: Path
) -> None:
    r = bad_then_clean(emu, tmp_path)
    assert 0.03 < r["agent_frames_lost"] / r["agent_frames_sent"] < 0.07, r  # the links did lose about 5 %
    print(
        f"training {EPISODES} episodes (B = {LEARNER['envs']}) over the agents' bad links ({LOSS:.0%} loss, "
        f"{DELAY * 1000:.0f} ms): {r['bad_s']} s, over clean links in the same namespaces {r['clean_s']} s "
        f"({r['ratio']}x); the agents' links lost {r['agent_frames_lost']} of {r['agent_frames_sent']} frames; "
        "the networks equal those of htlm train both times"
    )
