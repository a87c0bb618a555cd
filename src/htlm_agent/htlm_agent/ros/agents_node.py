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

from htlm_agent.ros.agent_node import AgentNode, cleanup
from htlm_msgs_py.ros.lifecycle import host_nodes, node_args, parse_hosted

__all__ = ["main", "node_args", "parse_hosted"]


def main(args: list[str] | None = None) -> int:
    """Entry point of `agents_node` (exit code: 0 every hosted agent done, 1 an exception, 2 bad arguments,
    parameters, policy or checkpoint of any hosted agent, 130/143 SIGINT/SIGTERM)."""
    return host_nodes("agents_node", "agent", AgentNode, cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
