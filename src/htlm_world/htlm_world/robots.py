"""Robots in the map frame, without ROS: arrival at a site, a robot that drives to its goal, and the stand-in
operation of the simulated robots (docs/ros.md, Connecting your robots).

The model has no travel: an assignment takes effect in the step it is chosen. With real robots an agent works on
its task, and observes it, only once its robot is at the task's site (within an arrival radius). The simulated
robots (`htlm_world.ros.robot_node`) and their stand-in operation (`htlm_world.ros.operation_node`) apply exactly
that: a robot that has not arrived adds no capability to its task and publishes no observation that step. A step
period that lets a robot reach any site within its step (`arrival_period`) is what makes a deployment the model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import IntArray


def site_distance(scenario: Scenario, site: int, x: float, y: float) -> float:
    """Distance (metres, map frame) from (x, y) to the position of `site`."""
    sx, sy = scenario.site_positions[site]
    return math.hypot(x - sx, y - sy)


def action_distance(model: Model, action: int, x: float, y: float) -> float:
    """Distance from (x, y) to the site of `action` (an index of G-bar)."""
    return site_distance(model.scenario, int(model.action_site[action]), x, y)


ROBOT_READY = "ready, waiting for the run"
"""What a simulated robot logs once it is up (`htlm launch` starts the agents and the world after it)."""

STILL_PERIOD = 1.0
"""Seconds between the odometry messages of a simulated robot that stands still (it publishes at its `rate` while it
drives, and once more when it stops): fifty robots waiting at their sites cost the team's cores little."""


def odometry_due(moving: bool, was_moving: bool, since: float) -> bool:
    """Whether a simulated robot publishes its odometry at a motion update: while it drives, at the update it stopped
    at, and once `STILL_PERIOD` passed since it last did (`since`, seconds)."""
    return moving or was_moving or since >= STILL_PERIOD


ARRIVAL_MARGIN = 0.5
"""Seconds a step leaves, beyond the drive, for an agent to hear its teammates and send its goal after the step's
instant (`arrival_period`)."""

DRIVE_SLACK = 1.1
"""The longest drive's time is stretched by this factor in `arrival_period` (a robot that accelerates or turns)."""


def longest_drive(scenario: Scenario) -> tuple[float, int, int]:
    """The longest straight drive between two of the scenario's sites: (metres, site a, site b); (0, 0, 0) with one
    site or every site at the same position."""
    pos = np.asarray(scenario.site_positions, dtype=float)
    d = np.hypot(pos[:, None, 0] - pos[None, :, 0], pos[:, None, 1] - pos[None, :, 1])
    a, b = np.unravel_index(int(d.argmax()), d.shape)
    return float(d[a, b]), int(a), int(b)


def arrival_period(scenario: Scenario, speed: float) -> float:
    """The shortest step period, seconds (a multiple of 0.1), in which a robot at `speed` m/s reaches any site of the
    scenario within the step it is sent there, as the model assumes (docs/ros.md, Arrival): the longest drive
    between two sites times `DRIVE_SLACK`, plus `ARRIVAL_MARGIN`. With no drive to make (or a robot that does not
    move) just the margin."""
    metres, _, _ = longest_drive(scenario)
    drive = metres / speed if speed > 0 and metres > 0 else 0.0
    return math.ceil((drive * DRIVE_SLACK + ARRIVAL_MARGIN) * 10.0 - 1e-9) / 10.0


@dataclass
class Drive:
    """A robot that drives in a straight line to its goal at a fixed speed (the navigation stack's stand-in)."""

    x: float
    """Position, metres, map frame."""
    y: float
    speed: float
    """Metres per second (0: the robot never moves)."""
    goal: tuple[float, float] | None = None
    """Where it drives to (None: it stays)."""

    def advance(self, dt: float) -> tuple[float, float]:
        """Drive `dt` seconds towards the goal (stopping on it); returns the velocity (vx, vy) of the move."""
        if self.goal is None or dt <= 0.0:
            return 0.0, 0.0
        gx, gy = self.goal
        dx, dy = gx - self.x, gy - self.y
        dist = math.hypot(dx, dy)
        if dist == 0.0:
            return 0.0, 0.0
        step = min(dist, self.speed * dt)
        self.x += dx / dist * step
        self.y += dy / dist * step
        v = step / dt
        return dx / dist * v, dy / dist * v


class StandInOperation:
    """The true task levels of one episode, as the simulated robots' world: T applied to the capabilities of the
    robots that are at their task's site (docs/model.md, Transition T), with the stream `seeds.robot_operation`."""

    def __init__(self, scenario: Scenario, model: Model, seed: int, episode: int) -> None:
        """Episode `episode` of the run with master seed `seed`, at the scenario's initial levels."""
        self.scenario = scenario
        self.model = model
        self.episode = episode
        self.rng = seeds.robot_operation(seed, episode)
        self.levels: IntArray = np.array([scenario.initial_levels], dtype=np.int64)  # (1, p)
        self.t = 0

    def step(self, actions: IntArray, arrived: np.ndarray) -> IntArray:
        """Apply step t + 1: `actions` (N,) the joint assignment the world applied, `arrived` (N,) whether each
        robot is at the site of its action; a robot on its way works on nothing. Returns the levels (p,)."""
        joint = np.where(arrived, actions, self.model.idle_action(actions)).astype(np.int64)[None, :]
        caps = self.model.joint_capability(joint)
        self.levels = self.model.sample_transition(self.levels, caps, self.rng.random(self.levels.shape))
        self.t += 1
        out: IntArray = self.levels[0].copy()
        return out


class Sensing:
    """One simulated robot's perception of its task: a level drawn from O (docs/model.md, Observation O) with its
    own stream `seeds.robot_sensing`."""

    def __init__(self, model: Model, agent: int, seed: int, episode: int) -> None:
        """Robot of agent index `agent` in `episode` of the run with master seed `seed`."""
        self.model = model
        self.agent = agent
        self.rng = seeds.robot_sensing(seed, agent, episode)

    def observe(self, task: int, true_level: int) -> int:
        """The observed level of task `task` whose true level is `true_level`."""
        z = self.model.sample_observation(
            np.array([task]),
            np.array([true_level]),
            self.model.sensing[self.agent : self.agent + 1],
            self.rng.random(1),
        )
        return int(z[0])


def map_bounds(sites: Sequence[tuple[float, float]], margin: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """((x_lo, y_lo), (x_hi, y_hi)): the bounding box of the sites' positions widened by `margin` metres, the map a
    robot takes goals in."""
    xs, ys = [float(p[0]) for p in sites], [float(p[1]) for p in sites]
    return (min(xs) - margin, min(ys) - margin), (max(xs) + margin, max(ys) + margin)
