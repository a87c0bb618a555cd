"""Benchmark: what a large team's agent processes cost, one process per agent against several agents per process
(`htlm launch --agents-per-process`). Run it by name, one launch at a time, on an otherwise quiet machine:

    .venv/bin/python tests/ros/bench_compose.py --scenario city-50 --per 1 --per 25 --json

For each value of --per it runs `htlm launch evaluate --policy greedy` (batch 1, --episodes, deadlines far above a
slow step so no agent turns absent) and reports:

- `up`: seconds from the launch to the last agent's line that it took the run (every agent node made, its policy
  loaded, the world's run announcement received);
- `first_episode`: seconds from the launch to the world's first logged episode (the agents' discovery of each other
  and the world, and one episode);
- `steady_episode`: the median seconds of the later episodes;
- `rss_mb`, `pss_mb`: the largest total, over the run, of the agent processes' resident memory (RSS counts the
  pages processes share in each of them, PSS shares them out), sampled every 0.5 s from /proc;
- `processes`: the agent processes; `absent`: absent agent-steps; `exit_code`: the launch's.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.ros import HTLM, next_domain

AGENT_MODULES = ("htlm_agent.ros.agent_node", "htlm_agent.ros.agents_node")
STAMP = re.compile(r"\[(?:INFO|WARN|ERROR)\] \[(\d+\.\d+)\] \[([^\]]+)\]: (.*)")


def _agent_pids(run: Path) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        words = [w.decode(errors="replace") for w in cmd]
        if any(m in words for m in AGENT_MODULES) and any(str(run) in w for w in words):
            out.append(int(d.name))
    return out


def _memory(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of a process in kB, (0, 0) once it is gone."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return 0, 0
    got = dict(re.findall(r"^(Rss|Pss):\s+(\d+) kB", text, re.M))
    return int(got.get("Rss", 0)), int(got.get("Pss", 0))


def measure(scenario: str, per: int, episodes: int, where: Path, extra: list[str] | None = None) -> dict[str, Any]:
    run = where / f"{scenario}-per{per}"
    patient = ["--world-param", "join_timeout=900", "--world-param", "act_deadline=60"]
    patient += ["--world-param", "update_deadline=60", "--agent-param", "broadcast_timeout=30"]
    cmd = [HTLM, "launch", "evaluate", "--scenario", scenario, "--policy", "greedy", "--episodes", str(episodes),
           "--batch", "1", "--agents-per-process", str(per), *patient, "--domain-id", str(next_domain()),
           "--run-dir", str(run), "--json", "--quiet", *(extra or [])]  # fmt: skip
    t0 = time.time()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    peak_rss = peak_pss = 0
    procs = 0
    while p.poll() is None:
        pids = _agent_pids(run)
        mem = [_memory(x) for x in pids]
        if sum(r for r, _ in mem) > peak_rss:
            peak_rss, peak_pss, procs = sum(r for r, _ in mem), sum(s for _, s in mem), len(pids)
        time.sleep(0.5)
    out, _ = p.communicate()
    summary = json.loads(out.strip().splitlines()[-1])
    up = 0.0
    for log in (run / "logs").iterdir():
        if log.name in ("world.log", "trainer.log"):
            continue
        for line in log.read_text(errors="replace").splitlines():
            m = STAMP.match(line)
            if m and re.match(r"run \S+: agent ", m.group(3)):
                up = max(up, float(m.group(1)) - t0)
    world = [STAMP.match(x) for x in (run / "logs" / "world.log").read_text().splitlines()]
    eps = [m for m in world if m and re.match(r"episodes? \d+", m.group(3))]
    secs = [float(re.search(r", ([0-9.]+) s$", m.group(3)).group(1)) for m in eps]  # type: ignore[union-attr]
    return {
        "scenario": scenario,
        "per": per,
        "processes": procs,
        "up": round(up, 1),
        "first_episode": round(float(eps[0].group(1)) - t0, 1) if eps else None,
        "steady_episode": round(statistics.median(secs[1:]), 2) if len(secs) > 1 else None,
        "rss_mb": round(peak_rss / 1024),
        "pss_mb": round(peak_pss / 1024),
        "absent": summary.get("absent_agent_steps"),
        "episodes": summary.get("episodes"),
        "exit_code": p.returncode,
        "seconds": round(time.time() - t0, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="city-50")
    ap.add_argument("--per", type=int, action="append", default=[], help="agents per process (repeatable)")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--agent-param", action="append", default=[], help="NAME=VALUE for every agent (executor=single)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="htlm-bench-compose-") as tmp:
        for per in args.per or [1, 0]:
            extra = [w for kv in args.agent_param for w in ("--agent-param", kv)]
            r = measure(args.scenario, per, args.episodes, Path(tmp), extra)
            r["agent_params"] = args.agent_param
            print(json.dumps(r) if args.json else r, flush=True)
            os.sync()


if __name__ == "__main__":
    main()
