"""`htlm train`: train a team with decentralized deep Q-learning (Algorithm 1), in process.

Every field of `learner.Settings` is an option (generated from the dataclass, its docstring as help). A run directory
gets settings.json, scenario.yaml, progress.csv, tb/, checkpoint/, eval/ and result.json; without --out it is
runs/{experiment}__{seed}__{timestamp}.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from htlm_agent.cli.common import add_scenario_arguments, experiment_name, run_name, scenario_from_args
from htlm_world.scenario import ScenarioError

EXPLICIT = ("seed", "episodes")
"""Settings fields with a hand-written option (the others are generated)."""


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_settings_arguments(p: argparse.ArgumentParser) -> None:
    """One option per field of `learner.Settings` (default None: keep the Settings default)."""
    from htlm_agent.learning.learners import DEFAULT_LEARNER, DEFAULT_Q_LEARNER, LEARNERS
    from htlm_agent.learning.settings import Settings
    from htlm_msgs_py.params import field_docs

    docs = field_docs(Settings)
    default_learner = (
        f"{DEFAULT_LEARNER}, or {DEFAULT_Q_LEARNER} given a setting the {DEFAULT_LEARNER} learner does not read"
    )
    g = p.add_argument_group(
        f"learner settings (defaults: the learner's preset over htlm_agent.learning.settings.Settings; the learner: "
        f"{default_learner})"
    )
    for f in dataclasses.fields(Settings):
        if f.name in EXPLICIT:
            continue
        default = default_learner if f.name == "learner" else f.default
        help_text = f"{docs.get(f.name, '')} (default: {default})".replace("%", "%%")
        if f.name == "learner":
            g.add_argument(_flag(f.name), choices=list(LEARNERS), default=None, help=help_text)
        elif f.name == "hidden":
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
    """Train and print where the run went and its final evaluation."""
    import json

    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
    from htlm_agent.learning.run import RESUMABLE_CHANGES, train
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
            settings = Settings(**Settings.for_users(changes))
            out = Path(args.out) if args.out else Path("runs") / run_name(experiment_name(sc), settings.seed)
        if not args.no_progress:
            print(
                f"htlm train: {'resuming' if args.resume else 'run'} {out} ({experiment_name(sc)}, seed "
                f"{settings.seed}, learner {settings.learner}, {settings.episodes} episodes)",
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
