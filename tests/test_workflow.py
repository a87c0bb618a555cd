"""The `htlm` workflow with tiny budgets: train, resume, evaluate (policies, baselines, inactivation), importance,
bench, and the messages for unusable checkpoints."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from htlm_agent.cli import main

TINY = [
    "--episodes",
    "32",
    "--envs",
    "16",
    "--learning-starts",
    "32",
    "--batch-size",
    "16",
    "--memory",
    "1000",
    "--hidden",
    "16,16",
    "--validate-every",
    "16",
    "--validate-episodes",
    "4",
    "--eval-episodes",
    "8",
    "--no-progress",
]


def htlm(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run `htlm argv...` in process; return stdout."""
    capsys.readouterr()
    assert main(list(argv)) == 0
    return capsys.readouterr().out


def htlm_fails(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run `htlm argv...` expecting it to stop with a message; return the message."""
    with pytest.raises(SystemExit) as e:
        main(list(argv))
    return str(e.value.code) + capsys.readouterr().err


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(["train", "--out", str(out), "--seed", "3", *TINY]) == 0
    return out


def test_train_writes_a_complete_run(run_dir: Path) -> None:
    for name in (
        "settings.json",
        "scenario.yaml",
        "progress.csv",
        "result.json",
        "checkpoint/meta.json",
        "checkpoint/agents.pt",
        "eval/metrics.json",
        "eval/summary.csv",
        "eval/episodes.csv",
        "eval/completion_hist.png",
    ):
        assert (run_dir / name).exists(), name
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))
    settings = json.loads((run_dir / "settings.json").read_text())
    assert settings["seed"] == 3 and settings["episodes"] == 32 and settings["hidden"] == [16, 16]
    rows = (run_dir / "progress.csv").read_text().splitlines()
    assert rows[0].startswith("episodes,") and [r.split(",")[0] for r in rows[1:]] == ["16", "32"]
    result = json.loads((run_dir / "result.json").read_text())
    assert result["metrics"]["episodes"] == 8


def test_train_resume_continues_the_run(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    run = shutil.copytree(run_dir, tmp_path / "run")
    out = json.loads(htlm(capsys, "train", "--resume", str(run), "--episodes", "48", "--no-progress", "--json"))
    assert out["episodes"] == 48
    rows = (run / "progress.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["16", "32", "48"]
    msg = htlm_fails(capsys, "train", "--resume", str(run), "--lr", "0.1")
    assert "cannot change ['lr']" in msg
    msg = htlm_fails(capsys, "train", "--out", str(run), *TINY)
    assert "already holds a run" in msg


def test_train_names_runs_and_rejects_bad_input(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    htlm(
        capsys,
        "train",
        "--team",
        "homogeneous",
        "--idle-incentive",
        "0",
        "--reassign",
        "high",
        "--seed",
        "7",
        "--no-tensorboard",
        "--episodes",
        "16",
        *TINY[2:],
    )
    (run,) = (tmp_path / "runs").iterdir()
    assert re.fullmatch(r"homogeneous-ii0-high__7__\d{8}-\d{6}", run.name), run.name
    assert "idle_incentive: 0.0" in (run / "scenario.yaml").read_text()
    assert "settings.lr: -1.0 must be > 0" in htlm_fails(capsys, "train", "--lr", "-1", *TINY)
    assert "invalid choice" in htlm_fails(capsys, "train", "--reassign", "extreme", *TINY)


def test_evaluate_a_trained_team(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = json.loads(
        htlm(capsys, "evaluate", "--policy", str(run_dir), "--episodes", "12", "--json", "--out", str(tmp_path / "ev"))
    )
    assert m["episodes"] == 12 and m["seed"] == 3 and m["policy"] == "htlm-dqn"
    for key in (
        "completion",
        "unused_capability",
        "unused_fraction",
        "idle_before_completion",
        "reassign_before_completion",
    ):
        assert key in m
    assert {"mean", "se", "failure_rate"} <= set(m["completion"])
    assert [a["agent"] for a in m["agents"]] == [f"agent{i}" for i in range(1, 6)]
    for name in ("metrics.json", "summary.csv", "episodes.csv", "completion_hist.png"):
        assert (tmp_path / "ev" / name).exists()
    assert len((tmp_path / "ev" / "episodes.csv").read_text().splitlines()) == 13
    text = htlm(capsys, "evaluate", "--policy", str(run_dir / "checkpoint"), "--episodes", "4")
    assert "completion step" in text and "agent5" in text
    assert (run_dir / "evaluations" / "seed3-4").is_dir()


def test_inactivated_agents_always_idle(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = json.loads(
        htlm(
            capsys,
            "evaluate",
            "--policy",
            str(run_dir),
            "--episodes",
            "8",
            "--json",
            "--inactivate",
            "agent2",
            "4",
            "--out",
            str(tmp_path / "ev"),
        )
    )
    assert m["inactive"] == ["agent2", "agent4"]
    by_name = {a["agent"]: a for a in m["agents"]}
    assert by_name["agent2"]["unused_fraction"]["mean"] == 1.0 and by_name["agent4"]["unused_fraction"]["mean"] == 1.0
    assert "unknown agent 'agent9'" in htlm_fails(
        capsys, "evaluate", "--policy", str(run_dir), "--inactivate", "agent9"
    )


@pytest.mark.parametrize("name", ["random", "greedy", "optimal"])
def test_evaluate_baselines(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = json.loads(
        htlm(capsys, "evaluate", "--baseline", name, "--episodes", "20", "--json", "--out", str(tmp_path / name))
    )
    assert m["policy"] == name and m["episodes"] == 20
    if name == "optimal":
        assert m["completion"]["failure_rate"] == 0.0 and m["completion"]["mean"] < 8.5


def test_evaluate_the_ht_learner(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    htlm(capsys, "train", "--mode", "ht", "--out", str(tmp_path / "ht"), "--no-tensorboard", *TINY)
    m = json.loads(
        htlm(
            capsys,
            "evaluate",
            "--baseline",
            "ht",
            "--ht-policy",
            str(tmp_path / "ht"),
            "--episodes",
            "8",
            "--json",
            "--out",
            str(tmp_path / "ev"),
        )
    )
    assert m["mode"] == "ht" and m["unused_fraction"]["mean"] == 0.0  # no idle locations in HT mode


def test_the_ht_baseline_refuses_an_htlm_checkpoint(run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    msg = htlm_fails(capsys, "evaluate", "--baseline", "ht", "--ht-policy", str(run_dir), "--episodes", "4")
    assert "not an HT learner" in msg


def test_importance_table(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t = json.loads(
        htlm(
            capsys, "importance", "--policy", str(run_dir), "--episodes", "10", "--json", "--out", str(tmp_path / "imp")
        )
    )
    assert set(t["omega"]) == {"fire", "rescue"}
    assert [set(a) for a in t["agents"]] == [{"agent", "C_fire", "C_rescue", "U_fire", "U_rescue", "zeta"}] * 5
    assert (tmp_path / "imp" / "importance.csv").exists() and (tmp_path / "imp" / "importance.json").exists()
    text = htlm(capsys, "importance", "--policy", str(run_dir), "--episodes", "4", "--out", str(tmp_path / "i2"))
    assert "omega_fire" in text and "zeta" in text


def test_unusable_checkpoints_stop_with_a_clear_message(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    msg = htlm_fails(capsys, "evaluate", "--policy", str(tmp_path / "nothing"))
    assert "htlm evaluate:" in msg and "missing checkpoint" in msg and "nothing" in msg
    import shutil

    bad = shutil.copytree(run_dir / "checkpoint", tmp_path / "bad")
    (bad / "agents.pt").write_bytes(b"garbage")
    msg = htlm_fails(capsys, "importance", "--policy", str(bad))
    assert "agents.pt: corrupt checkpoint file" in msg


def test_bench_json(capsys: pytest.CaptureFixture[str]) -> None:
    out = json.loads(htlm(capsys, "bench", "--json", "--seconds", "0.05", "--no-train"))
    for key in (
        "sim_agent_steps_per_s_B1",
        "sim_agent_steps_per_s_B1024",
        "team_agent_steps_per_s_B1",
        "team_agent_steps_per_s_B1024",
        "learner_updates_per_s",
    ):
        assert out[key] > 0, key
    for b in (128, 1024):  # the transition record's wire cost, binary beside JSON lists, in the same run
        w = out[f"transition_wire_B{b}"]
        assert all(w[f"{kind}_{op}_us"] > 0 for kind in ("binary", "json") for op in ("encode", "decode"))
        assert w["decode_ratio"] == pytest.approx(w["json_decode_us"] / w["binary_decode_us"], rel=0.05)
        assert w["encode_ratio"] == pytest.approx(w["json_encode_us"] / w["binary_encode_us"], rel=0.05)
        assert w["binary_chars"] < w["json_chars"]


def test_bench_measures_a_scenario_beside_the_papers_team(capsys: pytest.CaptureFixture[str]) -> None:
    out = json.loads(htlm(capsys, "bench", "--json", "--seconds", "0.05", "--no-train", "--scenario", "warehouse"))
    assert out["scenario"] == {"name": "warehouse", "team": "shift", "agents": 6, "sites": 3, "tasks": 7, "kinds": 3}
    assert out["team_agent_steps_per_s_B1024"] > 0 and out["paper_team_agent_steps_per_s_B1024"] > 0
    ratio = out["paper_team_agent_steps_per_s_B1024"] / out["team_agent_steps_per_s_B1024"]
    assert out["agent_step_cost_vs_paper_B1024"] == pytest.approx(ratio, abs=0.01)
    assert "bench: " in htlm_fails(capsys, "bench", "--no-train", "--scenario", "no-such-scenario")


def test_the_entry_point_runs(tmp_path: Path) -> None:
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "htlm_agent.cli",
            "evaluate",
            "--baseline",
            "greedy",
            "--episodes",
            "4",
            "--json",
            "--out",
            str(tmp_path / "g"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["policy"] == "greedy"
