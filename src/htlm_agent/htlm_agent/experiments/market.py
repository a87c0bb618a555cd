"""Learned vs the market (docs/results/market.md): on each scenario, the teams a user would
compare, on the same evaluation episodes: the token learner (`--learner tokens --credit difference`), the paper's
learner, greedy and the auction; then the same teams under the scenario's stress sets.

Every scenario runs with the roster on (`Scenario.roster`), so that the auction is the fair market that leaves a
silent teammate out, as Open-RMF reassigns the tasks of a robot that dropped out. Every learned team is trained in
process with `htlm train`'s code (`learning.run.train`) for each seed, and
evaluated on the seed's evaluation episodes, on which the baselines run too (their episodes are the same numbers:
the world's streams depend on the seed, not on the policy). Under a stress set, `htlm stress`'s figures
(`experiments.stress.run_stress`) with the most important agent named by the learned team's importance.

    python -m htlm_agent.experiments.market --scenarios paper warehouse --seeds 0 1 2 --out docs/results/market

writes market.json (every run), market.csv (one row per scenario, team and condition: mean over seeds ± SE),
tables.md (the same as Markdown) and market.png; a progress line on stderr per finished run. `--json` prints
market.json's rows on stdout only.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from htlm_agent.baselines.optimal import ProblemTooLarge
from htlm_agent.experiments.baselines import make_baseline
from htlm_agent.experiments.stress import run_stress
from htlm_agent.learning import learners
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.learners import team_policy
from htlm_agent.learning.run import train
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.context import Context
from htlm_agent.runtime.evaluate import evaluate, importance_table
from htlm_world.events import resolve_agent
from htlm_world.scenario import Scenario, load
from htlm_world.types import IntArray

LEARNERS: dict[str, dict[str, Any]] = {
    "tokens": {"settings": {"learner": "tokens"}, "credit": "difference"},
    "tokens-qmdp": {
        "settings": {"learner": "tokens", "imitate": "qmdp", "imitate_updates": 32, "hidden": (64, 64)},
        "credit": "difference",
    },
    "paper": {"settings": {}, "credit": None},
    "lookahead": {"settings": {"learner": "lookahead"}, "credit": None},
    "expert": {"settings": {"learner": "expert"}, "credit": None},
    "expert-no-travel": {"settings": {"learner": "expert"}, "credit": None, "blind": True},
}
"""The learned teams: `Settings.for_learner` changes and the credit of the scenario they train on; `blind`: trained
on the operation without its travel and acting in it with travel (`TravelBlind`), the default learner as it was
before travel was in the model."""


class TravelBlind:
    """A team policy trained on an operation without travel, acting in it with travel: it is shown the knowledge
    states without their places and arrivals (`knowledge.places`), as it learned them."""

    def __init__(self, policy: Any, blind: Scenario) -> None:
        """`policy` acts on knowledge states of `blind` (the operation without travel)."""
        self.policy, self.size = policy, blind.knowledge_size

    def act(self, ctx: Context) -> IntArray:
        """The policy's actions on the knowledge states cut to the layout it learned."""
        return np.asarray(self.policy.act(dataclasses.replace(ctx, knowledge=ctx.knowledge[..., : self.size])))


TRANSFER = ("tokens", "lookahead")
"""The learned teams `--transfer` trains once and acts with on changed operations (the first: its default)."""

BASELINES = ("greedy", "auction", "qmdp")
"""The teams a user would pick instead, and QMDP where the optimum can be computed (left out elsewhere): the
default of `--baselines`, which also takes `lookahead` (the auction improved by a learned value; slower)."""


def _baselines(sc: Scenario, seed: int, names: tuple[str, ...] = BASELINES) -> dict[str, tuple[Any, Scenario]]:
    """Every baseline of `names` that can be built for `sc` (QMDP needs the optimum: not on large scenarios)."""
    out: dict[str, tuple[Any, Scenario]] = {}
    for b in names:
        try:
            out[b] = make_baseline(b, sc, seed=seed)
        except ProblemTooLarge:
            _log(f"{sc.name}: no {b}: the optimum it needs is too large to compute")
    return out


