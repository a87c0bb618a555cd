"""Greedy evaluation of a team policy in the batched runtime, and the reports of `htlm evaluate` / `htlm importance`.

Every figure is a metric of docs/model.md (Metrics of one episode) computed by `htlm_world.metrics` from the recorded
trajectories; this module only runs the episodes, aggregates and writes files.
"""

from __future__ import annotations

import csv
import gc
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from htlm_agent.mind.context import Policy
from htlm_agent.mind.reward import confident_levels
from htlm_agent.runtime.team import Team, rollout
from htlm_world.metrics import EpisodeMetrics, episode_metrics, importance, mean_se
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray

MAX_BATCH = 1024
"""Episodes simulated at once; more are run in chunks (chunk c uses the episode index c for its seeds)."""


@dataclass
class Rollouts:
    """What `run_episodes` recorded of E episodes."""

    levels: IntArray  # (h+1, E, p) true levels, levels[0] the initial ones
    actions: IntArray  # (h, E, N) applied actions
    observations: IntArray  # (h, E, N) observed level of each agent's task, -1 when idle
    believed_complete: BoolArray  # (E,) every agent's belief says every task is at level 0 after the last step
    seconds: FloatArray  # (E,) wall time of the batch the episode ran in (as the world's log counts it)
    events: list[tuple[int, int, int]] = field(default_factory=list)
    """(step, episode, event index) of every scenario event that happened, in order."""


@dataclass
class Evaluation:
    """Result of `evaluate_run`: the aggregate metrics and the per-episode data."""

    metrics: dict[str, Any]
    episodes: EpisodeMetrics
    actions: IntArray  # (h, E, N)
    scenario: Scenario
    believed_complete: BoolArray  # (E,) every agent's belief says every task is at level 0 after the last step
    rollouts: Rollouts
    """The trajectories behind the metrics (written as world.jsonl by `write_reports`)."""


