"""`htlm stress`: a team under a set of events (docs/model.md, Events) beside the same team without them and beside
the baselines, on the same episodes (the same seed: the world draws the same numbers until an event changes what
happens).

The figures of an event (docs/model.md, Metrics under events): the time to recover, the steps from the event's step
until its tasks are back at level 0 (a surge or a new task: its task; a dropout or a return: every task), over the
episodes in which it happened, and the fraction that never recover by the horizon; the unused capability before the
first event of an episode and from it until the recovery (how much of the reserve the team used to respond).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.mind.context import Policy
from htlm_agent.progress import Progress
from htlm_agent.runtime.evaluate import Evaluation, evaluate_run, write_reports
from htlm_world.events import SURGE, EventRun
from htlm_world.metrics import mean_se
from htlm_world.scenario import EventSpec, Scenario
from htlm_world.types import IntArray


@dataclass(frozen=True)
class Recovery:
    """The recoveries from the events of E episodes."""

    steps: IntArray  # (occurrences,) steps from the event until its tasks are at 0; -1: never by the horizon
    first_step: IntArray  # (E,) step of the episode's first event; 0: none happened
    recovered_at: IntArray  # (E,) step at which the first event's tasks were back at 0; h + 1: never


def recoveries(scenario: Scenario, levels: IntArray, events: list[tuple[int, int, int]]) -> Recovery:
    """Recoveries of (step, episode, event) occurrences from the true levels (h+1, E, p) of the episodes."""
    h, e = levels.shape[0] - 1, levels.shape[1]
    codes = EventRun(scenario, 1, np.random.default_rng(0))
    steps = []
    first = np.zeros(e, dtype=np.int64)
    recovered = np.full(e, h + 1, dtype=np.int64)
    for t, ep, j in events:
        tasks = [int(codes.target[j])] if codes.code[j] == SURGE else list(range(scenario.n_tasks))
        done = (levels[t:, ep][:, tasks] == 0).all(axis=1)  # rows: after steps t .. h
        s = int(done.argmax()) + t if done.any() else -1
        steps.append(s - t + 1 if s >= 0 else -1)
        if first[ep] == 0:
            first[ep] = t
            recovered[ep] = s if s >= 0 else h + 1
    return Recovery(np.array(steps, dtype=np.int64), first, recovered)


def stress_figures(ev: Evaluation) -> dict[str, Any]:
    """The figures of one evaluation under events: completion, failures, how often events happened, recovery and
    unused capability before and during the response."""
    sc, ro = ev.scenario, ev.rollouts
    m = ev.metrics["completion"]
    out: dict[str, Any] = {
        "completion": {"mean": m["mean"], "se": m["se"]},
        "failure_rate": m["failure_rate"],
        "unused_fraction": ev.metrics["unused_fraction"],
    }
    if not sc.events:
        return out
    rec = recoveries(sc, ro.levels, ro.events)
    hit = rec.first_step > 0
    ok = rec.steps[rec.steps >= 0]
    r, r_se = mean_se(ok) if ok.size else (float("nan"), 0.0)
    caps = np.array([sc.total_capability(i) for i in range(sc.n_agents)], dtype=np.float64)
    idle = (ro.actions >= sc.n_tasks) | (ro.actions < 0)  # (h, E, N)
    unused = (idle * caps).sum(axis=2) / max(caps.sum(), 1e-9)  # (h, E) share of the team's capability unused
    step = np.arange(1, ro.actions.shape[0] + 1)[:, None]
    before = step < rec.first_step[None, :]
    during = (step >= rec.first_step[None, :]) & (step <= rec.recovered_at[None, :])

    def share(mask: np.ndarray) -> float | None:
        cols = mask[:, hit]
        return float((unused[:, hit] * cols).sum() / cols.sum()) if cols.sum() else None

    out.update(
        {
            "episodes_with_events": float(hit.mean()),
            "recovery": {"mean": r, "se": r_se, "never": float((rec.steps < 0).mean()) if rec.steps.size else 0.0},
            "unused_before_event": share(before),
            "unused_while_recovering": share(during),
        }
    )
    return out


def run_stress(
    policies: dict[str, tuple[Policy, Scenario]],
    events: tuple[EventSpec, ...],
    set_name: str,
    episodes: int,
    seed: int,
    out_dir: Path | None = None,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Every policy (name -> (policy, its scenario)) with and without `events`, on the same episodes; one row per
    policy with the figures of both (`stress_figures`). With `out_dir`, each run's reports (world.jsonl included:
    `htlm show` draws an episode with its events) go to out_dir/<set>/<policy>-<with|without>; `progress` counts
    the episodes run."""
    rows = []
    for name, (policy, sc) in policies.items():
        row: dict[str, Any] = {"set": set_name, "policy": name, "events": [e.label for e in events]}
        for tag, scenario in (("with", sc.with_events(events)), ("without", sc.replace(events=()))):
            ev = evaluate_run(policy, scenario, episodes, seed=seed, policy_name=name)
            row[tag] = stress_figures(ev)
            if out_dir is not None:
                write_reports(ev, out_dir / set_name / f"{name}-{tag}")
            if progress is not None:
                progress.update(progress.done + episodes, set=set_name, policy=f"{name} {tag} events")
        rows.append(row)
    return rows


