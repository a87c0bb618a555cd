"""`htlm bench scale` over real DDS, at its smallest: the paper's five agents for two episodes in both layouts (the
launcher's default is a process per agent at this size: one launch, reported for both), and a few episodes in
process. What it reads from /proc and the logs is tested on fixtures in tests/test_bench_scale.py; no figure here
is held to a time."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from support.ros import HTLM, alive_with, next_domain

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # CI budget: a launch of 5 agents through the benchmark; -m slow


def test_the_scale_benchmark_measures_a_team_of_five(tmp_path: Path) -> None:
    out = tmp_path / "scale"
    r = subprocess.run(
        [HTLM, "bench", "scale", "--scale-teams", "5", "--scale-episodes", "2", "--scale-eval-episodes", "4",
         "--scale-batch", "2", "--seconds", "0.1", "--domain-id", str(next_domain()), "--out", str(out), "--json"],
        capture_output=True,
        text=True,
        timeout=280,
        check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads(r.stdout)  # --json: the only thing on stdout
    assert json.loads((out / "scale.json").read_text()) == res
    assert {"scale.json", "ros.csv", "inprocess.csv", "scale.png"} <= {p.name for p in out.iterdir()}
    assert alive_with(str(out)) == []
    one, auto = res["ros"]
    assert (one["layout"], auto["layout"], auto["same_run_as"]) == ("1", "auto", "1")
    assert one["status"] == "ok", one
    assert one["agent_processes"] == 5 and one["agents_per_process"] == 1
    assert one["episodes"] == 2 and one["joined"] == 5
    for key in ("launcher_s", "join_s", "first_episode_s", "steady_episode_s", "cpu_share", "agent_steps_per_s"):
        assert one[key] is not None and one[key] > 0, key
    assert one["rss_mb"] >= one["pss_mb"] > 0
    assert isinstance(one["absent"], int) and one["absent"] >= 0
    summary = json.loads((out / "runs" / "paper-per1" / "launcher.out").read_text().strip().splitlines()[-1])
    assert summary["absent_agent_steps"] == one["absent"]  # what the launcher's summary counts from the same log
    [inproc] = res["inprocess"]
    assert inproc["scenario"] == "paper" and inproc["team_agent_steps_per_s"] > 0
    assert inproc["eval_episodes"] == 4 and inproc["greedy_eval_s"] >= 0 and inproc["auction_eval_s"] >= 0
    progress = r.stderr.splitlines()
    assert any(x.startswith("paper (5 agents), a process per agent (5 agent processes): joined in") for x in progress)
