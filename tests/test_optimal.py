"""`htlm optimal`: the centralized, fully observed optimum reproduces docs/model.md's reference figures."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from htlm_agent.baselines.optimal import solve
from htlm_world.scenario import builtin

REFERENCE = {"heterogeneous": 7.09, "semi-heterogeneous": 6.70, "homogeneous": 7.61}
SRC = Path(__file__).resolve().parent.parent / "src"


def _env() -> dict[str, str]:
    """The current environment, with the source packages importable even without an install."""
    paths = [str(SRC / pkg) for pkg in ("htlm_world", "htlm_agent", "htlm_msgs_py")]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def test_cli_reproduces_reference_figures() -> None:
    procs = {
        team: subprocess.Popen(
            [sys.executable, "-m", "htlm_agent.cli", "optimal", "--team", team, "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        for team in REFERENCE
    }  # the three solves run side by side
    for team, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        result = json.loads(out)
        assert result["team"] == team and result["horizon"] == 30
        assert round(result["expected_completion_step"], 2) == REFERENCE[team], result


def test_optimum_is_a_floor_for_the_horizon() -> None:
    sol = solve(builtin("homogeneous").replace(horizon=3))
    # nothing completes 4 tasks at level 4 in 3 steps (fire drops at most one level a step): every episode fails
    assert sol.expected_completion == pytest.approx(3.0)
