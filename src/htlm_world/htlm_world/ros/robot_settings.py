"""Settings of the simulated robots and of their stand-in operation (htlm_world.ros.robot_node, operation_node):
one ROS parameter per field. Plain dataclasses (no rclpy)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from htlm_msgs_py.params import SECONDS, problems, setting

EXECUTORS = ("events", "single")
"""events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


@dataclass(frozen=True)
class RobotSettings:
    """Parameters of one simulated robot (the stand-in for a robot stack: navigation, odometry, perception)."""

    agent: str = setting("")
    """The agent this robot carries out (its name in the scenario); required."""
    speed: float = setting(20.0, lo=0.0, hi=1e4)
    """Driving speed, metres per second (0: the robot never leaves its start site)."""
    rate: float = setting(20.0, lo=1.0, hi=1000.0)
    """Motion updates per second, each with an odometry message while the robot drives (standing still, one a
    second)."""
    arrival_radius: float = setting(2.0, lo=0.0, hi=1e6)
    """Metres from a site within which the robot is there: it works on its task and observes it."""
    start: str = setting("")
    """Start position "x,y" in the map frame (metres); empty: the site of the scenario's start assignment."""
    goal_topic: str = setting("")
    """Where the robot takes its goals (geometry_msgs/PoseStamped); empty: /htlm/<agent>/goal_pose."""
    odom_topic: str = setting("")
    """Where the robot publishes its nav_msgs/Odometry; empty: /htlm/<agent>/odom."""
    observation_topic: str = setting("")
    """Where the robot publishes its observations; empty: /htlm/<agent>/observation."""
    frame_id: str = setting("map")
    """Frame of the odometry's pose (the goal poses' frame)."""
    map_margin: float = setting(100.0, lo=0.0, hi=1e6)
    """Metres around the scenario's sites (their bounding box) within which the robot takes a goal; a goal beyond,
    or not finite, is rejected and counted."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run."""
    executor: str = setting("events", choices=EXECUTORS)
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


@dataclass(frozen=True)
class OperationSettings:
    """Parameters of the stand-in operation: the true task levels of the simulated robots' world."""

    arrival_radius: float = setting(2.0, lo=0.0, hi=1e6)
    """Metres from a site within which a robot works on its task there."""
    people: str = setting("")
    """Comma-separated agents that people play (no robot): each works on the task its agent sent for the step,
    wherever that is (a person walks there within the step)."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run."""
    executor: str = setting("events", choices=EXECUTORS)
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


def validate_robot_settings(s: RobotSettings) -> list[str]:
    """Problems of a RobotSettings, each naming the parameter and the value (empty when valid)."""
    bad = problems(s)
    if not s.agent or not s.agent.replace("_", "").isalnum() or not s.agent[0].isalpha():
        bad.append(f"agent: {s.agent!r} must be an agent name of the scenario (letters, digits, _)")
    if not s.frame_id:
        bad.append("frame_id: '' must not be empty")
    if s.start and start_position(s.start) is None:
        bad.append(f"start: {s.start!r} must be two finite numbers x,y (metres)")
    return bad


def start_position(text: str) -> tuple[float, float] | None:
    """The (x, y) of a `start` parameter, None when it is not two finite numbers."""
    parts = text.split(",")
    try:
        x, y = (float(v) for v in parts)
    except ValueError:
        return None
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


def validate_operation_settings(s: OperationSettings) -> list[str]:
    """Problems of an OperationSettings (empty when valid)."""
    return problems(s)
