"""A run recorded as a ROS 2 bag: the team's topics in MCAP storage, which `ros2 bag info/play` and Foxglove open.

ROS-free. The recorder node (`htlm_agent.ros.record_node`) hands over every message as rmw delivered it, serialized
in CDR, and `rosbags` writes it unchanged into a rosbag2 directory in MCAP storage, the layout `ros2 bag record -s
mcap` writes: `metadata.yaml` (format version 9, Jazzy's) beside `<name>.mcap`, every channel with its message
definition (schema encoding ros2msg, from ROS 2 Jazzy's interfaces: the type hashes are Jazzy's) and the QoS its
publishers offer (so `ros2 bag play` republishes state topics for late joiners). Nothing is serialized here.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from htlm_msgs_py import qos, topics
from htlm_msgs_py.params import SECONDS, problems, setting
from htlm_world.scenario import from_record

AGENT = "<agent>"


@dataclass(frozen=True)
class RecordSettings:
    """Parameters of the recorder node (one ROS parameter per field)."""

    path: str = setting("")
    """The bag directory to write (metadata.yaml and an MCAP file); when it exists, the first free PATH_1, PATH_2,
    ...; required."""
    agents: str = setting("")
    """Comma-separated agents whose topics are recorded from the start; empty: those the world's run announcement
    names, from then on."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run (once its last messages are in)."""
    stop_grace: float = setting(1.0, lo=SECONDS[0], hi=60.0)
    """After the run stopped or a SIGINT/SIGTERM, seconds without a message on a team topic before the bag is
    closed (at most 5 s after a signal)."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    executor: str = setting("events", choices=("events", "single"))
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


def validate_record_settings(s: RecordSettings) -> list[str]:
    """Problems of a RecordSettings, each naming the parameter and the value (empty when valid)."""
    bad: list[str] = []
    if not s.path:
        bad.append("path: '' : the recorder needs a directory for its bag")
    names = [a for a in s.agents.split(",") if a]
    if any(not a.replace("_", "").isalnum() or not a[0].isalpha() for a in names):
        bad.append(f"agents: {s.agents!r} must be agent names of the scenario (letters, digits, _), comma-separated")
    return bad + problems(s)


@dataclass(frozen=True)
class RecordedTopic:
    """A topic the recorder subscribes to."""

    name: str
    """Topic name."""
    msg_type: str
    """ROS 2 interface, e.g. std_msgs/msg/String."""
    offered: qos.QosSpec
    """The QoS its publishers offer (kept in the bag for `ros2 bag play`)."""

    @property
    def reader(self) -> qos.QosSpec:
        """How the recorder reads it: reliably, with a deep queue; a state topic's latest value from before the
        recorder joined comes too (transient local)."""
        return qos.STATE_READER if self.offered.durability == "transient_local" else qos.EVENTS


def recorded_topics(agents: Sequence[str]) -> list[RecordedTopic]:
    """Every topic of the topic table (`htlm_msgs_py.topics.TOPICS`), a per-agent topic once for each agent."""
    out: list[RecordedTopic] = []
    for t in topics.TOPICS:
        names = [t.name.replace(AGENT, a) for a in agents] if AGENT in t.name else [t.name]
        out += [RecordedTopic(n, t.msg_type, qos.PROFILES[t.qos]) for n in names]
    return out


def agent_topics(agent: str) -> list[RecordedTopic]:
    """The recorded topics of one agent (its observation, odometry, weights, belief and goal pose)."""
    return [t for t in recorded_topics([agent]) if f"/{agent}/" in t.name]


def free_path(base: Path) -> Path:
    """`base`, or base_1, base_2, ... : the first that does not exist (a restarted recorder starts a new bag)."""
    path, n = base, 0
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}_{n}")
    return path


class Recording:
    """A rosbag2 directory in MCAP storage being written."""

    def __init__(self, path: Path) -> None:
        """Create the bag directory `path` (it must not exist)."""
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()
        self.bytes = 0

    def add(self, topic: RecordedTopic) -> None:
        """Register a topic (once; later calls for it do nothing)."""
        if topic.name in self.connections:
            return
        self.connections[topic.name] = self.writer.add_connection(
            topic.name, topic.msg_type, typestore=self.typestore, offered_qos_profiles=[_qos(topic.offered)]
        )

    def write(self, topic: str, data: bytes, stamp_ns: int) -> None:
        """Write one CDR-serialized message of a registered topic, received at `stamp_ns` (Unix nanoseconds)."""
        self.writer.write(self.connections[topic], stamp_ns, data)
        self.counts[topic] += 1
        self.bytes += len(data)

    def close(self) -> None:
        """Write the MCAP summary and metadata.yaml: the bag is complete."""
        self.writer.close()


def _qos(spec: qos.QosSpec) -> Any:
    """The rosbags Qos of a QoS profile (durations as rmw's 'unspecified', liveliness automatic)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST,
        spec.depth,
        QosReliability.RELIABLE if spec.reliability == "reliable" else QosReliability.BEST_EFFORT,
        QosDurability.TRANSIENT_LOCAL if spec.durability == "transient_local" else QosDurability.VOLATILE,
        zero,
        zero,
        QosLiveliness.AUTOMATIC,
        zero,
        False,
    )


