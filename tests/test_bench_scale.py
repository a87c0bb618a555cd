"""`htlm bench scale` without ROS: what it reads from /proc and from a run's logs (join time, episodes, CPU share,
memory, absent agent-steps), the row it makes of them, and its process layouts, on fixtures. The benchmark through
`htlm launch` over real DDS is tests/ros/test_bench_scale.py."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.ros import scale
from htlm_agent.ros.scale import Layout, Samples, layout
from htlm_world.scenario import builtin

# /proc/PID/stat of a process whose command holds spaces and parentheses: utime 250, stime 50 ticks, started at
# tick 9000 after boot
STAT = (
    "4242 (python3 (x) y) S 4200 4242 4242 0 -1 4194560 9000 0 12 0 250 50 0 0 20 0 3 0 9000 812000000 30000 "
    "18446744073709551615 1 1 0 0 0 0 0 16781312 17642 0 0 0 17 1 0 0 0 0 0"
)
SMAPS = """55d0c0000000-7ffd00000000 ---p 00000000 00:00 0                          [rollup]
Rss:               76544 kB
Pss:               41234 kB
Pss_Anon:          30000 kB
Shared_Clean:      30000 kB
"""
AGENT1 = """[WARN] [100.500000000] [htlm_agent1]: unsigned: no team key (HTLM_TEAM_KEY_FILE)
[INFO] [101.250000000] [htlm_agent1]: run run-abc: agent agent1 (index 0) of paper/heterogeneous, mode evaluate
[INFO] [109.000000000] [htlm_agent1]: run run-abc: agent agent1 (index 0) of paper/heterogeneous, mode evaluate
"""
# a composed process's log: the lines of every agent it hosts
COMPOSED = """hosting agent2, agent3
[INFO] [102.000000000] [htlm_agent2]: run run-abc: agent agent2 (index 1) of paper/heterogeneous, mode evaluate
[INFO] [103.500000000] [htlm_agent3]: run run-abc: agent agent3 (index 2) of paper/heterogeneous, mode evaluate
[INFO] [130.000000000] [htlm_agent3]: run run-abc stopped by the world; 0 transitions unacknowledged
"""
WORLD_LOG = """[INFO] [100.000000000] [htlm_world]: run run-abc: paper/heterogeneous, 5 agents, h=30
[INFO] [106.000000000] [htlm_world]: episode 0: completion 10, idle 7, reassign 4, absent [0, 0, 0, 0, 0], 2.00 s
[WARN] [107.000000000] [htlm_world]: episode 1 step 4: no action from agents [2] within the deadline; idle
[INFO] [108.000000000] [htlm_world]: episode 1: completion 9, idle 5, reassign 3, absent [0, 0, 1, 0, 0], 2.00 s
[INFO] [110.000000000] [htlm_world]: episode 2: completion 12 (failed), idle 8, absent [0, 0, 0, 0, 0], 2.00 s
[INFO] [114.000000000] [htlm_world]: episodes 3..4: completion 9.50 (mean), 0 failed, absent [1, 1, 0, 0, 0], 4.00 s
"""


def _episode(e: int, absent: list[int], seconds: float, steps: int = 30) -> str:
    metrics = {"episode": e, "completion": 9, "failed": False, "absent": absent, "seconds": seconds}
    return json.dumps({"run": "run-abc", "metrics": metrics, "actions": [[0] * 5] * steps})


WORLD_JSONL = "\n".join(
    [
        _episode(0, [0] * 5, 2.0),
        _episode(1, [0, 0, 1, 0, 0], 2.0),
        _episode(2, [0] * 5, 2.0),
        _episode(3, [1, 1, 0, 0, 0], 4.0),  # a batch of two: its absences and seconds once
        _episode(4, [1, 1, 0, 0, 0], 4.0),
    ]
)


def test_cpu_and_start_are_read_past_a_command_with_spaces_and_parentheses() -> None:
    assert scale.stat_fields(STAT)[0] == "S"
    assert scale.cpu_seconds(STAT, 100) == pytest.approx(3.0)
    assert scale.start_ticks(STAT) == 9000


def test_memory_is_the_rss_and_pss_of_smaps_rollup() -> None:
    assert scale.memory_kb(SMAPS) == (76544, 41234)
    assert scale.memory_kb("") == (0, 0)


def test_an_agent_joined_at_its_first_line_that_it_took_the_run_in_its_own_or_a_composed_process() -> None:
    assert scale.join_times([AGENT1, COMPOSED]) == {"agent1": 101.25, "agent2": 102.0, "agent3": 103.5}
    assert scale.join_times(["[INFO] [1.0] [htlm_agent4]: starting\n"]) == {}


def test_episodes_end_at_the_worlds_episode_lines_and_not_at_its_warnings() -> None:
    assert scale.episode_ends(WORLD_LOG) == {0: 106.0, 1: 108.0, 2: 110.0, 3: 114.0, 4: 114.0}


def test_the_episode_log_counts_a_batchs_absences_once_and_skips_a_line_being_written() -> None:
    eps = scale.world_episodes(WORLD_JSONL + "\n" + '{"run": "run-abc", "metr', horizon=30)
    assert [(e.index, e.steps, e.absent, e.seconds) for e in eps] == [
        (0, 30, 0, 2.0),
        (1, 30, 1, 2.0),
        (2, 30, 0, 2.0),
        (3, 30, 2, 4.0),
        (4, 30, 0, 4.0),
    ]
    assert scale.world_episodes("", horizon=30) == []


def test_the_cpu_share_interpolates_between_looks_and_keeps_a_process_that_is_gone() -> None:
    s = Samples()
    s.add(100.0, {1: 10.0, 2: 5.0}, {2: (1000, 600)})
    s.add(102.0, {1: 12.0, 2: 7.0}, {2: (3000, 1800)})
    s.add(104.0, {1: 14.0}, {})  # process 2 is gone: its 7 CPU seconds stay counted
    assert s.cpu == [15.0, 19.0, 21.0]
    assert s.cpu_at(101.0) == pytest.approx(17.0)
    assert s.cpu_share(101.0, 104.0) == pytest.approx((21.0 - 17.0) / 3.0)
    assert s.cpu_share(99.0, 104.0) is None  # before the first look
    assert s.peak() == (3000, 1800, 1)


def _run(tmp_path: Path, world_log: str = WORLD_LOG, agents: tuple[str, ...] = (AGENT1, COMPOSED)) -> Path:
    logs = tmp_path / "run" / "logs"
    logs.mkdir(parents=True)
    (logs / "world.log").write_text(world_log)
    (logs / "trainer.log").write_text("[INFO] [101.0] [htlm_trainer]: run run-abc: agent agent9 (index 8) of x\n")
    for i, text in enumerate(agents):
        (logs / f"agents{i}.log").write_text(text)
    (tmp_path / "run" / "world.jsonl").write_text(WORLD_JSONL + "\n")
    return tmp_path / "run"


def _samples() -> Samples:
    s = Samples()
    s.started = {11: 100.0, 12: 100.4}
    for t, cpu in ((104.0, 2.0), (106.0, 5.0), (114.0, 17.0), (116.0, 18.0)):
        s.add(t, {11: cpu}, {11: (200 * 1024, 100 * 1024)})
    return s


def _row(tmp_path: Path, run: Path, code: int = 0, killed: bool = False, episodes: int = 5) -> dict[str, Any]:
    sc = builtin().replace(agents=builtin().agents[:3])
    return scale.result(sc, Layout("1", 1, 3), "greedy", episodes, run, tmp_path, _samples(), 98.0, code,
                        killed, 600.0)  # fmt: skip


def test_a_run_is_measured_from_its_logs_and_the_looks_at_its_processes(tmp_path: Path) -> None:
    r = _row(tmp_path, _run(tmp_path))
    assert r["status"] == "ok" and r["reason"] == ""
    assert r["launcher_s"] == 2.0  # from the command (98) to the team's first process (100)
    assert r["join_s"] == 3.5  # the last of the three agents took the run at 103.5; the trainer's log is no agent's
    assert r["first_episode_s"] == 6.0
    assert r["steady_episode_s"] == 3.0  # the median of episodes 1..4 as the world logged them (2, 2, 4, 4)
    # episodes 1..4 from the end of episode 0 (106) to the end of the last (114): 3 agents x 30 steps each, less
    # the 3 absent agent-steps, in 8 s; the team used 12 CPU seconds in them
    assert r["agent_steps_per_s"] == pytest.approx((4 * 3 * 30 - 3) / 8.0, abs=0.05)
    assert r["cpu_share"] == pytest.approx(12.0 / 8.0)
    assert r["absent"] == 3
    assert (r["rss_mb"], r["pss_mb"], r["agent_processes"]) == (200, 100, 1)


def test_a_run_that_did_not_finish_says_what_did_not_happen(tmp_path: Path) -> None:
    short = "\n".join(WORLD_LOG.splitlines()[:2]) + "\n"
    run = _run(tmp_path, short, (AGENT1,))
    (run / "world.jsonl").write_text(_episode(0, [0] * 5, 2.0) + "\n")
    r = _row(tmp_path, run, code=124)
    assert r["status"] == "timeout"
    assert r["reason"] == "stopped after the deadline of 600 s: 1 of 3 agents took the run; 1 of 5 episodes logged"
    assert r["join_s"] is None and r["first_episode_s"] == 6.0 and r["absent"] == 0
    (tmp_path / "launcher.err").write_text("htlm launch evaluate: ...\nagent2 exited with 1: Traceback\n")
    r = _row(tmp_path, run, code=1)
    assert r["status"] == "failed"
    assert r["reason"].startswith("the launch exited 1: 1 of 3 agents took the run; 1 of 5 episodes logged")
    assert r["reason"].endswith("(it said: agent2 exited with 1: Traceback)")


def test_layouts_resolve_to_agents_per_process() -> None:
    assert layout("1", 100, 2) == Layout("1", 1, 100)
    assert layout("auto", 100, 2) == Layout("auto", 50, 2)
    assert layout("auto", 5, 2) == Layout("auto", 1, 5)  # the launcher keeps a process per agent on a small team
    assert layout("30", 20, 2) == Layout("30", 20, 1)
    assert layout("auto", 20, 2).label == "the launcher's default"
    with pytest.raises(ValueError, match="not 1, auto or a number"):
        layout("two", 20, 2)


def test_teams_are_shipped_sizes_or_scenarios() -> None:
    got = scale.teams("5, city-50,100")
    assert [(w, sc.n_agents) for w, sc in got] == [("paper", 5), ("city-50", 50), ("region-100", 100)]
    with pytest.raises(SystemExit, match="no shipped team of 7 agents"):
        scale.teams("7")


def test_a_layout_with_too_many_processes_is_skipped_with_its_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def never(*_: Any, **__: Any) -> dict[str, Any]:
        raise AssertionError("nothing is launched")

    monkeypatch.setattr(scale, "measure", never)
    args = argparse.Namespace(scale_teams="100", scale_layouts="1", scale_max_processes=50, scale_episodes=2,
                              scale_policy="greedy", scale_timeout=0.0, scale_batch=1, scale_eval_episodes=0,
                              seconds=0.01, out=str(tmp_path), domain_id=99)  # fmt: skip
    res = scale.scale_bench(args)
    [row] = res["ros"]
    assert row["status"] == "skipped"
    assert row["reason"] == "100 agent processes, more than --scale-max-processes 50"
    assert res["inprocess"][0]["scenario"] == "region-100" and res["inprocess"][0]["team_agent_steps_per_s"] > 0
    assert {p.name for p in tmp_path.iterdir()} == {"scale.json", "ros.csv", "inprocess.csv", "scale.png"}
