"""The ROS-facing half of the wire contract: QoS profiles, message classes, diagnostics, record subscriptions.

This package is the only part of htlm_msgs_py that imports rclpy and the message classes of common_interfaces; the
rest of the package (and the whole model core) imports without them. Node parameters are declared by `parameters`,
and a node process's start-up, main and exit are `lifecycle`'s; both are re-exported here.
"""

from __future__ import annotations

import math
import os
import struct
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.subscription import Subscription
from std_msgs.msg import String

from .. import qos as _qos
from ..params import field_docs
from ..schema import Schema, WireError, decode, encode, record_text
from ..signing import Signer
from . import exit_timer
from .lifecycle import (
    FLUSH_SECONDS,
    TEARDOWN_SECONDS,
    flush,
    make_executor,
    run_node,
    run_nodes,
    spin_until,
    spin_until_finished,
    start_node,
)
from .parameters import SettingsError, declare_settings, parameter_descriptor

__all__ = [
    "DIAGNOSTICS",
    "EVENTS",
    "FLUSH_SECONDS",
    "ODOMETRY",
    "POSE_READER",
    "STATE",
    "STATE_READER",
    "STATUS_READER",
    "TEARDOWN_SECONDS",
    "WEIGHTS",
    "WORLD_STATUS",
    "DiagnosticArray",
    "Health",
    "PoseStamped",
    "SettingsError",
    "String",
    "WorldWatch",
    "declare_settings",
    "encode_msg",
    "exit_timer",
    "field_docs",
    "flush",
    "make_executor",
    "parameter_descriptor",
    "pose",
    "qos_profile",
    "run_node",
    "run_nodes",
    "say_unsigned",
    "spin_until",
    "spin_until_finished",
    "start_node",
    "string",
    "subscribe_records",
]


