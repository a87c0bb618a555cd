"""The ROS 2 launch file (share/htlm_agent/launch/team.launch.py) starts what `htlm launch` starts.

launch and launch_ros are not published as wheels, so the file cannot run here. These tests hold the one definition
both use (`htlm_agent.ros.launch.team_processes` and `prepare`, `htlm_agent.cli.launch.config`) and run the launch
file against stand-ins of the Jazzy classes it uses, which accept exactly the keyword arguments of their Jazzy
signatures (ros2/launch and ros2/launch_ros, branch jazzy): the nodes it describes must be the launcher's processes,
with the same parameters files, environment and node names, respawning in deploy.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.cli.launch import LaunchError, config
from htlm_agent.ros.launch import (
    MAX_RESTARTS,
    RESPAWN_DELAY,
    LaunchConfig,
    prepare,
    process_specs,
    ros_env,
    team_processes,
)
from htlm_world.scenario import builtin

LAUNCH_FILE = Path(__file__).resolve().parents[1] / "src" / "htlm_agent" / "launch" / "team.launch.py"

# keyword arguments of the Jazzy constructors (launch 3.4, launch_ros 0.26): Node's own, ExecuteProcess's,
# ExecuteLocal's and Action's
NODE_KWARGS = {
    *("executable", "package", "name", "namespace", "exec_name", "parameters", "remappings", "ros_arguments"),
    *("arguments", "prefix", "cwd", "env", "additional_env", "shell", "sigterm_timeout", "sigkill_timeout"),
    *("emulate_tty", "output", "output_format", "cached_output", "log_cmd", "on_exit", "respawn", "respawn_delay"),
    *("respawn_max_retries", "condition"),
}


def _checked(cls_name: str, allowed: set[str]) -> type:
    """A stand-in class that keeps its arguments and refuses a keyword its Jazzy namesake does not take."""

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        unknown = set(kwargs) - allowed
        assert not unknown, f"{cls_name} of Jazzy takes no {sorted(unknown)}"
        self.args, self.kwargs = args, kwargs

    return type(cls_name, (), {"__init__": init})


class _LaunchConfiguration:
    def __init__(self, name: str, *, default: Any = None) -> None:
        self.name = name

    def perform(self, context: Any) -> str:
        return str(context.launch_configurations.get(self.name, ""))


def _stand_ins(monkeypatch: pytest.MonkeyPatch) -> None:
    mods = {name: types.ModuleType(name) for name in ("launch", "launch.actions", "launch.event_handlers")}
    mods |= {name: types.ModuleType(name) for name in ("launch.events", "launch.substitutions")}
    mods |= {name: types.ModuleType(name) for name in ("launch_ros", "launch_ros.actions")}
    mods["launch"].LaunchContext = object  # type: ignore[attr-defined]
    mods["launch"].LaunchDescription = _checked("LaunchDescription", set())  # type: ignore[attr-defined]
    actions = mods["launch.actions"]
    actions.DeclareLaunchArgument = _checked(  # type: ignore[attr-defined]
        "DeclareLaunchArgument", {"default_value", "description", "choices", "condition"}
    )
    actions.EmitEvent = _checked("EmitEvent", {"event", "condition"})  # type: ignore[attr-defined]
    actions.LogInfo = _checked("LogInfo", {"msg", "condition"})  # type: ignore[attr-defined]
    actions.OpaqueFunction = _checked("OpaqueFunction", {"function", "args", "kwargs"})  # type: ignore[attr-defined]
    actions.RegisterEventHandler = _checked("RegisterEventHandler", {"condition"})  # type: ignore[attr-defined]
    mods["launch.event_handlers"].OnProcessExit = _checked(  # type: ignore[attr-defined]
        "OnProcessExit", {"target_action", "on_exit", "handle_once"}
    )
    mods["launch.events"].Shutdown = _checked("Shutdown", {"reason", "due_to_sigint"})  # type: ignore[attr-defined]
    mods["launch.substitutions"].LaunchConfiguration = _LaunchConfiguration  # type: ignore[attr-defined]
    mods["launch_ros.actions"].Node = _checked("Node", NODE_KWARGS)  # type: ignore[attr-defined]
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)


def _launch(monkeypatch: pytest.MonkeyPatch, **values: str) -> tuple[Any, list[Any]]:
    """The launch file's description and the actions of its OpaqueFunction for these launch arguments."""
    _stand_ins(monkeypatch)
    spec = importlib.util.spec_from_file_location("team_launch", LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    desc = module.generate_launch_description()
    entities = desc.args[0]
    declared = {
        e.args[0]: e.kwargs.get("default_value") for e in entities if type(e).__name__ == "DeclareLaunchArgument"
    }
    assert set(values) <= set(declared), set(values) - set(declared)
    context = types.SimpleNamespace(launch_configurations={k: v for k, v in declared.items() if v is not None} | values)
    opaque = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    assert len(opaque) == 1
    function: Callable[[Any], list[Any]] = opaque[0].kwargs["function"]
    return module, function(context)


def _cfg(tmp_path: Path, **kw: Any) -> LaunchConfig:
    return LaunchConfig(**{"mode": "evaluate", "scenario": builtin(), "run_dir": tmp_path / "run", **kw})


def test_the_process_list_is_the_launchers_with_what_ros2_run_needs(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, robots="sim", record=True, policy="greedy")
    procs = team_processes(cfg)
    assert [(p.name, p.module, p.params) for p in procs] == process_specs(cfg)
    names = [p.name for p in procs]
    assert names[:2] == ["world", "trainer"] and names[-1] == "recorder" and "robot_agent3" in names
    for p in procs:
        assert p.node == f"htlm_{p.name}" and not p.respawn
        assert (p.respawn_delay, p.max_restarts) == (cfg.respawn_delay, cfg.max_restarts)
        setup = (LAUNCH_FILE.parents[2] / p.package / "setup.py").read_text()
        assert f'"{p.executable} = {p.module}:main"' in setup, f"{p.package} installs no {p.executable}"
    recorder = procs[-1].params
    assert recorder == {
        "path": str((tmp_path / "run" / "recording").resolve()),
        "agents": "agent1,agent2,agent3,agent4,agent5",
    }
    assert all(p.respawn for p in team_processes(_cfg(tmp_path, mode="deploy", policy="greedy")))
    assert "recorder" not in [p.name for p in team_processes(_cfg(tmp_path))]


def test_prepare_writes_the_parameters_file_of_every_process(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, record=True)
    for spec, path in prepare(cfg):
        assert path == tmp_path / "run" / "parameters" / f"{spec.name}.yaml" and path.is_file()
    assert (tmp_path / "run" / "logs").is_dir()


def test_config_reads_a_command_line_as_htlm_launch_does(tmp_path: Path) -> None:
    cfg = config(["deploy", "--policy", "greedy", "--robots", "sim", "--run-dir", str(tmp_path / "r"), "--record"])
    assert (cfg.mode, cfg.batch, cfg.episodes, cfg.robots, cfg.record) == ("deploy", 1, 0, "sim", True)
    with pytest.raises(LaunchError) as err:
        config(["deploy", "--run-dir", str(tmp_path / "r"), "--robots", "sim", "--batch", "4"])
    lines = str(err.value).splitlines()
    assert any("needs --checkpoint" in x for x in lines) and any("--batch 1 (got 4)" in x for x in lines)
    with pytest.raises(LaunchError, match="recorder"):
        config(["evaluate", "--policy", "greedy", "--only", "recorder", "--run-dir", str(tmp_path / "r")])


def test_the_launch_file_starts_the_launchers_processes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / "run"
    argv = ["evaluate", "--policy", "greedy", "--episodes", "3", "--domain-id", "77", "--run-dir", str(run), "--record"]
    want = prepare(config(argv))
    expected = {spec.name: (spec, path.read_text()) for spec, path in want}
    for _, path in want:
        path.unlink()
    module, actions = _launch(
        monkeypatch, mode="evaluate", policy="greedy", episodes="3", domain_id="77", run_dir=str(run), record="true"
    )
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    assert [n.kwargs["name"] for n in nodes] == [f"htlm_{name}" for name in expected]
    env = ros_env(config(argv))
    for node in nodes:
        spec, params = expected[node.kwargs["name"].removeprefix("htlm_")]
        kw = node.kwargs
        assert (kw["package"], kw["executable"], kw["respawn"]) == (spec.package, spec.executable, False)
        (params_file,) = kw["parameters"]
        assert Path(params_file).read_text() == params  # the very file `htlm launch` writes
        assert kw["env"] == env and kw["env"]["ROS_DOMAIN_ID"] == "77"
    # lockstep: a process that fails (not one that finished or that the launch stopped) ends the launch, named
    handlers = [a.args[0].kwargs for a in actions if type(a).__name__ == "RegisterEventHandler"]
    assert [h["target_action"] for h in handlers] == nodes
    trainer = next(h for h in handlers if h["target_action"].kwargs["name"] == "htlm_trainer")
    for rc in (0, 130, 143, -2, -15):
        assert trainer["on_exit"](types.SimpleNamespace(returncode=rc), None) is None, rc
    for rc in (1, -9):
        (ended,) = trainer["on_exit"](types.SimpleNamespace(returncode=rc), None)
        assert ended.kwargs["event"].kwargs["reason"] == f"trainer exited with {rc}"
    assert module.command_line({"mode": "deploy", "record": "false", "args": "--agent-param belief_every=5"}) == [
        "deploy",
        "--agent-param",
        "belief_every=5",
    ]


def test_in_deploy_the_launch_file_respawns_and_ends_with_the_world(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, actions = _launch(monkeypatch, mode="deploy", policy="greedy", robots="sim", run_dir=str(tmp_path / "run"))
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    assert len(nodes) == 13 and all(n.kwargs["respawn"] for n in nodes)
    # the respawn parameters of `htlm launch`'s process list: its defaults, and its options given as arguments
    assert {(n.kwargs["respawn_delay"], n.kwargs["respawn_max_retries"]) for n in nodes} == {
        (RESPAWN_DELAY, MAX_RESTARTS)
    }
    _, actions = _launch(
        monkeypatch,
        mode="deploy",
        policy="greedy",
        respawn_delay="2.5",
        max_restarts="7",
        run_dir=str(tmp_path / "run2"),
    )
    assert {
        (a.kwargs["respawn_delay"], a.kwargs["respawn_max_retries"]) for a in actions if type(a).__name__ == "Node"
    } == {(2.5, 7)}
    _, actions = _launch(monkeypatch, mode="deploy", policy="greedy", robots="sim", run_dir=str(tmp_path / "run"))
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    (handler,) = [a for a in actions if type(a).__name__ == "RegisterEventHandler"]
    on_exit = handler.args[0].kwargs
    assert on_exit["target_action"] is nodes[0] and nodes[0].kwargs["name"] == "htlm_world"
    finished = on_exit["on_exit"](types.SimpleNamespace(returncode=0), None)
    assert type(finished[0]).__name__ == "EmitEvent" and type(finished[0].kwargs["event"]).__name__ == "Shutdown"
    assert on_exit["on_exit"](types.SimpleNamespace(returncode=-9), None) is None  # killed: respawned, not the end


def test_bad_launch_arguments_start_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(LaunchError, match="needs --checkpoint"):
        _launch(monkeypatch, mode="deploy", run_dir=str(tmp_path / "run"))
    assert not (tmp_path / "run" / "parameters").exists()


def test_setup_py_installs_the_launch_file() -> None:
    setup = (LAUNCH_FILE.parents[1] / "setup.py").read_text()
    m = re.search(r'\(f"share/\{PACKAGE\}/launch", sorted\(glob\("([^"]+)"\)\)\)', setup)
    assert m is not None, "setup.py installs no launch file into share/htlm_agent/launch"
    assert [p.name for p in LAUNCH_FILE.parents[1].glob(m.group(1))] == ["team.launch.py"]


def test_the_launch_file_composes_agents_as_the_launcher_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`agents_per_process:=3`: the agents run in `agents_node` processes, each named by the agents it hosts, with
    every hosted agent's node name and parameters file as its arguments (the files `htlm launch` writes), and no
    node name of its own (that would rename every node of the process)."""
    run = tmp_path / "run"
    argv = ["deploy", "--policy", "greedy", "--run-dir", str(run), "--agents-per-process", "3"]
    want = {spec.name: spec for spec, _ in prepare(config(argv))}
    _, actions = _launch(monkeypatch, mode="deploy", policy="greedy", run_dir=str(run), agents_per_process="3")
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    assert len(nodes) == 4
    composed = [n.kwargs for n in nodes if n.kwargs["executable"] == "agents_node"]
    assert len(composed) == 2 and all("name" not in kw and kw["respawn"] for kw in composed)
    params = run / "parameters"
    assert [kw["arguments"] for kw in composed] == [
        [f"htlm_agent{i}={params}/agent{i}.yaml" for i in (1, 2, 3)],
        [f"htlm_agent{i}={params}/agent{i}.yaml" for i in (4, 5)],
    ]
    assert [kw["parameters"] for kw in composed] == [
        [str(params / "agent1+agent2+agent3.yaml")],
        [str(params / "agent4+agent5.yaml")],
    ]
    assert want["agent4+agent5"].agents == ("agent4", "agent5")
    for i in range(1, 6):
        assert f'agent: "agent{i}"' in (params / f"agent{i}.yaml").read_text()
    _, actions = _launch(monkeypatch, mode="evaluate", policy="greedy", run_dir=str(run), agents_per_process="3")
    handlers = [a.args[0].kwargs for a in actions if type(a).__name__ == "RegisterEventHandler"]
    (ended,) = handlers[2]["on_exit"](types.SimpleNamespace(returncode=-9), None)
    assert ended.kwargs["event"].kwargs["reason"] == "agent1+agent2+agent3 exited with -9"
