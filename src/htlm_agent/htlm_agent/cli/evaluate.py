"""`htlm evaluate`: greedy evaluation of a trained team (--policy) or a baseline (--baseline) in the batched simulator.

Reports the metrics of docs/model.md per team and per agent, and writes metrics.json, summary.csv, episodes.csv,
completion_hist.png, scenario.yaml and world.jsonl (every episode's true levels, actions and observations, in the
format of the world's episode log over ROS; `htlm show OUT --episode E` draws one). `--inactivate` makes agents
always idle, without retraining.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from htlm_agent.cli.common import (
    add_scenario_arguments,
    checkpoint_run_dir,
    experiment_name,
    run_name,
    scenario_from_args,
    with_events_from_args,
)
from htlm_world.scenario import Scenario, ScenarioError


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm evaluate`."""
    from htlm_agent.baselines.heuristics import BASELINES

    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy", metavar="DIR", help="a run directory or checkpoint of `htlm train`")
    who.add_argument(
        "--baseline",
        choices=list(BASELINES),
        help="random | greedy (belief heuristic) | auction (sequential single-item auction on each agent's "
        "belief) | qmdp (the optimum's values on each agent's belief; small operations only) | lookahead (the "
        "auction improved by a learned value on each agent's belief) | ht (HT Dec-POMDP learner) | optimal "
        "(centralized, fully observed: the floor)",
    )
    p.add_argument("--episodes", type=int, default=500, help="evaluation episodes (default: 500)")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="seed of the evaluation episodes (default: the run's seed for --policy, else 0)",
    )
    p.add_argument(
        "--inactivate", nargs="+", default=[], metavar="AGENT", help="agents (names, or numbers 1..N) that always idle"
    )
    p.add_argument("--json", action="store_true", help="print the metrics as JSON on stdout")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="where to write the reports (default: RUN/evaluations/... for --policy, else runs/...)",
    )
    p.add_argument(
        "--ht-policy",
        default=None,
        metavar="DIR",
        help="for --baseline ht: a checkpoint of `htlm train --mode ht` (default: train one now)",
    )
    add_scenario_arguments(p)


def parse_agents(sc: Scenario, names: list[str]) -> tuple[int, ...]:
    """Agent indices from names or 1-based numbers; SystemExit naming a bad one."""
    out = []
    known = [a.name for a in sc.agents]
    for x in names:
        if x in known:
            out.append(known.index(x))
        elif x.isdigit() and 1 <= int(x) <= len(known):
            out.append(int(x) - 1)
        else:
            raise SystemExit(f"htlm evaluate: --inactivate: unknown agent {x!r}; agents are {known} or 1..{len(known)}")
    return tuple(sorted(set(out)))


