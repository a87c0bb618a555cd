"""`htlm optimal`: the centralized fully observed optimum of a team (value iteration)."""

from __future__ import annotations

import argparse
import json
import time

from htlm_world.scenario import ScenarioError, builtin, load


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm optimal`."""
    p.add_argument("--team", default=None, help="a team of the scenario's `teams` (default: the scenario's `team`; paper: heterogeneous, semi-heterogeneous, homogeneous)")
    p.add_argument("--scenario", default=None, help="scenario YAML file (default: the built-in 'paper')")
    p.add_argument("--json", action="store_true", help="print JSON")


def run(args: argparse.Namespace) -> int:
    """Solve and print the expected completion step from the initial state."""
    from htlm_agent.baselines.optimal import solve

    try:
        sc = load(args.scenario, team=args.team) if args.scenario else builtin(args.team or "heterogeneous")
    except ScenarioError as e:
        raise SystemExit(f"htlm optimal: {e}") from None
    t0 = time.perf_counter()
    sol = solve(sc)
    out = {
        "scenario": sc.name,
        "team": sc.team,
        "horizon": sc.horizon,
        "expected_completion_step": round(sol.expected_completion, 4),
        "capability_vectors": int(sol.cap_vectors.shape[0]),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if args.json:
        print(json.dumps(out))
    else:
        print(
            f"{sc.team}: expected completion step of the centralized optimum = {sol.expected_completion:.2f} "
            f"(h = {sc.horizon}, {out['capability_vectors']} capability vectors, {out['seconds']} s)"
        )
    return 0
