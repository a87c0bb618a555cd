"""Argument helpers shared by the `htlm` verbs: the scenario options, run names and trained runs on disk.

Every verb module (`cli/<verb>.py`) defines `add_arguments(parser)` and `run(args) -> int`; what two verbs share
lives here, so `htlm train`, `htlm evaluate` and `htlm importance` read their options and name their runs alike.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from htlm_world.scenario import REASSIGN_COSTS, Scenario, builtin, load, read_events

TEAM_HELP = (
    "a team of the scenario's `teams` (default: the scenario's `team`; paper: heterogeneous, semi-heterogeneous, "
    "homogeneous)"
)
"""The help of every verb's --team."""


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """--team, --idle-incentive, --reassign, --credit, --scenario, --mode, --events."""
    g = p.add_argument_group("scenario")
    g.add_argument(
        "--team",
        default=None,
        help=TEAM_HELP,
    )
    g.add_argument(
        "--idle-incentive",
        type=float,
        default=None,
        metavar="X",
        help="scale of the idle incentive R_II; 0 turns it off (default: 1.0)",
    )
    g.add_argument(
        "--reassign",
        choices=list(REASSIGN_COSTS),
        default=None,
        help="reassignment penalty T_RP level (default: medium)",
    )
    g.add_argument(
        "--credit",
        choices=["team", "difference"],
        default=None,
        help="what R_comp credits each agent with: team (the paper) or difference (its own contribution; "
        "docs/model.md, Reward) (default: the scenario's, team)",
    )
    g.add_argument(
        "--roster",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the knowledge state holds which teammates were heard from at the last step, so the auction and the "
        "learners leave out a silent teammate (docs/model.md, Knowledge state) (default: the scenario's)",
    )
    g.add_argument(
        "--teammates",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the knowledge state holds where the teammates were at the last step (their last known assignments), "
        "so a learned team sees who covers what (docs/model.md, Knowledge state) (default: the scenario's)",
    )
    g.add_argument("--scenario", default=None, metavar="FILE", help="scenario YAML (default: the built-in 'paper')")
    g.add_argument(
        "--mode",
        choices=["htlm", "ht"],
        default=None,
        help="htlm (default) or ht: the HT Dec-POMDP baseline (no idle locations, R_LM = 0)",
    )
    g.add_argument(
        "--events",
        nargs="+",
        default=None,
        metavar="FILE|SET",
        help="events in every episode (surges, new tasks, dropouts; docs/model.md, Events): events files or names "
        "of the scenario's stress sets",
    )


def scenario_from_args(args: argparse.Namespace) -> Scenario:
    """The scenario the options describe: a file or the built-in one, then the team, R_II, T_RP and mode given."""
    sc = load(args.scenario, team=args.team) if args.scenario else builtin(args.team or "heterogeneous")
    if args.idle_incentive is not None:
        sc = sc.with_reward(idle_incentive=args.idle_incentive)
    if args.reassign is not None:
        sc = sc.with_reward(reassign_cost=REASSIGN_COSTS[args.reassign])
    if args.mode is not None:
        sc = sc.replace(mode=args.mode)
    if getattr(args, "roster", None) is not None:
        sc = sc.replace(roster=args.roster)
    if getattr(args, "teammates", None) is not None:
        sc = sc.replace(teammates=args.teammates)
    if getattr(args, "credit", None) is not None:
        sc = sc.with_credit(args.credit)
    return with_events_from_args(sc, args)


def with_events_from_args(sc: Scenario, args: argparse.Namespace) -> Scenario:
    """The scenario with the events of --events added to its own (files or stress sets, in the order given)."""
    names = getattr(args, "events", None) or []
    if not names:
        return sc
    sc = sc.with_shipped_stress()
    return sc.with_events(sc.events + tuple(e for n in names for e in read_events(n, sc)), " ".join(names))


def experiment_name(sc: Scenario) -> str:
    """A short name of a training configuration, e.g. heterogeneous-ii1-medium."""
    levels = {v: k for k, v in REASSIGN_COSTS.items()}
    tc = levels.get(sc.reward.reassign_cost, f"tc{sc.reward.reassign_cost:g}")
    base = sc.team if sc.name == "paper" else (f"{sc.name}-{sc.team}" if sc.team else sc.name)
    diff = "-diff" if sc.reward.credit == "difference" else ""
    return f"{base}-ii{sc.reward.idle_incentive:g}-{tc}{diff}" + ("-ht" if sc.mode == "ht" else "")


def run_name(experiment: str, seed: int) -> str:
    """{experiment}__{seed}__{timestamp}."""
    return f"{experiment}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}"


def checkpoint_run_dir(checkpoint_path: Path) -> Path:
    """The run directory of a loaded checkpoint (RUN/checkpoint -> RUN; a bare checkpoint directory is its own)."""
    return checkpoint_path.parent if checkpoint_path.name == "checkpoint" else checkpoint_path
