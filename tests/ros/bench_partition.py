"""Benchmark: what a 10 s split costs a deployed team (test_deploy_network.py's partition, over more episodes).
Not collected by the default run; run it by name (root, network namespaces):

    .venv/bin/python -m pytest tests/ros/bench_partition.py -s -p no:cacheprovider

The same seeds run never split and split in two sides (agents 1-2 | agents 3-5) from step PART_FROM for PART_STEPS
steps of every episode. It prints completion and failures of both, and writes docs/results/partition/:
partition.json (both runs' metrics per episode and the sides' disagreement per step), disagreement.png (the
sides' excess disagreement per step, mean over the episodes, the split shaded) and episode.png (`htlm show` of the
split episode whose completion the split delayed most)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .test_deploy_network import PART_FROM, PART_STEPS, PERIOD, SC, LinkEmulator, Run, deploy, emu  # noqa: F401

pytestmark = [pytest.mark.ros, pytest.mark.timeout(3600)]

EPISODES, SEED = 8, 5
ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "results" / "partition"


def _per_step(r: Run) -> list[float]:
    """The sides' excess disagreement (cross minus within) at each step 1..h, mean over the episodes."""
    d = r.disagreement()
    return [
        float(np.mean([c - w for (_e, s), (c, w) in d.items() if s == t])) if any(s == t for _e, s in d) else np.nan
        for t in range(1, SC.horizon + 1)
    ]


def test_partition_comparison(emu: LinkEmulator, tmp_path: Path) -> None:  # noqa: F811
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    whole = deploy(emu, tmp_path / "whole", SEED, EPISODES, split=False)
    split = deploy(emu, tmp_path / "split", SEED, EPISODES, split=True)
    OUT.mkdir(parents=True, exist_ok=True)

    def rows(r: Run) -> list[dict[str, object]]:
        return [
            {k: w["metrics"][k] for k in ("episode", "completion", "failed", "unused_fraction", "absent")}
            for w in r.world
        ]

    result = {
        "seed": SEED,
        "episodes": EPISODES,
        "period": PERIOD,
        "split": {"from_step": PART_FROM, "steps": PART_STEPS, "seconds": PART_STEPS * PERIOD},
        "never_split": {"summary": whole.metrics(), "excess": whole.excess(), "episodes": rows(whole)},
        "split_run": {"summary": split.metrics(), "excess": split.excess(), "episodes": rows(split)},
        "excess_per_step": {"never_split": _per_step(whole), "split": _per_step(split)},
    }
    (OUT / "partition.json").write_text(json.dumps(result, indent=1) + "\n")

    fig, ax = plt.subplots(figsize=(7, 3.2))
    t = np.arange(1, SC.horizon + 1)
    ax.axvspan(PART_FROM, PART_FROM + PART_STEPS, color="0.9", label=f"split ({PART_STEPS * PERIOD:g} s)")
    ax.plot(t, result["excess_per_step"]["never_split"], marker=".", label="never split")
    ax.plot(t, result["excess_per_step"]["split"], marker=".", label="split in two")
    ax.set_xlabel("step")
    ax.set_ylabel("belief disagreement across sides\nminus within a side (TV)")
    ax.set_title(f"Deployed team, 0.5 s period, {EPISODES} episodes (seed {SEED})")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(OUT / "disagreement.png", dpi=120)
    plt.close(fig)

    later = {w["metrics"]["episode"]: w["metrics"]["completion"] for w in whole.world}
    worst = max(split.world, key=lambda w: w["metrics"]["completion"] - later[w["metrics"]["episode"]])
    e = worst["metrics"]["episode"]
    cmd = [sys.executable, "-m", "htlm_agent.cli", "show", str(split.run_dir), "--episode", str(e)]
    subprocess.run([*cmd, "--out", str(OUT / "episode.png")], check=True)
    print(
        f"never split: {whole.metrics()} excess {whole.excess()}; split {PART_STEPS * PERIOD:g} s per episode: "
        f"{split.metrics()} excess {split.excess()}; episode {e} drawn (completion {later[e]} never split, "
        f"{worst['metrics']['completion']} split); written to {OUT}"
    )
