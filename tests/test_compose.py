"""Several agents in one process (`htlm launch --agents-per-process`): the grouping rule, the composed processes'
names, files and command lines, and the hosted agents' arguments, without ROS. The composed team over real DDS is
tests/ros/test_compose.py."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.cli.launch import LaunchError, config
from htlm_agent.ros import launch
from htlm_agent.ros.agents_node import node_args, parse_hosted
from htlm_agent.ros.launch import (
    AGENT_NODE,
    AGENTS_NODE,
    ALONE_UP_TO,
    GROUP_NAME_MAX,
    LaunchConfig,
    auto_per_process,
    group_name,
    per_process,
    prepare,
    spawn,
    team_processes,
)
from htlm_world.robots import ROBOT_READY
from htlm_world.scenario import builtin, load


def _cfg(tmp_path: Path, **kw: Any) -> LaunchConfig:
    return LaunchConfig(
        **{"mode": "evaluate", "scenario": builtin(), "run_dir": tmp_path / "run", "policy": "greedy", **kw}
    )


@pytest.mark.parametrize(
    ("agents", "cores", "per"),
    [(1, 2, 1), (5, 2, 1), (8, 1, 1), (9, 2, 5), (20, 2, 10), (50, 2, 25), (50, 4, 13), (20, 16, 2), (50, 64, 1)],
)
def test_small_teams_run_a_process_per_agent_and_large_ones_one_process_per_core(
    agents: int, cores: int, per: int
) -> None:
    assert auto_per_process(agents, cores) == per
    if agents > ALONE_UP_TO:  # as many processes as cores (fewer when the agents do not fill them)
        assert -(-agents // per) <= cores


def test_the_default_counts_the_agents_this_host_starts(tmp_path: Path) -> None:
    city = load("city-50")
    names = [a.name for a in city.agents]
    assert per_process(_cfg(tmp_path, scenario=city, cores=2)) == 25
    assert per_process(_cfg(tmp_path, scenario=city, cores=2, only=("world", *names[:8]))) == 1
    assert per_process(_cfg(tmp_path, scenario=city, cores=2, only=tuple(names[:20]))) == 10
    assert per_process(_cfg(tmp_path, scenario=city, cores=2, agents_per_process=1)) == 1  # asked for: as asked
    assert per_process(_cfg(tmp_path, agents_per_process=3)) == 3


def test_the_paper_team_keeps_a_process_per_agent(tmp_path: Path) -> None:
    procs = team_processes(_cfg(tmp_path, cores=1))
    assert [p.name for p in procs] == ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]
    assert not any(p.hosted for p in procs)


def test_composed_processes_host_the_agents_in_order_each_as_its_own_process_would_be(tmp_path: Path) -> None:
    alone = {p.name: p for p in team_processes(_cfg(tmp_path, mode="deploy", robots="sim", record=True))}
    procs = team_processes(_cfg(tmp_path, mode="deploy", robots="sim", record=True, agents_per_process=2))
    names = [p.name for p in procs]
    assert names[:5] == ["world", "trainer", "agent1+agent2", "agent3+agent4", "agent5"]
    assert names[5] == "operation" and names[-1] == "recorder"
    for p in procs[2:4]:
        assert p.module == AGENTS_NODE and p.node == "" and p.params == {} and p.respawn
        assert p.hosted == tuple(alone[a] for a in p.agents)  # node names, parameters and respawn of their own
        assert p.package == "htlm_agent" and p.executable == "agents_node"
    assert procs[4] == alone["agent5"] and procs[4].module == AGENT_NODE  # a group of one is an agent's own process
    assert [h.node for h in procs[2].hosted] == ["htlm_agent1", "htlm_agent2"]
    assert procs[2].arguments(Path("/p")) == ["htlm_agent1=/p/agent1.yaml", "htlm_agent2=/p/agent2.yaml"]
    assert procs[0].arguments(Path("/p")) == [] and procs[0].node == "htlm_world"


def test_only_groups_the_agents_this_launch_runs(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, agents_per_process=2, only=("agent1", "agent3", "agent4"))
    assert [(p.name, p.agents) for p in team_processes(cfg)] == [
        ("agent1+agent3", ("agent1", "agent3")),
        ("agent4", ("agent4",)),
    ]


def test_a_long_group_is_named_by_its_first_and_last_agent() -> None:
    assert group_name(["a", "b"]) == "a+b"
    names = [f"surveyor{i}" for i in range(25)]
    assert group_name(names) == "surveyor0..surveyor24_25" and len("+".join(names)) > GROUP_NAME_MAX


def test_prepare_writes_every_hosted_agents_file_and_spawn_names_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _cfg(tmp_path, agents_per_process=3)
    got = prepare(cfg)
    params = tmp_path / "run" / "parameters"
    alone = {spec.name: path.read_text() for spec, path in prepare(dataclasses.replace(cfg, agents_per_process=1))}
    assert [spec.name for spec, _ in got] == ["world", "trainer", "agent1+agent2+agent3", "agent4+agent5"]
    for spec, path in got:
        assert path == params / f"{spec.name}.yaml"
        for h in spec.hosted:  # the file its own process would get
            assert (params / f"{h.name}.yaml").read_text() == alone[h.name]
    spec, path = got[2]
    assert path.read_text() == "/**:\n  ros__parameters: {}\n"
    seen: dict[str, Any] = {}

    class Popen:
        def __init__(self, cmd: list[str], **kw: Any) -> None:
            seen["cmd"] = cmd

    monkeypatch.setattr(launch.subprocess, "Popen", Popen)
    spawn(spec, path, tmp_path / "x.log", {})
    assert seen["cmd"][1:] == [
        *("-m", AGENTS_NODE),
        *(f"htlm_agent{i}={params}/agent{i}.yaml" for i in (1, 2, 3)),
        *("--ros-args", "--params-file", str(path)),
    ]
    spawn(got[0][0], got[0][1], tmp_path / "y.log", {})
    assert seen["cmd"][3:7] == ["--ros-args", "-r", "__node:=htlm_world", "--params-file"]


def test_the_option_is_read_and_checked(tmp_path: Path) -> None:
    run = str(tmp_path / "r")
    assert config(["evaluate", "--policy", "greedy", "--run-dir", run]).agents_per_process == 0
    assert (
        config(["evaluate", "--policy", "greedy", "--run-dir", run, "--agents-per-process", "4"]).agents_per_process
        == 4
    )
    with pytest.raises(LaunchError, match="--agents-per-process -1"):
        config(["evaluate", "--policy", "greedy", "--run-dir", run, "--agents-per-process", "-1"])


def test_with_simulated_robots_the_period_lets_a_robot_reach_any_site_within_a_step(tmp_path: Path) -> None:
    run = ["--policy", "greedy", "--run-dir", str(tmp_path / "r")]
    cfg = config(["deploy", "--scenario", "facility-20", "--robots", "sim", *run])
    assert cfg.period == 7.5 and "7.5 s" in cfg.notes[0] and "zone1 to zone8" in cfg.notes[0]
    fast = config(["deploy", "--scenario", "facility-20", "--robots", "sim", "--robot-param", "speed=200.0", *run])
    assert fast.period == 1.2
    short = config(["deploy", "--scenario", "facility-20", "--robots", "sim", "--period", "0.5", *run])
    assert short.period == 0.5 and short.notes[0].startswith("warning: --period 0.5 s is shorter than the 7.5 s")
    assert config(["deploy", "--scenario", "facility-20", "--robots", "sim", "--period", "8", *run]).notes == ()
    plain = config(["deploy", "--scenario", "facility-20", *run])  # no robots: the free clock's default
    assert plain.period == launch.FREE_PERIOD and plain.notes == ()


def test_the_hosted_agents_are_named_node_equals_file() -> None:
    assert parse_hosted(["htlm_agent1=/a b/p1.yaml", "htlm_agent2=p=2.yaml"]) == [
        ("htlm_agent1", "/a b/p1.yaml"),
        ("htlm_agent2", "p=2.yaml"),
    ]
    for bad, why in ((["x"], "NODE=PARAMETERS_FILE"), (["=p"], "NODE="), ([], "no agent"), (["a=1", "a=2"], "twice")):
        with pytest.raises(ValueError, match=why):
            parse_hosted(bad)
    assert node_args("htlm_agent1", "p.yaml") == ["--ros-args", "-r", "__node:=htlm_agent1", "--params-file", "p.yaml"]


def test_the_robots_start_first_and_the_team_once_they_are_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = dataclasses.replace(_cfg(tmp_path), robots="sim", operation="external")
    events: list[str] = []

    def spawn(spec: Any, *_: Any) -> Any:
        events.append(f"start {spec.name}")
        return spec.name

    def wait(proc: Any, text: str, timeout: float, count: int = 1) -> bool:
        events.append(f"wait {proc}")
        assert text == ROBOT_READY and 0 < timeout <= launch.ROBOTS_START and count == 1
        return True

    monkeypatch.setattr(launch, "spawn", spawn)
    monkeypatch.setattr(launch, "_wait_for_line", wait)
    (cfg.run_dir / "logs").mkdir(parents=True)
    launch._start_slots(cfg)
    robots = [f"robot_agent{i}" for i in range(1, 6)]
    assert events[:5] == [f"start {r}" for r in robots] and events[5:10] == [f"wait {r}" for r in robots]
    assert {e.split()[1] for e in events[10:]} == {"world", "trainer", "operation", *(f"agent{i}" for i in range(1, 6))}


def test_the_world_waits_for_the_agents_as_long_as_the_launchs_processes_take_to_start(tmp_path: Path) -> None:
    def join(*args: str) -> Any:
        procs = launch.team_processes(config([*args, "--policy", "greedy", "--run-dir", str(tmp_path / "r")]))
        (world,) = [p for p in procs if p.name == "world"]
        return len(procs), world.params["join_timeout"]

    assert join("deploy") == (7, launch.JOIN_TIMEOUT)  # the paper's team: few processes, the least wait
    assert join("deploy", "--scenario", "city-50", "--robots", "sim") == (7, launch.JOIN_TIMEOUT)  # all composed
    n, wait = join("deploy", "--scenario", "city-50", "--robots", "sim", "--agents-per-process", "1")
    assert n == 103 and wait == n * launch.JOIN_PER_PROCESS  # a process per agent and per robot
    assert join("deploy", "--scenario", "city-50", "--world-param", "join_timeout=10")[1] == 10  # given: kept


def test_the_simulated_robots_share_processes_as_the_agents_do(tmp_path: Path) -> None:
    cfg = config(
        ["deploy", "--scenario", "facility-20", "--robots", "sim", "--policy", "greedy", "--run-dir", str(tmp_path)]
    )
    procs = launch.team_processes(cfg)
    robots = [p for p in procs if p.module == launch.ROBOTS_NODE]
    assert [len(p.hosted) for p in robots] == [10, 10] and all(p.name.startswith("robot_") for p in robots)
    assert [h.name for h in robots[0].hosted] == [f"robot_{a.name}" for a in cfg.scenario.agents[:10]]
    assert robots[0].arguments(tmp_path)[0] == f"htlm_robot_scout1={tmp_path / 'robot_scout1.yaml'}"
    assert robots[0].hosted[0].params == {"agent": "scout1"} and robots[0].executable == "robots_node"
