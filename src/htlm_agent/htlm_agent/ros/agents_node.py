"""agents_node: several agents of the team in one process, each its own node (a composed process).

As a ROS 2 component container hosts components, this process hosts several `AgentNode`s in one rclpy executor:
each keeps its own node name, parameters, belief, policy, publishers, subscriptions and timers, so on the graph the
agents are the nodes their own processes would be (`ros2 node list`, `ros2 param get /htlm_agent3 policy`); they
only share the process, its DDS participant, the interpreter and its imports (torch, rclpy, numpy are loaded once
instead of once per agent). `htlm launch --agents-per-process N` starts them so (docs/ros.md, A large team on one
machine).

    python -m htlm_agent.ros.agents_node htlm_agent1=RUN/parameters/agent1.yaml htlm_agent2=RUN/parameters/agent2.yaml
    ros2 run htlm_agent agents_node htlm_agent1=p1.yaml htlm_agent2=p2.yaml --ros-args --log-level debug

Every word before `--ros-args` is NODE=PARAMETERS_FILE: a hosted agent, its node name and its parameters file (the
file an agent_node of its own would get). ROS arguments after `--ros-args` apply to every hosted node (a node's own
name and file win). The process keeps a process's rules for all of them (`htlm_msgs_py.ros.lifecycle.run_nodes`):
an agent whose run is over stops at once and the process exits 0 when the last one has; SIGINT or
SIGTERM stops every agent (130, 143); a bad parameter of any agent (2 at start), a fatal error of one (2: a policy
or checkpoint that does not fit, which stops the launch as it would for one agent) or an exception in any agent's
callback (1) ends the process, and with it every agent it hosts: the launcher restarts or stops the process as its
rules say for one agent, and the restarted agents rejoin as a restarted agent_node does.
"""

from __future__ import annotations

import sys

import rclpy
from rclpy.utilities import remove_ros_args

from htlm_agent.ros.agent_node import AgentNode, cleanup
from htlm_msgs_py.ros import SettingsError, run_nodes

USAGE = "usage: agents_node NODE=PARAMETERS_FILE [NODE=PARAMETERS_FILE ...] [--ros-args ...]"


def parse_hosted(words: list[str]) -> list[tuple[str, str]]:
    """(node name, parameters file) of every hosted agent, from the words before `--ros-args`.

    Raises:
        ValueError: no agent, a word that is not NODE=FILE, or a node named twice.
    """
    hosted: list[tuple[str, str]] = []
    for w in words:
        node, sep, path = w.partition("=")
        if not sep or not node or not path:
            raise ValueError(f"{w!r}: expected NODE=PARAMETERS_FILE")
        if node in (n for n, _ in hosted):
            raise ValueError(f"{node}: named twice")
        hosted.append((node, path))
    if not hosted:
        raise ValueError("no agent to host")
    return hosted


def node_args(node: str, params_file: str) -> list[str]:
    """The ROS arguments of one hosted node: its name and its parameters file."""
    return ["--ros-args", "-r", f"__node:={node}", "--params-file", params_file]


def main(args: list[str] | None = None) -> int:
    """Entry point of `agents_node` (exit code: 0 every hosted agent done, 1 an exception, 2 bad arguments,
    parameters, policy or checkpoint of any hosted agent, 130/143 SIGINT/SIGTERM)."""
    argv = sys.argv if args is None else args
    try:
        hosted = parse_hosted(remove_ros_args(argv)[1:])
    except ValueError as e:
        print(f"agents_node: {e}\n{USAGE}", file=sys.stderr)
        return 2

    def make_nodes() -> list[AgentNode]:
        log = rclpy.logging.get_logger("htlm_agents")
        log.info(f"hosting {len(hosted)} agents in one process: {', '.join(n for n, _ in hosted)}")
        nodes: list[AgentNode] = []
        try:
            for node, path in hosted:
                try:
                    nodes.append(AgentNode(node_args(node, path)))
                except SettingsError as e:
                    raise SettingsError(f"{node}: {e}") from None
        except BaseException:
            for n in nodes:  # the ones already made, so rclpy shuts down cleanly
                n.destroy_node()
            raise
        return nodes

    return run_nodes("agents_node", make_nodes, cleanup, argv)


if __name__ == "__main__":
    sys.exit(main())
