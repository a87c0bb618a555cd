"""The step clock of a deployed team, without ROS (docs/ros.md, Connecting your robots).

In an external operation (deployment) no node gates the steps: the run announcement fixes the `period` and the
`epoch`, and every process keeps the clock itself. Step t (1..h) of episode e is applied at its instant

    epoch + ((e - first_episode) * h + t - 1) * period      (wall-clock seconds)

an agent acts for step t before that instant, observes and hears its teammates after it, and acts for step t + 1
before the next one. A process that (re)starts mid-run computes the current step from the epoch and joins at the
next instant. This module is the one definition of that rule; the agents (`AgentSession`), the observing world
(`WorldProtocol`) and the robots' stand-in operation read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

FUTURE_STEPS = 3
"""How many steps ahead of a receiver's own clock a per-step record may name: an action for step t is sent before
its instant (one step ahead), and the hosts' clocks may differ by a quarter period. A record further ahead is
rejected and counted (`future`) before it takes a place in any per-step table, so no sender can fill a table with
steps far ahead and push out the records of the steps in progress."""


@dataclass(frozen=True)
class StepClock:
    """The instants of a run's steps on the wall clock (batch 1: one episode at a time)."""

    epoch: float
    """Wall-clock seconds of the instant of step 1 of the run's first episode."""
    period: float
    """Seconds between two instants."""
    horizon: int
    """h, steps per episode."""
    first_episode: int = 0
    """The run's first episode."""
    episodes: int = 0
    """Episodes of the run (0: until stopped)."""

    def index(self, episode: int, t: int) -> int:
        """The run-wide index of step t of `episode` (0 for the first step of the run)."""
        return (episode - self.first_episode) * self.horizon + t - 1

    def at(self, episode: int, t: int) -> float:
        """The wall-clock instant of step t of `episode`."""
        return self.epoch + self.index(episode, t) * self.period

    def step(self, i: int) -> tuple[int, int]:
        """(episode, t) of the run-wide index i."""
        e, t0 = divmod(i, self.horizon)
        return self.first_episode + e, t0 + 1

    def last(self, wall: float) -> int:
        """The index of the newest instant at or before `wall` (-1 before the epoch)."""
        if wall < self.epoch:
            return -1
        return math.floor((wall - self.epoch) / self.period + 1e-9)

    def ahead(self, episode: int, t: int, wall: float) -> int:
        """How many steps step t of `episode` lies ahead of the newest instant at or before `wall`."""
        return self.index(episode, t) - self.last(wall)

    def in_run(self, i: int) -> bool:
        """Whether index i is a step of the run."""
        return i >= 0 and (self.episodes == 0 or i < self.episodes * self.horizon)