def run_episodes(
    policy: Policy,
    scenario: Scenario,
    episodes: int,
    seed: int = 0,
    inactive: tuple[int, ...] = (),
    batch: int = MAX_BATCH,
) -> Rollouts:
    """Run `episodes` episodes of `policy` in batches of at most `batch` (batch c from the episode index c, as batch c
    of a launch with `--batch` `batch` runs its episodes over ROS): true levels, actions, observations, whether every
    agent believes, after the last step, that every task is at level 0 (confident levels of the reward) and the
    seconds of each batch."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes!r}")
    if not 1 <= batch <= MAX_BATCH:
        raise ValueError(f"batch must be in 1..{MAX_BATCH}, got {batch!r}")
    levels, actions, observations, believed, seconds = [], [], [], [], []
    events: list[tuple[int, int, int]] = []
    chunk = 0
    left = episodes
    while left > 0:
        b = min(left, batch)
        t0 = time.perf_counter()
        team = Team(scenario, b, seed, episode=chunk, inactive=inactive)
        tr = rollout(team, policy)
        levels.append(tr.levels)
        actions.append(tr.actions)
        observations.append(tr.observations)
        believed.append((confident_levels(team.marg, team.tables.threshold) == 0).all(axis=(1, 2)))
        seconds.append(np.full(b, time.perf_counter() - t0))
        events += [(t, episodes - left + e, j) for t, e, j in team.events.log]
        left -= b
        chunk += 1
    return Rollouts(
        levels=np.concatenate(levels, axis=1),
        actions=np.concatenate(actions, axis=1),
        observations=np.concatenate(observations, axis=1),
        believed_complete=np.concatenate(believed),
        seconds=np.concatenate(seconds),
        events=events,
    )


def _ms(x: Any) -> dict[str, float]:
    m, se = mean_se(np.asarray(x, dtype=np.float64))
    return {"mean": m, "se": se}


def summarize(
    scenario: Scenario,
    em: EpisodeMetrics,
    seed: int,
    inactive: tuple[int, ...],
    policy_name: str,
    believed_complete: BoolArray | None = None,
) -> dict[str, Any]:
    """Aggregate per-episode metrics into the report dictionary (team and per agent).

    Besides the metrics of docs/model.md, "completion" holds `mean_completed` (mean over the completed episodes) and
    `false_completion_rate` (episodes that failed although every agent's belief says every task is done: agents that
    idle on a wrong belief, which no learning from the belief-based reward can correct).
    """
    n_ep = int(em.completion.shape[0])
    comp_mean, comp_se = mean_se(em.completion)
    ok = ~em.failed
    mean_completed = float(em.completion[ok].mean()) if ok.any() else None
    false_completion = float((em.failed & believed_complete).mean()) if believed_complete is not None else None
    agents = []
    for i, a in enumerate(scenario.agents):
        cap = scenario.total_capability(i)
        unused = em.agent_unused[:, i]
        agents.append(
            {
                "agent": a.name,
                "capabilities": {k.name: a.capability(k.uses) for k in scenario.kinds},
                "inactive": i in inactive,
                "unused_capability": _ms(unused),
                "unused_fraction": _ms(unused / cap) if cap > 0 else {"mean": 0.0, "se": 0.0},
                "idle_before_completion": _ms(em.agent_idle_before[:, i]),
                "reassign_before_completion": _ms(em.agent_reassign_before[:, i]),
            }
        )
        if em.agent_metres is not None and em.agent_driving is not None:
            agents[-1]["metres"] = _ms(em.agent_metres[:, i])
            agents[-1]["driving_steps"] = _ms(em.agent_driving[:, i])
    travel: dict[str, Any] = {}
    if em.agent_metres is not None and em.agent_driving is not None:  # docs/model.md, Travel
        travel = {
            "step_seconds": scenario.step_seconds,
            "mission_seconds": _ms(em.completion * scenario.step_seconds),
            "metres_per_agent": _ms(em.agent_metres.mean(axis=1)),
            "driving_share": _ms(em.agent_driving.mean(axis=1) / scenario.horizon),
        }
    return {
        "policy": policy_name,
        "scenario": scenario.name,
        "team": scenario.team,
        "mode": scenario.mode,
        "idle_incentive": scenario.reward.idle_incentive,
        "reassign_cost": scenario.reward.reassign_cost,
        "episodes": n_ep,
        "seed": seed,
        "inactive": [scenario.agents[i].name for i in inactive],
        "events": [e.label for e in scenario.events],
        "completion": {
            "mean": comp_mean,
            "se": comp_se,
            "failure_rate": float(em.failed.mean()),
            "mean_completed": mean_completed,
            "false_completion_rate": false_completion,
        },
        "unused_capability": _ms(em.unused_capability),
        "unused_fraction": _ms(em.unused_fraction),
        "unused_fraction_open": _ms(em.unused_open),
        "idle_before_completion": _ms(em.idle_before),
        "reassign_before_completion": _ms(em.reassign_before),
        **({"travel": travel} if travel else {}),
        "agents": agents,
    }


def evaluate_run(
    policy: Policy,
    scenario: Scenario,
    episodes: int = 500,
    seed: int = 0,
    inactive: tuple[int, ...] = (),
    policy_name: str = "",
    batch: int = MAX_BATCH,
) -> Evaluation:
    """Evaluate `policy` (greedy, as it acts) over `episodes` episodes: metrics and per-episode data.

    Args:
        policy: anything with act(Context) -> (B, N) actions.
        scenario: the operation (must be the one the policy was made for).
        episodes: number of episodes.
        seed: master seed of the evaluation episodes.
        inactive: agent indices forced to idle whatever they decide (no retraining).
        policy_name: label for reports.
        batch: episodes simulated at once (`run_episodes`).
    """
    ro = run_episodes(policy, scenario, episodes, seed, inactive, batch)
    em = episode_metrics(scenario, ro.levels, ro.actions)
    metrics = summarize(scenario, em, seed, inactive, policy_name or type(policy).__name__, ro.believed_complete)
    return Evaluation(metrics, em, ro.actions, scenario, ro.believed_complete, ro)


def evaluate(
    policy: Policy,
    scenario: Scenario,
    episodes: int = 500,
    seed: int = 0,
    inactive: tuple[int, ...] = (),
) -> dict[str, Any]:
    """The metrics dictionary of `evaluate_run` (team figures and an "agents" list)."""
    return evaluate_run(policy, scenario, episodes, seed, inactive).metrics


def write_reports(ev: Evaluation, out_dir: str | Path, settings: Any = None) -> dict[str, Path]:
    """Write metrics.json, summary.csv (one row per agent and one for the team), episodes.csv (one row per episode),
    world.jsonl (every episode's trajectory, `write_episode_log`), completion_hist.png and scenario.yaml (and
    settings.json of the learner, when given) into out_dir; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.yaml").write_text(yaml.safe_dump(ev.scenario.to_dict(), sort_keys=False))
    if settings is not None:
        (out / "settings.json").write_text(json.dumps(settings.to_dict(), indent=2) + "\n")
    m = ev.metrics
    paths = {
        "json": out / "metrics.json",
        "summary": out / "summary.csv",
        "episodes": out / "episodes.csv",
        "png": out / "completion_hist.png",
        "trajectories": out / EPISODE_LOG,
    }
    write_episode_log(ev, paths["trajectories"], run=out.resolve().name)
    paths["json"].write_text(json.dumps(m, indent=2) + "\n")
    cols = [
        "who",
        "unused_capability",
        "unused_capability_se",
        "unused_fraction",
        "unused_fraction_se",
        "idle_before_completion",
        "idle_before_completion_se",
        "reassign_before_completion",
        "reassign_before_completion_se",
        "completion",
        "completion_se",
        "failure_rate",
    ]
    with paths["summary"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for a in m["agents"]:
            w.writerow([a["agent"]] + [a[k][s] for k in cols[1:9:2] for s in ("mean", "se")] + ["", "", ""])
        w.writerow(
            ["team"]
            + [m[k][s] for k in cols[1:9:2] for s in ("mean", "se")]
            + [m["completion"]["mean"], m["completion"]["se"], m["completion"]["failure_rate"]]
        )
    em = ev.episodes
    names = [a.name for a in ev.scenario.agents]
    with paths["episodes"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "episode",
                "completion",
                "failed",
                "unused_capability",
                "unused_fraction",
                "idle_before_completion",
                "reassign_before_completion",
            ]
            + [f"unused_{n}" for n in names]
        )
        for e in range(em.completion.shape[0]):
            w.writerow(
                [
                    e,
                    int(em.completion[e]),
                    int(em.failed[e]),
                    f"{em.unused_capability[e]:.6g}",
                    f"{em.unused_fraction[e]:.6g}",
                    int(em.idle_before[e]),
                    int(em.reassign_before[e]),
                ]
                + [f"{x:.6g}" for x in em.agent_unused[e]]
            )
    plot_completion(ev, paths["png"])
    return paths


