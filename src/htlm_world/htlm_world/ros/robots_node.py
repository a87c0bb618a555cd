"""robots_node: several simulated robots in one process, each its own node (a composed process).

As `htlm_agent.ros.agents_node` hosts agents, this process hosts several `RobotNode`s in one rclpy executor, each with
its own node name, parameters, odometry, goal and observation topics: on the graph they are the nodes their own
processes would be; they share the interpreter, its imports and one DDS participant. `htlm launch --robots sim` groups
the robots as it groups the agents (`--agents-per-process`; docs/ros.md, A large team on one machine): fifty
simulated robots in fifty processes are fifty interpreters and fifty participants that discover one another.

    python -m htlm_world.ros.robots_node htlm_robot_agent1=RUN/parameters/robot_agent1.yaml htlm_robot_agent2=...

Every word before `--ros-args` is NODE=PARAMETERS_FILE, the file the robot's own robot_node would get. The process
keeps a process's rules for all of them (`htlm_msgs_py.ros.lifecycle.run_nodes`).
"""

from __future__ import annotations

import sys

from htlm_msgs_py.ros.lifecycle import host_nodes
from htlm_world.ros.robot_node import RobotNode


def main(args: list[str] | None = None) -> int:
    """Entry point of `robots_node` (exit code: 0 every hosted robot done, 1 an exception, 2 bad arguments or
    parameters of any hosted robot, 130/143 SIGINT/SIGTERM)."""
    return host_nodes("robots_node", "robot", RobotNode, lambda node: None, args)


if __name__ == "__main__":
    sys.exit(main())