def _cell(x: dict[str, float] | None, digits: int = 2) -> str:
    if x is None or x["mean"] != x["mean"]:
        return "-"
    return f"{x['mean']:.{digits}f} ± {x['se']:.{digits}f}"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def format_stress(rows: list[dict[str, Any]]) -> str:
    """The stress table as text: one block per set of events, one line per policy."""
    lines = []
    for set_name in dict.fromkeys(r["set"] for r in rows):
        block = [r for r in rows if r["set"] == set_name]
        lines.append(f"{set_name}: {'; '.join(block[0]['events'])}")
        lines.append(
            f"  {'policy':<12} {'completion':>14} {'fail':>7} {'no events':>14} {'fail':>7} {'hit':>7} "
            f"{'recovery':>14} {'never':>7} {'unused before':>14} {'while recov.':>13}"
        )
        for r in block:
            w, wo = r["with"], r["without"]
            lines.append(
                f"  {r['policy']:<12} {_cell(w['completion']):>14} {_pct(w['failure_rate']):>7} "
                f"{_cell(wo['completion']):>14} {_pct(wo['failure_rate']):>7} {_pct(w.get('episodes_with_events')):>7} "
                f"{_cell(w.get('recovery')):>14} {_pct(w.get('recovery', {}).get('never')):>7} "
                f"{_pct(w.get('unused_before_event')):>14} {_pct(w.get('unused_while_recovering')):>13}"
            )
    return "\n".join(lines)


CSV_COLUMNS = (
    "set",
    "policy",
    "completion",
    "completion_se",
    "failure_rate",
    "completion_without",
    "completion_without_se",
    "failure_rate_without",
    "episodes_with_events",
    "recovery",
    "recovery_se",
    "never_recovered",
    "unused_before_event",
    "unused_while_recovering",
)


def write_stress(rows: list[dict[str, Any]], out_dir: Path) -> dict[str, Path]:
    """stress.json, stress.csv and stress.png in out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "stress.json", "csv": out_dir / "stress.csv", "png": out_dir / "stress.png"}
    paths["json"].write_text(json.dumps(rows, indent=2) + "\n")
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            a, b = r["with"], r["without"]
            rec = a.get("recovery", {})
            w.writerow(
                [
                    r["set"],
                    r["policy"],
                    a["completion"]["mean"],
                    a["completion"]["se"],
                    a["failure_rate"],
                    b["completion"]["mean"],
                    b["completion"]["se"],
                    b["failure_rate"],
                    a.get("episodes_with_events", ""),
                    rec.get("mean", ""),
                    rec.get("se", ""),
                    rec.get("never", ""),
                    a.get("unused_before_event", ""),
                    a.get("unused_while_recovering", ""),
                ]
            )
    plot_stress(rows, paths["png"])
    return paths


def plot_stress(rows: list[dict[str, Any]], path: Path) -> None:
    """One panel per set of events: every policy's completion with and without the events (bars, ± SE), its
    failures and its mean time to recover written above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(r["set"] for r in rows))
    fig, axes = plt.subplots(1, len(sets), figsize=(4.6 * len(sets), 3.8), squeeze=False)
    for ax, set_name in zip(axes[0], sets, strict=True):
        block = [r for r in rows if r["set"] == set_name]
        x = np.arange(len(block))
        for k, (tag, colour) in enumerate((("without", "0.65"), ("with", "#c0392b"))):
            means = [r[tag]["completion"]["mean"] for r in block]
            ses = [r[tag]["completion"]["se"] for r in block]
            ax.bar(x + (k - 0.5) * 0.38, means, 0.38, yerr=ses, color=colour, label=f"{tag} the events", capsize=2)
        for i, r in enumerate(block):
            rec = r["with"].get("recovery")
            text = f"fail {100 * r['with']['failure_rate']:.1f} %"
            if rec is not None and rec["mean"] == rec["mean"]:
                text += f"\nrecover {rec['mean']:.1f}"
            ax.text(i, r["with"]["completion"]["mean"] + 0.6, text, ha="center", va="bottom", fontsize=7.5)
        ax.set_xticks(x, [r["policy"] for r in block], fontsize=8)
        ax.set_title(set_name, fontsize=9)
        ax.set_ylabel("completion step (mean ± SE)", fontsize=8)
        ax.margins(y=0.25)
    axes[0][0].legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
