"""Benchmark: a hundred agents on two hosts, deployed for ten minutes, then one host cut off the network for 10 s.
Not collected by the default run; run it by name (root, network namespaces; about 15 minutes):

    .venv/bin/python -m pytest tests/ros/bench_hosts.py -s -p no:cacheprovider

region-100's team (100 agents, greedy) deployed as docs/ros.md "Agents on other hosts" says: two network namespaces
on a bridge acting as hosts (test_netns.Net; DDS forced onto UDP, so the hosts talk over the veth links), each its
own `htlm launch deploy --only ... --discovery subnet` on the same domain: host A runs the world, the trainer and the
first 50 agents, host B the other 50 (each host hosts its agents in the launcher's default composed processes).
The world's deadlines are the defaults. After DEPLOY_S seconds of episodes, host B's link goes down for CUT_S
seconds and comes back; the team runs AFTER_S seconds more and is stopped with Ctrl-C.

Prints and writes docs/results/scale/hosts.json (per episode: its start and end, completion, failure and absent
agent-steps per host; the CPU share and memory of the whole team) and hosts.png (seconds per step and absent
agent-steps per episode over the run, the cut shaded)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from htlm_agent.ros.scale import Samples, episode_ends, look
from htlm_world.scenario import load
from support.ros import next_domain

from .test_netns import Net

pytestmark = [pytest.mark.ros, pytest.mark.timeout(3600)]

SCENARIO = "region-100"
HOSTS = ["a", "b"]
DEPLOY_S, CUT_S, AFTER_S = 600.0, 10.0, 120.0
"""Seconds of episodes before the cut, of the cut, and after it."""
SAMPLE_S = 1.0
"""Seconds between two looks at the team's processes (CPU, memory)."""
ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "results" / "scale"


def _lines(f: Path) -> list[str]:
    text = f.read_text() if f.exists() else ""
    return text[: text.rfind("\n") + 1].splitlines()


