"""`htlm reproduce --quick`: every figure, table and claim of the report is produced, and a finished configuration
is not retrained when the command runs again (a smoke test of the pipeline, not of the numbers)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

FIGURES = (
    "idle_effect.png",
    "reassign_effect.png",
    "behaviour.png",
    "inactivation.png",
    "baselines.png",
    "learning_curves.png",
    "resilience.png",
    "importance_predictor.png",
)


RUN_TIMEOUT = 600
"""Seconds one `htlm reproduce --quick` may take: about 150 on 2 quiet cores, twice that on a loaded machine."""


def _run(out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "htlm_agent.cli", "reproduce", "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT,
    )


@pytest.mark.slow  # CI budget: a quick reproduction trains 30 configurations (about 2 min): -m slow
@pytest.mark.timeout(2 * RUN_TIMEOUT + 60)  # two runs, each bounded by its own timeout, not the suite's 300 s
def test_quick_reproduction_produces_every_result(tmp_path: Path) -> None:
    out = tmp_path / "rep"
    p = _run(out)
    assert p.returncode == 0, p.stderr[-3000:]
    for f in (*FIGURES, "report.md", "results.json", "configs.csv"):
        assert (out / f).stat().st_size > 0, f
    data = json.loads((out / "results.json").read_text())
    assert [c["id"] for c in data["claims"]] == ["C1", "C2", "C3", "C4", "C5", "C5b", "Q"]
    assert all(isinstance(c["held"], bool) and c["numbers"] for c in data["claims"])
    assert set(data["importance"]) == {"heterogeneous", "semi-heterogeneous", "homogeneous"}
    # 9 configurations + the 2 of the first calibration + 4 for events, x 2 seeds, each with its own evaluation
    rows = (out / "configs.csv").read_text().strip().splitlines()[1:]
    assert len(rows) == 30
    assert sum(r.startswith("first-calibration_") for r in rows) == 4
    report = (out / "report.md").read_text()
    for f in FIGURES:
        assert f"({f})" in report
    assert "C5" in report and "QUICK" in report and "## 7. The first calibration" in report
    # the optimum baseline in the table is the value-iteration floor's neighbourhood, not a constant
    assert 5.0 < data["baselines"]["optimal"]["completion"][0] < 10.0
    assert {"random", "greedy", "auction", "optimal"} <= set(data["baselines"]) and "| auction |" in report
    # the teams under events, and importance judged as a predictor, in their own sections
    assert set(data["resilience"]["R_II, medium T_RP"]) == {"flare-up", "new-fire", "lose-most-important"}
    assert "## 8. The unexpected" in report and "## 9. Importance as a predictor" in report
    assert "before completion, while the mission is open" in data["claims"][0]["numbers"]
    # a second run reuses every finished configuration: no result file is rewritten
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/result.json")}
    assert len(stamps) == 30
    p2 = _run(out)
    assert p2.returncode == 0, p2.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/result.json")} == stamps
