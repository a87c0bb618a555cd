"""QoS profiles of the HTLM topics, named once (docs/architecture.md, The wire contract).

Plain data, so this module imports without rclpy; `htlm_msgs_py.ros.qos_profile` turns a spec into an
rclpy QoSProfile.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

FASTDDS_PROFILE = Path(__file__).with_name("fastdds.xml")
"""The Fast DDS participant profile of the launched processes (discovery announcements every 0.25 s)."""
FASTDDS_LOOPBACK_PROFILE = Path(__file__).with_name("fastdds_loopback.xml")
"""The same with UDP on the loopback interface only and no shared memory: what the launched processes use with
discovery localhost (under ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET; docs/ros.md, "Running a team")."""


@dataclass(frozen=True)
class QosSpec:
    """A QoS profile: history KEEP_LAST of `depth`, with the given reliability and durability."""

    name: str
    """Profile name used in the topic table."""
    reliability: Literal["reliable", "best_effort"]
    """RELIABLE retransmits lost samples; BEST_EFFORT does not."""
    durability: Literal["transient_local", "volatile"]
    """TRANSIENT_LOCAL keeps the last `depth` samples for subscribers that join later."""
    depth: int
    """KEEP_LAST queue depth."""


STATE = QosSpec("STATE", "reliable", "transient_local", 1)
"""State topics (scenario, weights, beliefs, goal poses, the world's markers): a late joiner gets the latest value.
RViz2 and Foxglove subscribe to markers with reliable, volatile readers, which match this writer."""

STATE_READER = QosSpec("STATE_READER", "reliable", "transient_local", 1000)
"""How nodes subscribe to state topics: the writer keeps only the latest value (STATE), the reader queues a burst
of updates instead of overwriting them unread, so every update (and every bad record) is seen and counted."""

EVENTS = QosSpec("EVENTS", "reliable", "volatile", 1000)
"""Per-step events: reliable, not replayed to late joiners. The queue is deep enough for bursts (transitions resent
to a restarted trainer, a flood of bad records) so that a slow reader does not lose the records in between: a
record the protocol no longer needs is dropped (and counted) when read, never silently overwritten."""

WEIGHTS = QosSpec("WEIGHTS", "reliable", "transient_local", 8)
"""Weights (the trainer's writer): like STATE, but the writer keeps the last 8 versions, so an agent that joins or
acts with the weights of an earlier step than the newest (the trainer's lag) still receives every version on the
cadence; agents read with STATE_READER, so a burst of other records never overwrites a version unread."""

DIAGNOSTICS = QosSpec("DIAGNOSTICS", "reliable", "volatile", 10)
"""/diagnostics, as the ROS diagnostics tools expect it."""

ODOMETRY = QosSpec("ODOMETRY", "reliable", "volatile", 10)
"""Robot poses (nav_msgs/Odometry of the simulated robots): a stream, as robot drivers publish /odom."""

POSE_READER = QosSpec("POSE_READER", "best_effort", "volatile", 10)
"""How agents read a robot's pose topic: best effort matches a robot stack's publisher whether it is reliable or
best effort (sensor data), and only the newest pose matters."""

STATUS_READER = QosSpec("STATUS_READER", "best_effort", "volatile", 10)
"""How agents and the trainer read /diagnostics for the world's status: best effort, as a lost status is followed
by the next a second later. A reliable reader acknowledges every status of every node: in a team of N agents about
N² acknowledgements a second (a 100-agent team sent 61 % fewer datagrams a step without them)."""

PROFILES: dict[str, QosSpec] = {
    q.name: q for q in (STATE, STATE_READER, EVENTS, WEIGHTS, DIAGNOSTICS, ODOMETRY, POSE_READER, STATUS_READER)
}
