"""The launcher (`launch_scripts/team.sh` = `htlm launch`): a team of 7 processes with a log file each, a summary,
a killed world started again, a clean stop on Ctrl-C with no orphaned process, and an exit code that says how the run
ended."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from support.ros import alive_with, next_domain

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]


def test_team_script_runs_an_evaluation(repo_root: Path, tmp_path: Path) -> None:
    run = tmp_path / "eval"
    r = subprocess.run(
        [
            str(repo_root / "launch_scripts" / "team.sh"),
            "evaluate",
            "--policy",
            "greedy",
            "--episodes",
            "2",
            "--domain-id",
            str(next_domain()),
            "--run-dir",
            str(run),
            "--json",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=100,
        check=False,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["episodes"] == 2 and summary["exit_code"] == 0 and summary["absent_agent_steps"] == 0
    logs = sorted(p.name for p in (run / "logs").iterdir())
    assert logs == ["agent1.log", "agent2.log", "agent3.log", "agent4.log", "agent5.log", "trainer.log", "world.log"]
    assert "episodes 0..1:" in (run / "logs" / "world.log").read_text()  # one batch of the two episodes
    assert alive_with(str(run)) == []


@pytest.mark.slow  # CI budget: the default run keeps the lookahead over ROS of test_equivalence; this one with -m slow
def test_agents_run_the_lookahead_each_with_its_own_value_network(tmp_path: Path) -> None:
    """`--policy lookahead`: every agent process fits the value network when it joins (before the first step, within
    the join timeout) and acts on its own belief; no agent misses a step and the team completes its episodes."""
    run = tmp_path / "eval"
    r = subprocess.run(
        [sys.executable, "-m", "htlm_agent.cli", "launch", "evaluate", "--policy", "lookahead", "--episodes", "8",
         "--batch", "8", "--domain-id", str(next_domain()), "--run-dir", str(run), "--json", "--quiet"],
        capture_output=True,
        text=True,
        timeout=110,
        check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["episodes"] == 8 and summary["absent_agent_steps"] == 0, summary
    for i in range(1, 6):
        assert "policy lookahead" in (run / "logs" / f"agent{i}.log").read_text()
    assert summary["completion_mean"] < 15.0, summary  # random: 21.5, greedy: 10.1


def test_json_is_the_only_output_on_stdout(tmp_path: Path) -> None:
    """`htlm launch ... --json | jq .` works: the world's episode lines and the launcher's messages go to stderr."""
    run = tmp_path / "eval"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "htlm_agent.cli",
            "launch",
            "evaluate",
            "--policy",
            "greedy",
            "--episodes",
            "2",
            "--batch",
            "2",
            "--domain-id",
            str(next_domain()),
            "--run-dir",
            str(run),
            "--json",  # not --quiet: the episode lines are echoed, on stderr
        ],
        capture_output=True,
        text=True,
        timeout=100,
        check=False,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads(r.stdout)  # the whole of stdout is one JSON document
    assert {"mode", "run_dir", "exit_code", "episodes", "completion_mean", "failure_rate"} <= summary.keys()
    assert summary["mode"] == "evaluate" and summary["episodes"] == 2 and summary["exit_code"] == 0
    assert "[world] episodes 0..1:" in r.stderr and "htlm launch evaluate:" in r.stderr
    assert alive_with(str(run)) == []


@pytest.mark.slow  # CI budget: the default run keeps the launcher's other tests; this one with -m slow
def test_a_killed_world_is_restarted_and_ctrl_c_stops_every_process(repo_root: Path, tmp_path: Path) -> None:
    """The team outlives its world: SIGKILLed, it is started again and the run goes on; then Ctrl-C stops it all."""
    run = tmp_path / "deploy"
    said = tmp_path / "launcher.out"
    with open(said, "wb") as out:
        launcher = subprocess.Popen(
            [
                str(repo_root / ".venv" / "bin" / "htlm"),
                "launch",
                "deploy",
                "--policy",
                "greedy",
                "--respawn-delay",
                "0.2",
                "--domain-id",
                str(next_domain()),
                "--run-dir",
                str(run),
                "--quiet",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def episodes() -> int:
        f = run / "world.jsonl"
        return len(f.read_text().splitlines()) if f.exists() else 0

    def wait_for(what: Callable[[], bool], timeout: float, why: str) -> None:
        end = time.monotonic() + timeout
        while not what():
            assert launcher.poll() is None, f"the launcher exited before {why}:\n{said.read_text()}"
            assert time.monotonic() < end, f"timed out waiting for {why}:\n{said.read_text()}"
            time.sleep(0.1)

    try:
        wait_for(lambda: episodes() >= 1, 60, "the first episode")
        world = alive_with(str(run / "parameters" / "world.yaml"))
        assert len(world) == 1, world
        os.kill(world[0], signal.SIGKILL)
        killed_at = episodes()
        wait_for(lambda: "world restarted" in said.read_text(), 30, "the launcher to restart the world")
        wait_for(lambda: episodes() > killed_at, 60, "an episode of the restarted world")
        assert "world exited with -9; restarting it" in said.read_text()
        children = [p for p in alive_with(str(run)) if p != launcher.pid]
        assert len(children) == 7, children  # world, trainer, five agents (deploy runs until stopped)
        os.kill(launcher.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
        rc = launcher.wait(timeout=30)
        text = said.read_text()
        assert rc == 130, text
        assert "SIGINT" in text and "restarts: world 1" in text  # the launcher says why it stopped
        time.sleep(0.2)
        assert alive_with(str(run)) == [], "orphaned processes"
        log = (run / "logs" / "world.log").read_text()
        assert f"continuing at episode {killed_at}" in log, log[-2000:]
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)


def test_a_trainer_that_fails_stops_a_training_launch_at_once_with_its_message(tmp_path: Path) -> None:
    """A process that fails by itself in a lockstep run is not restarted: the launch stops and says why."""
    run = tmp_path / "train"
    blocker = tmp_path / "a-file"
    blocker.write_text("")  # the trainer cannot make its run directory under a file: it fails once it starts
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "htlm_agent.cli",
            "launch",
            "train",
            "--episodes",
            "8",
            "--set",
            "envs=4",
            "--eval-episodes",
            "0",
            "--trainer-param",
            f"run_dir={blocker / 'trainer'}",
            "--domain-id",
            str(next_domain()),
            "--run-dir",
            str(run),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=100,
        check=False,
    )
    assert r.returncode == 1, r.stdout + r.stderr
    assert "htlm launch: trainer exited with 1: NotADirectoryError:" in r.stderr, r.stderr
    assert "in train a process that fails by itself is not restarted: stopping the team" in r.stderr, r.stderr
    assert not (run / "world.jsonl").exists() or len((run / "world.jsonl").read_text().splitlines()) < 8
    assert alive_with(str(run)) == []
