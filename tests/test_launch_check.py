"""`htlm launch` checks its whole input before any process starts (htlm_agent.ros.launch_check): every problem of
the scenario file, the learner settings, the nodes' parameters and the checkpoint in one run, on stderr, naming the
file or option, the field and the value; exit code 2 and nothing started. No ROS process is needed."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.cli import main
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.settings import Settings
from htlm_agent.ros.launch import LaunchConfig, process_specs
from htlm_agent.ros.launch_check import NODES, check_launch, scenario_problems
from htlm_world.scenario import Scenario, builtin, load

GOOD_SCENARIO = "name: small\nhorizon: 10\n"
"""A valid scenario file: the built-in layout with a shorter horizon."""


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A valid checkpoint of the scenario GOOD_SCENARIO (an untrained learner)."""
    d = tmp_path_factory.mktemp("ckpt")
    (d / "small.yaml").write_text(GOOD_SCENARIO)
    with np.errstate(all="ignore"):
        return Learner(load(d / "small.yaml"), Settings(memory=1000, envs=1), seed=42).save(d / "checkpoint")


def _copy(ckpt: Path, dest: Path) -> Path:
    shutil.copytree(ckpt, dest)
    return dest


@pytest.fixture()
def no_process(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Record any attempt of the launcher to start a process (and refuse it)."""
    started: list[Any] = []

    def refuse(cmd: Any, *args: Any, **kwargs: Any) -> Any:
        started.append(cmd)
        raise AssertionError(f"a process was started: {cmd}")

    monkeypatch.setattr(subprocess, "Popen", refuse)  # the launcher starts every process with it
    return started


def test_every_problem_is_reported_at_once_and_nothing_starts(
    tmp_path: Path, checkpoint: Path, no_process: list[Any], capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = tmp_path / "bad.yaml"
    scenario.write_text("horizon: 0\ngamma: high\n")  # two bad fields: a range and a type
    ckpt = _copy(checkpoint, tmp_path / "ckpt")
    (ckpt / "agents.pt").write_bytes((ckpt / "agents.pt").read_bytes()[:100])  # truncated
    run_dir = tmp_path / "run"
    code = main(
        [
            "launch",
            "evaluate",
            "--scenario",
            str(scenario),
            "--checkpoint",
            str(ckpt),
            "--world-param",
            "act_deadline=-1.5",
            "--agent-param",
            "speed=3",
            "--run-dir",
            str(run_dir),
        ]
    )
    out = capsys.readouterr()
    assert code == 2
    assert out.out == ""  # the problems go to stderr
    lines = out.err.splitlines()
    assert all(line.startswith("htlm launch: ") for line in lines)
    assert f"{scenario}: horizon: 0 must be at least 1" in out.err
    assert f"{scenario}: gamma: expected `float`, got str 'high'" in out.err
    assert f"--checkpoint: {ckpt / 'agents.pt'}: corrupt checkpoint file" in out.err
    assert "--world-param: act_deadline: -1.5 must be in [0.001, 3600]" in out.err
    assert "--agent-param: speed: unknown parameter of agent_node (value 3); known: agent, policy," in out.err
    assert len(lines) == 5, out.err  # each once, though every agent gets the agent parameters
    assert no_process == []
    assert not run_dir.exists()


def test_a_good_configuration_has_no_problem(tmp_path: Path, checkpoint: Path) -> None:
    scenario = tmp_path / "small.yaml"
    scenario.write_text(GOOD_SCENARIO)
    cfg = LaunchConfig(
        mode="evaluate",
        scenario=load(scenario),
        scenario_file=str(scenario),
        run_dir=tmp_path / "run",
        checkpoint=str(checkpoint),
        learner={"lr": 0.001, "hidden": [64, 64]},
        world_params={"act_deadline": 1, "clock": "lockstep"},  # an int is taken for a float, as the node does
        agent_params={"epsilon": 0.0, "belief_every": 0},
        trainer_params={"round_deadline": 2.0},
    )
    assert check_launch(cfg) == []
    assert not cfg.run_dir.exists()


def test_a_checkpoint_of_another_team_or_with_corrupt_metadata_is_named(tmp_path: Path, checkpoint: Path) -> None:
    two = tmp_path / "two.yaml"
    two.write_text(GOOD_SCENARIO + "agents:\n  - {name: a1, fire: 3, rescue: 1}\n  - {name: a2, fire: 1, rescue: 3}\n")
    cfg = LaunchConfig(
        mode="deploy", scenario=load(two), scenario_file=str(two), run_dir=tmp_path / "run", checkpoint=str(checkpoint)
    )
    [problem] = check_launch(cfg)
    assert problem.startswith(f"--checkpoint: {checkpoint / 'meta.json'}: wrong agent count")
    ckpt = _copy(checkpoint, tmp_path / "ckpt")
    meta = json.loads((ckpt / "meta.json").read_text())
    (ckpt / "meta.json").write_text(json.dumps({**meta, "version": 99}))
    sc = load(checkpoint.parent / "small.yaml")
    cfg = LaunchConfig(mode="deploy", scenario=sc, run_dir=tmp_path / "run", checkpoint=str(ckpt))
    assert check_launch(cfg) == [f"--checkpoint: {ckpt / 'meta.json'}: checkpoint version 99, this build reads 1"]
    (ckpt / "meta.json").write_text("{")
    [problem] = check_launch(cfg)
    assert problem.startswith(f"--checkpoint: {ckpt / 'meta.json'}: corrupt checkpoint metadata (not valid JSON")


def test_the_checkpoint_is_checked_only_where_an_agent_loads_it(tmp_path: Path) -> None:
    missing = str(tmp_path / "nowhere")
    sc: Scenario = builtin()
    for mode, policy, only, problems in [
        ("evaluate", "auto", (), 1),
        ("evaluate", "greedy", (), 0),
        ("train", "auto", (), 0),  # the agents take the trainer's weights
        ("evaluate", "auto", ("world",), 0),  # no agent on this host
    ]:
        cfg = LaunchConfig(mode, sc, run_dir=tmp_path / "run", policy=policy, checkpoint=missing, only=only)
        assert len(check_launch(cfg)) == problems, (mode, policy, only)


def test_parameters_the_launcher_derives_are_named_by_their_process(tmp_path: Path) -> None:
    cfg = LaunchConfig(mode="evaluate", scenario=builtin(), run_dir=tmp_path / "run", seed=-3, policy="greedy")
    assert check_launch(cfg) == ["world parameter: seed: -3 must be in [0, 9223372036854775807]"]


def test_bad_learner_settings_are_all_named(tmp_path: Path) -> None:
    cfg = LaunchConfig(
        mode="train", scenario=builtin(), run_dir=tmp_path / "run", learner={"lr": "fast", "memory": 0, "envs": 1}
    )
    problems = check_launch(cfg)
    assert len(problems) == 2, problems
    assert problems[0] == "--set: settings.lr: expected `float`, got str 'fast'"
    assert problems[1].startswith("--set: settings.memory: 0")


def test_a_scenario_problem_on_a_required_field_is_reported_once(tmp_path: Path) -> None:
    f = tmp_path / "team.yaml"
    f.write_text("agents:\n  - {name: a1, fire: 9, rescue: 1}\n  - {name: a2, fire: 1, rescue: x}\nlevels: 1\n")
    assert scenario_problems(str(f)) == [
        f"{f}: agents[1].capabilities.rescue: expected an integer level, got 'x'",  # as htlm_world.scenario.load
        f"{f}: levels: 1 must be at least 2",
    ]  # no "agents[1].rescue: missing": a required field takes its whole list (and agents[0].fire) with it
    assert scenario_problems(str(tmp_path / "none.yaml"))[0].startswith(f"{tmp_path / 'none.yaml'}: cannot read")


def test_every_process_the_launcher_starts_has_its_parameters_checked(tmp_path: Path) -> None:
    cfg = LaunchConfig(mode="evaluate", scenario=builtin(), run_dir=tmp_path / "run", robots="sim")
    modules = {module for _, module, _ in process_specs(cfg)}
    assert modules <= set(NODES), modules - set(NODES)


def test_the_progress_of_a_launched_training_says_how_long_it_will_take(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from htlm_agent.ros.launch import _ProgressTail

    log = tmp_path / "world.log"
    log.write_text("[INFO] [1.0] [htlm_world]: run started\n")
    tail = _ProgressTail(log, total=1024, first=0)
    tail.poll()
    assert "about" not in capsys.readouterr().err  # no batch yet: nothing to estimate from
    with log.open("a") as f:  # the first batch waits for everyone to join: no estimate from it
        f.write("[INFO] [2.0] [htlm_world]: episodes 0..255: completion 22.26 (mean), 24 failed, absent [0], 9.50 s\n")
    tail.poll()
    assert "more of training" not in capsys.readouterr().err
    with log.open("a") as f:
        f.write("[INFO] [3.0] [htlm_world]: episodes 256..511: completion 20.00 (mean), 2 failed, absent [0], 2.50 s\n")
    tail.poll()
    err = capsys.readouterr().err
    assert "1,024 episodes in batches of 256" in err and "a batch takes 2.5 s: about 0:05 more of training" in err
    with log.open("a") as f:
        f.write("[INFO] [4.0] [htlm_world]: episodes 512..767: completion 19.00 (mean), 2 failed, absent [0], 2.00 s\n")
    tail.poll()
    tail.close()
    assert capsys.readouterr().err.count("more of training") == 0  # said once