def _log(text: str) -> None:
    print(f"market: {text}", file=sys.stderr, flush=True)


def _figures(metrics: dict[str, Any]) -> dict[str, float]:
    c = metrics["completion"]
    out = {
        "completion": float(c["mean"]),
        "failure_rate": float(c["failure_rate"]),
        "unused_fraction": float(metrics["unused_fraction"]["mean"]),
    }
    if "travel" in metrics:  # docs/model.md, Travel: the mission in seconds, the metres per agent
        out["mission_s"] = float(metrics["travel"]["mission_seconds"]["mean"])
        out["metres"] = float(metrics["travel"]["metres_per_agent"]["mean"])
    return out


def run_scenario(
    name: str,
    seeds: list[int],
    learners: list[str],
    episodes: int | None,
    eval_episodes: int,
    out: Path,
    stress: bool,
    changes: dict[str, Any] | None = None,
    idle_incentive: float | None = None,
    baselines: tuple[str, ...] = BASELINES,
) -> list[dict[str, Any]]:
    """Every run of one scenario: rows {scenario, team, condition, seed, completion, failure_rate, unused_fraction,
    recovery, train_s}. `changes`: settings of every learned team beyond its learner's (`--set`); `idle_incentive`:
    the scale of R_II of the scenario (`--idle-incentive`, default the scenario's); `baselines`: the baselines beside
    them (`--baselines`)."""
    sc = load(name).replace(roster=True)  # the auction is the fair market: it leaves a silent teammate out
    if idle_incentive is not None:
        sc = sc.with_reward(idle_incentive=idle_incentive)
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        teams: dict[str, tuple[Any, Any]] = {}
        for learner in learners:
            spec = LEARNERS[learner]
            lsc = sc.with_credit(spec["credit"]) if spec["credit"] else sc
            if spec.get("blind"):
                if not sc.travel:
                    _log(f"{name}: no {learner}: the operation has no travel")
                    continue
                lsc = lsc.without_travel()
            budget = {} if episodes is None else {"episodes": episodes}
            settings = Settings.for_learner(
                **{**spec["settings"], **(changes or {})}, seed=seed, eval_episodes=eval_episodes, **budget
            )
            run_dir = out / "runs" / f"{name}__{learner}__{seed}"
            t0 = time.perf_counter()
            res = train(lsc, settings, run_dir, progress=False, tensorboard=False)
            took = time.perf_counter() - t0
            rows.append({"scenario": name, "team": learner, "condition": "none", "seed": seed, "train_s": took})
            pol = team_policy(load_checkpoint(run_dir))
            if spec.get("blind"):  # acting in the operation with travel, on the same episodes as the others
                pol, lsc = TravelBlind(pol, lsc), sc
                res.metrics = evaluate(pol, sc, eval_episodes, seed=seed)
            rows[-1].update(_figures(res.metrics))
            teams[learner] = (pol, lsc)
            _log(f"{name} {learner} seed {seed}: {rows[-1]['completion']:.2f} steps in {took:.0f} s")
        for b, (pol, bsc) in _baselines(sc, seed, baselines).items():
            rows.append({"scenario": name, "team": b, "condition": "none", "seed": seed})
            rows[-1].update(_figures(evaluate(pol, bsc, eval_episodes, seed=seed)))
            teams[b] = (pol, bsc)
        if not stress:
            continue
        stressed = sc.with_shipped_stress()
        # the sets whose events surely happen (a set of chance events is for training)
        sets = {k: v for k, v in stressed.stress.items() if all(e.probability == 1.0 for e in v)}
        if any(ev.agent == "most_important" for evs in sets.values() for ev in evs):
            first = learners[0] if learners else "greedy"
            table = importance_table(teams[first][0], teams[first][1], min(eval_episodes, 500), seed=seed)
            top = max(table["agents"], key=lambda a: a["zeta"])["agent"]
            sets = {k: resolve_agent(stressed, evs, top) for k, evs in sets.items()}
        for set_name, events in sets.items():
            for r in run_stress(teams, events, set_name, eval_episodes, seed):
                w = r["with"]
                row = {"scenario": name, "team": r["policy"], "condition": set_name, "seed": seed}
                row.update(
                    {
                        "recovery_s": w.get("recovery", {}).get("mean", float("nan")) * max(sc.step_seconds, 1.0)
                        if sc.travel
                        else float("nan"),
                        "completion": w["completion"]["mean"],
                        "failure_rate": w["failure_rate"],
                        "unused_fraction": w["unused_fraction"]["mean"],
                        "recovery": w.get("recovery", {}).get("mean", float("nan")),
                        "never": w.get("recovery", {}).get("never", float("nan")),
                    }
                )
                rows.append(row)
            _log(f"{name} seed {seed}: stress set {set_name} done")
    return rows


