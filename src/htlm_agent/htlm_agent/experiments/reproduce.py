"""`htlm reproduce`: every result of the paper's Results section, from scratch, in the in-process runtime.

Reads top to bottom, one function per figure or table. Training runs are cached in OUT/runs/ and
never retrained unless forced; figures read the runs' results and never retrain.
"""

from __future__ import annotations

import csv
import json
import multiprocessing as mp
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.experiments.baselines import make_baseline
from htlm_agent.experiments.evaluate import evaluate, evaluate_run, importance_columns, importance_table
from htlm_agent.experiments.train import train
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.qpolicy import QPolicy
from htlm_agent.learning.settings import Settings
from htlm_agent.progress import Progress
from htlm_agent.runtime.team import Team, rollout
from htlm_world.metrics import mean_se
from htlm_world.scenario import REASSIGN_COSTS, Scenario, builtin, load

TEAM_NAMES = ("heterogeneous", "semi-heterogeneous", "homogeneous")


@dataclass(frozen=True)
class Config:
    """One trained configuration of the reproduction."""

    team: str
    idle: bool
    reassign: str
    mode: str = "htlm"
    base: str = "paper"
    """The shipped scenario the configuration starts from (`first-calibration`: the model's first numbers)."""

    @property
    def name(self) -> str:
        """Directory-safe name, e.g. heterogeneous_ii-on_rp-medium."""
        prefix = "" if self.base == "paper" else f"{self.base}_"
        if self.mode == "ht":
            return f"{prefix}{self.team}_ht"
        return f"{prefix}{self.team}_ii-{'on' if self.idle else 'off'}_rp-{self.reassign}"

    @property
    def label(self) -> str:
        """Human label for plots."""
        suffix = "" if self.base == "paper" else f" ({self.base})"
        if self.mode == "ht":
            return "HT Dec-POMDP" + suffix
        return f"{'R_II' if self.idle else 'no R_II'}, {self.reassign} T_RP" + suffix

    def scenario(self) -> Scenario:
        """The scenario of this configuration (docs/model.md defaults otherwise)."""
        sc = builtin(self.team, 1.0 if self.idle else 0.0, self.reassign, mode="ht" if self.mode == "ht" else "htlm")
        if self.base == "paper":
            return sc
        base = load(self.base)
        return base.replace(agents=sc.agents, team=sc.team, mode=sc.mode).with_reward(
            idle_incentive=sc.reward.idle_incentive, reassign_cost=sc.reward.reassign_cost
        )


HET = "heterogeneous"
IDLE_CONFIGS = [Config(HET, idle, rp) for rp in REASSIGN_COSTS for idle in (False, True)]
TEAM_CONFIGS = [Config(t, True, "medium") for t in TEAM_NAMES]
HT_CONFIG = Config(HET, False, "none", mode="ht")
FIRST_CONFIGS = [Config(HET, idle, "medium", base="first-calibration") for idle in (False, True)]
"""The model's first calibration, kept to show its failure mode beside the defaults."""


def all_configs() -> list[Config]:
    """Every configuration to train, without duplicates, in training order."""
    out: list[Config] = []
    for c in [*IDLE_CONFIGS, *TEAM_CONFIGS, HT_CONFIG, *FIRST_CONFIGS]:
        if c not in out:
            out.append(c)
    return out


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


# ----- the paper's claims -----------------------------------------------------------------------------------------


C2_TOLERANCE = 0.3
"""C2 holds when R_II costs at most this many steps of completion (none and medium T_RP)."""
C5_LEAST_COST, C5_MOST_COST = 0.5, 2.0
"""C5 holds when idling the least important agent costs at most 0.5 steps and the most important at least 2."""
QUALITY = {"completion": 8.5, "failure_rate": 0.005, "unused_fraction": 0.72}
"""The project's target for the default team (R_II, medium T_RP): 1.2 times the optimum 7.09, rare failures."""


