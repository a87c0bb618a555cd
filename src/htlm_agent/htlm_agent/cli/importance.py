"""`htlm importance`: the agent importance table of the paper (Eqs. 6-9) from greedy episodes of a trained team."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from htlm_agent.cli.common import checkpoint_run_dir


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm importance`."""
    p.add_argument("--policy", required=True, metavar="DIR", help="a run directory or checkpoint of `htlm train`")
    p.add_argument("--episodes", type=int, default=500, help="episodes E (default: 500)")
    p.add_argument("--seed", type=int, default=None, help="seed of the episodes (default: the run's seed)")
    p.add_argument("--json", action="store_true", help="print the table as JSON on stdout")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="where to write importance.csv/.json (default: RUN/importance/seed{S}-{E})",
    )


def run(args: argparse.Namespace) -> int:
    """Compute, print and write the table."""
    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
    from htlm_agent.learning.learners import team_policy
    from htlm_agent.runtime.evaluate import format_importance, importance_table, write_importance

    if args.episodes < 1:
        raise SystemExit(f"htlm importance: --episodes must be >= 1, got {args.episodes}")
    try:
        ck = load_checkpoint(args.policy)
    except CheckpointError as e:
        raise SystemExit(f"htlm importance: {e}") from None
    seed = ck.seed if args.seed is None else args.seed
    table = importance_table(team_policy(ck), ck.scenario, args.episodes, seed=seed)
    run_dir = checkpoint_run_dir(ck.path)
    out = Path(args.out) if args.out else run_dir / "importance" / f"seed{seed}-{args.episodes}"
    paths = write_importance(table, out)
    if args.json:
        print(json.dumps(table))
    else:
        print(format_importance(table))
        print(f"reports: {paths['csv'].parent}")
    return 0
