"""`htlm train`: train a team with decentralized deep Q-learning (Algorithm 1), in process.

Every field of `learner.Settings` is an option (generated from the dataclass, its docstring as help). A run directory
gets settings.json, scenario.yaml, progress.csv, tb/, checkpoint/, eval/ and result.json; without --out it is
runs/{experiment}__{seed}__{timestamp}.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from htlm_world.scenario import REASSIGN_COSTS, TEAMS, Scenario, ScenarioError, builtin, load

EXPLICIT = ("seed", "episodes")
"""Settings fields with a hand-written option (the others are generated)."""


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_settings_arguments(p: argparse.ArgumentParser) -> None:
    """One option per field of `learner.Settings` (default None: keep the Settings default)."""
    from htlm_agent.learning.settings import Settings, field_docs

    docs = field_docs(Settings)
    g = p.add_argument_group("learner settings (defaults: htlm_agent.learning.settings.Settings)")
    for f in dataclasses.fields(Settings):
        if f.name in EXPLICIT:
            continue
        help_text = f"{docs.get(f.name, '')} (default: {f.default})".replace("%", "%%")
        if f.name == "hidden":
            g.add_argument(_flag(f.name), type=_int_list, default=None, metavar="H1,H2", help=help_text)
        elif isinstance(f.default, bool):
            g.add_argument(_flag(f.name), action=argparse.BooleanOptionalAction, default=None, help=help_text)
        else:
            g.add_argument(_flag(f.name), type=type(f.default), default=None, metavar=f.name.upper(), help=help_text)


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers separated by commas, got {text!r}") from None


def settings_changes(args: argparse.Namespace) -> dict[str, Any]:
    """The Settings fields given on the command line."""
    from htlm_agent.learning.settings import Settings

    out = {}
    for f in dataclasses.fields(Settings):
        v = getattr(args, f.name, None)
        if v is not None:
            out[f.name] = v
    return out


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """--team, --idle-incentive, --reassign, --scenario, --mode."""
    g = p.add_argument_group("scenario")
    g.add_argument("--team", choices=sorted(TEAMS), default=None, help="built-in team (default: heterogeneous)")
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
    g.add_argument("--scenario", default=None, metavar="FILE", help="scenario YAML (default: the built-in 'paper')")
    g.add_argument(
        "--mode",
        choices=["htlm", "ht"],
        default=None,
        help="htlm (default) or ht: the HT Dec-POMDP baseline (no idle locations, R_LM = 0)",
    )


def scenario_from_args(args: argparse.Namespace) -> Scenario:
    """The scenario the options describe: a file or the built-in one, then the team, R_II, T_RP and mode given."""
    sc = load(args.scenario) if args.scenario else builtin(args.team or "heterogeneous")
    if args.scenario and args.team:
        sc = sc.replace(agents=builtin(args.team).agents, team=args.team)
    if args.idle_incentive is not None:
        sc = sc.with_reward(idle_incentive=args.idle_incentive)
    if args.reassign is not None:
        sc = sc.with_reward(reassign_cost=REASSIGN_COSTS[args.reassign])
    if args.mode is not None:
        sc = sc.replace(mode=args.mode)
    return sc


def experiment_name(sc: Scenario) -> str:
    """A short name of a training configuration, e.g. heterogeneous-ii1-medium."""
    levels = {v: k for k, v in REASSIGN_COSTS.items()}
    tc = levels.get(sc.reward.reassign_cost, f"tc{sc.reward.reassign_cost:g}")
    base = sc.team if sc.name == "paper" else f"{sc.name}-{sc.team}"
    return f"{base}-ii{sc.reward.idle_incentive:g}-{tc}" + ("-ht" if sc.mode == "ht" else "")


def run_name(experiment: str, seed: int) -> str:
    """{experiment}__{seed}__{timestamp}."""
    return f"{experiment}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm train`."""
    add_scenario_arguments(p)
    p.add_argument("--seed", type=int, default=None, help="master seed (default: 0)")
    p.add_argument("--episodes", type=int, default=None, help="training episodes in total (default: Settings)")
    p.add_argument(
        "--out", default=None, metavar="DIR", help="run directory (default: runs/{experiment}__{seed}__{timestamp})"
    )
    p.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR from its checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress line on stderr")
    p.add_argument("--no-tensorboard", action="store_true", help="no TensorBoard logs")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_settings_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Train and print where the run went and its final greedy evaluation."""
    import json

    from htlm_agent.experiments.train import RESUMABLE_CHANGES, train
    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
    from htlm_agent.learning.settings import Settings

    changes = settings_changes(args)
    try:
        if args.resume:
            given = [
                k
                for k in ("team", "idle_incentive", "reassign", "scenario", "mode", "out")
                if getattr(args, k) is not None
            ]
            bad = sorted(set(changes) - set(RESUMABLE_CHANGES)) + given
            if bad:
                raise SystemExit(
                    f"htlm train: --resume continues a run as it was; cannot change {bad} "
                    f"(only {list(RESUMABLE_CHANGES)})"
                )
            ck = load_checkpoint(args.resume)
            out = ck.path.parent if ck.path.name == "checkpoint" else Path(args.resume)
            settings = ck.settings.replace(**changes)
            sc = ck.scenario
        else:
            sc = scenario_from_args(args)
            settings = Settings(**changes)
            out = Path(args.out) if args.out else Path("runs") / run_name(experiment_name(sc), settings.seed)
        if not args.no_progress:
            print(
                f"htlm train: {'resuming' if args.resume else 'run'} {out} ({experiment_name(sc)}, seed "
                f"{settings.seed}, {settings.episodes} episodes)",
                file=sys.stderr,
            )
        res = train(
            sc,
            settings,
            out,
            progress=not args.no_progress,
            resume=bool(args.resume),
            tensorboard=not args.no_tensorboard,
        )
    except (ScenarioError, CheckpointError, FileExistsError) as e:
        raise SystemExit(f"htlm train: {e}") from None
    except ValueError as e:  # bad settings
        raise SystemExit(f"htlm train: {e}") from None
    if args.json:
        print(
            json.dumps(
                {
                    "out": str(res.out_dir),
                    "episodes": res.episodes,
                    "wall_time_s": round(res.wall_time, 2),
                    "train_time_s": round(res.train_time, 2),
                    "metrics": res.metrics,
                }
            )
        )
    else:
        print(f"run directory: {res.out_dir}")
    return 0
