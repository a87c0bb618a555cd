"""WorldWatch reads /diagnostics serialized: the world's status (and only it) tells it the world is heard, a
teammate's status is skipped unread, and a malformed message that looks like the world's is counted, not raised."""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import serialize_message

from htlm_msgs_py.ros import WORLD_STATUS, WorldWatch

pytestmark = pytest.mark.ros


class _Node:
    """What WorldWatch asks of its node: a subscription (kept, to be called with serialized messages)."""

    def __init__(self) -> None:
        self.subs: list[tuple[Any, ...]] = []

    def create_subscription(self, *args: Any, **kwargs: Any) -> None:
        self.subs.append((*args, kwargs))


class _Health:
    def __init__(self) -> None:
        self.rejected: Counter[str] = Counter()

    def reject(self, topic: str, reason: str, detail: object) -> None:
        self.rejected[f"{topic}/{reason}"] += 1


def _status(*names: str, value: str = "") -> bytes:
    arr = DiagnosticArray()
    arr.status = [
        DiagnosticStatus(name=n, message="ok", values=[KeyValue(key="note", value=value)] * 40) for n in names
    ]
    return serialize_message(arr)


def test_only_the_world_status_marks_the_world_heard() -> None:
    node, health = _Node(), _Health()
    watch = WorldWatch(node, health, timeout=5.0)  # type: ignore[arg-type]
    ((_msg, topic, callback, _qos, kw),) = node.subs
    assert topic == "/diagnostics" and kw == {"raw": True}
    watch.last = 0.0
    callback(_status("htlm: agent7", "htlm: trainer", value="htlm: world is a value here, not a status name"))
    callback(_status("htlm: worldly"))
    assert watch.last == 0.0, "a teammate's status marked the world heard"
    before = time.monotonic()
    callback(_status("htlm: agent7", WORLD_STATUS))
    assert watch.last >= before
    assert not health.rejected


def test_a_malformed_message_holding_the_world_name_is_counted() -> None:
    node, health = _Node(), _Health()
    watch = WorldWatch(node, health, timeout=5.0)  # type: ignore[arg-type]
    callback = node.subs[0][2]
    watch.last = 0.0
    good = _status(WORLD_STATUS)
    callback(good[: good.index(WORLD_STATUS.encode()) + len(WORLD_STATUS) + 1])  # cut after the name
    assert watch.last == 0.0
    assert health.rejected == Counter({"diagnostics/malformed": 1})
