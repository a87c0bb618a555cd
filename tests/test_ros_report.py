"""The main job's result: the learned team's row comes from the world's episode log, the baselines are evaluated,
and the table, CSV, JSON and PNG hold those numbers."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from htlm_agent.experiments.ros_report import ReportError, baseline_rows, learned_row, table, write_report
from htlm_world.scenario import builtin, load


def _world_log(path: Path, completions: list[int]) -> Path:
    lines = [
        json.dumps(
            {
                "run": "r",
                "metrics": {"episode": i, "completion": c, "failed": c >= 30, "unused_fraction": 0.5 + i / 100},
            }
        )
        for i, c in enumerate(completions)
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_report_rows_come_from_the_logged_episodes_and_the_evaluated_baselines(tmp_path: Path) -> None:
    row = learned_row(_world_log(tmp_path / "world.jsonl", [8, 10, 30, 12]))
    assert row["episodes"] == 4 and row["completion_mean"] == 15.0 and row["failure_rate"] == 0.25
    assert row["unused_fraction"] == pytest.approx(0.515) and row["completion_se"] > 0
    base = baseline_rows(builtin(), 20, seed=3)
    assert [r["policy"] for r in base] == ["random", "greedy", "auction", "qmdp", "lookahead (learner)", "optimal"]
    assert base[5]["completion_mean"] < base[1]["completion_mean"] < base[0]["completion_mean"]
    assert base[2]["completion_mean"] < base[0]["completion_mean"]
    doc = write_report(tmp_path, [row, *base], {"team": "heterogeneous", "seed": 3, "train_episodes": 4})
    with (tmp_path / "result.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["policy"] for r in rows] == [r["policy"] for r in doc["rows"]]
    assert float(rows[0]["completion_mean"]) == 15.0
    assert json.loads((tmp_path / "result.json").read_text())["rows"][1] == base[0]
    assert (tmp_path / "result.png").stat().st_size > 10_000
    assert "15.00 ±" in table(doc["rows"]).splitlines()[2]


def test_a_baseline_too_large_here_is_left_out_with_its_reason() -> None:
    skipped: dict[str, str] = {}
    base = baseline_rows(load("warehouse"), 10, seed=0, skipped=skipped)
    assert [r["policy"] for r in base] == ["random", "greedy", "auction", "lookahead (learner)"]  # no optimum
    assert list(skipped) == ["qmdp", "optimal"] and "too large to compute here" in skipped["optimal"]
    skipped = {}
    base = baseline_rows(load("facility-20"), 2, seed=0, skipped=skipped)  # 20 agents: the lookahead too
    assert [r["policy"] for r in base] == ["random", "greedy", "auction"]
    assert list(skipped) == ["qmdp", "lookahead", "optimal"] and "20 agents" in skipped["lookahead"]


def test_report_without_episodes_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match=r"world\.jsonl: no episode log"):
        learned_row(tmp_path / "world.jsonl")
    (tmp_path / "world.jsonl").write_text("\n")
    with pytest.raises(ReportError, match="no finished episode"):
        learned_row(tmp_path / "world.jsonl")


def test_launch_refuses_what_training_over_ros_cannot_do(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from htlm_agent.cli import main

    assert main(["launch", "train", "--set", "dropout=0.1", "--run-dir", str(tmp_path / "r")]) == 2
    assert "dropout=0.1" in capsys.readouterr().err
    assert main(["launch", "evaluate", "--policy", "greedy", "--batch", "3", "--first-episode", "4"]) == 2
    assert "--batch 3" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # nothing started


def test_the_baselines_run_the_episodes_of_the_launchs_batches() -> None:
    """In batches of 8, batch c is the episodes a launch with `--batch 8` runs as its batch c (`Team` of episode c):
    the baselines of a launch's report stand on the learned team's episodes, not on those of one batch of 20."""
    from htlm_agent.baselines.heuristics import GreedyPolicy
    from htlm_agent.runtime.evaluate import run_episodes
    from htlm_agent.runtime.team import Team, rollout
    from htlm_world.metrics import completion_step

    sc = builtin()
    ro = run_episodes(GreedyPolicy(sc), sc, 20, seed=3, batch=8)
    second = rollout(Team(sc, 8, 3, episode=1), GreedyPolicy(sc))
    assert (ro.levels[:, 8:16] == second.levels).all() and ro.levels.shape[1] == 20
    assert (ro.levels != run_episodes(GreedyPolicy(sc), sc, 20, seed=3).levels).any()
    greedy = baseline_rows(sc, 20, seed=3, batch=8)[1]
    assert greedy["policy"] == "greedy"
    comp, failed = completion_step(ro.levels)
    assert greedy["completion_mean"] == pytest.approx(np.where(failed, sc.horizon, comp).mean(), abs=1e-3)
    with pytest.raises(ValueError, match=r"batch must be in 1\.\.1024, got 0"):
        run_episodes(GreedyPolicy(sc), sc, 20, batch=0)
