"""The world's markers on ROS 2: htlm_world.markers' plain markers as visualization_msgs/MarkerArray on
/htlm/markers (frame `map`, for RViz2 and Foxglove), and back.

`MarkerPublisher` is what world_node uses: it hands every record of the protocol to `htlm_world.markers.MarkerView`
and publishes the markers that changed. Run as a program, this module renders what the topic shows (its updates
applied as RViz applies them), as a PNG seen from above (with matplotlib, where no RViz is at hand):

    python -m htlm_world.ros.markers --snapshot OUT.png [--episode E --step T] [--timeout 120]

It subscribes to /htlm/markers, waits for the update of episode E, step T (without --step: the episode's last update
before the run's DELETEALL; without either: the run's last scene) and draws the markers shown then.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from htlm_msgs_py import topics
from htlm_msgs_py.ros import STATE, STATE_READER
from htlm_world.markers import DELETEALL, FRAME, Mark, MarkerView, accumulate, parse_status, render
from htlm_world.scenario import Scenario


def fill(k: Marker, m: Mark) -> None:
    """Write the plain marker `m` into the message `k` (frame FRAME, lifetime 0: forever; the stamp is not set)."""
    k.header.frame_id = FRAME
    k.ns = m.ns
    k.id = m.id
    k.type = m.type
    k.action = m.action
    k.pose.position.x = m.x
    k.pose.position.y = m.y
    k.pose.position.z = m.z
    k.pose.orientation.w = 1.0
    k.scale.x, k.scale.y, k.scale.z = m.sx, m.sy, m.sz
    k.color.r, k.color.g, k.color.b, k.color.a = m.rgba
    k.text = m.text


def from_msg(msg: MarkerArray) -> list[Mark]:
    """The plain markers of a MarkerArray (what `fill` put in; frame and stamp are not kept)."""
    return [
        Mark(
            ns=k.ns,
            id=k.id,
            type=k.type,
            x=k.pose.position.x,
            y=k.pose.position.y,
            z=k.pose.position.z,
            sx=k.scale.x,
            sy=k.scale.y,
            sz=k.scale.z,
            rgba=(k.color.r, k.color.g, k.color.b, k.color.a),
            text=k.text,
            action=k.action,
        )
        for k in msg.markers
    ]


_UNFILLED = Mark("", -1, 0)
"""Stands for the plain marker of a message not filled yet."""

CATCH_UP = 0.5
"""Seconds between two looks for a new subscriber that has not seen the current scene."""


KEYFRAME = 2.0
"""Most seconds between two updates that carry the whole scene (the others carry only the markers that changed)."""


class MarkerPublisher:
    """The world node's markers on /htlm/markers (STATE QoS: a late-joining RViz gets the latest update at once).

    Follows every record of the protocol (`on_record`, cheap) and publishes only while someone subscribes, and
    always the DELETEALL of the end of the run. An update carries the markers that changed since the previous one
    (RViz keeps the others, lifetime 0); the whole scene goes out when a batch begins, when a subscriber joins
    (seen at the next record or within CATCH_UP seconds) and at least every KEYFRAME seconds. Marker messages are
    kept and only the fields of the markers that changed are rewritten.
    """

    def __init__(self, node: Node, scenario: Scenario, index: Callable[[], int]) -> None:
        """Create the publisher on `node`; `index()` tells which episode of a batch to show (read at every
        record, so the parameter may change at run time)."""
        self.node = node
        self.index = index
        self.view = MarkerView(scenario)
        self.pub = node.create_publisher(MarkerArray, topics.MARKERS, STATE)
        self.pending = False
        """The current scene has not been published."""
        self.readers = 0
        """Subscribers at the latest update."""
        self.full_at = -math.inf
        """Monotonic time of the latest update that carried the whole scene."""
        self.msgs: list[Marker] = []
        self.kept: list[Mark] = []
        """The plain marker each of `msgs` holds."""
        node.create_timer(CATCH_UP, self._catch_up)

    def on_record(self, kind: str, fields: dict[str, Any]) -> None:
        """A record the protocol asked to publish: publish what changed if someone looks."""
        if self.view.on_record(kind, fields, self.index()):
            self.pending = True
            if self.view.stopped or self.pub.get_subscription_count() > 0:
                self.publish()

    def _catch_up(self) -> None:
        n = self.pub.get_subscription_count()
        if n > 0 and (self.pending or n > self.readers or time.monotonic() - self.full_at > KEYFRAME):
            self.publish()

    def publish(self) -> None:
        """Publish an update of the current scene, every marker in it stamped now."""
        marks = self.view.marks()
        n, now = self.pub.get_subscription_count(), time.monotonic()
        full = n > self.readers or self.view.shown[1] == 0 or now - self.full_at > KEYFRAME or self.view.stopped
        if len(marks) != len(self.kept):
            self.msgs = [Marker() for _ in marks]
            self.kept = [_UNFILLED] * len(marks)
        stamp = self.node.get_clock().now().to_msg()
        out = MarkerArray()
        for i, m in enumerate(marks):
            k = self.msgs[i]
            if m is not self.kept[i]:  # markers are cached by what they show: same object, same fields
                fill(k, m)
                self.kept[i] = m
            elif not full:
                continue
            k.header.stamp = stamp
            out.markers.append(k)
        self.pub.publish(out)
        self.pending, self.readers = False, n
        if full:
            self.full_at = now
        if self.view.stopped:
            self.kept = []

    def close(self, timeout: float = 1.0) -> None:
        """Give the last update (the DELETEALL of the end of the run) up to `timeout` seconds to reach every
        subscriber before the node goes away."""
        self.pub.wait_for_all_acked(Duration(seconds=timeout))


def snapshot(out: str, episode: int | None, step: int | None, timeout: float) -> int:
    """Render the update of (episode, step) of /htlm/markers into `out` (see the module's docstring)."""
    node = Node("htlm_markers_snapshot")
    best: list[list[Mark]] = []  # the latest scene that fits
    seen: dict[tuple[str, int], Mark] = {}  # what RViz would show now
    ended: list[bool] = []
    exact = episode is not None and step is not None

    def on_markers(msg: MarkerArray) -> None:
        update = from_msg(msg)
        if any(m.action == DELETEALL for m in update):
            ended.append(True)
            return
        accumulate(seen, update)
        status = seen.get(("status", 0))
        shown = parse_status(status.text) if status is not None else None
        if shown is None or (episode is not None and shown[0] != episode) or (step is not None and shown[1] != step):
            return
        best[:] = [list(seen.values())]

    node.create_subscription(MarkerArray, topics.MARKERS, on_markers, STATE_READER)
    end = time.monotonic() + timeout
    while time.monotonic() < end and not (best and exact) and not ended and rclpy.ok():
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    if not best:
        print(f"no update of episode {episode} step {step} on {topics.MARKERS} within {timeout:g} s", file=sys.stderr)
        return 1
    marks = best[0]
    shown = next((m.text for m in marks if m.ns == "status"), "")
    render(marks, out, f"{topics.MARKERS} ({shown}), frame {FRAME}, seen from above; drawn with matplotlib")
    print(f"wrote {out}: {shown}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m htlm_world.ros.markers --snapshot OUT.png [--episode E --step T] [--timeout S]`."""
    p = argparse.ArgumentParser(description="Render the world's markers (/htlm/markers) from above into a PNG.")
    p.add_argument("--snapshot", required=True, help="PNG file to write")
    p.add_argument("--episode", type=int, default=None, help="episode to draw (default: the last one shown)")
    p.add_argument("--step", type=int, default=None, help="its step (0: the initial state; default: the last)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for it")
    a = p.parse_args(argv)
    rclpy.init()
    try:
        return snapshot(a.snapshot, a.episode, a.step, a.timeout)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
