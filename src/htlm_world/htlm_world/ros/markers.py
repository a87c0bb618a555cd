"""The world's markers on ROS 2: htlm_world.markers' plain markers as visualization_msgs/MarkerArray on
/htlm/markers (frame `map`, for RViz2 and Foxglove), and back.

`MarkerPublisher` is what world_node uses: it hands every record of the protocol to `htlm_world.markers.MarkerView`
and publishes the markers it returns. Run as a program, this module renders what the topic shows, as a PNG seen
from above (with matplotlib, where no RViz is at hand):

    python -m htlm_world.ros.markers --snapshot OUT.png [--episode E --step T] [--timeout 120]

It subscribes to /htlm/markers, waits for the update of episode E, step T (without --step: the episode's last update
before the run's DELETEALL; without either: the run's last update) and draws that MarkerArray.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from htlm_msgs_py import topics
from htlm_msgs_py.ros import STATE, STATE_READER
from htlm_world.markers import ADD, DELETEALL, FRAME, Mark, MarkerView, parse_status, render
from htlm_world.model import Model
from htlm_world.scenario import Scenario


def to_msg(marks: Sequence[Mark], stamp: Any) -> MarkerArray:
    """The MarkerArray of `marks`, every marker in FRAME with header stamp `stamp` and lifetime 0 (forever)."""
    out = MarkerArray()
    for m in marks:
        k = Marker()
        k.header.frame_id = FRAME
        k.header.stamp = stamp
        k.ns = m.ns
        k.id = m.id
        k.type = m.type
        k.action = m.action
        if m.action == ADD:
            k.pose.position.x = m.x
            k.pose.position.y = m.y
            k.pose.position.z = m.z
            k.pose.orientation.w = 1.0
            k.scale.x, k.scale.y, k.scale.z = m.sx, m.sy, m.sz
            k.color.r, k.color.g, k.color.b, k.color.a = m.rgba
            k.text = m.text
        out.markers.append(k)
    return out


def from_msg(msg: MarkerArray) -> list[Mark]:
    """The plain markers of a MarkerArray (what `to_msg` put in; frame and stamp are not kept)."""
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


class MarkerPublisher:
    """The world node's markers: follows the protocol's records and publishes on /htlm/markers (STATE QoS, so a
    late-joining RViz gets the current scene at once)."""

    def __init__(self, node: Node, scenario: Scenario, model: Model, index: Callable[[], int]) -> None:
        """Create the publisher on `node`; `index()` tells which episode of a batch to show (read at every
        record, so the parameter may change at run time)."""
        self.node = node
        self.index = index
        self.view = MarkerView(scenario, model)
        self.pub = node.create_publisher(MarkerArray, topics.MARKERS, STATE)

    def on_record(self, kind: str, fields: dict[str, Any]) -> None:
        """A record the protocol asked to publish: publish the markers it changes, if any."""
        marks = self.view.on_record(kind, fields, self.index())
        if marks is not None:
            self.pub.publish(to_msg(marks, self.node.get_clock().now().to_msg()))

    def close(self, timeout: float = 1.0) -> None:
        """Give the last update (the DELETEALL of the end of the run) up to `timeout` seconds to reach every
        subscriber before the node goes away."""
        self.pub.wait_for_all_acked(Duration(seconds=timeout))


def snapshot(out: str, episode: int | None, step: int | None, timeout: float) -> int:
    """Render the update of (episode, step) of /htlm/markers into `out` (see the module's docstring)."""
    node = Node("htlm_markers_snapshot")
    best: list[list[Mark]] = []  # the latest update that fits
    ended: list[bool] = []
    exact = episode is not None and step is not None

    def on_markers(msg: MarkerArray) -> None:
        marks = from_msg(msg)
        if any(m.action == DELETEALL for m in marks):
            ended.append(True)
            return
        shown = next((parse_status(m.text) for m in marks if m.ns == "status"), None)
        if shown is None or (episode is not None and shown[0] != episode) or (step is not None and shown[1] != step):
            return
        best[:] = [marks]

    node.create_subscription(MarkerArray, topics.MARKERS, on_markers, STATE_READER)
    end = time.monotonic() + timeout
    while time.monotonic() < end and not (best and exact) and not ended:
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
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