EPISODE_LOG = "world.jsonl"
"""The episode log's file name: the same as the world node's (htlm_world.protocol, `WorldEffects.episode_log`),
since its lines are the same records; `htlm show` reads both."""


LOG_BLOCK = 256
"""Episodes converted to Python lists together, then written one JSON line each."""


def write_episode_log(ev: Evaluation, path: Path, run: str) -> None:
    """One JSON line per episode, in the world's episode log format (what the world node writes to world.jsonl over
    ROS): {"run", "metrics": {episode, severity, completion, failed, unused_capability, unused_fraction, idle_before,
    reassign_before, absent, seconds}, "levels": (h+1, p), "actions": (h, N), "observations": (h, N)} and, when the
    scenario has events, "events": [[step, label], ...]. The levels are simulated, no agent is ever absent in
    process, and "seconds" is the wall time of the batch the episode ran in."""
    collecting = gc.isenabled()
    gc.disable()  # the many small lists made here hold no cycles: collecting on the way only costs time (half)
    try:
        with path.open("w") as f:
            for first in range(0, ev.rollouts.actions.shape[1], LOG_BLOCK):
                f.writelines(_log_lines(ev, run, first))
    finally:
        if collecting:
            gc.enable()


def _log_lines(ev: Evaluation, run: str, first: int) -> list[str]:
    """The episode log lines of episodes first .. first + LOG_BLOCK - 1 (`write_episode_log`)."""
    ro, em = ev.rollouts, ev.episodes
    block = slice(first, first + LOG_BLOCK)
    levels = ro.levels[:, block].transpose(1, 0, 2).tolist()
    actions = ro.actions[:, block].transpose(1, 0, 2).tolist()
    observations = ro.observations[:, block].transpose(1, 0, 2).tolist()
    columns = zip(
        em.completion[block].tolist(),
        em.failed[block].tolist(),
        em.unused_capability[block].tolist(),
        em.unused_fraction[block].tolist(),
        em.idle_before[block].tolist(),
        em.reassign_before[block].tolist(),
        np.round(ro.seconds[block], 6).tolist(),
        strict=True,
    )
    absent = [0] * ev.scenario.n_agents
    labels = [e.label for e in ev.scenario.events]
    happened: dict[int, list[list[Any]]] = {}
    for t, e, j in ro.events:
        if block.start <= e < block.stop:
            happened.setdefault(e - first, []).append([t, labels[j]])
    lines = []
    for i, (completion, failed, unused, fraction, idle, reassign, seconds) in enumerate(columns):
        metrics = {
            "episode": first + i,
            "severity": "simulated",
            "completion": completion,
            "failed": failed,
            "unused_capability": unused,
            "unused_fraction": fraction,
            "idle_before": idle,
            "reassign_before": reassign,
            "absent": absent,
            "seconds": seconds,
        }
        line = {
            "run": run,
            "metrics": metrics,
            "levels": levels[i],
            "actions": actions[i],
            "observations": observations[i],
        }
        if labels:
            line["events"] = happened.get(i, [])
        lines.append(json.dumps(line, separators=(",", ":")) + "\n")
    return lines


