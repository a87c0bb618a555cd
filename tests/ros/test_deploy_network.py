"""A deployed team over a network that fails it: split in two, and over bad links.

**Split in two** (partition): every agent with its simulated robot on a host of its own
(a network namespace joined by the user-space switch of tests/ros/links.py), the observing world, the trainer and
the robots' stand-in operation on a host both sides reach (the physical world and the observer do not split). In
every episode, from step PART_FROM on, the switch lets no frame pass between agents 1-2 and agents 3-5 for
PART_STEPS steps (10 s at the 0.5 s period), then heals. The same episodes run once without the partition.

Checked:
- each side keeps acting on its own clock and beliefs: no agent misses a step (by its own log), split or not;
- the sides do not hear each other while split (the other side's broadcasts are missing from each agent's updates)
  and their beliefs drift apart; after the heal the broadcasts bring them back together: the disagreement between
  the sides' beliefs falls back to what it is in the run that was never split;
- completion and failures of both runs are printed side by side (measured, not bounded: 4 episodes are too few).

**Bad links**: the same deployment at 2 Hz with every agent's link losing 5 % of the frames it sends and delaying them
by 100 ms (the shared host's link is clean): absent agent-steps, by the world's count and by the agents' own logs,
are at most 1 %.

`python tests/ros/bench_partition.py` runs the split comparison over more episodes and draws one partitioned
episode with `htlm show` (docs/results/partition)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.ros.launch import LaunchConfig, ros_env
from htlm_world.clock import StepClock
from htlm_world.scenario import builtin
from support.ros import TOOLS, next_domain, wait_team

from .links import LinkEmulator

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(600)]

SC = builtin()
AGENTS = [a.name for a in SC.agents]
SIDES = [AGENTS[:2], AGENTS[2:]]
HOSTS = ["shared", *AGENTS]
PERIOD = 0.5
PART_FROM, PART_STEPS = 3, 20
"""The split lasts from the instant of step PART_FROM to that of step PART_FROM + PART_STEPS of every episode."""
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Run:
    """What one deployed run left: its episodes (world log), each agent's episode log, the belief records."""

    world: list[dict[str, Any]]
    agents: dict[str, list[dict[str, Any]]]
    beliefs: list[tuple[str, float, dict[str, Any]]]
    clock: StepClock
    run_dir: Path
    seconds: float
    split: list[tuple[float, float]] = field(default_factory=list)

    def metrics(self) -> dict[str, float]:
        """Mean completion step (failures count as h + 1) and failure rate over the episodes."""
        m = [w["metrics"] for w in self.world]
        done = [x["completion"] if not x["failed"] else SC.horizon + 1 for x in m]
        return {"completion": float(np.mean(done)), "failures": float(np.mean([x["failed"] for x in m]))}

    def disagreement(self) -> dict[tuple[int, int], tuple[float, float]]:
        """Per (episode, step): the mean total-variation distance between the belief marginals (per task, averaged
        over tasks) of an agent of one side and an agent of the other, and the same within a side (the newest
        record of each agent for that step). Teammates that hear each other still differ a little (each hears the
        others' observations through its own noisy channel): the cross-side excess is what the split adds."""
        latest: dict[tuple[int, int], dict[str, np.ndarray]] = {}
        for topic, _at, rec in self.beliefs:
            agent = topic.split("/")[-2]
            latest.setdefault((rec["episode"], rec["step"]), {})[agent] = np.asarray(rec["marginals"])

        def tv(x: np.ndarray, y: np.ndarray) -> float:
            return float(0.5 * np.abs(x - y).reshape(-1, SC.levels).sum(axis=1).mean())

        out = {}
        for key, by in latest.items():
            if len(by) == len(AGENTS):
                cross = [tv(by[a], by[b]) for a in SIDES[0] for b in SIDES[1]]
                within = [tv(by[a], by[b]) for side in SIDES for a in side for b in side if a < b]
                out[key] = (float(np.mean(cross)), float(np.mean(within)))
        return out

    def excess(self) -> dict[str, float]:
        """The mean cross-side excess disagreement (cross minus within) before the split, while split (from its
        second step), and from two steps after the heal to the end of the episode."""
        d = {k: c - w for k, (c, w) in self.disagreement().items()}
        heal = PART_FROM + PART_STEPS
        parts = {
            "before": [v for (_e, t), v in d.items() if t < PART_FROM],
            "split": [v for (_e, t), v in d.items() if PART_FROM < t < heal],
            "after": [v for (_e, t), v in d.items() if t >= heal + 2],
        }
        return {k: round(float(np.mean(v)), 4) if v else float("nan") for k, v in parts.items()}


@pytest.fixture
def emu(links: Callable[..., LinkEmulator]) -> LinkEmulator:
    """The hosts of the module's docstring on the user-space switch (conftest's `links`)."""
    return links(HOSTS)