def changed_operations(sc: Scenario) -> dict[str, Scenario]:
    """The changes a trained team meets without retraining: its last agent lost, an agent added (the first agent's
    twin), the first agent's capabilities rotated between the kinds it uses, and a site added (the first site's
    twin, further on). The changed scenarios keep no stress sets (they may name the agent that is lost)."""
    sc = sc.replace(stress={}, events=())
    first = sc.agents[0]
    names = list(first.capabilities)
    rotated = {names[(i + 1) % len(names)]: v for i, v in enumerate(first.capabilities.values())}
    site = sc.sites[0]
    far = max(s.position[0] for s in sc.sites) + 50.0
    return {
        "agent lost": sc.replace(agents=sc.agents[:-1]),
        "agent added": sc.replace(agents=(*sc.agents, dataclasses.replace(first, name=f"{first.name}_twin"))),
        "capabilities changed": sc.replace(agents=(dataclasses.replace(first, capabilities=rotated), *sc.agents[1:])),
        "site added": sc.replace(
            sites=(*sc.sites, dataclasses.replace(site, name=f"{site.name}_twin", position=(far, site.position[1])))
        ),
    }


def run_transfer(
    name: str, seed: int, episodes: int | None, eval_episodes: int, out: Path, learner: str = TRANSFER[0]
) -> list[dict[str, Any]]:
    """The team of `learner` (one of `TRANSFER`) trained once on `name`, acting on every `changed_operations` without
    retraining where its network can (`LearnerKind.transfer_policy`), beside a team retrained on the change, greedy
    and the auction, on the same episodes. The lookahead's value network reads every task's level, so it acts on a
    change that keeps the tasks (not a site added: its team is retrained only)."""
    spec = LEARNERS[learner]
    sc = load(name).replace(roster=True)
    sc = sc.with_credit(spec["credit"]) if spec["credit"] else sc
    budget = {} if episodes is None else {"episodes": episodes}
    settings = Settings.for_learner(**spec["settings"], seed=seed, eval_episodes=eval_episodes, **budget)
    base = out / "runs" / f"{name}__{learner}__transfer__{seed}"
    train(sc, settings, base, progress=False, tensorboard=False)
    ck = load_checkpoint(base)
    kind = learners.learner(settings.learner)
    rows = []
    for change, changed in changed_operations(sc).items():
        teams: dict[str, Any] = {}
        before = kind.transfer_policy(ck, changed)
        if before is not None:
            teams["trained before"] = before
        retrained = out / "runs" / f"{name}__{learner}__{change.replace(' ', '-')}__{seed}"
        t0 = time.perf_counter()
        train(changed, settings, retrained, progress=False, tensorboard=False, evaluate_at_end=False)
        took = time.perf_counter() - t0
        teams["retrained"] = team_policy(load_checkpoint(retrained))
        for b, (pol, _) in _baselines(changed, seed).items():
            teams[b] = pol
        for team, pol in teams.items():
            row = {"scenario": name, "learner": learner, "change": change, "team": team, "seed": seed}
            row.update(_figures(evaluate(pol, changed, eval_episodes, seed=seed)))
            if team == "retrained":
                row["train_s"] = took
            rows.append(row)
        _log(f"{name} {change}: " + ", ".join(f"{r['team']} {r['completion']:.2f}" for r in rows[-len(teams) :]))
    return rows