def plot_completion(ev: Evaluation, path: Path) -> None:
    """Histogram of completion steps (failures at h, marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = ev.scenario.horizon
    m = ev.metrics["completion"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.hist(ev.episodes.completion, bins=[x + 0.5 for x in range(h + 1)], color="tab:blue", edgecolor="white")
    ax.axvline(m["mean"], color="k", ls="--", lw=1)
    ax.set_xlabel("completion step")
    ax.set_ylabel("episodes")
    ax.set_title(
        f"{ev.metrics['policy']} ({ev.scenario.team}): mean {m['mean']:.2f} ± {m['se']:.2f}, "
        f"failures {m['failure_rate']:.1%}",
        fontsize=9,
    )
    ax.set_xlim(0.5, h + 0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----- agent importance -------------------------------------------------------------------------------------------


def importance_table(policy: Policy, scenario: Scenario, episodes: int = 500, seed: int = 0) -> dict[str, Any]:
    """The agent importance table (Eqs. 6-9) from `episodes` greedy episodes: per agent C_k and U_k for every kind k
    (keys "C_<kind>", "U_<kind>") and ζ; per kind ω ("omega", by kind name)."""
    imp = importance(scenario, run_episodes(policy, scenario, episodes, seed).actions)
    kinds = scenario.kind_names
    return {
        "scenario": scenario.name,
        "team": scenario.team,
        "episodes": episodes,
        "seed": seed,
        "kinds": list(kinds),
        "omega": {k: float(imp.omega[j]) for j, k in enumerate(kinds)},
        "agents": [
            {
                "agent": a.name,
                **{f"C_{k}": float(imp.capability[i, j]) for j, k in enumerate(kinds)},
                **{f"U_{k}": float(imp.usage[i, j]) for j, k in enumerate(kinds)},
                "zeta": float(imp.zeta[i]),
            }
            for i, a in enumerate(scenario.agents)
        ],
    }


def importance_columns(table: dict[str, Any]) -> list[str]:
    """The per-agent columns of an importance table: C_k for every kind, then U_k for every kind."""
    kinds = table.get("kinds") or list(table["omega"])
    return [f"C_{k}" for k in kinds] + [f"U_{k}" for k in kinds]


def format_importance(table: dict[str, Any]) -> str:
    """The importance table as text, the most important agent's row marked."""
    rows = table["agents"]
    cols = importance_columns(table)
    top = max(range(len(rows)), key=lambda i: rows[i]["zeta"]) if rows else -1
    widths = [max(8, len(c)) for c in cols]
    lines = [f"{'agent':<10} " + " ".join(f"{c:>{w}}" for c, w in zip(cols, widths, strict=True)) + f" {'zeta':>8}"]
    for i, r in enumerate(rows):
        mark = " *" if i == top else ""
        cells = [
            f"{r[c]:>{w}.0f}" if c.startswith("C_") else f"{r[c]:>{w}.2f}" for c, w in zip(cols, widths, strict=True)
        ]
        lines.append(f"{r['agent']:<10} " + " ".join(cells) + f" {r['zeta']:>8.2f}{mark}")
    om = ", ".join(f"omega_{k} = {v:.2f}" for k, v in table["omega"].items())
    lines.append(f"{om}  ({table['team']}, {table['episodes']} episodes; * most important)")
    return "\n".join(lines)


def write_importance(table: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """importance.json and importance.csv in out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "importance.json", "csv": out / "importance.csv"}
    paths["json"].write_text(json.dumps(table, indent=2) + "\n")
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        cols = importance_columns(table)
        omega = table["omega"]
        w.writerow(["agent", *cols, "zeta", *[f"omega_{k}" for k in omega]])
        for r in table["agents"]:
            w.writerow([r["agent"], *[r[c] for c in cols], r["zeta"], *omega.values()])
    return paths