def format_metrics(m: dict[str, Any]) -> str:
    """The metrics as a table: team line, then one line per agent."""
    c = m["completion"]
    shown = [", ".join(f"{k} {v}" for k, v in a["capabilities"].items() if v) or "-" for a in m["agents"]]
    width = max(12, *(len(text) for text in shown))
    team = f"{m['scenario']}/{m['team']}" if m["team"] else m["scenario"]
    lines = [
        f"{m['policy']} · {team} · {m['mode']} · R_II x{m['idle_incentive']:g} · tc {m['reassign_cost']:g} · "
        f"{m['episodes']} episodes (seed {m['seed']})"
        + (f" · inactive: {', '.join(m['inactive'])}" if m["inactive"] else "")
        + (f" · events: {'; '.join(m['events'])}" if m.get("events") else ""),
        f"completion step {c['mean']:.2f} ± {c['se']:.2f} (failure rate {c['failure_rate']:.1%}, of which every agent "
        f"believed the operation complete {c['false_completion_rate']:.1%}; completed episodes "
        f"{'-' if c['mean_completed'] is None else format(c['mean_completed'], '.2f')})",
        f"unused capability per agent per step {m['unused_capability']['mean']:.3f} ± "
        f"{m['unused_capability']['se']:.3f} (fraction {m['unused_fraction']['mean']:.1%})",
        f"team idle count before completion {m['idle_before_completion']['mean']:.2f} · team reassignment count "
        f"before completion {m['reassign_before_completion']['mean']:.2f}",
        *(
            [
                f"mission time {tr['mission_seconds']['mean']:.0f} ± {tr['mission_seconds']['se']:.0f} s (steps of "
                f"{tr['step_seconds']:g} s) · driven per agent {tr['metres_per_agent']['mean']:.0f} m · on the way "
                f"{tr['driving_share']['mean']:.1%} of the steps"
            ]
            if (tr := m.get("travel"))
            else []
        ),
        f"{'agent':<10} {'capabilities':<{width}} {'unused':>8} {'fraction':>8} {'idle<=c':>8} {'reassign<=c':>11}",
    ]
    for a, caps in zip(m["agents"], shown, strict=True):
        lines.append(
            f"{a['agent'] + (' (off)' if a['inactive'] else ''):<10} {caps:<{width}} "
            f"{a['unused_capability']['mean']:>8.3f} {a['unused_fraction']['mean']:>8.1%} "
            f"{a['idle_before_completion']['mean']:>8.2f} {a['reassign_before_completion']['mean']:>11.2f}"
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Evaluate, print and write the reports."""
    from htlm_agent.experiments.baselines import make_baseline
    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
    from htlm_agent.learning.learners import team_policy
    from htlm_agent.runtime.evaluate import evaluate_run, write_reports

    if args.episodes < 1:
        raise SystemExit(f"htlm evaluate: --episodes must be >= 1, got {args.episodes}")
    try:
        if args.policy:
            given = [
                k
                for k in ("team", "idle_incentive", "reassign", "scenario", "mode", "ht_policy")
                if getattr(args, k) is not None
            ]
            if given:
                raise SystemExit(f"htlm evaluate: {given} apply to --baseline; a policy acts in its own scenario")
            ck = load_checkpoint(args.policy)
            sc = with_events_from_args(ck.scenario, args)
            policy: Any = team_policy(ck)
            learner_settings: Any = ck.settings
            name = "htlm-dqn" if sc.mode == "htlm" else "ht-dqn"
            seed = ck.seed if args.seed is None else args.seed
            run_dir = checkpoint_run_dir(ck.path)
            inactive = parse_agents(sc, args.inactivate)
            tag = f"seed{seed}-{args.episodes}" + (
                "-without-" + "-".join(sc.agents[i].name for i in inactive) if inactive else ""
            )
            out = Path(args.out) if args.out else run_dir / "evaluations" / tag
        else:
            seed = 0 if args.seed is None else args.seed
            learner_settings = None
            base = scenario_from_args(args)
            ht_out = None
            if args.baseline == "ht" and args.ht_policy is None:
                ht_out = Path("runs") / run_name(experiment_name(base.replace(mode="ht")), seed)
                print(
                    f"htlm evaluate: training the HT Dec-POMDP learner first (into {ht_out}; pass --ht-policy to "
                    "reuse one)",
                    file=sys.stderr,
                )
            policy, sc = make_baseline(
                args.baseline, base, seed=seed, ht_policy=args.ht_policy, ht_out=ht_out, progress=not args.json
            )
            name = args.baseline
            inactive = parse_agents(sc, args.inactivate)
            out = (
                Path(args.out)
                if args.out
                else Path("runs") / run_name(f"evaluate-{args.baseline}-{experiment_name(sc)}", seed)
            )
    except (ScenarioError, CheckpointError, ValueError) as e:
        raise SystemExit(f"htlm evaluate: {e}") from None
    ev = evaluate_run(policy, sc, args.episodes, seed=seed, inactive=inactive, policy_name=name)
    paths = write_reports(ev, out, settings=learner_settings)
    if args.json:
        print(json.dumps(ev.metrics))
    else:
        print(format_metrics(ev.metrics))
        where = paths["json"].parent
        print(f"reports: {where} (one episode as a picture: htlm show {where} --episode 0)")
    return 0
