"""`htlm reproduce`: regenerate the paper's results with one command."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm reproduce`."""
    p.add_argument("--out", default="runs/reproduce", help="output directory (report.md, figures, tables, runs/)")
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test that every figure is produced")
    p.add_argument("--force", action="store_true", help="retrain configurations that already finished")
    p.add_argument("--jobs", type=int, default=1, help="training runs in parallel processes (one core each)")
    p.add_argument("--episodes", type=int, default=None, help="training episodes per run (default: the learner's)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="training seeds (default 0 1 2; quick: 0 1)")


def run(args: argparse.Namespace) -> int:
    """Run the reproduction and print where the report is and which claims held."""
    from htlm_agent.experiments.reproduce import reproduce

    out = Path(args.out)
    cmd = (
        "htlm " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["reproduce"] else "htlm reproduce"
    )
    data = reproduce(
        out,
        quick=args.quick,
        force=args.force,
        seeds=tuple(args.seeds) if args.seeds else None,
        command=cmd,
        jobs_in_parallel=args.jobs,
        episodes=args.episodes,
    )
    for c in data["claims"]:
        print(f"{c['id']}: {'held' if c['held'] else 'NOT held'} — {c['numbers']}")
    print(f"report: {out / 'report.md'} ({data['wall_time_s'] / 60:.1f} min)")
    return 0
