"""`htlm reproduce`: every result of the paper's Results section, from scratch, in the in-process runtime.

Reads top to bottom, one function per figure or table. Training runs are cached in OUT/runs/ and
never retrained unless forced; figures read the runs' results and never retrain.
"""

from __future__ import annotations

import csv
import json
import multiprocessing as mp
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.experiments.baselines import make_baseline
from htlm_agent.experiments.configs import (
    FIRST_CONFIGS,
    HET,
    HT_CONFIG,
    IDLE_CONFIGS,
    STRESS_TEAMS,
    TEAM_NAMES,
    TRAINING_EVENTS,
    Config,
    all_configs,
)
from htlm_agent.experiments.report import claims, git_commit, write_report
from htlm_agent.experiments.stress import run_stress
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.qpolicy import QPolicy
from htlm_agent.learning.run import train
from htlm_agent.learning.settings import Settings
from htlm_agent.progress import Progress
from htlm_agent.runtime.evaluate import evaluate, evaluate_run, importance_table
from htlm_agent.runtime.team import Team, rollout
from htlm_world.events import resolve_agent
from htlm_world.metrics import mean_se, spearman
from htlm_world.scenario import REASSIGN_COSTS, EventSpec, Scenario, read_events


@dataclass(frozen=True)
class Budget:
    """Sizes of a reproduction run."""

    seeds: tuple[int, ...]
    """Training seeds (results are reported as mean ± SE across them)."""
    episodes: int | None
    """Training episodes per run (None: the learner's default)."""
    envs: int | None
    """Parallel training episodes (None: default)."""
    eval_episodes: int
    """Evaluation episodes per configuration (docs/model.md: 500)."""
    inactivation_episodes: int
    """Episodes per inactivation histogram (paper: 200)."""


FULL = Budget(seeds=(0, 1, 2), episodes=None, envs=None, eval_episodes=500, inactivation_episodes=200)
QUICK = Budget(seeds=(0, 1), episodes=128, envs=32, eval_episodes=20, inactivation_episodes=20)


# ----- training (cached) ------------------------------------------------------------------------------------------


def train_config(cfg: Config, seed: int, budget: Budget, runs: Path, force: bool) -> dict[str, Any]:
    """Train one configuration with one seed unless a finished run exists; returns its final evaluation metrics."""
    run_dir = runs / f"{cfg.name}__{seed}"
    done = run_dir / "result.json"
    if done.exists() and not force:
        return dict(json.loads(done.read_text()))
    if run_dir.exists():  # forced, or an unfinished run: start it again cleanly
        shutil.rmtree(run_dir)
    changes: dict[str, Any] = {"seed": seed, "eval_episodes": budget.eval_episodes}
    if "keep_replay" in Settings.__dataclass_fields__:  # the report needs the networks, not the replay memories
        changes["keep_replay"] = False
    if budget.episodes is not None:
        changes["episodes"] = budget.episodes
        changes["checkpoint_every"] = budget.episodes
    if budget.envs is not None:
        changes["envs"] = budget.envs
        changes["learning_starts"] = min(Settings().learning_starts, budget.envs * 4)
    settings = Settings().replace(**changes)
    res = train(cfg.scenario(), settings, run_dir, progress=False, tensorboard=False)
    out = {
        "config": cfg.name,
        "seed": seed,
        "train_time": res.train_time,
        "wall_time": res.wall_time,
        "metrics": res.metrics,
    }
    done.write_text(json.dumps(out, indent=2) + "\n")
    return out


def load_policy(run_dir: Path) -> Any:
    """The greedy team policy of a finished run."""
    return QPolicy.from_checkpoint(load_checkpoint(run_dir / "checkpoint"))


# ----- helpers ------------------------------------------------------------------------------------------------------


