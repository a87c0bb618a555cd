"""`htlm optimal`: the centralized fully observed optimum of a team (value iteration)."""

from __future__ import annotations

import argparse
import json
import sys
import time

from htlm_agent.cli.common import TEAM_HELP
from htlm_world.scenario import ScenarioError, builtin, load

PROGRESS_AFTER = 2.0
"""Estimated seconds from which the solve shows progress lines (rate, ETA) on stderr."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm optimal`."""
    from htlm_agent.baselines.optimal import DEFAULT_LIMITS

    p.add_argument(
        "--team",
        default=None,
        help=TEAM_HELP,
    )
    p.add_argument("--scenario", default=None, help="scenario YAML file (default: the built-in 'paper')")
    p.add_argument(
        "--max-minutes",
        type=float,
        default=DEFAULT_LIMITS.seconds / 60,
        help="refuse (exit 2, before building anything) a problem estimated to take longer "
        f"(default {DEFAULT_LIMITS.seconds / 60:g})",
    )
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=DEFAULT_LIMITS.memory_bytes / 2**30,
        help=f"refuse a problem estimated to need more memory, GiB (default {DEFAULT_LIMITS.memory_bytes / 2**30:g})",
    )
    p.add_argument("--json", action="store_true", help="print JSON (only JSON on stdout; progress goes to stderr)")
    p.epilog = "exit codes: 0 solved; 1 bad scenario; 2 bad option, or a problem over the limits (nothing built)"


def run(args: argparse.Namespace) -> int:
    """Estimate the problem (refuse it, exit 2, when over the limits), solve it and print the expected completion
    step from the initial state."""
    from htlm_agent.baselines.optimal import Limits, ProblemTooLarge, check, solve
    from htlm_world.model import Model

    try:
        sc = load(args.scenario, team=args.team) if args.scenario else builtin(args.team or "heterogeneous")
    except ScenarioError as e:
        raise SystemExit(f"htlm optimal: {e}") from None
    for name, value in (("--max-minutes", args.max_minutes), ("--max-memory-gb", args.max_memory_gb)):
        if not value > 0:
            print(f"htlm optimal: {name} {value!r}: must be > 0", file=sys.stderr)
            return 2
    limits = Limits(seconds=args.max_minutes * 60, memory_bytes=int(args.max_memory_gb * 2**30))
    try:
        est = check(Model.build(sc), limits)
    except ProblemTooLarge as e:
        print(f"htlm optimal: {e}; --max-minutes and --max-memory-gb raise the limits", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    sol = solve(sc, limits, progress=est.seconds >= PROGRESS_AFTER)
    out = {
        "scenario": sc.name,
        "team": sc.team,
        "horizon": sc.horizon,
        "expected_completion_step": round(sol.expected_completion, 4),
        "capability_vectors": int(sol.cap_vectors.shape[0]),
        "seconds": round(time.perf_counter() - t0, 3),
        "estimate": est.to_dict(),
    }
    if args.json:
        print(json.dumps(out))
    else:
        print(
            f"{sc.team}: expected completion step of the centralized optimum = {sol.expected_completion:.2f} "
            f"(h = {sc.horizon}, {out['capability_vectors']} capability vectors, {out['seconds']} s; estimated "
            f"at most {est.seconds:.1f} s)"
        )
    return 0