@dataclass(frozen=True)
class Message:
    """One message of a recording."""

    topic: str
    msg_type: str
    stamp_ns: int
    """When the recorder received it (Unix nanoseconds)."""
    msg: Any
    """The message, deserialized (rosbags' message classes: the fields of the ROS interface)."""


def find_bag(path: Path) -> Path | None:
    """The bag of `path`: the bag directory itself (it holds metadata.yaml), or a run directory's `recording`."""
    for p in (path, path / "recording"):
        if (p / "metadata.yaml").is_file():
            return p
    return None


def messages(bag: Path, only: Sequence[str] = ()) -> Iterator[Message]:
    """Every message of a bag (of the topics in `only` when given), in the order received."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if not only or c.topic in only]
        if not conns:  # (rosbags reads every connection when given none)
            return
        for conn, stamp, data in reader.messages(connections=conns):
            yield Message(conn.topic, conn.msgtype, stamp, store.deserialize_cdr(data, conn.msgtype))


def records(bag: Path, topic: str) -> list[dict[str, Any]]:
    """The records (the JSON of std_msgs/String) of one topic of a bag, in the order received."""
    return [json.loads(m.msg.data) for m in messages(bag, [topic])]


def episode_log(bag: Path) -> list[dict[str, Any]]:
    """The world's episode log (the lines of `world.jsonl`) rebuilt from a recording of a simulated run.

    Every episode whose metrics were recorded (/htlm/episode_metrics), with the true levels (h + 1) x p (step 0 the
    scenario's initial levels, then /htlm/ground_truth), the joint assignments applied h x N (ground truth) and each
    agent's observed level h x N (its /htlm/<agent>/observation; -1 where it observed nothing). A step the recording
    lacks keeps -1 everywhere.
    """
    announced = records(bag, topics.SCENARIO)
    if not announced:
        return []
    sc = from_record(announced[0])
    h, n, p = sc.horizon, sc.n_agents, sc.n_tasks
    metrics = {r["episode"]: r for r in records(bag, topics.EPISODE_METRICS)}
    truth: dict[tuple[int, int], tuple[list[int], list[int]]] = {}
    for r in records(bag, topics.GROUND_TRUTH):
        for i, (levels, actions) in enumerate(zip(r["levels"], r["actions"], strict=True)):
            truth[(r["episode"] + i, r["step"])] = (levels, actions)
    seen: dict[tuple[int, int, int], int] = {}
    for k, agent in enumerate(sc.agents):
        for r in records(bag, topics.observation(agent.name)):
            for i, level in enumerate(r["levels"]):
                seen[(r["episode"] + i, r["step"], k)] = level
    out = []
    for e in sorted(metrics):
        m = metrics[e]
        levels = [list(sc.initial_levels)] + [truth.get((e, t), ([-1] * p, []))[0] for t in range(1, h + 1)]
        actions = [truth.get((e, t), ([], [-1] * n))[1] for t in range(1, h + 1)]
        observations = [[seen.get((e, t, k), -1) for k in range(n)] for t in range(1, h + 1)]
        fields = {k: v for k, v in m.items() if k not in ("schema", "v", "sig")}
        out.append(
            {"run": m["run"], "metrics": fields, "levels": levels, "actions": actions, "observations": observations}
        )
    return out
