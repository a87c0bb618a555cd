"""`htlm stress`: a trained team (or a baseline) under a set of events (surges, new tasks, dropouts; docs/model.md,
Events) beside the same team without them and beside the baselines: completion, failures, time to recover, unused
capability before the event and while recovering. Writes stress.json, stress.csv and stress.png, and every run's
reports (world.jsonl: `htlm show OUT/SET/POLICY-with --episode E` draws an episode with its events).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from htlm_agent.baselines.heuristics import BASELINES
from htlm_agent.cli.common import checkpoint_run_dir

STRESSED_BASELINES = [b for b in BASELINES if b not in ("ht", "optimal")]
"""The baselines `htlm stress` runs, beside a team or as the team under stress: every baseline but the HT learner
(trained apart) and the optimum (it reads the true levels); QMDP only where the optimum can be computed."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm stress`."""
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy", metavar="DIR", help="a run directory or checkpoint of `htlm train`")
    who.add_argument(
        "--baseline",
        choices=STRESSED_BASELINES,
        help="stress a baseline instead of a trained team, on --scenario (default: the paper's operation)",
    )
    p.add_argument(
        "--scenario",
        default=None,
        metavar="FILE",
        help="with --baseline: a scenario file or the name of a shipped one (default: the paper's operation)",
    )
    p.add_argument(
        "--events",
        nargs="+",
        default=None,
        metavar="FILE|SET",
        help="events files (a list of events, or `events:`) or names of the scenario's stress sets "
        "(default: every stress set of the scenario)",
    )
    p.add_argument(
        "--baselines",
        nargs="*",
        default=["greedy", "auction"],
        choices=STRESSED_BASELINES,
        help="baselines beside the team (default: greedy auction)",
    )
    p.add_argument("--episodes", type=int, default=500, help="episodes per run (default: 500)")
    p.add_argument(
        "--seed", type=int, default=None, help="seed of the episodes (default: the run's seed; 0 with --baseline)"
    )
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="where to write (default: RUN/stress/seed{S}-{E}; with --baseline runs/stress-NAME-SCENARIO__S-E)",
    )
    p.add_argument("--json", action="store_true", help="print the rows as JSON on stdout (logs on stderr)")


def run(args: argparse.Namespace) -> int:
    """Evaluate and write the table."""
    from htlm_agent.experiments.baselines import make_baseline
    from htlm_agent.experiments.stress import format_stress, run_stress, write_stress
    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
    from htlm_agent.learning.learners import team_policy
    from htlm_agent.progress import Progress
    from htlm_agent.runtime.evaluate import importance_table
    from htlm_world.events import resolve_agent
    from htlm_world.scenario import ScenarioError, builtin, load, read_events

    if args.episodes < 1:
        raise SystemExit(f"htlm stress: --episodes must be >= 1, got {args.episodes}")
    try:
        if args.policy is not None:
            if args.scenario is not None:
                raise ScenarioError("--scenario goes with --baseline; a trained team brings its own scenario")
            ck = load_checkpoint(args.policy)
            base, seed = ck.scenario, ck.seed if args.seed is None else args.seed
        else:
            base, seed = load(args.scenario) if args.scenario else builtin(), 0 if args.seed is None else args.seed
        sc = base.replace(events=()).with_shipped_stress()
        names = args.events if args.events is not None else list(sc.stress)
        if not names:
            raise ScenarioError(f"scenario {sc.name!r} has no stress sets: give events files with --events FILE")
        sets = {Path(n).stem if Path(n).suffix else n: read_events(n, sc) for n in names}
        policies: dict[str, Any] = {}
        if args.policy is not None:
            policies["learned"] = (team_policy(ck), sc)
            out_default = checkpoint_run_dir(ck.path) / "stress" / f"seed{seed}-{args.episodes}"
        else:
            policies[args.baseline] = make_baseline(args.baseline, sc, seed=seed)
            out_default = Path("runs") / f"stress-{args.baseline}-{sc.name}__{seed}-{args.episodes}"
        for b in args.baselines:
            policies.setdefault(b, make_baseline(b, sc, seed=seed))
    except (CheckpointError, ScenarioError, ValueError) as e:
        raise SystemExit(f"htlm stress: {e}") from None
    stressed = next(iter(policies.values()))[0]
    if any(ev.agent == "most_important" for evs in sets.values() for ev in evs):
        table = importance_table(stressed, sc, min(args.episodes, 500), seed=seed)
        top = max(table["agents"], key=lambda a: a["zeta"])["agent"]
        sets = {k: resolve_agent(sc, evs, top) for k, evs in sets.items()}
        print(f"htlm stress: the most important agent of the team (ζ, Eq. 6) is {top}", file=sys.stderr)
    out = Path(args.out) if args.out else out_default
    progress = Progress(len(sets) * len(policies) * 2 * args.episodes, unit="episodes")
    rows = []
    for name, events in sets.items():
        rows += run_stress(policies, events, name, args.episodes, seed, out, progress)
    progress.close()
    paths = write_stress(rows, out)
    if args.json:
        print(json.dumps(rows))
    else:
        print(format_stress(rows))
        first = next(iter(sets))
        team = next(iter(policies))
        print(f"reports: {paths['png'].parent} (an episode: htlm show {out / first / (team + '-with')} --episode 0)")
    return 0
