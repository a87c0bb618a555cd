"""An agent's observations in a deployed team, without ROS (docs/ros.md, Connecting your robots).

In a deployed team (operation external) the world simulates nothing: its step record says that step t was applied
and whose actions it applied, and the agent's own robot publishes the observation of its task, or nothing (it is on
its way, idle, or its perception saw nothing). `DeployObservations` pairs the two: the step is observed as soon as
both are in, or `wait` seconds after the step record with no observation (level -1: the belief predicts). A robot's
observation that comes after that is late and dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Observed:
    """A step ready for `AgentMind.observe`."""

    episode: int
    step: int
    levels: list[int]
    """Per episode of the batch, the observed level (-1: no observation)."""
    acted: list[int]
    """The agents whose actions the world applied (from its step record)."""


class DeployObservations:
    """Pairs the world's step records with the robot's observations (batch of `size` episodes)."""

    KEEP = 64
    """Most unpaired records kept (the oldest are forgotten first)."""

    def __init__(self, size: int = 1) -> None:
        """Nothing heard yet."""
        self.size = size
        self.robot: dict[tuple[int, int], list[int]] = {}
        self.steps: dict[tuple[int, int], tuple[list[int], float]] = {}
        self.done: set[tuple[int, int]] = set()
        self.late = 0
        """Robot observations that came after their step was observed without them."""
        self.missing = 0
        """Steps observed without a robot observation."""

    def on_step(self, episode: int, step: int, acted: list[int], now: float, wait: float) -> list[Observed]:
        """The world's step record: step t was applied with the actions of `acted`."""
        key = (episode, step)
        if key in self.done or key in self.steps:
            return []
        self.steps[key] = (list(acted), now + wait)
        self._trim(self.steps)
        return self._pair(key)

    def on_robot(self, episode: int, step: int, levels: list[int]) -> list[Observed]:
        """The robot's observation of step t (one level per episode of the batch)."""
        key = (episode, step)
        if key in self.done:
            self.late += 1
            return []
        self.robot[key] = list(levels)
        self._trim(self.robot)
        return self._pair(key) if key in self.steps else []

    def due(self, now: float) -> list[Observed]:
        """The steps whose wait is over: observed without the robot."""
        out = []
        for key, (_acted, deadline) in sorted(self.steps.items()):
            if now >= deadline:
                self.missing += 1
                out += self._pair(key, [-1] * self.size)
        return out

    def next_deadline(self) -> float | None:
        """When `due` next has something to return (None: nothing waits)."""
        return min((d for _a, d in self.steps.values()), default=None)

    def values(self) -> dict[str, str]:
        """The counts of steps observed without the robot and of its late observations, for the node's
        /diagnostics."""
        return {"observations_missing": str(self.missing), "observations_late": str(self.late)}

    def _pair(self, key: tuple[int, int], levels: list[int] | None = None) -> list[Observed]:
        got = self.robot.pop(key, None) if levels is None else levels
        if got is None:
            return []
        acted, _deadline = self.steps.pop(key)
        self.done.add(key)
        if len(self.done) > self.KEEP:
            self.done.remove(min(self.done))
        return [Observed(key[0], key[1], got, acted)]

    def _trim(self, table: dict[tuple[int, int], Any]) -> None:
        while len(table) > self.KEEP:
            del table[min(table)]
