"""A team over ROS 2 from `ros2 launch`: the processes and parameters of `htlm launch`, started by launch_ros.

    ros2 launch htlm_agent team.launch.py mode:=deploy checkpoint:=runs/x/checkpoint robots:=sim
    ros2 launch htlm_agent team.launch.py mode:=evaluate policy:=greedy episodes:=20 record:=true
    ros2 launch htlm_agent team.launch.py mode:=deploy checkpoint:=DIR args:="--agent-param belief_every=5"

Thin on purpose: the launch arguments become the words of an `htlm launch` command line, which
`htlm_agent.cli.launch.config` reads and checks exactly as `htlm launch` does (every problem at once, nothing
started), and `htlm_agent.ros.launch.prepare` gives the processes, their parameters files and their environment from
the one definition both use, with the respawn parameters (`respawn_delay`, `respawn_max_retries`). In deploy every
process respawns when it exits (the team keeps stepping on its own clock meanwhile), and the launch ends when the world
finishes its run; in train and evaluate a process that exits with an error or is killed ends the launch (launch_ros
cannot restart only the killed ones, as `htlm launch` does). A large team's agents share processes as with
`htlm launch` (`agents_per_process`): such a process is `agents_node` with every hosted agent's node name and
parameters file as its arguments, and it respawns or ends the launch as one agent's process would.
"""

from __future__ import annotations

import shlex
from typing import Any

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from htlm_agent.cli.launch import config
from htlm_agent.ros.launch import prepare, ros_env

ARGUMENTS = {
    # launch argument: (option of `htlm launch`, description); an empty value leaves the option out (its default)
    "scenario": ("--scenario", "scenario YAML file or shipped scenario name (default: the built-in 'paper')"),
    "team": ("--team", "a built-in team instead of a scenario file"),
    "checkpoint": ("--checkpoint", "checkpoint directory of `htlm train` (evaluate, deploy)"),
    "policy": ("--policy", "agents' policy: auto, checkpoint, greedy, auction, qmdp, lookahead, random"),
    "robots": ("--robots", "sim: a simulated robot per agent and their stand-in operation; none"),
    "episodes": ("--episodes", "episodes to run (deploy: 0, until stopped)"),
    "batch": ("--batch", "B, episodes run at once"),
    "seed": ("--seed", "master seed"),
    "period": (
        "--period",
        "step period of the free clock, seconds (external operation; default with robots:=sim: long enough for a "
        "robot to drive between the two farthest sites within a step)",
    ),
    "run_dir": ("--run-dir", "run directory (default: runs/launch-MODE__SEED__TIMESTAMP)"),
    "only": ("--only", "comma-separated processes to start on this host"),
    "domain_id": ("--domain-id", "ROS_DOMAIN_ID of every process (default 42)"),
    "discovery": ("--discovery", "localhost (default), subnet, system_default, off"),
    "peers": ("--peers", "ROS_STATIC_PEERS for unicast discovery of other hosts"),
    "key_file": ("--key-file", "team key file: sign every message"),
    "respawn_delay": ("--respawn-delay", "deploy: seconds before a process that exited starts again (default 1)"),
    "max_restarts": ("--max-restarts", "deploy: restarts of one process before it is left down (default 5)"),
    "agents_per_process": (
        "--agents-per-process",
        "most agents one process hosts (1: a process per agent; default: 1 up to 8 agents, else as many processes "
        "as cores)",
    ),
}


def command_line(values: dict[str, str]) -> list[str]:
    """The `htlm launch` words of the launch arguments' values."""
    argv = [values["mode"]]
    for name, (option, _) in ARGUMENTS.items():
        if values.get(name, ""):
            argv += [option, values[name]]
    if values.get("record", "false").lower() in ("true", "1", "yes"):
        argv.append("--record")
    return argv + shlex.split(values.get("args", ""))


def team(context: LaunchContext) -> list[Any]:
    """The team's processes as launch_ros nodes (OpaqueFunction: the arguments' values are known here)."""
    names = ["mode", "record", "args", *ARGUMENTS]
    cfg = config(command_line({n: LaunchConfiguration(n).perform(context) for n in names}))
    env = ros_env(cfg)
    actions: list[Any] = [LogInfo(msg=f"htlm launch: {line}") for line in cfg.notes]  # the period chosen, a warning
    for spec, params_file in prepare(cfg):
        # a composed process has no node name of its own: its arguments name each hosted agent and its file
        named: dict[str, Any] = {"name": spec.node} if spec.node else {"arguments": spec.arguments(params_file.parent)}
        node = Node(
            package=spec.package,
            executable=spec.executable,
            **named,
            parameters=[str(params_file)],
            env=env,
            output="screen",
            respawn=spec.respawn,
            respawn_delay=spec.respawn_delay,
            respawn_max_retries=spec.max_restarts,
        )
        actions.append(node)
        if spec.name == "world" and spec.respawn:  # its run is over when it exits by itself with 0
            actions.append(RegisterEventHandler(OnProcessExit(target_action=node, on_exit=_world_finished)))
        elif not spec.respawn:  # lockstep: launch_ros cannot tell a kill from an error, so a failure ends the launch
            actions.append(RegisterEventHandler(OnProcessExit(target_action=node, on_exit=_failed(spec.name))))
    return actions


STOPPED = (0, 130, 143, -2, -15)
"""Exit codes of a process that finished or that the launch stopped (SIGINT, SIGTERM)."""


def _world_finished(event: Any, _context: Any) -> list[Any] | None:
    """Deploy: the launch ends when the world exits by itself with 0 (its run is over); else it is respawned."""
    if event.returncode == 0:
        return [EmitEvent(event=Shutdown(reason="the world finished its run"))]
    return None


def _failed(name: str) -> Any:
    """Train, evaluate: a process that exits otherwise than finished or stopped ends the launch, naming it."""

    def on_exit(event: Any, _context: Any) -> list[Any] | None:
        if event.returncode in STOPPED:
            return None
        return [EmitEvent(event=Shutdown(reason=f"{name} exited with {event.returncode}"))]

    return on_exit


def generate_launch_description() -> LaunchDescription:
    """The launch arguments of `htlm launch` and the team they describe."""
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "mode", description="train, evaluate or deploy", choices=["train", "evaluate", "deploy"]
            ),
            DeclareLaunchArgument("record", default_value="false", description="record the team into RUN/recording"),
            DeclareLaunchArgument("args", default_value="", description="further `htlm launch` options, as one string"),
            *(DeclareLaunchArgument(n, default_value="", description=d) for n, (_, d) in ARGUMENTS.items()),
            OpaqueFunction(function=team),
        ]
    )
