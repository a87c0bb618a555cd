"""The part every stand-in node of the robots' world shares: follow the run the world announces on /htlm/scenario.

A `RunFollower` decodes the world's scenario records (rejecting and counting bad ones), takes the scenario, seed
and run of the first valid one, and finishes when that run stops (`exit_on_stop`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from rclpy.node import Node

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    STATE_READER,
    Health,
    say_unsigned,
    start_node,
    subscribe_records,
)
from htlm_msgs_py.run_control import REFUSED, RunControl
from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.model import Model
from htlm_world.scenario import Scenario, ScenarioRecordError, from_record


class RunFollower(Node):
    """A node that follows the world's run: `scenario`, `model`, `seed`, `run` once announced; `on_run` hook."""

    def __init__(
        self,
        node_name: str,
        settings_cls: Any,
        validate: Callable[[Any], list[str]],
        health_name: str,
        cli_args: list[str] | None = None,
    ) -> None:
        """Declare the parameters of `settings_cls` (checked by `validate`, which lists their problems), the
        diagnostics and the scenario reader. `cli_args`: the node's own ROS arguments (a composed process's)."""
        super().__init__(node_name, cli_args=cli_args)
        self.settings, self.signer = start_node(self, settings_cls, validate)
        self.health = Health(self, health_name, self.signer)
        self.stop_signal = 0
        self.fatal: str | None = None
        self.run: str | None = None
        self.seed = 0
        self.scenario: Scenario | None = None
        self.model: Model | None = None
        self.lim: dict[str, int] | None = None
        self.stopped = False
        self.epoch = 0.0
        """The run's step clock epoch (external operation; 0 until announced)."""
        self.period, self.first_episode, self.episodes = 0.5, 0, 0
        self.control = RunControl()
        subscribe_records(self, topics.SCENARIO, STATE_READER, self._on_scenario)
        self.create_timer(self.settings.diagnostics_period, self._publish_health)
        say_unsigned(self, self.signer)

    def _on_scenario(self, msg: bytes) -> None:
        rec = self.health.decode("scenario", msg, S.SCENARIO)
        if rec is None:
            return
        verdict = self.control.take(rec)
        if verdict in REFUSED:
            self.health.reject("scenario", verdict, self.control.refused(rec))
            return
        if verdict != "join":
            self.stopped = verdict == "stop" or (self.stopped and verdict == "update")
            if self.epoch == 0.0 and self.run is not None:
                self.epoch = rec["epoch"]
            return
        try:
            sc = from_record(rec)
        except ScenarioRecordError as e:
            self.health.reject("scenario", e.reason, str(e))
            return
        self.run, self.seed, self.scenario, self.model = rec["run"], rec["seed"], sc, Model.build(sc)
        self.signer.run = self.run  # what we send carries it; records of other runs are rejected
        self.lim = S.limits(
            sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, rec["batch"], sc.knowledge_size
        )
        self.epoch = rec["epoch"]
        self.period, self.first_episode, self.episodes = rec["period"], rec["first_episode"], rec["episodes"]
        self.on_run(rec)
        self.stopped = rec["state"] == "stopped"

    def clock(self) -> StepClock | None:
        """The run's step clock (its epoch may still be 0: then every step lies ahead of it)."""
        if self.scenario is None:
            return None
        return StepClock(self.epoch, self.period, self.scenario.horizon, self.first_episode, self.episodes)

    def future(self, topic: str, rec: dict[str, Any]) -> bool:
        """Whether the per-step record `rec` names a step more than FUTURE_STEPS ahead of the run's clock (before
        the epoch is fixed: of the run's first step); such a record is rejected and counted (`future`), so no
        sender can fill a table of steps with far ones and push out the steps in progress."""
        c = self.clock()
        if c is None:
            return False
        wall = time.time() if self.epoch > 0.0 else -math.inf
        ahead = c.index(rec["episode"], rec["step"]) - (c.last(wall) if self.epoch > 0.0 else -1)
        if ahead <= FUTURE_STEPS:
            return False
        self.health.reject(topic, "future", f"episode {rec['episode']} step {rec['step']}: {ahead} steps ahead")
        return True

    def on_run(self, rec: dict[str, Any]) -> None:
        """The run `rec` (a scenario record) was announced: `scenario`, `model`, `seed`, `run` are set."""

    def fail(self, why: str) -> None:
        """A fatal problem: report it and finish (exit code 2)."""
        self.fatal = why
        self.health.error(why)
        self.get_logger().error(why)

    def finished(self) -> bool:
        """Whether the process should exit: a fatal problem, or the run stopped."""
        return self.fatal is not None or (self.stopped and bool(self.settings.exit_on_stop))

    def health_values(self) -> tuple[str, dict[str, str]]:
        """The status message and values of this node's diagnostics."""
        return "running", {}

    def _publish_health(self) -> None:
        message, values = self.health_values()
        self.health.values.update({"run": str(self.run), **values})
        if self.fatal is None:
            self.health.ok(message if self.run else "waiting for the world")
        self.health.publish()
