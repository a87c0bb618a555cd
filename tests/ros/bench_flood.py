"""Benchmark: how a flood of rejected records on /htlm/action slows the lockstep, by flood rate (a team of real
processes over real DDS, as in test_flood.py). Not collected by the default run; run it by name:

    .venv/bin/python -m pytest tests/ros/bench_flood.py -s -p no:cacheprovider

It prints one line per rate and writes docs/results/flood.csv and docs/images/flood.png (slowdown against flood
rate, measured in one run per rate: mean batch duration flooded / not flooded; for the flood as fast as the process
can publish, the batches finished during the flood against those the same time holds unflooded)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import pytest

from .test_flood import run_flood

pytestmark = [pytest.mark.ros, pytest.mark.timeout(1800)]

RATES = [1000, 2000, 4000, 8000, 16000]
ROOT = Path(__file__).resolve().parents[2]


def test_flood_sweep(ros_team: Any) -> None:
    rows = []
    for rate in [*RATES, 0]:
        args = ["--rate", str(rate)] if rate else ["--seconds", "10"]
        f = run_flood(ros_team, args, flooded=3)
        # at full speed: the batches the flood's time holds unflooded / those finished; none finished: at least that
        finished = f.progress * f.expected
        slowdown = f.slowdown if rate else f.expected / max(finished, 1.0)
        rows.append(
            {
                "rate_set": rate or "max",
                "rate_sent": f.sent["rate"],
                "rejected_counted": sum(f.rejected.values()),
                "sent": f.sent["sent"],
                "slowdown": round(slowdown, 2),
                "slowdown_is_lower_bound": bool(not rate and finished < 1.0),
                "progress_while_flooded": round(f.progress, 3),
                "absent_agent_steps": f.absent,
                "warnings": f.warnings,
                "flood_seconds": round(f.flood_seconds, 1),
            }
        )
        print("BENCH", rows[-1], flush=True)
    out = ROOT / "docs" / "results" / "flood.csv"
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, ROOT / "docs" / "images" / "flood.png")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    timed = [r for r in rows if r["rate_set"] != "max"]
    ax.plot([r["rate_sent"] for r in timed], [r["slowdown"] for r in timed], "o-", label="flood at a set rate")
    full = [r for r in rows if r["rate_set"] == "max"]
    ax.plot(
        [r["rate_sent"] for r in full],
        [r["slowdown"] for r in full],
        "s",
        color="tab:red",
        label="as fast as one process can (no batch finished: a lower bound)",
    )
    ax.axhline(2.0, color="grey", ls="--", lw=1, label="2x")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("rejected records/s sent to /htlm/action")
    ax.set_ylabel("lockstep slowdown (flooded / unflooded)")
    ax.set_title("A flood of bad records vs the lockstep (greedy team, B = 8, 2-core machine)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