def test_hundred_agents_on_two_hosts(tmp_path: Path) -> None:
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need Linux, root and iproute2's `ip`")
    sc = load(SCENARIO)
    names = [a.name for a in sc.agents]
    half = len(names) // 2
    only = {"a": ["world", "trainer", *names[:half]], "b": names[half:]}
    run = tmp_path / "run"
    world_log = run / "world.jsonl"
    net = Net(next_domain(), HOSTS)
    net.up()
    procs: dict[str, subprocess.Popen[bytes]] = {}
    samples = Samples()
    ticks = os.sysconf("SC_CLK_TCK")
    try:
        env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
        for h in HOSTS:
            cmd = ["ip", "netns", "exec", net.ns[h], sys.executable, "-m", "htlm_agent.cli", "launch", "deploy"]
            cmd += ["--scenario", SCENARIO, "--policy", "greedy", "--only", ",".join(only[h]), "--run-dir", str(run)]
            cmd += ["--discovery", "subnet", "--domain-id", str(net.tag), "--quiet", "--json"]
            procs[h] = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=(tmp_path / f"{h}.err").open("w"))
        started = time.time()

        def watch(until: float, what: str, done: Callable[[], bool] | None = None) -> None:
            """Look at the team every SAMPLE_S until `until` (or `done`), every launch still running."""
            while time.time() < until:
                for h, p in procs.items():
                    assert p.poll() is None, f"host {h}'s launch ended ({p.returncode}) {what}"
                look(run, procs["a"].pid, samples, ticks)
                if done is not None and done():
                    return
                time.sleep(SAMPLE_S)
            if done is not None:
                raise AssertionError(f"{what}: not within {until - started:.0f} s of the start")

        watch(started + 300, "before the first episode", lambda: len(_lines(world_log)) >= 1)
        first = time.time()
        watch(first + DEPLOY_S, "while deployed")
        cut = time.time()
        net.cut("b")
        watch(cut + CUT_S, "while host b was cut off")
        net.heal("b")
        healed = time.time()
        watch(healed + AFTER_S, "after the heal")
        for p in procs.values():
            p.send_signal(signal.SIGINT)
        codes = {h: p.wait(timeout=120) for h, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        net.down()
    assert all(c in (0, 130) for c in codes.values()), codes

    ends = episode_ends((run / "logs" / "world.log").read_text())
    rows = []
    for line in _lines(world_log):
        m = json.loads(line)["metrics"]
        end = ends[m["episode"]]
        rows.append(
            {
                "episode": m["episode"],
                "start": end - m["seconds"],
                "end": end,
                "seconds": m["seconds"],
                "completion": m["completion"],
                "failed": m["failed"],
                "absent_a": sum(m["absent"][:half]),
                "absent_b": sum(m["absent"][half:]),
            }
        )
    before = [r for r in rows if r["end"] <= cut]
    during = [r for r in rows if r["end"] > cut and r["start"] < healed]
    after = [r for r in rows if r["start"] >= healed]
    steady = [r for r in before if r["start"] >= first]
    share = samples.cpu_share(steady[0]["start"], steady[-1]["end"]) if steady else None
    rss, pss, agent_procs = samples.peak()
    last_absent = max((r["end"] for r in rows if r["absent_b"]), default=None)
    result = {
        "scenario": SCENARIO,
        "hosts": {"a": f"world, trainer, agents 1-{half}", "b": f"agents {half + 1}-{len(names)}"},
        "deploy_s": DEPLOY_S,
        "cut_s": CUT_S,
        "after_s": AFTER_S,
        "deployed_before_cut_s": cut - first,
        "episodes_before_cut": len(before),
        "absent_before_cut": sum(r["absent_a"] + r["absent_b"] for r in before),
        "agent_steps_before_cut": len(before) * sc.horizon * len(names),
        "failed_before_cut": sum(r["failed"] for r in before),
        "completion_before_cut": sum(r["completion"] for r in before) / max(1, len(before)),
        "seconds_per_step_before_cut": sum(r["seconds"] for r in steady) / max(1, len(steady)) / sc.horizon,
        "absent_during_cut": {"a": sum(r["absent_a"] for r in during), "b": sum(r["absent_b"] for r in during)},
        "episodes_after_heal": len(after),
        "absent_after_heal": sum(r["absent_a"] + r["absent_b"] for r in after),
        "last_absence_after_heal_s": None if last_absent is None else last_absent - healed,
        "cpu_share": share,
        "agent_processes": agent_procs,
        "agents_rss_mb": rss / 1024,
        "agents_pss_mb": pss / 1024,
        "cut": {"first_episode": first, "at": cut, "healed": healed},
        "episodes": rows,
    }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "hosts.json").write_text(json.dumps(result, indent=1) + "\n")
    _plot(rows, cut, healed, first, sc.horizon)
    summary = {k: v for k, v in result.items() if k not in ("episodes", "cut")}
    print(json.dumps(summary, indent=1))
    assert rows and before, "no episode logged before the cut"


def _plot(rows: list[dict[str, float]], cut: float, healed: float, t0: float, horizon: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 4.6), sharex=True)
    mid = [((r["start"] + r["end"]) / 2 - t0) / 60 for r in rows]
    for ax in (ax1, ax2):
        ax.axvspan((cut - t0) / 60, (healed - t0) / 60, color="0.85", label=f"host b cut off ({healed - cut:.0f} s)")
    ax1.plot(mid, [r["seconds"] / horizon for r in rows], marker=".", lw=0.8)
    ax1.set_ylabel("seconds a step\n(episode mean)")
    ax1.set_ylim(bottom=0)
    ax2.bar(mid, [r["absent_a"] for r in rows], width=0.08, label="host a's agents")
    ax2.bar(mid, [r["absent_b"] for r in rows], width=0.08, bottom=[r["absent_a"] for r in rows], label="host b's")
    ax2.set_ylabel("absent agent-steps\n(per episode)")
    ax2.set_xlabel("minutes since the first episode")
    ax2.legend(loc="upper left", fontsize=8)
    ax1.set_title(f"{SCENARIO}: 100 agents on two hosts, deployed (lockstep, default deadlines)", fontsize=10)
    fig.tight_layout()
    fig.savefig(OUT / "hosts.png", dpi=120)
    plt.close(fig)
