"""The result of a team trained and evaluated over ROS, beside the baselines: a table (printed), result.csv,
result.json and result.png in the run directory.

The learned team's row comes from the world's episode log (world.jsonl) of the evaluation run over ROS; the
baselines (random, greedy, auction, QMDP and the centralized optimum that reads the true state; the last two where
the optimum can be computed) are evaluated in process on the same number of episodes with the same master seed
(`htlm evaluate --baseline`), so every row is measured, none is drawn from constants.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.baselines.optimal import ProblemTooLarge
from htlm_agent.experiments.baselines import make_baseline
from htlm_agent.runtime.evaluate import MAX_BATCH, evaluate_run
from htlm_world.metrics import mean_se
from htlm_world.scenario import Scenario

FIELDS = ("policy", "runtime", "episodes", "completion_mean", "completion_se", "failure_rate", "unused_fraction")
"""Columns of result.csv (and keys of every row of result.json)."""

BASELINES = ("random", "greedy", "auction", "qmdp", "lookahead", "optimal")
"""Baselines shown beside the learned team."""

LOOKAHEAD_MAX_AGENTS = 10
"""Most agents of a team whose report evaluates the lookahead baseline: its agents act in N² p per step (each runs the
auction of the whole team on its own belief and values every candidate), 500 episodes of 16 agents took 8.5 minutes
on the 2-core development machine; `htlm evaluate --baseline lookahead` still evaluates it by name."""

LABELS = {"lookahead": "lookahead (learner)"}
"""Row names other than the baseline's own: the lookahead with the run's seed is what `htlm train --learner
lookahead` trains (same settings and seed), in process; over ROS it acts the same, bit for bit."""


class ReportError(ValueError):
    """No finished episode to report on; names the file."""


def world_rows(world_log: Path) -> list[dict[str, Any]]:
    """The per-episode metrics of a world.jsonl (one line per finished episode).

    Raises:
        ReportError: the file is missing or holds no episode.
    """
    if not world_log.exists():
        raise ReportError(f"{world_log}: no episode log (did the run start?)")
    rows = [json.loads(line)["metrics"] for line in world_log.read_text().splitlines() if line.strip()]
    if not rows:
        raise ReportError(f"{world_log}: no finished episode")
    return rows


def _row(policy: str, runtime: str, completion: Any, failed: Any, unused: Any) -> dict[str, Any]:
    m, se = mean_se(np.asarray(completion, dtype=np.float64))
    return {
        "policy": policy,
        "runtime": runtime,
        "episodes": len(completion),
        "completion_mean": round(m, 4),
        "completion_se": round(se, 4),
        "failure_rate": round(float(np.mean(failed)), 4),
        "unused_fraction": round(float(np.mean(unused)), 4),
    }


def learned_row(world_log: Path, name: str = "learned") -> dict[str, Any]:
    """The row of the team evaluated over ROS, from its world.jsonl."""
    eps = world_rows(world_log)
    return _row(
        name,
        "ROS 2",
        [e["completion"] for e in eps],
        [e["failed"] for e in eps],
        [e["unused_fraction"] for e in eps],
    )


def baseline_rows(
    scenario: Scenario, episodes: int, seed: int, skipped: dict[str, str] | None = None, batch: int = MAX_BATCH
) -> list[dict[str, Any]]:
    """`BASELINES` (random, greedy, auction, QMDP, the lookahead, the optimum), evaluated in process on `episodes`
    episodes of master seed `seed`, in batches of `batch` (those of the team evaluated over ROS: the same
    episodes).
    A baseline that cannot be had here (the optimum of a large scenario; the lookahead above LOOKAHEAD_MAX_AGENTS
    agents) is left out, and why goes into `skipped` by its name and onto stderr, as each baseline's time does."""
    rows = []
    for name in BASELINES:
        why = None
        if name == "lookahead" and scenario.n_agents > LOOKAHEAD_MAX_AGENTS:
            why = (
                f"{scenario.n_agents} agents: its agents act in N² p a step (more than {LOOKAHEAD_MAX_AGENTS} agents: "
                f"minutes to hours for {episodes} episodes); `htlm evaluate --baseline lookahead` evaluates it"
            )
        else:
            try:
                policy, sc = make_baseline(name, scenario, seed=seed)
            except ProblemTooLarge as e:
                why = str(e)
        if why is not None:
            if skipped is not None:
                skipped[name] = why
            print(f"htlm launch: {name}: left out, {why}", file=sys.stderr)
            continue
        start = time.monotonic()
        ev = evaluate_run(policy, sc, episodes, seed=seed, policy_name=name, batch=batch)
        em = ev.episodes
        rows.append(_row(LABELS.get(name, name), "in process", em.completion, em.failed, em.unused_fraction))
        print(f"htlm launch: {name}: {episodes} episodes in {time.monotonic() - start:.1f} s", file=sys.stderr)
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as an aligned text table."""
    head = f"{'policy':<22} {'runtime':<11} {'episodes':>8}  {'completion':>15}  {'failures':>8}  {'unused':>7}"
    lines = [head, "-" * len(head)]
    for r in rows:
        comp = f"{r['completion_mean']:.2f} ± {r['completion_se']:.2f}"
        lines.append(
            f"{r['policy']:<22} {r['runtime']:<11} {r['episodes']:>8}  {comp:>15}  {r['failure_rate']:>8.1%}  "
            f"{r['unused_fraction']:>7.1%}"
        )
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Completion step (mean ± 2 SE) and failure rate of every row, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["policy"].replace(" (", "\n(") for r in rows]  # "learned (expert)" on two lines, clear of its neighbour
    x = np.arange(len(rows))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(max(10.0, 1.8 * len(rows)), 4))  # room for every label
    colors = ["tab:green" if r["runtime"] == "ROS 2" else "tab:gray" for r in rows]
    ax1.bar(x, [r["completion_mean"] for r in rows], yerr=[2 * r["completion_se"] for r in rows], color=colors)
    ax1.set_xticks(x, names)
    ax1.set_ylabel("completion step (lower is better), mean ± 2 SE")
    ax2.bar(x, [100 * r["failure_rate"] for r in rows], color=colors)
    ax2.set_xticks(x, names)
    ax2.set_ylabel("failed episodes (%)")
    for i, r in enumerate(rows):  # the numbers on the bars
        ax1.annotate(f"{r['completion_mean']:.2f}", (i, r["completion_mean"]), ha="center", va="bottom", fontsize=9)
        ax2.annotate(
            f"{100 * r['failure_rate']:.1f}", (i, 100 * r["failure_rate"]), ha="center", va="bottom", fontsize=9
        )
    for ax in (ax1, ax2):
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(out_dir: Path, rows: list[dict[str, Any]], info: dict[str, Any]) -> dict[str, Any]:
    """result.csv, result.json and result.png in `out_dir`; returns the JSON document."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / "result.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        w.writeheader()
        w.writerows(rows)
    doc = {**info, "rows": rows}
    (out_dir / "result.json").write_text(json.dumps(doc, indent=2) + "\n")
    title = f"{info.get('team', '')}: team trained over ROS 2 ({info.get('train_episodes', '?')} episodes) vs baselines"
    plot(rows, out_dir / "result.png", title)
    return doc