def qos_profile(spec: _qos.QosSpec) -> QoSProfile:
    """The rclpy QoSProfile of a named spec of htlm_msgs_py.qos."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=spec.depth,
        reliability=ReliabilityPolicy.RELIABLE if spec.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=(
            DurabilityPolicy.TRANSIENT_LOCAL if spec.durability == "transient_local" else DurabilityPolicy.VOLATILE
        ),
    )


STATE = qos_profile(_qos.STATE)
STATE_READER = qos_profile(_qos.STATE_READER)
EVENTS = qos_profile(_qos.EVENTS)
WEIGHTS = qos_profile(_qos.WEIGHTS)
DIAGNOSTICS = qos_profile(_qos.DIAGNOSTICS)
ODOMETRY = qos_profile(_qos.ODOMETRY)
POSE_READER = qos_profile(_qos.POSE_READER)
STATUS_READER = qos_profile(_qos.STATUS_READER)


def pose(x: float, y: float, frame: str, stamp: Any) -> PoseStamped:
    """A goal pose at (x, y) in `frame`, facing +x."""
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.header.stamp = stamp
    msg.pose.position.x = float(x)
    msg.pose.position.y = float(y)
    msg.pose.orientation.w = 1.0
    return msg


class Health:
    """Counters and status of one node, published as a diagnostic_msgs/DiagnosticArray on /diagnostics.

    Also the node's single place to decode received records: `decode` counts every rejection under
    `rejected/<topic>/<reason>` and logs it with a rate-limited warning, never raising.
    """

    def __init__(self, node: Node, name: str, signer: Signer, hardware_id: str = "") -> None:
        """Create the publisher of /diagnostics for `node`, reported under the status name `name`."""
        self.node = node
        self.name = name
        self.signer = signer
        self.hardware_id = hardware_id or os.uname().nodename
        self.counters: Counter[str] = Counter()
        self._warned: dict[str, float] = {}
        self.values: dict[str, str] = {}
        self.level = DiagnosticStatus.OK
        self.message = "starting"
        self.pub = node.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS)
        self.started = time.monotonic()
        self._key_values: dict[str, KeyValue] = {}  # made once per key: a message is costly to make in Python

    def decode(self, topic: str, data: bytes | str, schema: Schema, lim: Any = None) -> dict[str, Any] | None:
        """The validated fields of a received record (a serialized std_msgs/String as `subscribe_records` hands
        it over, or its text), or None (counted and logged) when it is rejected."""
        self.counters[f"arrived/{topic}"] += 1
        try:
            rec = decode(data if isinstance(data, str) else record_text(data), schema, lim, self.signer)
        except WireError as e:
            self.reject(topic, e.reason, e)  # explained only if warned about
            return None
        except Exception as e:
            self.reject(topic, "error", f"{type(e).__name__}: {e}")
            return None
        self.counters[f"received/{topic}"] += 1
        return rec

    def reject(self, topic: str, reason: str, detail: object) -> None:
        """Count a rejected or dropped record and warn (at most once every 5 s per topic); `detail` (a text or an
        exception) is turned into text only for the warning."""
        self.counters["rejected"] += 1
        self.counters[f"rejected/{topic}/{reason}"] += 1
        now = time.monotonic()
        if now - self._warned.get(topic, -1e9) >= 5.0:  # at most one warning per topic every 5 s
            self._warned[topic] = now
            n = self.counters[f"rejected/{topic}/{reason}"]
            self.node.get_logger().warning(f"rejected a record on {topic} ({reason}, {n} so far): {str(detail)[:200]}")

    def take(
        self,
        drops: Iterable[tuple[str, str]],
        rejects: Iterable[tuple[str, str, object]],
        counters: Mapping[str, int],
    ) -> None:
        """Count what a ROS-free core (WorldProtocol, AgentSession, TrainerCore) decided to drop or reject, and its
        own counters: the one place a node carries a core's effects into its health."""
        for topic, reason in drops:
            self.drop(topic, reason)
        for topic, reason, detail in rejects:
            self.reject(topic, reason, detail)
        self.counters.update(counters)

    def drop(self, topic: str, reason: str) -> None:
        """Count a well-formed record dropped by the protocol (past or future step, duplicate, ...)."""
        self.counters["dropped"] += 1
        self.counters[f"dropped/{topic}/{reason}"] += 1

    def error(self, why: str) -> None:
        """Report the node as failed (level ERROR) with the reason."""
        self.level = DiagnosticStatus.ERROR
        self.message = why

    def warn(self, why: str) -> None:
        """Report a degraded node (level WARN) with the reason."""
        self.level = DiagnosticStatus.WARN
        self.message = why

    def ok(self, message: str) -> None:
        """Report the node as healthy."""
        self.level = DiagnosticStatus.OK
        self.message = message

    def _key_value(self, key: str, value: str) -> KeyValue:
        """The KeyValue message of a key, made at its first use and given its new value after (publishing
        serializes a message at once, so the next status may reuse it)."""
        kv = self._key_values.get(key)
        if kv is None:
            kv = self._key_values[key] = KeyValue(key=key, value=value)
        elif kv.value != value:
            kv.value = value
        return kv

    def publish(self) -> None:
        """Publish the status and every counter on /diagnostics."""
        st = DiagnosticStatus()
        st.level = self.level
        st.name = self.name
        st.message = self.message
        st.hardware_id = self.hardware_id
        vals = {"uptime_s": f"{time.monotonic() - self.started:.1f}", **self.values}
        vals.update({k: str(v) for k, v in sorted(self.counters.items())})
        st.values = [self._key_value(k, v) for k, v in vals.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        arr.status = [st]
        self.pub.publish(arr)


def say_unsigned(node: Node, signer: Signer) -> None:
    """Say at start, once, that the node runs without a team key and what that allows (docs/ros.md, Run control)."""
    if not signer.enabled:
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        node.get_logger().warning(
            f"unsigned: no team key (HTLM_TEAM_KEY_FILE); any participant on ROS domain {domain} can send this team "
            "records that it accepts, including run announcements"
        )


WORLD_STATUS = "htlm: world"
"""The name of the world node's status on /diagnostics."""


def cdr_string(text: str) -> tuple[bytes, bytes]:
    """`text` as a CDR string field (its length with the NUL, then the bytes and the NUL), little and big endian."""
    b = text.encode() + b"\0"
    return struct.pack("<I", len(b)) + b, struct.pack(">I", len(b)) + b


class WorldWatch:
    """Whether the world is heard: its records (`heard()`) or its status on /diagnostics (WORLD_STATUS). A node
    that follows a run says on its /diagnostics (WARN, with the seconds) and in its log (every `period` seconds at
    most) when the world has been silent for longer than `timeout` seconds.

    /diagnostics is read best effort (STATUS_READER) and taken serialized: every node of the team publishes its
    status there every second, so each of N agents hears about N statuses a second; turning each into Python
    messages (a status carries every counter of its node) cost a composed process of 25 agents of a 100-agent team
    half its time. A message that does not hold the world's status name as a string is skipped unread; one that
    does is deserialized and checked."""

    def __init__(self, node: Node, health: Health, timeout: float, period: float = 10.0) -> None:
        """Listen to /diagnostics for the world's status."""
        self.node, self.health, self.timeout, self.period = node, health, timeout, period
        self.last = time.monotonic()
        self.logged = -math.inf
        self._marks = cdr_string(WORLD_STATUS)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, STATUS_READER, raw=True)

    def _on_diagnostics(self, data: bytes) -> None:
        if not any(m in data for m in self._marks):
            return
        try:
            msg = deserialize_message(data, DiagnosticArray)
        except Exception as e:  # a malformed status: counted, and it tells nothing about the world
            self.health.reject("diagnostics", "malformed", f"{type(e).__name__}: {e}")
            return
        if any(st.name == WORLD_STATUS for st in msg.status):
            self.last = time.monotonic()

    def heard(self) -> None:
        """A record of the world arrived."""
        self.last = time.monotonic()

    def check(self) -> bool:
        """Report a silent world (call before publishing the node's health); returns whether it is silent."""
        now = time.monotonic()
        silent = now - self.last
        self.health.values["world_silent_s"] = f"{silent:.1f}"
        if silent <= self.timeout:
            return False
        self.health.warn(f"the world is silent for {silent:.0f} s")
        if now - self.logged >= self.period:
            self.logged = now
            self.node.get_logger().warning(
                f"the world is silent for {silent:.0f} s (last heard at its records or status)"
            )
        return True


