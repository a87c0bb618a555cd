"""trainer_node: collects every agent's transitions in a durable store, trains each agent's own Q-network with the
learner of `htlm train`, publishes weights and writes checkpoints in the same format.

A thin adapter around the ROS-free `htlm_agent.trainer.core.TrainerCore`, which decides everything (the run it
serves, resuming from run_dir, when to train, publish weights and checkpoint): the node decodes messages, feeds them
to the core and publishes what it returns. Transitions are acknowledged only after the store has fsynced them; an
agent keeps every unacknowledged transition and sends it again, so a trainer killed and restarted loses nothing an
agent had sent. Run: `ros2 run htlm_agent trainer_node --ros-args -p run_dir:=runs/x` or
`python -m htlm_agent.ros.trainer_node ...`.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from rclpy.node import Node

from htlm_agent.ros.settings import TrainerSettings, validate_trainer_settings
from htlm_agent.trainer.core import TrainerCore, TrainerEffects, load_learner_data
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    EVENTS,
    STATE_READER,
    WEIGHTS,
    Health,
    SettingsError,
    String,
    WorldWatch,
    run_node,
    say_unsigned,
    spin_until_finished,
    start_node,
    string,
    subscribe_records,
)
from htlm_msgs_py.schema import encode, limits


class TrainerNode(Node):
    """The trainer process."""

    def __init__(self) -> None:
        """Declare parameters, create publishers, subscriptions and timers; the learner waits for the scenario."""
        super().__init__("htlm_trainer")
        self.settings, self.signer = start_node(
            self, TrainerSettings, validate_trainer_settings, on_change=self._on_settings
        )
        s = self.settings
        try:
            data = load_learner_data(s.settings_file, s.settings_json)
        except ValueError as e:
            raise SettingsError(str(e)) from None
        self.core = TrainerCore(s.run_dir, s.schedule(), data, s.settings_file or "settings_json", s.resume)
        try:
            self.core.learner_settings(0)  # bad learner settings stop the node now, not when the run starts
        except ValueError as e:
            raise SettingsError(str(e)) from None
        self.core.control.wanted = s.run
        self.health = Health(self, "htlm: trainer", self.signer)
        self.stop_signal = 0
        self.fatal: str | None = None
        self.lim: dict[str, int] | None = None
        self.pub_weights: list[Any] = []
        self.pub_ack = self.create_publisher(String, topics.TRANSITION_ACK, EVENTS)
        self.pub_progress = self.create_publisher(String, topics.TRAINER_PROGRESS, EVENTS)
        subscribe_records(self, topics.SCENARIO, STATE_READER, self._on_scenario)
        subscribe_records(self, topics.TRANSITIONS, EVENTS, self._on_transition)
        subscribe_records(self, topics.EPISODE_METRICS, EVENTS, self._on_metrics)
        subscribe_records(self, topics.STEP, EVENTS, self._on_step)
        subscribe_records(self, topics.GROUND_TRUTH, EVENTS, self._on_ground_truth)
        self.world = WorldWatch(self, self.health, s.world_timeout)
        say_unsigned(self, self.signer)
        self.create_timer(s.diagnostics_period, self._publish_health)
        self.create_timer(s.ack_period, lambda: self._apply(self.core.flush()))
        self.create_timer(0.25, lambda: self._apply(self.core.tick(time.monotonic())))

    def _on_settings(self, new: TrainerSettings) -> None:
        self.settings = new
        self.core.schedule = new.schedule()

    def finished(self) -> bool:
        """Whether the process should exit: fatal error, or the run stopped and no transition came for a while."""
        if self.fatal is not None:
            return True
        if not (self.core.stopping and self.settings.exit_on_stop):
            return False
        return self.core.quiet_for(time.monotonic()) > self.settings.stop_grace

    # ----- messages in ------------------------------------------------------------------------------------------
    def _on_scenario(self, msg: bytes) -> None:
        rec = self.health.decode("scenario", msg, S.SCENARIO)
        if rec is None:
            return
        if rec["run"] == self.core.run or self.core.run is None:
            self.world.heard()
        self._apply(self.core.on_scenario(rec, time.monotonic()))
        sc = self.core.scenario
        if sc is not None and self.lim is None:
            self.lim = limits(
                sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, self.core.batch, sc.knowledge_size
            )

    def _on_transition(self, msg: bytes) -> None:
        if self.core.store is None:  # no scenario yet: the agents send it again until acknowledged
            self.health.counters["ignored/transitions/no_scenario"] += 1
            return
        rec = self.health.decode("transitions", msg, S.TRANSITION, self.lim)
        if rec is not None:
            self._apply(self.core.on_transition(rec, time.monotonic()))

    def _on_step(self, msg: bytes) -> None:
        rec = self.health.decode("step", msg, S.STEP, self.lim)  # validated and counted even when not training
        if rec is None:
            return
        if self.core.learner is None:  # no scenario yet, or a run that trains nothing: the steps pace nothing here
            self.health.drop("step", "not_training" if self.core.store is not None else "no_scenario")
            self._apply(self.core.on_step(rec, time.monotonic()))  # how far the run is, for the episode metrics
            return
        self.world.heard()
        self._apply(self.core.on_step(rec, time.monotonic()))

    def _on_ground_truth(self, msg: bytes) -> None:
        if self.core.rounds_of is None:  # only the expert-iteration learner reads the true levels
            return
        rec = self.health.decode("ground_truth", msg, S.GROUND_TRUTH, self.lim)
        if rec is not None:
            self._apply(self.core.on_ground_truth(rec))

    def _on_metrics(self, msg: bytes) -> None:
        rec = self.health.decode("episode_metrics", msg, S.EPISODE_METRICS, self.lim)
        if rec is not None:
            self._apply(self.core.on_metrics(rec))

    # ----- effects out ------------------------------------------------------------------------------------------
    def _apply(self, eff: TrainerEffects) -> None:
        self.signer.run = self.core.run  # what we send carries it; records of other runs are rejected
        h = self.health
        h.take(eff.drops, eff.rejects, eff.counters)
        log = self.get_logger()
        for level, text in eff.log:  # one call site per severity: rclpy's logger refuses to mix them on one line
            if level == "error":
                log.error(text)
            elif level == "warning":
                log.warning(text)
            else:
                log.info(text)
        if eff.fatal is not None:
            self.fatal = eff.fatal
            h.error(eff.fatal)
        for rec in eff.acks:
            self.pub_ack.publish(string(encode(S.TRANSITION_ACK, rec, self.signer)))
        if eff.weights and not self.pub_weights:
            assert self.core.scenario is not None
            self.pub_weights = [
                self.create_publisher(String, topics.weights(a.name), WEIGHTS) for a in self.core.scenario.agents
            ]
        for rec in eff.weights:  # the weights before the progress: an agent gets them no later than the world's step
            self.pub_weights[rec["agent"]].publish(string(encode(S.WEIGHTS, rec, self.signer)))
        for rec in eff.progress:
            self.pub_progress.publish(string(encode(S.TRAINER_PROGRESS, rec, self.signer)))

    def shutdown(self) -> None:
        """Flush the store, acknowledge, and write the final checkpoint."""
        self._apply(self.core.shutdown())

    def _publish_health(self) -> None:
        h = self.health
        h.values.update({**self.core.values(), "signed": str(self.signer.enabled).lower()})
        if self.fatal is None:
            h.ok("waiting for the world" if self.core.store is None else f"{self.core.updates} updates")
            if self.core.run is not None and not self.core.stopping:
                self.world.check()
        h.publish()


def _cleanup(node: TrainerNode) -> None:
    node.shutdown()
    node._publish_health()


def main(args: list[str] | None = None) -> int:
    """Entry point of `trainer_node` (exit code: 0 done, 2 bad parameters or store, 130/143 SIGINT/SIGTERM)."""
    return run_node("trainer_node", TrainerNode, spin_until_finished, _cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