def claims(idle: dict[str, Any], reassign: dict[str, Any], inact: dict[str, Any]) -> list[dict[str, Any]]:
    """C1-C5 of the paper, each held / not held with its numbers."""

    def cfg(idle_on: bool, rp: str) -> dict[str, Any]:
        return dict(idle[Config(HET, idle_on, rp).name])

    out = []
    on = cfg(True, "medium")["unused_fraction"][0]
    off = cfg(False, "medium")["unused_fraction"][0]
    out.append(
        {
            "id": "C1",
            "claim": "with R_II unused capability is a large share (paper ≈ 71%; held at ≥ 70%); without it "
            "nearly none (paper ≈ 2.5%; held at ≤ 10%)",
            "held": bool(on >= 0.70 and off <= 0.10),
            "numbers": f"medium T_RP: unused fraction {on:.1%} with R_II, {off:.1%} without",
        }
    )
    parts, ok = [], True
    for rp in ("none", "medium"):
        a, b = cfg(True, rp)["completion"], cfg(False, rp)["completion"]
        diff = a[0] - b[0]
        tol = C2_TOLERANCE
        ok &= diff <= tol
        parts.append(
            f"{rp}: {a[0]:.2f}±{a[1]:.2f} with vs {b[0]:.2f}±{b[1]:.2f} without (Δ {diff:+.2f}, tolerance {tol:.2f})"
        )
    out.append(
        {
            "id": "C2",
            "claim": f"under none and medium T_RP the idle incentive does not slow completion (held: at most "
            f"{C2_TOLERANCE} steps slower)",
            "held": bool(ok),
            "numbers": "; ".join(parts),
        }
    )
    hi, med = reassign["high"]["completion"], reassign["medium"]["completion"]
    d = hi[0] - med[0]
    out.append(
        {
            "id": "C3",
            "claim": "a high T_RP slows completion compared with medium",
            "held": bool(d > 2 * float(np.hypot(hi[1], med[1]))),
            "numbers": f"high {hi[0]:.2f}±{hi[1]:.2f} vs medium {med[0]:.2f}±{med[1]:.2f} (Δ {d:+.2f})",
        }
    )
    n, m = reassign["none"], reassign["medium"]
    more_idle = m["idle_before_completion"][0] > n["idle_before_completion"][0]
    fewer_moves = m["reassign_before_completion"][0] < n["reassign_before_completion"][0]
    dc = m["completion"][0] - n["completion"][0]
    same = abs(dc) <= max(2 * float(np.hypot(m["completion"][1], n["completion"][1])), 0.5)
    out.append(
        {
            "id": "C4",
            "claim": "medium T_RP vs none: more idling and fewer reassignments before completion at "
            "the same completion step",
            "held": bool(more_idle and fewer_moves and same),
            "numbers": f"idle {m['idle_before_completion'][0]:.2f} vs {n['idle_before_completion'][0]:.2f}; "
            f"reassignments {m['reassign_before_completion'][0]:.2f} vs {n['reassign_before_completion'][0]:.2f}; "
            f"completion {m['completion'][0]:.2f} vs {n['completion'][0]:.2f}",
        }
    )
    parts, ok = [], True
    for team, r in inact.items():
        a, lo, hi_ = r["completion_all"], r["completion_least_inactive"], r["completion_most_inactive"]
        lo_same = lo["mean"] - a["mean"] <= C5_LEAST_COST
        hi_worse = hi_["mean"] - a["mean"] >= C5_MOST_COST
        ok &= lo_same and hi_worse
        parts.append(
            f"{team}: all {a['mean']:.2f}, least ({r['least_important']}) off {lo['mean']:.2f}, "
            f"most ({r['most_important']}) off {hi_['mean']:.2f} (failures {hi_['failure_rate']:.0%})"
        )
    out.append(
        {
            "id": "C5",
            "claim": f"inactivating the least important agent leaves completion essentially unchanged (held: at "
            f"most {C5_LEAST_COST} steps slower); the most important one degrades it markedly (at least "
            f"{C5_MOST_COST} steps)",
            "held": bool(ok),
            "numbers": "; ".join(parts),
        }
    )
    q = cfg(True, "medium")
    fail = q["failure_rate"]
    out.append(
        {
            "id": "Q",
            "claim": f"quality target of the project (not a claim of the paper): with R_II and medium T_RP, "
            f"completion at most {QUALITY['completion']} steps, failures at most {QUALITY['failure_rate']:.1%}, "
            f"unused fraction at least {QUALITY['unused_fraction']:.0%}",
            "held": bool(
                q["completion"][0] <= QUALITY["completion"]
                and fail <= QUALITY["failure_rate"]
                and q["unused_fraction"][0] >= QUALITY["unused_fraction"]
            ),
            "numbers": f"completion {q['completion'][0]:.2f} ± {q['completion'][1]:.2f}, failures {fail:.1%}, "
            f"unused fraction {q['unused_fraction'][0]:.1%}",
        }
    )
    return out