DRAIN = 256
"""Records a subscription callback of `subscribe_records` reads at most beyond the one it was called for."""


def subscribe_records(
    node: Node, topic: str, qos: QoSProfile, callback: Callable[[bytes], None], drain: int = DRAIN
) -> Subscription:
    """Subscribe to a topic of records (std_msgs/String) and call `callback` with each record serialized (CDR
    bytes; `Health.decode` takes them).

    Records are taken serialized, skipping the conversion to a Python message, and each call of the executor drains
    up to `drain` more from the reader's queue, so a flood of bad records costs the node little beyond what Fast DDS
    and the executor spend on each (docs/ros.md, Flooding). The text is decoded from the bytes by `Health.decode`,
    which rejects (and counts) a payload that is not a String of UTF-8."""

    def on_message(first: bytes) -> None:
        callback(first)
        with sub.handle:
            for _ in range(drain):
                got = sub.handle.take_message(String, True)
                if got is None:
                    return
                callback(got[0])

    sub = node.create_subscription(String, topic, on_message, qos, raw=True)
    return sub


def string(text: str) -> String:
    """A std_msgs/String holding a record text."""
    m = String()
    m.data = text
    return m


def encode_msg(schema: Schema, fields: dict[str, Any], signer: Signer | None) -> String:
    """A std_msgs/String holding the record of `fields` under `schema`."""
    return string(encode(schema, fields, signer))
