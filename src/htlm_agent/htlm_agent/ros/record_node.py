"""record_node: the team's topics into a ROS 2 bag in MCAP storage (`htlm launch --record`).

A thin node: it subscribes to every topic of the topic table (`htlm_agent.experiments.recording.recorded_topics`:
every /htlm/* topic, the per-agent ones for each agent, and /diagnostics), takes each message serialized, as rmw
delivered it (`raw=True`: nothing is deserialized or serialized again), and hands it with its arrival time to the
ROS-free `Recording`, which writes it with `rosbags`. It reads the world's run announcements only to learn the agents
(when not given) and when the run stops; after that, or after SIGINT/SIGTERM, it closes the bag once the team has
been quiet for `stop_grace` seconds. Run: `ros2 run htlm_agent record_node --ros-args -p path:=runs/x/recording`.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.executors import Executor
from rclpy.node import Node

from htlm_agent.experiments.recording import (
    RecordedTopic,
    Recording,
    RecordSettings,
    agent_topics,
    free_path,
    recorded_topics,
    validate_record_settings,
)
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    Health,
    qos_profile,
    run_node,
    start_node,
)
from htlm_msgs_py.run_control import REFUSED, RunControl, Verdict

SIGNAL_LIMIT = 5.0
"""Longest the recorder goes on after a SIGINT or SIGTERM, seconds."""


class RecordNode(Node):
    """Subscriptions that write every message into a Recording."""

    def __init__(self) -> None:
        """Parameters, the bag, a subscription per topic (the agents' once known)."""
        super().__init__("htlm_recorder")
        self.settings, self.signer = start_node(self, RecordSettings, validate_record_settings)
        self.health = Health(self, "htlm: recorder", self.signer)
        self.stop_signal = 0
        self.fatal: str | None = None
        self.control = RunControl()
        self.stopped_at: float | None = None
        """When the run's stop was heard (monotonic), None while it goes on."""
        self.last = time.monotonic()
        """When the last message of a team topic (not /diagnostics) arrived."""
        self.recording = Recording(free_path(Path(self.settings.path)))
        self._readers: dict[str, Any] = {}
        agents = [a for a in self.settings.agents.split(",") if a]
        for t in recorded_topics(agents):
            if "<agent>" not in t.name:
                self._subscribe(t)
        self.create_timer(self.settings.diagnostics_period, self._publish_health)
        self.get_logger().info(f"recording {len(self._readers)} topics into {self.recording.path}")

    def _subscribe(self, t: RecordedTopic) -> None:
        if t.name in self._readers:
            return
        self.recording.add(t)
        msg_class = _message_class(t.msg_type)
        self._readers[t.name] = self.create_subscription(
            msg_class, t.name, functools.partial(self._on_message, t.name), qos_profile(t.reader), raw=True
        )

    def _on_message(self, topic: str, data: bytes) -> None:
        self.recording.write(topic, data, time.time_ns())
        if topic != topics.DIAGNOSTICS:
            self.last = time.monotonic()
        if topic == topics.SCENARIO:
            self._on_scenario(data)

    def _on_scenario(self, data: bytes) -> None:
        rec = self.health.decode("scenario", data, S.SCENARIO)
        if rec is None:
            return
        verdict = self.control.take(rec)
        if verdict in REFUSED:
            self.health.reject("scenario", verdict, self.control.refused(rec))
            return
        if verdict == Verdict.JOIN:
            for a in rec["scenario"].get("agents", []):
                for t in agent_topics(str(a["name"])):
                    self._subscribe(t)
        if rec["state"] == "stopped" and self.stopped_at is None:
            self.stopped_at = time.monotonic()
        elif rec["state"] == "running":
            self.stopped_at = None

    def finished(self) -> bool:
        """Whether the run stopped and its last messages are in (exit_on_stop)."""
        return (
            self.settings.exit_on_stop
            and self.stopped_at is not None
            and time.monotonic() - max(self.stopped_at, self.last) > self.settings.stop_grace
        )

    def _publish_health(self) -> None:
        self.health.values.update(
            {"bag": str(self.recording.path), "bytes": str(self.recording.bytes), "run": str(self.control.run)}
        )
        self.health.ok(f"{sum(self.recording.counts.values())} messages recorded")
        self.health.publish()


def _message_class(msg_type: str) -> Any:
    """The rclpy message class of an interface name such as std_msgs/msg/String."""
    import importlib

    package, _, name = msg_type.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def record(node: RecordNode, executor: Executor) -> int:
    """Spin until the run is over (or a signal), then until the team is quiet; returns the exit code."""
    while not node.stop_signal and not node.finished():
        executor.spin_once(timeout_sec=0.25)
    if node.stop_signal:  # the world's last messages (its stop, the markers' removal) are on their way
        end = time.monotonic() + SIGNAL_LIMIT
        node.last = time.monotonic()
        while time.monotonic() < end and time.monotonic() - node.last <= node.settings.stop_grace:
            executor.spin_once(timeout_sec=0.1)
        return 128 + int(node.stop_signal)
    return 0


def close(node: RecordNode) -> None:
    """Complete the bag (the MCAP summary and metadata.yaml) and log what it holds."""
    node.recording.close()
    counts = node.recording.counts
    wall = time.monotonic() - node.health.started
    node.get_logger().info(
        f"recorded {sum(counts.values())} messages ({node.recording.bytes} bytes) on {len(counts)} topics into "
        f"{node.recording.path} in {wall:.1f} s, {time.process_time():.1f} s of CPU"
    )


def main(args: list[str] | None = None) -> int:
    """Entry point of `record_node` (exit code: 0 run over, 2 bad parameters, 130/143 SIGINT/SIGTERM)."""
    return run_node("record_node", RecordNode, record, close, args)


if __name__ == "__main__":
    sys.exit(main())