FIGURES = ("completion", "failure_rate", "unused_fraction", "recovery", "never", "train_s")
"""What every row may hold, averaged over seeds by `summarize`."""

TRAVEL_FIGURES = ("mission_s", "metres", "recovery_s")
"""And on an operation with travel: the mission and the recovery in seconds, the metres per agent."""


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean over seeds ± SE of every figure, per scenario, team and condition."""
    keys = list(dict.fromkeys((r["scenario"], r["condition"], r["team"]) for r in rows))
    out = []
    for sc, cond, team in keys:
        group = [r for r in rows if (r["scenario"], r["condition"], r["team"]) == (sc, cond, team)]
        row: dict[str, Any] = {"scenario": sc, "condition": cond, "team": team, "seeds": len(group)}
        for f in (*FIGURES, *TRAVEL_FIGURES):
            vals = np.array([r[f] for r in group if f in r and r[f] == r[f]], dtype=np.float64)
            if vals.size:
                row[f] = float(vals.mean())
                row[f + "_se"] = float(vals.std(ddof=1) / np.sqrt(vals.size)) if vals.size > 1 else 0.0
        out.append(row)
    return out


def tables(summary: list[dict[str, Any]]) -> str:
    """The summary as Markdown: one table per scenario, a row per condition and team."""

    def cell(r: dict[str, Any], f: str, pct: bool = False) -> str:
        if f not in r:
            return "-"
        if pct:
            return f"{100 * r[f]:.1f} %"
        se = r.get(f + "_se")
        return f"{r[f]:.2f}" + (f" ± {se:.2f}" if se else "")

    out = []
    for sc in dict.fromkeys(r["scenario"] for r in summary):
        travel = any("mission_s" in r for r in summary if r["scenario"] == sc)
        out += [
            f"### {sc}",
            "",
            "| condition | team | seeds | completion | failures | unused | recovery | never recovered |"
            + (" mission (s) | metres per agent | recovery (s) |" if travel else ""),
            "|---|---|---|---|---|---|---|---|" + ("---|---|---|" if travel else ""),
        ]
        for r in (x for x in summary if x["scenario"] == sc):
            cond = "no events" if r["condition"] == "none" else r["condition"]
            out.append(
                f"| {cond} | {r['team']} | {r['seeds']} | {cell(r, 'completion')} | {cell(r, 'failure_rate', True)} "
                f"| {cell(r, 'unused_fraction', True)} | {cell(r, 'recovery')} | {cell(r, 'never', True)} |"
                + (f" {cell(r, 'mission_s')} | {cell(r, 'metres')} | {cell(r, 'recovery_s')} |" if travel else "")
            )
        out.append("")
    return "\n".join(out)


def plot(summary: list[dict[str, Any]], path: Path) -> None:
    """One panel per scenario: each team's completion step (bars, ± SE over seeds) without events and under each
    stress set, its failure rate written above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = list(dict.fromkeys(r["scenario"] for r in summary))
    fig, axes = plt.subplots(len(scenarios), 1, figsize=(11, 3.2 * len(scenarios)), squeeze=False)
    colours = {
        "tokens": "#1f6f8b",
        "tokens-qmdp": "#16a085",
        "paper": "#7fb3d5",
        "expert": "#1a5276",
        "expert-no-travel": "#85c1e9",
        "greedy": "0.6",
        "auction": "#c0392b",
        "qmdp": "#8e44ad",
    }
    for ax, sc in zip(axes[:, 0], scenarios, strict=True):
        block = [r for r in summary if r["scenario"] == sc]
        conds = list(dict.fromkeys(r["condition"] for r in block))
        teams = list(dict.fromkeys(r["team"] for r in block))
        width = 0.8 / len(teams)
        for k, team in enumerate(teams):
            for i, cond in enumerate(conds):
                r = next((x for x in block if x["team"] == team and x["condition"] == cond), None)
                if r is None:
                    continue
                x = i + (k - (len(teams) - 1) / 2) * width
                ax.bar(
                    x,
                    r["completion"],
                    width,
                    yerr=r.get("completion_se", 0.0),
                    capsize=2,
                    color=colours.get(team, "0.3"),
                    label=team if i == 0 else None,
                )
                ax.text(x, r["completion"] + 0.3, f"{100 * r['failure_rate']:.0f}%", ha="center", fontsize=6.5)
        ax.set_xticks(range(len(conds)), ["no events" if c == "none" else c for c in conds], fontsize=8)
        ax.set_ylabel("completion step", fontsize=8)
        ax.set_title(f"{sc}: completion (mean ± SE over seeds; failures above)", fontsize=9)
        ax.margins(y=0.2)
        ax.legend(fontsize=7, ncol=len(teams), loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(out: Path, rows: list[dict[str, Any]]) -> None:
    """market.json (every run and the summary), market.csv, market.png and tables.md of the runs `rows`."""
    summary = summarize(rows)
    (out / "market.json").write_text(json.dumps({"runs": rows, "summary": summary}, indent=1) + "\n")
    fields = ["scenario", "condition", "team", "seeds"] + [
        f + s for f in (*FIGURES, *TRAVEL_FIGURES) for s in ("", "_se")
    ]
    with (out / "market.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(summary)
    plot(summary, out / "market.png")
    (out / "tables.md").write_text(tables(summary))


def main(argv: list[str] | None = None) -> int:
    """Run the comparison and write market.json, market.csv and market.png."""
    p = argparse.ArgumentParser(prog="python -m htlm_agent.experiments.market", description=__doc__.splitlines()[0])
    p.add_argument("--scenarios", nargs="+", required=True, help="shipped scenario names or files")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--learners", nargs="*", default=["tokens", "paper"], choices=list(LEARNERS))
    p.add_argument(
        "--episodes", type=int, default=None, help="training episodes of every learned team (default: its learner's)"
    )
    p.add_argument("--eval-episodes", type=int, default=500)
    p.add_argument(
        "--baselines", nargs="*", default=list(BASELINES), choices=[*BASELINES, "lookahead"], help="baselines beside"
    )
    p.add_argument("--no-stress", action="store_true", help="skip the stress sets")
    p.add_argument("--idle-incentive", type=float, default=None, metavar="X", help="scale of R_II (0: off)")
    p.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE", help="learner settings of every learned team (YAML values)"
    )
    p.add_argument("--out", default="runs/market")
    p.add_argument("--json", action="store_true", help="print the rows as JSON on stdout")
    p.add_argument(
        "--transfer",
        action="store_true",
        help="instead: train the team of each of --learners (tokens, lookahead; default tokens) on each scenario once "
        "(the first seed) and act on a changed team and operation without retraining, beside a team retrained on "
        "the change (transfer.json, transfer.csv)",
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]]
    if args.transfer:
        rows = [
            r
            for n in args.scenarios
            for learner in [x for x in args.learners if x in TRANSFER] or [TRANSFER[0]]
            for r in run_transfer(n, args.seeds[0], args.episodes, args.eval_episodes, out, learner)
        ]
        (out / "transfer.json").write_text(json.dumps(rows, indent=1) + "\n")
        with (out / "transfer.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, list(dict.fromkeys(k for r in rows for k in r)))
            w.writeheader()
            w.writerows(rows)
        if args.json:
            print(json.dumps(rows))
        return 0
    changes = {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set)}
    rows = []
    for name in args.scenarios:
        rows += run_scenario(
            name,
            args.seeds,
            args.learners,
            args.episodes,
            args.eval_episodes,
            out,
            not args.no_stress,
            changes,
            args.idle_incentive,
            tuple(args.baselines),
        )
        write_outputs(out, rows)
    if args.json:
        print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