# ----- the report -------------------------------------------------------------------------------------------------


def _git_commit() -> str:
    try:
        return (
            subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"],
                capture_output=True,
                text=True,
                cwd=Path(__file__).resolve().parent,
                timeout=10,
            ).stdout.strip()
            or "unknown"
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def write_report(out: Path, data: dict[str, Any], command: str, wall: float) -> None:
    """report.md: each figure beside the paper's statement it tests."""
    idle, reassign, inact, base, cl = (
        data["idle_effect"],
        data["reassign_effect"],
        data["importance"],
        data["baselines"],
        data["claims"],
    )
    seeds = data["seeds"]
    budget_note = "QUICK (smoke-test budgets; numbers are not meaningful)" if data["quick"] else "full budgets"
    lines = [
        "# HTLM: reproduction of the paper's results",
        "",
        f"Command: `{command}` · commit `{data['commit']}` · wall time {wall / 60:.1f} min · seeds {list(seeds)} · "
        f"{data['eval_episodes']} evaluation episodes per configuration · training episodes per run: "
        f"{data['train_episodes'] or 'the learner default'} · {budget_note}.",
        "",
        "Values are mean ± standard error across training seeds (with one seed: across evaluation episodes).",
        "",
        "## The paper's claims",
        "",
        "| claim | statement | held | numbers |",
        "|---|---|---|---|",
    ]
    for c in cl:
        lines.append(f"| {c['id']} | {c['claim']} | {'held' if c['held'] else '**not held**'} | {c['numbers']} |")
    lines += [
        "",
        "## 1. Effect of the idle incentive",
        "",
        "Paper: with R_II the team leaves about 71% of its capability unused, without it about 2.5%, and "
        "completion does not slow under none and medium T_RP.",
        "",
        "![idle effect](idle_effect.png)",
        "",
        "| configuration | completion step | unused capability per agent per step |",
        "|---|---|---|",
    ]
    for k, v in idle.items():
        lines.append(
            f"| {k} | {v['completion'][0]:.2f} ± {v['completion'][1]:.2f} | "
            f"{v['unused_capability'][0]:.3f} ± {v['unused_capability'][1]:.3f} |"
        )
    lines += [
        "",
        "## 2. Effect of the reassignment penalty",
        "",
        "Paper: medium T_RP gives more idling and fewer reassignments before completion at the same completion "
        "step as none; high T_RP slows completion.",
        "",
        "![reassign effect](reassign_effect.png)",
        "",
        "| T_RP | completion step | idle before completion | reassignments before completion |",
        "|---|---|---|---|",
    ]
    for k, v in reassign.items():
        lines.append(
            f"| {k} | {v['completion'][0]:.2f} ± {v['completion'][1]:.2f} | "
            f"{v['idle_before_completion'][0]:.2f} ± {v['idle_before_completion'][1]:.2f} | "
            f"{v['reassign_before_completion'][0]:.2f} ± {v['reassign_before_completion'][1]:.2f} |"
        )
    lines += [
        "",
        "## 3. Learned behaviour",
        "",
        "Paper: without load management agents keep working after tasks are done and move between sites; with "
        "R_II and medium T_RP they idle once the need is met and stay at their site.",
        "",
        "![behaviour](behaviour.png)",
        "",
        "## 4. Agent importance",
        "",
    ]
    for team, r in inact.items():
        t = r["importance"]
        cols = importance_columns(t)
        omega = ", ".join(f"ω_{k} = {v:.2f}" for k, v in t["omega"].items())
        lines += [
            f"**{team}** ({omega}; seed {t['seed']}; ζ mean over seeds in the last column)",
            "",
            "| agent | " + " | ".join(cols) + " | ζ | ζ (seeds) |",
            "|---" * (len(cols) + 3) + "|",
        ]
        for i, a in enumerate(t["agents"]):
            cells = [f"{a[c]:.0f}" if c.startswith("C_") else f"{a[c]:.2f}" for c in cols]
            lines.append(
                f"| {a['agent']} | " + " | ".join(cells) + f" | {a['zeta']:.2f} | {r['zeta_mean_over_seeds'][i]:.2f} ± "
                f"{r['zeta_se_over_seeds'][i]:.2f} |"
            )
        lines.append("")
    lines += [
        "## 5. Inactivation",
        "",
        "Paper: inactivating the least important agent leaves completion essentially unchanged; the most "
        "important one degrades it.",
        "",
        "![inactivation](inactivation.png)",
        "",
        "| team | all agents | least important inactive | most important inactive |",
        "|---|---|---|---|",
    ]
    for team, r in inact.items():
        a, lo, hi = r["completion_all"], r["completion_least_inactive"], r["completion_most_inactive"]
        lines.append(
            f"| {team} | {a['mean']:.2f} ± {a['se']:.2f} | {r['least_important']}: {lo['mean']:.2f} ± "
            f"{lo['se']:.2f} | {r['most_important']}: {hi['mean']:.2f} ± {hi['se']:.2f} "
            f"(failures {hi['failure_rate']:.1%}) |"
        )
    lines += [
        "",
        "## 6. Beyond the paper: baselines and learning curves",
        "",
        "random: uniform over Â; greedy: the belief heuristic; auction: the sequential single-item auction every "
        "agent runs on its own belief, keeping its own assignment (the market-based allocation of ROS robot teams); "
        "optimal: the centralized, fully observed optimum (docs/model.md, Baselines).",
        "",
        "![baselines](baselines.png)",
        "",
        "| policy | completion step | failure rate | unused fraction |",
        "|---|---|---|---|",
    ]
    for k, v in base.items():
        lines.append(
            f"| {k} | {v['completion'][0]:.2f} ± {v['completion'][1]:.2f} | {v['failure_rate']:.1%} | "
            f"{v['unused_fraction'][0]:.3f} ± {v['unused_fraction'][1]:.3f} |"
        )
    first = {c.label: base[c.label] for c in FIRST_CONFIGS if c.label in base}
    if first:
        lines += [
            "",
            "## 7. The first calibration",
            "",
            "The model's first numbers (shipped as the scenario `first-calibration`: perception accuracy 0.8, "
            "τ 0.6, b_th 0.8, an idle bonus that ignores the belief) beside the defaults. With them a team with "
            'the idle incentive stops checking once every task is believed done, so a wrong "all done" belief '
            "is never corrected: it completes later than the same team without R_II and fails more often. "
            "docs/model.md (Calibration) records why the defaults changed.",
            "",
            "| configuration | completion step | failure rate | unused fraction |",
            "|---|---|---|---|",
        ]
        for k, v in {**first, **{c.label: base[c.label] for c in IDLE_CONFIGS[2:4]}}.items():
            lines.append(
                f"| {k} | {v['completion'][0]:.2f} ± {v['completion'][1]:.2f} | {v['failure_rate']:.1%} | "
                f"{v['unused_fraction'][0]:.3f} ± {v['unused_fraction'][1]:.3f} |"
            )
    lines += [
        "",
        "![learning curves](learning_curves.png)",
        "",
        "Files: `results.json` (everything above), `configs.csv` (one row per configuration and seed), "
        "`runs/` (each training run: settings, scenario, progress.csv, checkpoint, evaluation).",
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))


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
    data = {
        "quick": quick,
        "seeds": list(budget.seeds),
        "train_episodes": budget.episodes,
        "eval_episodes": budget.eval_episodes,
        "commit": _git_commit(),
        "idle_effect": idle,
        "reassign_effect": reassign,
        "behaviour": behaviour,
        "importance": inact,
        "baselines": base,
    }
    data["claims"] = claims(idle, reassign, inact)
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
