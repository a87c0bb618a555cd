"""robot_node: a simulated robot, the stand-in for one agent's robot stack (docs/ros.md, Connecting your robots).

It does what a real robot stack does for an HTLM agent: it follows the agent's goal pose (geometry_msgs/PoseStamped
on /htlm/<agent>/goal_pose) at a set speed, publishes its nav_msgs/Odometry (frame map) and, when it is at the site
of the task its agent works on, publishes the agent's observation of that task on /htlm/<agent>/observation: a
level drawn from the model's O (its own stream) from the true level the stand-in operation reports on
/htlm/severity. A robot on its way, or idle, observes nothing. Start one per agent with an external-operation world:
`python -m htlm_world.ros.robot_node --ros-args -p agent:=agent1` (or `htlm launch deploy --robots sim`).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from nav_msgs.msg import Odometry

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    EVENTS,
    ODOMETRY,
    STATE_READER,
    PoseStamped,
    String,
    run_node,
    spin_until_finished,
    string,
    subscribe_records,
)
from htlm_msgs_py.schema import encode
from htlm_world.robots import ROBOT_READY, Drive, Sensing, action_distance, map_bounds, odometry_due
from htlm_world.ros.follower import RunFollower
from htlm_world.ros.robot_settings import RobotSettings, start_position, validate_robot_settings


class RobotNode(RunFollower):
    """One simulated robot."""

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """Parameters, publishers, subscriptions, the motion timer; the robot appears once the run is announced.
        `cli_args`: its own ROS arguments when a composed process hosts it (`robots_node`)."""
        super().__init__("htlm_robot", RobotSettings, validate_robot_settings, "htlm: robot", cli_args)
        s: RobotSettings = self.settings
        self.name = s.agent
        self.health.name = f"htlm: robot {self.name}"
        self.index = -1
        self.drive: Drive | None = None
        self.actions: dict[tuple[int, int], int] = {}  # (episode, step) -> its agent's action
        self.sensing: Sensing | None = None
        self.sensing_episode = -1
        self.sent = 0
        self.last = time.monotonic()
        self.pub_odom = self.create_publisher(Odometry, s.odom_topic or topics.odometry(self.name), ODOMETRY)
        self.pub_obs = self.create_publisher(String, s.observation_topic or topics.observation(self.name), EVENTS)
        self.create_subscription(PoseStamped, s.goal_topic or topics.goal_pose(self.name), self._on_goal, STATE_READER)
        subscribe_records(self, topics.goal(self.name), STATE_READER, self._on_goal_record)
        self.goal_sent = -math.inf
        """When the agent sent the last goal record taken (its wall clock): an older one is a replay."""
        subscribe_records(self, topics.ACTION, EVENTS, self._on_action)
        subscribe_records(self, topics.SEVERITY, EVENTS, self._on_severity)
        self.odom_sent = -math.inf
        self.was_moving = False
        self.create_timer(1.0 / s.rate, self._move)
        self.get_logger().info(f"robot of {self.name}: {ROBOT_READY}")

    def on_run(self, rec: dict[str, Any]) -> None:
        """Place the robot at the site of the scenario's start assignment."""
        sc, model = self.scenario, self.model
        assert sc is not None and model is not None
        names = [a.name for a in sc.agents]
        if self.name not in names:
            self.fail(f"agent {self.name!r} is not in the scenario's team {names}")
            return
        self.index = names.index(self.name)
        x, y = start_position(self.settings.start) or sc.site_positions[int(model.action_site[sc.start_assignment])]
        # an operation with travel gives every agent its speed (docs/model.md, Travel): the robot drives at it
        speed = sc.agent_speed(self.index) if sc.travel else self.settings.speed
        self.drive = Drive(float(x), float(y), speed)
        self.get_logger().info(f"run {self.run}: robot of {self.name} at ({x:g}, {y:g}), {speed:g} m/s")

    def _on_goal(self, msg: PoseStamped) -> None:
        """A goal pose. With a team key it is not followed (anybody on the domain could have sent it): the signed
        twin on /htlm/<agent>/goal is (`_on_goal_record`)."""
        if self.signer.enabled:
            self.health.counters["ignored/goal_pose/unsigned"] += 1
            return
        if msg.header.frame_id != self.settings.frame_id:
            self.health.reject("goal_pose", "frame", f"frame {msg.header.frame_id!r}, not {self.settings.frame_id!r}")
            return
        self._drive_to("goal_pose", float(msg.pose.position.x), float(msg.pose.position.y))

    def _on_goal_record(self, msg: bytes) -> None:
        """The goal as a record (signed with the team key): followed when it is its agent's, newer than the last
        one taken, and in the map."""
        rec = self.health.decode("goal", msg, S.GOAL, self.lim)
        if rec is None or self.drive is None:
            return
        if rec["agent"] != self.index:
            self.health.reject("goal", "agent", f"goal for agent {rec['agent']} on {self.name}'s topic")
            return
        if rec["frame"] != self.settings.frame_id:
            self.health.reject("goal", "frame", f"frame {rec['frame']!r}, not {self.settings.frame_id!r}")
            return
        if rec["sent"] <= self.goal_sent:
            self.health.drop("goal", "past")
            return
        if self._drive_to("goal", rec["x"], rec["y"]):
            self.goal_sent = rec["sent"]

    def _drive_to(self, topic: str, x: float, y: float) -> bool:
        """Drive to (x, y) if it is a finite point in the map (within `map_margin` of the scenario's sites), else
        reject and count it (`range`); returns whether the goal was taken."""
        if self.drive is None or self.scenario is None:
            return False
        lo, hi = map_bounds(self.scenario.site_positions, self.settings.map_margin)
        if not (math.isfinite(x) and math.isfinite(y) and lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]):
            self.health.reject(topic, "range", f"goal ({x}, {y}) outside the map [{lo}, {hi}]")
            return False
        self.drive.goal = (x, y)
        return True

    def _on_action(self, msg: bytes) -> None:
        rec = self.health.decode("action", msg, S.ACTION, self.lim)
        if rec is None or rec["agent"] != self.index or self.future("action", rec):
            return
        self.actions[(rec["episode"], rec["step"])] = int(rec["actions"][0])
        while len(self.actions) > 64:
            del self.actions[min(self.actions)]

    def _on_severity(self, msg: bytes) -> None:
        """The true levels after step t: observe the task our agent works on if we are at its site."""
        rec = self.health.decode("severity", msg, S.SEVERITY, self.lim)
        if rec is None or self.drive is None or self.model is None or self.scenario is None:
            return
        e, t = rec["episode"], rec["step"]
        a = self.actions.get((e, t))
        if a is None or a >= self.scenario.n_tasks:
            return  # idle, or no action of ours was heard for the step: nothing to observe
        if action_distance(self.model, a, self.drive.x, self.drive.y) > self.settings.arrival_radius:
            self.health.counters["not_there"] += 1
            return
        if self.sensing is None or self.sensing_episode != e:
            self.sensing, self.sensing_episode = Sensing(self.model, self.index, self.seed, e), e
        z = self.sensing.observe(a, int(rec["levels"][0][a]))
        fields = {"agent": self.index, "episode": e, "step": t, "tasks": [a], "levels": [z], "acted": [self.index]}
        self.pub_obs.publish(string(encode(S.OBSERVATION, fields, self.signer)))
        self.sent += 1

    def _move(self) -> None:
        now = time.monotonic()
        dt, self.last = now - self.last, now
        if self.drive is None:
            return
        vx, vy = self.drive.advance(dt)
        moving = (vx, vy) != (0.0, 0.0)
        if not odometry_due(moving, self.was_moving, now - self.odom_sent):
            return
        self.was_moving, self.odom_sent = moving, now
        msg = Odometry()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.settings.frame_id
        msg.child_frame_id = f"{self.name}/base_link"
        msg.pose.pose.position.x = self.drive.x
        msg.pose.pose.position.y = self.drive.y
        msg.pose.pose.orientation.w = 1.0
        msg.twist.twist.linear.x = vx
        msg.twist.twist.linear.y = vy
        self.pub_odom.publish(msg)

    def health_values(self) -> tuple[str, dict[str, str]]:
        """Position, goal and observations sent."""
        d = self.drive
        if d is None:
            return "waiting for the world", {}
        goal = "none" if d.goal is None else f"{d.goal[0]:g},{d.goal[1]:g}"
        moving = d.goal is not None and (d.x, d.y) != d.goal
        return (
            f"{'driving to' if moving else 'at'} {goal if moving else f'{d.x:g},{d.y:g}'}",
            {"x": f"{d.x:.3f}", "y": f"{d.y:.3f}", "goal": goal, "observations_sent": str(self.sent)},
        )


def main(args: list[str] | None = None) -> int:
    """Entry point of `robot_node` (exit code: 0 run over, 2 bad parameters, 130/143 SIGINT/SIGTERM)."""
    return run_node("robot_node", RobotNode, spin_until_finished, lambda node: None, args)


if __name__ == "__main__":
    sys.exit(main())
