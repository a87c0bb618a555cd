"""The `htlm` command line: one subcommand per module, imported only when used (fast start, no torch for
`htlm optimal`)."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# numpy's matrix products on one thread unless the environment says otherwise (OpenBLAS reads it when numpy is first
# imported, after this): a team step's products are small, and a second BLAS thread spinning for a core that another
# process holds made them several times slower (docs/results/scale.md, "... and one BLAS thread").
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# subcommand -> (module implementing add_arguments(parser) and run(args) -> int, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "optimal": ("htlm_agent.cli.optimal", "expected completion step of the centralized fully observed optimum"),
    "train": ("htlm_agent.cli.train", "train a team (expert iteration unless told otherwise)"),
    "evaluate": ("htlm_agent.cli.evaluate", "evaluate a trained team or a baseline"),
    "importance": ("htlm_agent.cli.importance", "agent importance table (Eqs. 6-9)"),
    "stress": ("htlm_agent.cli.stress", "a trained team or a baseline under events (surges, dropouts)"),
    "bench": ("htlm_agent.cli.bench", "measure simulator, learner and ROS runtime speed"),
    "reproduce": ("htlm_agent.cli.reproduce", "regenerate the paper's results"),
    "launch": ("htlm_agent.cli.launch", "start a team over ROS 2 (world + one process per agent + trainer)"),
    "watch": ("htlm_agent.cli.watch", "live terminal view of a running team (ROS 2)"),
    "show": ("htlm_agent.cli.show", "picture of one episode of a run: true severities and every agent's decisions"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; with `only`, import just that subcommand's module."""
    parser = argparse.ArgumentParser(prog="htlm", description="HTLM: task allocation with load management")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or only == name:
            try:
                mod = importlib.import_module(module)
            except ModuleNotFoundError as e:
                if e.name != module:
                    raise
                continue
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `htlm`."""
    argv = sys.argv[1:] if argv is None else argv
    only = argv[0] if argv and argv[0] in COMMANDS else None
    parser = build_parser(only)
    args = parser.parse_args(argv)
    run = getattr(args, "_run", None)
    if run is None:
        parser.error(f"command {args.command!r} is not available in this build")
    return int(run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
