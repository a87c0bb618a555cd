"""world_node: the simulated operation over ROS 2, the world's side of the lockstep protocol (docs/ros.md).

A thin adapter: it decodes the agents' actions and readies, feeds them and the time to the ROS-free protocol of
the run's operation (`htlm_world.protocol.world_protocol`: the lockstep sequencer, or the observer of a deployed
team; it decides phases, deadlines, presence, late and duplicate answers, the free
clock, the episodes), and publishes the records the protocol returns. Run: `ros2 run htlm_world world_node` or
`python -m htlm_world.ros.world_node --ros-args -p episodes:=5`.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.node import Node

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.files import write_atomic
from htlm_msgs_py.ros import (
    EVENTS,
    STATE,
    WORLD_STATUS,
    Health,
    SettingsError,
    String,
    run_node,
    say_unsigned,
    start_node,
    string,
    subscribe_records,
)
from htlm_msgs_py.run_control import unique_run_id
from htlm_msgs_py.schema import encode, limits
from htlm_world.model import Model
from htlm_world.protocol import WorldEffects, world_protocol
from htlm_world.ros.markers import MarkerPublisher
from htlm_world.ros.settings import WorldSettings, load_scenario, validate_world_settings
from htlm_world.scenario import ScenarioError

SCHEMAS = {
    "scenario": S.SCENARIO,
    "step": S.STEP,
    "observation": S.OBSERVATION,
    "ground_truth": S.GROUND_TRUTH,
    "episode_metrics": S.EPISODE_METRICS,
}
"""The schema of every kind of record the protocol asks to publish."""


class WorldNode(Node):
    """The world process: owns the simulated operation and the lockstep clock."""

    def __init__(self) -> None:
        """Declare parameters, load the scenario, create publishers, subscriptions and timers."""
        super().__init__("htlm_world")
        self.settings, self.signer = start_node(self, WorldSettings, validate_world_settings, self._on_settings)
        s = self.settings
        try:
            self.scenario = load_scenario(s)
        except ScenarioError as e:
            raise SettingsError(f"scenario: {e}") from None
        sc = self.scenario
        self.lim = limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, s.batch, sc.knowledge_size)
        self.run_id = s.run_id or unique_run_id(f"run-{s.seed}-{int(time.time())}")
        self.signer.run = self.run_id  # every record carries it; records of other runs are rejected
        self.health = Health(self, WORLD_STATUS, self.signer)
        self.stop_signal = 0
        # publishers (QoS profiles from htlm_msgs_py)
        self.pub: dict[str, Any] = {
            "scenario": self.create_publisher(String, topics.SCENARIO, STATE),
            "step": self.create_publisher(String, topics.STEP, EVENTS),
            "ground_truth": self.create_publisher(String, topics.GROUND_TRUTH, EVENTS),
            "episode_metrics": self.create_publisher(String, topics.EPISODE_METRICS, EVENTS),
        }
        deployed = s.operation == "external"
        # simulated: the world sends every observation; deployed: the robots do, the world only listens (logs)
        self.pub_obs = (
            [] if deployed else [self.create_publisher(String, topics.observation(a.name), EVENTS) for a in sc.agents]
        )
        # the protocol: an episode begins once every agent answered and listens to its observations
        self.protocol = world_protocol(
            sc,
            s.lockstep(self.run_id),
            Model.build(sc),
            None if deployed else (lambda k: self.pub_obs[k].get_subscription_count() > 0),
        )
        self.markers = (  # /htlm/markers, for RViz2 and Foxglove
            MarkerPublisher(self, sc, lambda: self.settings.marker_episode) if s.markers else None
        )
        # subscriptions
        subscribe_records(self, topics.ACTION, EVENTS, self._on_action)
        subscribe_records(self, topics.READY, EVENTS, self._on_ready)
        subscribe_records(self, topics.TRAINER_PROGRESS, EVENTS, self._on_trainer)
        if deployed:
            subscribe_records(self, topics.SEVERITY, EVENTS, self._on_severity)
            for a in sc.agents:
                subscribe_records(self, topics.observation(a.name), EVENTS, self._on_observation)
        # timers
        self.create_timer(s.diagnostics_period, self._publish_health)
        self.log_file: Any = None
        self.progress_file: Path | None = None
        if s.run_dir:
            Path(s.run_dir).mkdir(parents=True, exist_ok=True)
            self.progress_file = Path(s.run_dir) / "world_progress.json"
            self._resume()
            self.log_file = open(Path(s.run_dir) / "world.jsonl", "a", encoding="utf-8")  # noqa: SIM115

    def _resume(self) -> None:
        """A world restarted in the run directory of its run continues it: the next episode it had not logged, the
        announcements' sequence after its last (world_progress.json, written durably as the run goes)."""
        assert self.progress_file is not None
        try:
            old = json.loads(self.progress_file.read_text())
        except FileNotFoundError:
            return
        except (OSError, ValueError) as e:
            raise SettingsError(f"run_dir: {self.progress_file}: unreadable progress ({e}); move it away") from None
        if not (isinstance(old, dict) and isinstance(old.get("seq"), int) and isinstance(old.get("next_episode"), int)):
            raise SettingsError(f"run_dir: {self.progress_file}: not a world progress record: {str(old)[:200]}")
        if old.get("run") != self.run_id:
            return  # another run used this directory: a new run starts
        nxt = self._logged_until(old["next_episode"])
        epoch = old.get("epoch", 0.0)
        self.protocol.resume(old["seq"], nxt, float(epoch) if isinstance(epoch, (int, float)) else 0.0)
        self.get_logger().warning(
            f"run {self.run_id}: the world restarted; continuing at episode {nxt} (announcement {old['seq'] + 1})"
        )

    def _logged_until(self, nxt: int) -> int:
        """The episode after the last one of this run in world.jsonl, at least `nxt`: the log is made durable before
        the progress, so a world killed between the two has logged a batch its progress does not hold yet."""
        assert self.progress_file is not None
        try:
            lines = self.progress_file.with_name("world.jsonl").read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            return nxt
        for line in lines:
            try:
                rec = json.loads(line)
                if rec["run"] == self.run_id:
                    nxt = max(nxt, int(rec["metrics"]["episode"]) + 1)
            except (ValueError, TypeError, KeyError):  # a line torn by the kill
                continue
        return nxt

    def _save_progress(self) -> None:
        """Write the protocol's progress durably (fsync, then an atomic rename)."""
        if self.progress_file is None:
            return
        write_atomic(self.progress_file, json.dumps(self.protocol.progress()), durable=True)

    def _on_settings(self, new: WorldSettings) -> None:
        self.settings = new
        self.protocol.settings = new.lockstep(self.run_id)

    # ----- messages in ------------------------------------------------------------------------------------------
    def _on_action(self, msg: bytes) -> None:
        rec = self.health.decode("action", msg, S.ACTION, self.lim)
        if rec is not None:
            self._apply(self.protocol.on_action(rec, time.monotonic()))

    def _on_ready(self, msg: bytes) -> None:
        rec = self.health.decode("ready", msg, S.READY, self.lim)
        if rec is not None:
            self._apply(self.protocol.on_ready(rec, time.monotonic()))

    def _on_trainer(self, msg: bytes) -> None:
        rec = self.health.decode("trainer_progress", msg, S.TRAINER_PROGRESS, self.lim)
        if rec is not None:
            self._apply(self.protocol.on_trainer(rec, time.monotonic()))

    def _on_severity(self, msg: bytes) -> None:
        rec = self.health.decode("severity", msg, S.SEVERITY, self.lim)
        if rec is not None:
            self._apply(self.protocol.on_severity(rec, time.monotonic()))

    def _on_observation(self, msg: bytes) -> None:
        rec = self.health.decode("observation", msg, S.OBSERVATION, self.lim)
        if rec is not None:
            self._apply(self.protocol.on_observation(rec, time.monotonic()))

    # ----- effects out ------------------------------------------------------------------------------------------
    def _apply(self, eff: WorldEffects) -> None:
        h = self.health
        h.take(eff.drops, eff.rejects, eff.counters)
        for kind, fields in eff.publish:
            if self.markers is not None:  # every record, also ground truth that nobody subscribes to
                self.markers.on_record(kind, fields)
            if kind == "observation":
                pub = self.pub_obs[fields["agent"]]
            else:
                pub = self.pub[kind]
                if kind == "ground_truth" and pub.get_subscription_count() == 0:
                    continue  # monitoring only: not worth encoding for nobody
            pub.publish(string(encode(SCHEMAS[kind], fields, self.signer)))
        log = self.get_logger()
        for level, text in eff.log:  # one call site per severity: rclpy's logger refuses to mix them on one line
            if level == "warning":
                log.warning(text)
            else:
                log.info(text)
        if self.log_file is not None and eff.episode_log:
            for line in eff.episode_log:
                self.log_file.write(json.dumps(line) + "\n")
            self.log_file.flush()
            os.fsync(self.log_file.fileno())  # once per batch: the log is durable before the progress says so
        if eff.episode_log or any(kind == "scenario" for kind, _ in eff.publish):
            self._save_progress()
        if eff.status_changed:
            self._publish_health()

    def _publish_health(self) -> None:
        h = self.health
        h.values.update({"run": self.run_id, **self.protocol.values(), "signed": str(self.signer.enabled).lower()})
        healthy, message = self.protocol.status()
        if healthy:
            h.ok(message)
        else:
            h.warn(message)
        h.publish()

    # ----- the run ------------------------------------------------------------------------------------------------
    def run(self, executor: Executor) -> int:
        """Run every episode; returns the exit code (0 done, 128 + signal number when stopped by a signal)."""
        s, sc, proto = self.settings, self.scenario, self.protocol
        self.health.message = "running"
        self.get_logger().info(
            f"run {self.run_id}: {sc.name}/{sc.team}, {sc.n_agents} agents, h={sc.horizon}, seed {s.seed}, "
            f"mode {s.mode}, clock {s.clock}, operation {s.operation}, "
            f"{s.episodes or 'unlimited'} episodes in batches of {s.batch}, "
            f"pace {'on' if proto.settings.pace else 'off'}, "
            f"signing {'on' if self.signer.enabled else 'off'}"
        )
        say_unsigned(self, self.signer)
        proto.wall_offset = time.time() - time.monotonic()  # the agents' step clock is on the wall clock
        self._apply(proto.start(time.monotonic()))
        while not proto.done and not self.stop_signal:
            wait = proto.next_wakeup() - time.monotonic()
            executor.spin_once(timeout_sec=min(max(wait, 0.0), 0.25))
            if not rclpy.ok():
                raise ExternalShutdownException()
            if not self.stop_signal:
                self._apply(proto.tick(time.monotonic()))
        if self.stop_signal:
            self._apply(proto.stop(time.monotonic()))
        if self.markers is not None:
            self.markers.close()  # the DELETEALL of the end reaches RViz before the node goes away
        if self.log_file is not None:
            self.log_file.close()
        return 128 + self.stop_signal if self.stop_signal else 0


def main(args: list[str] | None = None) -> int:
    """Entry point of `world_node` (exit code: 0 done, 2 bad parameters, 130/143 stopped by SIGINT/SIGTERM)."""
    return run_node("world_node", WorldNode, lambda node, executor: node.run(executor), lambda node: None, args)


if __name__ == "__main__":
    sys.exit(main())