def deploy(emu: LinkEmulator, run: Path, seed: int, episodes: int, split: bool) -> Run:
    """One deployed run (greedy agents, simulated robots, the 0.5 s clock), split in every episode when `split`."""
    domain = next_domain()
    script = str(ROOT / "launch_scripts" / "team.sh")
    args = ["deploy", "--policy", "greedy", "--seed", str(seed), "--episodes", str(episodes), "--robots", "sim"]
    args += ["--period", str(PERIOD), "--world-param", "begin_deadline=20.0", "--agent-param", "broadcast_timeout=0.2"]
    args += ["--timeout", str(60 + episodes * SC.horizon * PERIOD), "--discovery", "subnet"]
    args += ["--domain-id", str(domain), "--run-dir", str(run), "--quiet"]
    env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    rec_env = ros_env(LaunchConfig(mode="deploy", scenario=SC, run_dir=run, domain_id=domain, discovery="subnet"))
    only = {"shared": "world,trainer,operation", **{a: f"{a},robot_{a}" for a in AGENTS}}
    beliefs = run / "beliefs.json"
    run.mkdir(parents=True, exist_ok=True)
    rec_cmd = ["ip", "netns", "exec", emu.ns["shared"], sys.executable, str(TOOLS)]
    rec_cmd += ["record_all", "--out", str(beliefs), *[f"/htlm/{a}/belief" for a in AGENTS]]
    recorder = subprocess.Popen(rec_cmd, env=rec_env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    procs = {
        h: subprocess.Popen(
            ["ip", "netns", "exec", emu.ns[h], script, *args, "--only", only[h]],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        for h in HOSTS
    }
    announced = run / f"{AGENTS[0]}.run.json"
    end = time.monotonic() + 90
    while not announced.exists():
        assert time.monotonic() < end, f"no epoch from {AGENTS[0]} within 90 s ({announced})"
        assert all(p.poll() is None for p in procs.values()), {h: p.poll() for h, p in procs.items()}
        time.sleep(0.05)
    rec = json.loads(announced.read_text())
    clock = StepClock(rec["epoch"], PERIOD, SC.horizon, 0, episodes)
    splits = []
    if split:
        for e in range(episodes):
            a, b = clock.at(e, PART_FROM), clock.at(e, PART_FROM + PART_STEPS)
            time.sleep(max(0.0, a - time.time()))
            emu.partition(SIDES, shared=["shared"])
            time.sleep(max(0.0, b - time.time()))
            emu.heal()
            splits.append((a, b))
    wait_team(procs, run, 90 + episodes * SC.horizon * PERIOD)
    seconds = time.monotonic() - t0
    recorder.terminate()
    recorder.wait(timeout=20)

    def lines(f: Path) -> list[dict[str, Any]]:
        return [json.loads(x) for x in f.read_text().splitlines()] if f.exists() else []

    got = [(t, at, json.loads(text)) for t, at, text in json.loads(beliefs.read_text())]
    return Run(
        world=lines(run / "world.jsonl"),
        agents={a: lines(run / f"{a}.jsonl") for a in AGENTS},
        beliefs=got,
        clock=clock,
        run_dir=run,
        seconds=seconds,
        split=splits,
    )


def test_a_deployed_team_over_lossy_slow_links_misses_at_most_1_percent_of_its_steps(
    emu: LinkEmulator, tmp_path: Path
) -> None:
    seed, episodes = 3, 2
    for a in AGENTS:
        emu.set_link(a, loss=0.05, delay=0.1)
    r = deploy(emu, tmp_path / "bad", seed, episodes, split=False)
    assert [w["metrics"]["episode"] for w in r.world] == list(range(episodes))
    steps = episodes * SC.horizon * len(AGENTS)
    absent = sum(sum(w["metrics"]["absent"]) for w in r.world)
    missed = {a: sum(not x for ep in eps for x in ep["acted"]) for a, eps in r.agents.items()}
    counts = emu.counters()
    print(
        f"over 5 % loss and 100 ms delay on every agent's link, {episodes} episodes at {1 / PERIOD:g} Hz: "
        f"{absent} of {steps} agent-steps absent by the world's count, missed by the agents' own logs {missed}; "
        f"{r.metrics()}; frames lost by sender { ({h: c.lost for h, c in counts.items()}) } of "
        f"{ ({h: c.sent for h, c in counts.items()}) }"
    )
    assert sum(c.lost for c in counts.values()) > 0, "the links lost nothing"
    assert absent <= 0.01 * steps, f"{absent} of {steps} agent-steps absent (the world's count)"
    assert sum(missed.values()) <= 0.01 * steps, f"agents missed {missed} of {steps} agent-steps"


def test_a_team_split_in_two_keeps_acting_and_comes_back_together(emu: LinkEmulator, tmp_path: Path) -> None:
    seed, episodes = 2, 3
    whole = deploy(emu, tmp_path / "whole", seed, episodes, split=False)
    split = deploy(emu, tmp_path / "split", seed, episodes, split=True)
    for r in (whole, split):
        assert [w["metrics"]["episode"] for w in r.world] == list(range(episodes)), r.run_dir
        for a, eps in r.agents.items():
            assert [x["episode"] for x in eps] == list(range(episodes)), (a, r.run_dir)
            missed = [(x["episode"], t + 1) for x in eps for t, acted in enumerate(x["acted"]) if not acted]
            assert missed == [], f"{a} missed steps {missed} ({r.run_dir.name})"
    pw, ps = whole.excess(), split.excess()
    blocked = {h: c.blocked for h, c in emu.counters().items()}
    print(
        f"never split: {whole.metrics()}, excess disagreement of the sides {pw}; split {PART_STEPS * PERIOD:g} s "
        f"per episode: {split.metrics()}, {ps}; frames the split blocked, by sender: {blocked}"
    )
    assert sum(blocked.values()) > 0, "the switch never blocked a frame"
    assert ps["split"] > pw["split"] + 0.05, f"the sides' beliefs did not drift apart while split: {ps} vs {pw}"
    assert ps["after"] <= pw["after"] + 0.02, f"the sides did not come back together after the heal: {ps} vs {pw}"