def seed_stats(results: list[dict[str, Any]], key: tuple[str, ...]) -> tuple[float, float, list[float]]:
    """Mean and SE across seeds of a metric; with one seed, the SE over episodes of that seed."""
    vals = []
    for r in results:
        x: Any = r["metrics"]
        for k in key:
            x = x[k]
        vals.append(float(x["mean"]) if isinstance(x, dict) else float(x))
    if len(vals) == 1:
        x = results[0]["metrics"]
        for k in key:
            x = x[k]
        return vals[0], float(x.get("se", 0.0)) if isinstance(x, dict) else 0.0, vals
    m, se = mean_se(np.array(vals))
    return m, se, vals


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ----- 1. and 2.: effect of the idle incentive and of the reassignment penalty --------------------------------------


def figure_idle_effect(res: dict[str, list[dict[str, Any]]], out: Path) -> dict[str, Any]:
    """Bars of completion step and unused capability for the 6 heterogeneous configurations."""
    plt = _plt()
    table = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    x = np.arange(len(REASSIGN_COSTS))
    for j, idle in enumerate((False, True)):
        comp, comp_se, un, un_se = [], [], [], []
        for rp in REASSIGN_COSTS:
            r = res[Config(HET, idle, rp).name]
            m, s, _ = seed_stats(r, ("completion",))
            u, us, _ = seed_stats(r, ("unused_capability",))
            comp.append(m)
            comp_se.append(s)
            un.append(u)
            un_se.append(us)
            f, fs, _ = seed_stats(r, ("unused_fraction",))
            table[Config(HET, idle, rp).name] = {
                "failure_rate": float(np.mean([x["metrics"]["completion"]["failure_rate"] for x in r])),
                "completion": [m, s],
                "unused_capability": [u, us],
                "unused_fraction": [f, fs],
            }
        lbl = "with R_II" if idle else "without R_II"
        axes[0].bar(x + (j - 0.5) * 0.38, comp, 0.38, yerr=comp_se, capsize=3, label=lbl)
        axes[1].bar(x + (j - 0.5) * 0.38, un, 0.38, yerr=un_se, capsize=3, label=lbl)
    for ax, yl in zip(axes, ("completion step", "unused capability per agent per step"), strict=True):
        ax.set_xticks(x, [f"{k} T_RP" for k in REASSIGN_COSTS])
        ax.set_ylabel(yl)
        ax.legend(fontsize=8)
    fig.suptitle("Effect of the idle incentive (heterogeneous team; mean ± SE)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "idle_effect.png", dpi=110)
    plt.close(fig)
    return table


def figure_reassign_effect(res: dict[str, list[dict[str, Any]]], out: Path) -> dict[str, Any]:
    """Completion step, idle count and reassignment count before completion for none/medium/high T_RP."""
    plt = _plt()
    keys = (
        ("completion", "completion step"),
        ("idle_before_completion", "team idle count before completion"),
        ("reassign_before_completion", "team reassignments before completion"),
    )
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    table: dict[str, Any] = {}
    for ax, (k, yl) in zip(axes, keys, strict=True):
        ms, ses = [], []
        for rp in REASSIGN_COSTS:
            m, s, _ = seed_stats(res[Config(HET, True, rp).name], (k,))
            ms.append(m)
            ses.append(s)
            table.setdefault(rp, {})[k] = [m, s]
        ax.bar(list(REASSIGN_COSTS), ms, yerr=ses, capsize=3, color=["tab:green", "tab:orange", "tab:red"])
        ax.set_ylabel(yl)
        ax.set_xlabel("T_RP")
    fig.suptitle("Effect of the reassignment penalty (heterogeneous team, with R_II; mean ± SE)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "reassign_effect.png", dpi=110)
    plt.close(fig)
    return table


# ----- 3. learned behaviour ---------------------------------------------------------------------------------------


def figure_behaviour(runs: Path, seed: int, out: Path, steps: int = 15) -> dict[str, Any]:
    """Decisions of agents 1 and 5 over the first `steps` steps of one seeded episode, over the true severities."""
    plt = _plt()
    cfgs = [Config(HET, False, "none"), Config(HET, True, "medium")]
    fig, axes = plt.subplots(len(cfgs), 1, figsize=(10, 3.2 * len(cfgs)))
    data: dict[str, Any] = {}
    for ax, cfg in zip(axes, cfgs, strict=True):
        sc = cfg.scenario()
        tr = rollout(Team(sc, 1, seed=seed, episode=0), load_policy(runs / f"{cfg.name}__{seed}"))
        levels = tr.levels[1 : steps + 1, 0]  # (steps, p)
        acts = tr.actions[:steps, 0]  # (steps, N)
        names = sc.action_names
        im = ax.imshow(
            levels.T,
            aspect="auto",
            cmap="Reds",
            vmin=0,
            vmax=sc.levels - 1,
            extent=(0.5, steps + 0.5, sc.n_tasks - 0.5, -0.5),
        )
        for k, (agent, mk, col) in enumerate(((0, "o", "tab:blue"), (4, "s", "tab:green"))):
            ys = [a if a < sc.n_tasks else sc.n_tasks + (a - sc.n_tasks) * 0.5 - 0.25 for a in acts[:, agent]]
            ax.plot(
                np.arange(1, steps + 1) + (k - 0.5) * 0.25,
                ys,
                mk,
                color=col,
                ms=7,
                label=f"{sc.agents[agent].name} decision",
            )
        ax.set_yticks(
            list(range(sc.n_tasks)) + [sc.n_tasks - 0.25, sc.n_tasks + 0.25],
            list(names[: sc.n_tasks]) + list(names[sc.n_tasks :]),
        )
        ax.set_ylim(sc.n_actions - 1, -0.5) if sc.n_idle else None
        ax.set_xlabel("step")
        ax.set_title(cfg.label, fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
        fig.colorbar(im, ax=ax, label="true severity")
        data[cfg.name] = {
            "levels": levels.tolist(),
            "agent1": acts[:, 0].tolist(),
            "agent5": acts[:, 4].tolist(),
            "action_names": list(names),
        }
    fig.tight_layout()
    fig.savefig(out / "behaviour.png", dpi=110)
    plt.close(fig)
    return data


# ----- 4. and 5.: importance and inactivation ---------------------------------------------------------------------


def importance_and_inactivation(runs: Path, seeds: tuple[int, ...], budget: Budget, out: Path) -> dict[str, Any]:
    """Importance tables for the three teams and the inactivation histograms (least / most important agent)."""
    plt = _plt()
    result: dict[str, Any] = {}
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    for col, team in enumerate(TEAM_NAMES):
        cfg = Config(team, True, "medium")
        sc = cfg.scenario()
        tables = [
            importance_table(load_policy(runs / f"{cfg.name}__{s}"), sc, budget.eval_episodes, seed=s) for s in seeds
        ]
        zetas = np.array([[a["zeta"] for a in t["agents"]] for t in tables])  # (seeds, N)
        zeta_m = zetas.mean(axis=0)
        least, most = int(np.argmin(zeta_m)), int(np.argmax(zeta_m))
        seed0 = seeds[0]
        pol = load_policy(runs / f"{cfg.name}__{seed0}")
        n = budget.inactivation_episodes
        full = evaluate_run(pol, sc, n, seed=1000)
        lo = evaluate_run(pol, sc, n, seed=1000, inactive=(least,))
        hi = evaluate_run(pol, sc, n, seed=1000, inactive=(most,))
        bins = np.arange(0.5, sc.horizon + 1.5)
        for row, (ev, who) in enumerate(((lo, least), (hi, most))):
            ax = axes[row, col]
            ax.hist(full.episodes.completion, bins=bins, alpha=0.55, label="all agents")
            ax.hist(
                ev.episodes.completion,
                bins=bins,
                alpha=0.55,
                label=f"{sc.agents[who].name} inactive ({'least' if row == 0 else 'most'} important)",
            )
            ax.set_title(f"{team}", fontsize=9)
            ax.legend(fontsize=7)
            ax.set_xlabel("completion step")
        result[team] = {
            "importance": tables[0],
            "zeta_mean_over_seeds": zeta_m.tolist(),
            "zeta_se_over_seeds": (zetas.std(axis=0, ddof=1) / np.sqrt(len(seeds))).tolist()
            if len(seeds) > 1
            else [0.0] * len(zeta_m),
            "least_important": sc.agents[least].name,
            "most_important": sc.agents[most].name,
            "completion_all": full.metrics["completion"],
            "completion_least_inactive": lo.metrics["completion"],
            "completion_most_inactive": hi.metrics["completion"],
            "hist_all": np.bincount(full.episodes.completion, minlength=sc.horizon + 1).tolist(),
            "hist_least_inactive": np.bincount(lo.episodes.completion, minlength=sc.horizon + 1).tolist(),
            "hist_most_inactive": np.bincount(hi.episodes.completion, minlength=sc.horizon + 1).tolist(),
        }
    fig.suptitle(
        f"Inactivation: completion over {budget.inactivation_episodes} episodes (seed-{seeds[0]} policies)", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(out / "inactivation.png", dpi=110)
    plt.close(fig)
    return result


# ----- 8. beyond the paper: the unexpected (events) and importance as a predictor ---------------------------------


def stress_sets(sc: Scenario) -> list[str]:
    """The scenario's stress sets (paper.yaml `stress`) every team of STRESS_TEAMS is put under: all but the one
    teams train with."""
    return [name for name in sc.stress if name != TRAINING_EVENTS]


STRESS_SEED = 1000
"""Seed of the stress episodes: every team meets the same worlds (common random numbers)."""


def resilience(runs: Path, seeds: tuple[int, ...], budget: Budget, out: Path) -> dict[str, Any]:
    """The premise of load management: every team of STRESS_TEAMS under every stress set, per training seed, with
    and without the events (`htlm stress`); mean ± SE across seeds of completion, failures, time to recover and the
    unused capability before the event and while recovering. The dropout set drops each team's own most important
    agent (ζ of that seed's policy)."""
    table: dict[str, Any] = {}
    for cfg in STRESS_TEAMS:
        sc = cfg.scenario().replace(events=())
        per_seed: dict[str, list[dict[str, Any]]] = {s: [] for s in stress_sets(sc)}
        for seed in seeds:
            pol = load_policy(runs / f"{cfg.name}__{seed}")
            imp = importance_table(pol, sc, budget.inactivation_episodes, seed=STRESS_SEED)
            top = max(imp["agents"], key=lambda a: a["zeta"])["agent"]
            for set_name in stress_sets(sc):
                events = resolve_agent(sc, read_events(set_name, sc), top)
                (row,) = run_stress({cfg.label: (pol, sc)}, events, set_name, budget.eval_episodes, STRESS_SEED)
                per_seed[set_name].append(row)
        table[cfg.label] = {s: _across_seeds(rows) for s, rows in per_seed.items()}
    plot_resilience(table, seeds, budget.eval_episodes, out / "resilience.png")
    return table


def plot_resilience(table: dict[str, Any], seeds: tuple[int, ...] | list[int], episodes: int, path: Path) -> None:
    """One column per stress set, one row of bars per team: completion with and without the events (top), and the
    share of episodes never recovered with the mean steps to recover written beside (bottom); mean ± SE over seeds."""
    plt = _plt()
    labels = list(table)
    sets = list(next(iter(table.values())))
    y = np.arange(len(labels))
    fig, axes = plt.subplots(2, len(sets), figsize=(4.2 * len(sets) + 2.6, 2.0 + 0.75 * len(labels)), sharey=True,
                             squeeze=False)  # fmt: skip
    for col, set_name in enumerate(sets):
        top, bottom = axes[0][col], axes[1][col]
        for k, (tag, colour) in enumerate((("with", "#c0392b"), ("without", "0.65"))):
            vals = [table[lb][set_name][f"completion_{tag}"] for lb in labels]
            top.barh(y + (k - 0.5) * 0.38, [v[0] for v in vals], 0.38, xerr=[v[1] for v in vals], color=colour,
                     capsize=2, label=f"{tag} the events")  # fmt: skip
        never = [100 * table[lb][set_name]["never_recovered"][0] for lb in labels]
        never_se = [100 * table[lb][set_name]["never_recovered"][1] for lb in labels]
        bottom.barh(y, never, 0.6, xerr=never_se, color="#2c7fb8", capsize=2)
        for i, lb in enumerate(labels):
            rec = table[lb][set_name]["recovery"][0]
            text = "-" if rec != rec else f"recovers in {rec:.1f}"
            bottom.text(never[i] + never_se[i] + 2.0, i, text, va="center", fontsize=7)
        bottom.set_xlim(0, 130)
        top.set_title(set_name, fontsize=10)
        top.set_xlabel("completion step", fontsize=8)
        bottom.set_xlabel("episodes never recovered (%)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_yticks(y, labels, fontsize=8)
    axes[0][0].invert_yaxis()  # the axes share y: once inverts them all
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="upper right", fontsize=8, ncol=2)
    fig.suptitle(f"Teams under events (mean ± SE over seeds {list(seeds)}, {episodes} episodes each)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _across_seeds(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One stress set's figures of one team, mean ± SE across the seeds' rows."""

    def stat(get: Any) -> list[float]:
        vals = np.array([get(r) for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        return list(mean_se(vals)) if vals.size else [float("nan"), 0.0]

    return {
        "events": rows[0]["events"],
        "completion_with": stat(lambda r: r["with"]["completion"]["mean"]),
        "completion_without": stat(lambda r: r["without"]["completion"]["mean"]),
        "failures_with": stat(lambda r: r["with"]["failure_rate"]),
        "failures_without": stat(lambda r: r["without"]["failure_rate"]),
        "recovery": stat(lambda r: r["with"]["recovery"]["mean"]),
        "never_recovered": stat(lambda r: r["with"]["recovery"]["never"]),
        "unused_before_event": stat(lambda r: r["with"]["unused_before_event"] or np.nan),
        "unused_while_recovering": stat(lambda r: r["with"]["unused_while_recovering"] or np.nan),
        "per_seed_completion_with": [r["with"]["completion"]["mean"] for r in rows],
    }


DROPOUT_STEP = 3
"""The step of the mid-episode dropout when importance is judged as a predictor."""


def importance_as_predictor(runs: Path, seeds: tuple[int, ...], budget: Budget, out: Path) -> dict[str, Any]:
    """For every agent of the three teams and every seed: ζ (Eq. 6) beside the cost of losing it, for the whole
    episode (inactive) and from step DROPOUT_STEP on (a dropout event); Spearman's rank correlation of ζ with each
    cost per team and seed, and whether the least important agent is the cheapest to lose."""
    plt = _plt()
    n = budget.inactivation_episodes
    result: dict[str, Any] = {}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for t_i, team in enumerate(TEAM_NAMES):
        cfg = Config(team, True, "medium")
        sc = cfg.scenario()
        rows = []
        for seed in seeds:
            pol = load_policy(runs / f"{cfg.name}__{seed}")
            zeta = [a["zeta"] for a in importance_table(pol, sc, n, seed=STRESS_SEED)["agents"]]
            base = evaluate_run(pol, sc, n, seed=STRESS_SEED).metrics["completion"]["mean"]
            full, mid = [], []
            for k, a in enumerate(sc.agents):
                full.append(
                    evaluate_run(pol, sc, n, seed=STRESS_SEED, inactive=(k,)).metrics["completion"]["mean"] - base
                )
                dropped = sc.with_events([EventSpec("dropout", agent=a.name, at=DROPOUT_STEP)])
                mid.append(evaluate_run(pol, dropped, n, seed=STRESS_SEED).metrics["completion"]["mean"] - base)
            least = int(np.argmin(zeta))
            rows.append(
                {
                    "seed": seed,
                    "zeta": zeta,
                    "cost_full": full,
                    "cost_dropout": mid,
                    "spearman_full": spearman(zeta, full),
                    "spearman_dropout": spearman(zeta, mid),
                    "least_is_cheapest_full": bool(full[least] == min(full)),
                    "least_is_cheapest_dropout": bool(mid[least] == min(mid)),
                }
            )
            for ax, cost in zip(axes, (full, mid), strict=True):
                ax.scatter(zeta, cost, s=18, color=f"C{t_i}", label=team if seed == seeds[0] else None)
        rho_f = [r["spearman_full"] for r in rows]
        rho_d = [r["spearman_dropout"] for r in rows]
        result[team] = {
            "agents": [a.name for a in sc.agents],
            "per_seed": rows,
            "spearman_full": list(mean_se(np.array(rho_f))),
            "spearman_dropout": list(mean_se(np.array(rho_d))),
            "least_is_cheapest_full": sum(r["least_is_cheapest_full"] for r in rows),
            "least_is_cheapest_dropout": sum(r["least_is_cheapest_dropout"] for r in rows),
        }
    for ax, title in zip(
        axes, ("agent inactive for the whole episode", f"agent drops out at step {DROPOUT_STEP}"), strict=True
    ):
        ax.set_xlabel("importance ζ (Eq. 6)")
        ax.set_ylabel("completion steps lost")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"Importance as a predictor of the cost of losing an agent (seeds {list(seeds)}, {n} episodes)", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(out / "importance_predictor.png", dpi=110)
    plt.close(fig)
    return result


# ----- 6. beyond the paper: baselines, learning curves ------------------------------------------------------------


def baselines(budget: Budget, res: dict[str, list[dict[str, Any]]], out: Path) -> dict[str, Any]:
    """Every learned heterogeneous configuration beside random, greedy, auction, HT Dec-POMDP and the optimum."""
    sc = Config(HET, True, "medium").scenario()
    rows: dict[str, Any] = {}
    for name in ("random", "greedy", "auction", "optimal"):
        policy, bsc = make_baseline(name, sc, seed=0)
        m = evaluate(policy, bsc, budget.eval_episodes, seed=0)
        rows[name] = {
            "completion": [m["completion"]["mean"], m["completion"]["se"]],
            "failure_rate": m["completion"]["failure_rate"],
            "unused_fraction": [m["unused_fraction"]["mean"], m["unused_fraction"]["se"]],
        }
    for cfg in [*IDLE_CONFIGS, HT_CONFIG, *FIRST_CONFIGS]:
        r = res[cfg.name]
        c = seed_stats(r, ("completion",))
        u = seed_stats(r, ("unused_fraction",))
        fails = [x["metrics"]["completion"]["failure_rate"] for x in r]
        rows[cfg.label] = {
            "completion": [c[0], c[1]],
            "failure_rate": float(np.mean(fails)),
            "unused_fraction": [u[0], u[1]],
            "per_seed_completion": c[2],
        }
    plt = _plt()
    names = list(rows)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4))
    for ax, key, yl in ((axes[0], "completion", "completion step"), (axes[1], "unused_fraction", "unused fraction")):
        ax.bar(range(len(names)), [rows[n][key][0] for n in names], yerr=[rows[n][key][1] for n in names], capsize=3)
        ax.set_xticks(range(len(names)), names, rotation=35, ha="right", fontsize=7)
        ax.set_ylabel(yl)
    axes[0].axhline(rows["optimal"]["completion"][0], color="k", ls="--", lw=1, label="centralized optimum")
    axes[0].legend(fontsize=7)
    fig.suptitle("Learned configurations beside the baselines (heterogeneous team)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "baselines.png", dpi=110)
    plt.close(fig)
    return rows


def learning_curves(runs: Path, seeds: tuple[int, ...], out: Path) -> None:
    """Running completion step and unused fraction during training, one line per configuration (seed mean)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for cfg in [*IDLE_CONFIGS, HT_CONFIG]:
        curves = []
        for s in seeds:
            rows = list(csv.DictReader((runs / f"{cfg.name}__{s}" / "progress.csv").open()))
            curves.append([(float(r["episodes"]), float(r["completion"]), float(r["unused_fraction"])) for r in rows])
        n = min(len(c) for c in curves)
        arr = np.array([c[:n] for c in curves])  # (seeds, n, 3)
        axes[0].plot(arr[0, :, 0], arr[:, :, 1].mean(axis=0), label=cfg.label)
        axes[1].plot(arr[0, :, 0], arr[:, :, 2].mean(axis=0), label=cfg.label)
    axes[0].set_ylabel("completion step (training episodes, ε-greedy)")
    axes[1].set_ylabel("unused capability fraction")
    for ax in axes:
        ax.set_xlabel("training episodes")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "learning_curves.png", dpi=110)
    plt.close(fig)


def reproduce(
    out: Path,
    quick: bool = False,
    force: bool = False,
    seeds: tuple[int, ...] | None = None,
    command: str = "htlm reproduce",
    jobs_in_parallel: int = 1,
    episodes: int | None = None,
) -> dict[str, Any]:
    """Train (or reuse) every configuration, then compute every figure and table and write the report."""
    t0 = time.perf_counter()
    budget = QUICK if quick else FULL
    if seeds is not None:
        budget = Budget(seeds, budget.episodes, budget.envs, budget.eval_episodes, budget.inactivation_episodes)
    if episodes is not None:
        budget = Budget(budget.seeds, episodes, budget.envs, budget.eval_episodes, budget.inactivation_episodes)
    out.mkdir(parents=True, exist_ok=True)
    runs = out / "runs"
    configs = all_configs()
    jobs = [(c, s) for c in configs for s in budget.seeds]
    bar = Progress(len(jobs), unit="run", log_interval=0.0)
    res: dict[str, list[dict[str, Any]]] = {c.name: [] for c in configs}
    results: dict[tuple[str, int], dict[str, Any]] = {}

    def record(k: int, c: Config, s: int, r: dict[str, Any]) -> None:
        results[(c.name, s)] = r
        m = r["metrics"]
        bar.update(
            k, last=f"{c.name}/{s}: completion {m['completion']['mean']:.2f}, unused {m['unused_fraction']['mean']:.0%}"
        )

    if jobs_in_parallel <= 1:
        for k, (c, s) in enumerate(jobs):
            bar.update(k, training=f"{c.name} seed {s}")
            record(k + 1, c, s, train_config(c, s, budget, runs, force))
    else:
        with ProcessPoolExecutor(jobs_in_parallel, mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(train_config, c, s, budget, runs, force): (c, s) for c, s in jobs}
            for k, fut in enumerate(as_completed(futures)):
                c, s = futures[fut]
                record(k + 1, c, s, fut.result())
    for c, s in jobs:
        res[c.name].append(results[(c.name, s)])
    bar.close()
    print("reproduce: computing figures", file=sys.stderr)
    idle = figure_idle_effect(res, out)
    reassign = figure_reassign_effect(res, out)
    behaviour = figure_behaviour(runs, budget.seeds[0], out)
    inact = importance_and_inactivation(runs, budget.seeds, budget, out)
    base = baselines(budget, res, out)
    learning_curves(runs, budget.seeds, out)
    print("reproduce: teams under events", file=sys.stderr)
    stress = resilience(runs, budget.seeds, budget, out)
    predictor = importance_as_predictor(runs, budget.seeds, budget, out)
    unused_open = {c.name: list(seed_stats(res[c.name], ("unused_fraction_open",))[:2]) for c in IDLE_CONFIGS}
    data: dict[str, Any] = {
        "quick": quick,
        "seeds": list(budget.seeds),
        "train_episodes": budget.episodes,
        "eval_episodes": budget.eval_episodes,
        "commit": git_commit(),
        "idle_effect": idle,
        "reassign_effect": reassign,
        "behaviour": behaviour,
        "importance": inact,
        "baselines": base,
        "resilience": stress,
        "importance_predictor": predictor,
        "unused_open": unused_open,
    }
    data["claims"] = claims(idle, reassign, inact, unused_open, predictor)
    wall = time.perf_counter() - t0
    data["wall_time_s"] = wall
    (out / "results.json").write_text(json.dumps(data, indent=2) + "\n")
    with (out / "configs.csv").open("w") as f:
        f.write(
            "config,seed,completion,completion_se,failure_rate,unused_fraction,idle_before,reassign_before,"
            "train_time_s\n"
        )
        for name, rs in res.items():
            for r in rs:
                m = r["metrics"]
                f.write(
                    f"{name},{r['seed']},{m['completion']['mean']:.4f},{m['completion']['se']:.4f},"
                    f"{m['completion']['failure_rate']:.4f},{m['unused_fraction']['mean']:.4f},"
                    f"{m['idle_before_completion']['mean']:.3f},{m['reassign_before_completion']['mean']:.3f},"
                    f"{r['train_time']:.1f}\n"
                )
    write_report(out, data, command, wall)
    return data
