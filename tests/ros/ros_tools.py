"""Helper processes of the ROS integration tests, each run as its own OS process (`python ros_tools.py CMD ...`):

- diag: record the latest /diagnostics status of every node into a JSON file, rewritten every 0.3 s;
- fuzz: publish malformed records on every subscribed topic of a team, then write how many went out per topic;
- rogue: a stranger without the team key publishing plausible, well-formed forged observations, broadcasts and
  actions (v2: one value per episode of the batch it sees) for every step of the batch in progress; with
  --wrong-lengths, arrays of the wrong length instead;
- setparam: set a parameter of a running node (what `ros2 param set` does);
- describe: list and describe every parameter of running nodes (what `ros2 param describe` shows);
- record: record every record text of one topic (e.g. /htlm/scenario) into a JSON list, rewritten as they arrive,
  so that a record (signed or not) can be published again later, in this run or another;
- publish: publish a recorded record again: as it was (a replay, signature and all) or with some fields changed
  and encoded anew (a forgery, signed with --key if given), once every expected subscriber is matched;
- markers: record every visualization_msgs/MarkerArray of /htlm/markers (frames, stamps, lifetimes, plain markers)
  into a JSON file, rewritten every 0.3 s while new ones arrive.
- send: publish a list of record texts (recorded earlier, or made by the test) on one topic, each once, every
  subscriber matched first and every record acknowledged before it exits;
- goal_pose: publish geometry_msgs/PoseStamped goals (NaN, out of the map, ...) on one agent's goal_pose topic;
- odometry: record how many odometry messages of each agent came, how many held a value that is not finite, and
  the last position, into a JSON file rewritten every 0.3 s;
- flood: publish records that every receiver of one topic rejects (cut JSON, unknown schema, wrong version, a
  value out of range, bytes that are not UTF-8; or well-formed records signed with a wrong key), as fast as it can
  (or at --rate) from a start signal until stopped, and write how many went out; --hog burns as much CPU without
  publishing;
- graph: what the graph shows of some nodes (what `ros2 node info` and `ros2 param get` show): each node's
  publishers, subscriptions and services with their types, and some of its parameters, once every one is there and
  nothing changed for a second;
- listen: read one topic with the team's QoS for records as a node does (serialized), --cost seconds of work per
  record, and count what came and what the reader's message_lost QoS event reported lost.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import faulthandler
import json
import random
import signal
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/: wire_fuzz

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import EVENTS, STATE, STATE_READER, String, string
from htlm_msgs_py.signing import Signer

AGENTS = [f"agent{i}" for i in range(1, 6)]


def _spin_and_dump(node: Any, out: Path, data: Any) -> None:
    """Spin until SIGTERM or SIGINT, writing `data` as JSON to `out` (atomically) about every 0.3 s and at the end."""
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    last = 0.0
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
        if time.monotonic() - last > 0.3:
            tmp = out.with_suffix(".tmp")
            tmp.write_text(json.dumps(data))
            tmp.replace(out)
            last = time.monotonic()
    out.write_text(json.dumps(data))


def subscribed_topics(mode: str) -> dict[str, tuple[S.Schema, Any]]:
    """Every topic some node of a 5-agent team subscribes to in `mode`, with its schema and QoS."""
    out: dict[str, tuple[S.Schema, Any]] = {
        topics.SCENARIO: (S.SCENARIO, STATE),
        topics.STEP: (S.STEP, EVENTS),
        topics.ACTION: (S.ACTION, EVENTS),
        topics.READY: (S.READY, EVENTS),
        topics.BROADCAST: (S.BROADCAST, EVENTS),
        topics.TRANSITIONS: (S.TRANSITION, EVENTS),
        topics.TRANSITION_ACK: (S.TRANSITION_ACK, EVENTS),
        topics.EPISODE_METRICS: (S.EPISODE_METRICS, EVENTS),
    }
    for a in AGENTS:
        out[topics.observation(a)] = (S.OBSERVATION, EVENTS)
        if mode == "train":
            out[topics.weights(a)] = (S.WEIGHTS, STATE)
    return out


SUBSCRIBERS: dict[str, list[tuple[str, str]]] = {
    topics.SCENARIO: [(a, "scenario") for a in AGENTS] + [("trainer", "scenario")],
    topics.STEP: [(a, "step") for a in AGENTS] + [("trainer", "step")],
    topics.ACTION: [("world", "action")],
    topics.READY: [("world", "ready")],
    topics.BROADCAST: [(a, "broadcast") for a in AGENTS],
    topics.TRANSITIONS: [("trainer", "transitions")],
    topics.TRANSITION_ACK: [(a, "transition_ack") for a in AGENTS],
    topics.EPISODE_METRICS: [("trainer", "episode_metrics")],
    **{topics.observation(a): [(a, "observation")] for a in AGENTS},
    **{topics.weights(a): [(a, "weights")] for a in AGENTS},
}
"""Which node (its /diagnostics status name without "htlm: ") subscribes to each topic, and its counter tag."""


def _spin_for(node: Node, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=min(0.05, max(0.0, end - time.monotonic())))


def diag(args: argparse.Namespace) -> None:
    node = Node("test_diag_listener")
    latest: dict[str, dict[str, Any]] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            latest[st.name] = {
                "level": int.from_bytes(st.level, "little") if isinstance(st.level, bytes) else int(st.level),
                "message": st.message,
                **{kv.key: kv.value for kv in st.values},
            }

    node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, 50)
    _spin_and_dump(node, Path(args.out), latest)


def team_run(node: Node, seconds: float = 30.0) -> str:
    """The run id of the team's announcement on /htlm/scenario (what any participant of the domain can read)."""
    got: list[str] = []

    def on_scenario(msg: String) -> None:
        with contextlib.suppress(ValueError, KeyError, TypeError):
            got.append(json.loads(msg.data)["run"])

    sub = node.create_subscription(String, topics.SCENARIO, on_scenario, STATE_READER)
    end = time.monotonic() + seconds
    while not got and time.monotonic() < end:
        _spin_for(node, 0.05)
    node.destroy_subscription(sub)
    if not got:
        raise SystemExit("no run announcement on /htlm/scenario")
    return got[-1]


def fuzz(args: argparse.Namespace) -> None:
    from wire_fuzz import malformed

    node = Node("test_fuzzer")
    lim = S.limits(5, 4, 6, 5, args.horizon, 1)  # the fuzzed team runs batches of 1
    targets = subscribed_topics(args.mode)
    if args.topics:
        keep = args.topics.split(",")
        targets = {t: v for t, v in targets.items() if any(t.endswith(k) for k in keep)}

    # writers that keep the whole burst: reliable delivery of every record, also on the state topics (where the
    # team's own writers keep only the latest value), and publishing never waits for acknowledgements
    def deep(state: bool) -> QoSProfile:
        durability = DurabilityPolicy.TRANSIENT_LOCAL if state else DurabilityPolicy.VOLATILE
        return QoSProfile(
            depth=2 * args.count,
            reliability=ReliabilityPolicy.RELIABLE,
            history=HistoryPolicy.KEEP_LAST,
            durability=durability,
        )

    pubs = {t: node.create_publisher(String, t, deep(qos is STATE)) for t, (_, qos) in targets.items()}
    # wait until every topic is matched with all its subscribers
    want = {t: len(SUBSCRIBERS.get(t, [])) or 1 for t in pubs}
    end = time.monotonic() + 30
    while time.monotonic() < end and any(p.get_subscription_count() < want[t] for t, p in pubs.items()):
        _spin_for(node, 0.1)
    unmatched = [t for t, p in pubs.items() if p.get_subscription_count() < want[t]]
    run = team_run(node)
    rng = random.Random(args.seed)
    texts = {
        t: list(malformed(schema, rng, args.count, (args.first, args.first + args.episodes), lim))
        for t, (schema, _) in targets.items()
    }
    for t, (schema, _) in targets.items():  # records bound to a run name the team's: judged by their episode
        if schema.bound:
            texts[t] = [x.replace('"run": "r1"', f'"run": "{run}"') for x in texts[t]]
    # flow control: after each batch, wait until every subscriber has read what was sent (its /diagnostics
    # counter arrived/<tag> grew by as much), so that no reader queue overflows however loaded the machine is;
    # a reader that makes no progress for 1 s is not waited for any longer (the end waits for repairs)
    status: dict[str, dict[str, str]] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            status[st.name.split(": ", 1)[-1]] = {kv.key: kv.value for kv in st.values}

    node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, 50)

    def arrivals(name: str, tag: str) -> int:
        return int(status.get(name, {}).get(f"arrived/{tag}", 0))

    readers = [(t, name, tag) for t in targets for name, tag in SUBSCRIBERS.get(t, [])]
    end = time.monotonic() + 20
    while time.monotonic() < end and not all(name in status for _, name, _ in readers):
        _spin_for(node, 0.1)
    base = {(name, tag): arrivals(name, tag) for _, name, tag in readers}
    sent = dict.fromkeys(targets, 0)
    t0 = time.monotonic()
    for i in range(args.count):
        for t, pub in pubs.items():
            pub.publish(string(texts[t][i]))
            sent[t] += 1
        if i % 10 == 9:
            _spin_for(node, args.pause)
        if i % args.batch == args.batch - 1 or i == args.count - 1:
            last, progress = time.monotonic(), -1
            while True:
                behind = [(t, n, g) for t, n, g in readers if arrivals(n, g) - base[(n, g)] < sent[t]]
                done = sum(min(arrivals(n, g) - base[(n, g)], sent[t]) for t, n, g in readers)
                if not behind or time.monotonic() - last > 1.0:
                    break
                if done > progress:
                    progress, last = done, time.monotonic()
                _spin_for(node, 0.05)
            print(f"{i + 1} records per topic after {time.monotonic() - t0:.1f} s; behind: {behind}", flush=True)
    # the writers must outlive the repair of whatever DDS lost on the way (reliable delivery retransmits from the
    # writer): wait until every reader acknowledged every record (a topic that is not is reported), and every node
    # has read them
    from rclpy.duration import Duration

    unacked = [t for t, pub in pubs.items() if not pub.wait_for_all_acked(Duration(seconds=30))]
    end = time.monotonic() + 10
    while time.monotonic() < end and any(arrivals(n, g) - base[(n, g)] < sent[t] for t, n, g in readers):
        _spin_for(node, 0.1)
    _spin_for(node, 0.5)
    took = time.monotonic() - t0
    report = {"sent": sent, "unmatched": unmatched, "unacked": unacked, "seconds": round(took, 2)}
    Path(args.out).write_text(json.dumps(report))


def rogue(args: argparse.Namespace) -> None:
    node = Node("test_rogue")
    signer = Signer(args.key.encode()) if args.key else None
    pubs = {
        "broadcast": node.create_publisher(String, topics.BROADCAST, EVENTS),
        "action": node.create_publisher(String, topics.ACTION, EVENTS),
        **{a: node.create_publisher(String, topics.observation(a), EVENTS) for a in AGENTS},
    }
    seen: list[int] = []
    sizes: dict[int, int] = {}  # episode -> episodes in its batch

    def on_record(msg: String) -> None:  # anything of the team tells the batch in progress and its size
        try:
            rec = json.loads(msg.data)
            e = rec.get("episode")
            size = rec.get("size", len(rec.get("levels", [])))
        except (ValueError, AttributeError, TypeError):
            return
        if isinstance(e, int) and isinstance(size, int) and size > 0:
            sizes.setdefault(e, size)
            if e not in seen:
                seen.append(e)

    node.create_subscription(String, topics.STEP, on_record, EVENTS)
    for a in AGENTS:
        node.create_subscription(String, topics.observation(a), on_record, EVENTS)
    kinds = set(args.kinds.split(","))
    run = args.run or team_run(node)  # the team's own run unless told another
    rng = random.Random(args.seed)
    count = 0
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    end = time.monotonic() + args.seconds
    while not stop and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.01)
        if not seen:
            continue
        e = seen[-1]
        b = sizes[e]
        # plausible records of the batch: one value per episode; --wrong-lengths: an action record with B - 1
        # actions, a broadcast and an observation with B + 1 levels (everything else well-formed)
        na, nl = (b - 1, b + 1) if args.wrong_lengths else (b, b)
        if na < 1:
            na = b + 1
        for t in range(1, args.horizon + 1):
            k = rng.randrange(5)
            recs = [
                (
                    "broadcast",
                    S.BROADCAST,
                    {
                        "agent": k,
                        "episode": e,
                        "step": t,
                        "actions": [rng.randrange(4) for _ in range(b)],
                        "levels": [rng.randrange(5) for _ in range(nl)],
                        "sent": time.time(),
                    },
                ),
                (
                    "action",
                    S.ACTION,
                    {
                        "agent": k,
                        "episode": e,
                        "step": t,
                        "actions": [rng.randrange(4) for _ in range(na)],
                        "before": [],
                    },
                ),
                (
                    AGENTS[k],
                    S.OBSERVATION,
                    {
                        "agent": k,
                        "episode": e,
                        "step": t,
                        "tasks": [0] * nl,
                        "levels": [rng.randrange(5) for _ in range(nl)],
                        "acted": [0, 1, 2, 3, 4],
                    },
                ),
            ]
            for topic, schema, fields in recs:
                if "all" not in kinds and schema.name.removeprefix("htlm/") not in kinds:
                    continue
                pubs[topic].publish(string(S.encode(schema, {"run": run, **fields}, signer)))
                count += 1
        _spin_for(node, args.pause)
    Path(args.out).write_text(json.dumps({"sent": count, "episodes": seen, "sizes": sizes}))


def setparam(args: argparse.Namespace) -> None:
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    node = Node("test_setparam")
    client = AsyncParameterClient(node, args.node)
    if not client.wait_for_services(timeout_sec=20.0):
        raise SystemExit(f"no parameter services of {args.node}")
    value = json.loads(args.value)
    future = client.set_parameters([Parameter(args.name, value=value)])
    rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
    result = future.result()
    ok = result is not None and all(r.successful for r in result.results)
    reasons = [r.reason for r in result.results] if result is not None else ["no answer"]
    Path(args.out).write_text(json.dumps({"successful": ok, "reasons": reasons}))


def describe(args: argparse.Namespace) -> None:
    from rclpy.parameter_client import AsyncParameterClient

    node = Node("test_describe")
    out: dict[str, dict[str, Any]] = {}
    for name in args.nodes.split(","):
        client = AsyncParameterClient(node, name)
        if not client.wait_for_services(timeout_sec=30.0):
            raise SystemExit(f"no parameter services of {name}")
        future = client.list_parameters()
        rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
        listed = future.result()
        if listed is None:
            raise SystemExit(f"{name}: list_parameters did not answer")
        names = sorted(listed.result.names)
        future = client.describe_parameters(names)
        rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
        described = future.result()
        if described is None:
            raise SystemExit(f"{name}: describe_parameters did not answer")
        out[name] = {
            d.name: {
                "type": d.type,
                "description": d.description,
                "additional_constraints": d.additional_constraints,
                "read_only": d.read_only,
                "floating_point_range": [[r.from_value, r.to_value, r.step] for r in d.floating_point_range],
                "integer_range": [[r.from_value, r.to_value, r.step] for r in d.integer_range],
            }
            for d in described.descriptors
        }
    Path(args.out).write_text(json.dumps(out))


def graph(args: argparse.Namespace) -> None:
    from rclpy.parameter_client import AsyncParameterClient

    node = Node("test_graph")
    names = args.nodes.split(",")

    def seen() -> dict[str, Any]:
        there = {n for n, _ in node.get_node_names_and_namespaces()}
        if not all(n in there for n in names):
            return {}
        return {
            n: {
                "publishers": sorted([t, ty] for t, ty in node.get_publisher_names_and_types_by_node(n, "/")),
                "subscriptions": sorted([t, ty] for t, ty in node.get_subscriber_names_and_types_by_node(n, "/")),
                "services": sorted([t, ty] for t, ty in node.get_service_names_and_types_by_node(n, "/")),
            }
            for n in names
        }

    end, last, since = time.monotonic() + 60.0, {}, time.monotonic()
    while time.monotonic() < end:
        _spin_for(node, 0.2)
        now = seen()
        if now != last:
            last, since = now, time.monotonic()
        elif now and time.monotonic() - since >= 1.0:
            break
    else:
        raise SystemExit(f"the graph did not settle with {names}: {sorted(last)}")
    for n in names:
        client = AsyncParameterClient(node, f"/{n}")
        if not client.wait_for_services(timeout_sec=30.0):
            raise SystemExit(f"no parameter services of {n}")
        future = client.get_parameters(args.params.split(","))
        rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
        got = future.result()
        if got is None:
            raise SystemExit(f"{n}: get_parameters did not answer")
        last[n]["parameters"] = {k: v.string_value for k, v in zip(args.params.split(","), got.values, strict=True)}
    Path(args.out).write_text(json.dumps(last))


def markers(args: argparse.Namespace) -> None:
    from visualization_msgs.msg import MarkerArray

    from htlm_msgs_py.ros import STATE_READER
    from htlm_world.ros.markers import from_msg

    node = Node("test_markers")
    got: list[dict[str, Any]] = []
    out = Path(args.out)

    def write() -> None:
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(got))
        tmp.replace(out)

    def on_markers(msg: MarkerArray) -> None:
        got.append(
            {
                "frames": sorted({k.header.frame_id for k in msg.markers}),
                "stamps": sorted({k.header.stamp.sec + 1e-9 * k.header.stamp.nanosec for k in msg.markers}),
                "lifetimes": sorted({k.lifetime.sec + 1e-9 * k.lifetime.nanosec for k in msg.markers}),
                "marks": [dataclasses.asdict(m) for m in from_msg(msg)],
            }
        )

    node.create_subscription(MarkerArray, topics.MARKERS, on_markers, STATE_READER)
    write()  # the subscription exists: the file tells the test so
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    written, last = 0, time.monotonic()
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
        if len(got) > written and time.monotonic() - last > 0.3:
            written, last = len(got), time.monotonic()
            write()
    write()


def _topic(name: str) -> tuple[str, S.Schema, Any]:
    """(topic, schema, QoS) of a team topic named by its last part (scenario, episode_metrics, ...)."""
    for t, (schema, qos) in subscribed_topics("train").items():
        if t.rsplit("/", 1)[-1] == name:
            return t, schema, qos
    raise SystemExit(f"no such topic: {name}")


def _record_until_stopped(node: Node, got: list[Any], out: Path) -> None:
    """Spin `node` until SIGTERM or SIGINT, writing `got` (which its subscriptions fill) to `out` as JSON once now
    (the subscriptions exist: the file tells the test so) and again whenever it grew."""

    def write() -> None:
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(got))
        tmp.replace(out)

    write()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    written = 0
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
        if len(got) > written:
            written = len(got)
            write()
    write()


def record(args: argparse.Namespace) -> None:
    from htlm_msgs_py.ros import STATE_READER

    topic, _schema, qos = _topic(args.topic)
    node = Node("test_recorder")
    got: list[str] = []
    node.create_subscription(String, topic, lambda m: got.append(m.data), STATE_READER if qos is STATE else qos)
    _record_until_stopped(node, got, Path(args.out))


def record_all(args: argparse.Namespace) -> None:
    """Every record on the given full topic names (STATE records read as late joiners would), with its topic and
    arrival time (Unix seconds), written to --out as a JSON list of [topic, time, text] whenever new ones came."""
    from htlm_msgs_py.ros import STATE_READER

    node = Node("test_recorder_all")
    got: list[tuple[str, float, str]] = []
    for name in args.topics:
        qos = STATE_READER if args.qos == "state" else EVENTS
        node.create_subscription(String, name, lambda m, n=name: got.append((n, time.time(), m.data)), qos)
    _record_until_stopped(node, got, Path(args.out))


def publish(args: argparse.Namespace) -> None:
    from rclpy.duration import Duration

    topic, schema, qos = _topic(args.topic)
    node = Node("test_publisher")
    pub = node.create_publisher(String, topic, qos)
    end = time.monotonic() + 30
    while time.monotonic() < end and pub.get_subscription_count() < args.subscribers:
        _spin_for(node, 0.1)
    matched = pub.get_subscription_count()
    while args.go and not Path(args.go).exists():  # matched already; publish when the test says so
        _spin_for(node, 0.05)
    text = json.loads(Path(args.source).read_text())[args.index]
    if args.set is not None:  # a forgery: the recorded fields with some changed, encoded anew
        fields = json.loads(text)
        for k in ("schema", "v", "sig"):
            fields.pop(k, None)
        fields.update(json.loads(args.set))
        text = S.encode(schema, fields, Signer(args.key.encode()) if args.key else None)
    pub.publish(string(text))
    pub.wait_for_all_acked(Duration(seconds=10))
    _spin_for(node, args.linger)
    Path(args.out).write_text(json.dumps({"sent": 1, "matched": matched, "text": text}))


def _wait_matched(node: Node, pubs: list[Any], subscribers: int, seconds: float = 30.0) -> int:
    """Spin until every publisher of `pubs` is matched with `subscribers` subscriptions (at most `seconds`); returns
    the fewest matched."""
    end = time.monotonic() + seconds
    while time.monotonic() < end and min(p.get_subscription_count() for p in pubs) < subscribers:
        _spin_for(node, 0.1)
    return min(p.get_subscription_count() for p in pubs)


def send(args: argparse.Namespace) -> None:
    """Publish record texts once each, in order: --source is a JSON object {topic: [texts]} (or a list of texts for
    --topic), read once --go exists. Each topic's writer is deep enough to keep them all (reliable, transient-local
    with --qos state as the team's state topics are) and is matched with --subscribers readers first (the file
    <out>.ready tells the test so); then every reader's acknowledgement is waited for."""
    from rclpy.duration import Duration

    node = Node("test_sender")
    names = args.topics.split(",") if args.topics else [args.topic]

    def writer(topic: str) -> Any:
        qos = QoSProfile(
            depth=args.depth,
            reliability=ReliabilityPolicy.RELIABLE,
            history=HistoryPolicy.KEEP_LAST,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if args.qos == "state" else DurabilityPolicy.VOLATILE,
        )
        return node.create_publisher(String, topic, qos)

    pubs = {t: writer(t) for t in names}
    want = json.loads(args.subscribers)  # readers to wait for: one number for every topic, or {topic: number}
    matched = {t: _wait_matched(node, [p], want[t] if isinstance(want, dict) else want) for t, p in pubs.items()}
    Path(args.out + ".ready").write_text(json.dumps(matched))
    while args.go and not Path(args.go).exists():
        _spin_for(node, 0.05)
    source = json.loads(Path(args.source).read_text())
    texts: dict[str, list[str]] = source if isinstance(source, dict) else {args.topic: source}
    sent = dict.fromkeys(texts, 0)
    for t, items in texts.items():
        for text in items:
            pubs[t].publish(string(text))
            sent[t] += 1
            if sent[t] % 20 == 0:
                _spin_for(node, args.pause)
    acked = {t: pubs[t].wait_for_all_acked(Duration(seconds=30)) for t in texts}
    _spin_for(node, args.linger)
    Path(args.out).write_text(json.dumps({"sent": sent, "matched": matched, "acked": acked}))


def goal_pose(args: argparse.Namespace) -> None:
    """Publish the goals of --goals (a JSON list of [x, y]; "nan" and "inf" stand for those values) as
    PoseStamped on --agent's goal_pose topic, --every seconds apart, with the team's QoS for it (a late joiner's
    state topic), once the agent's robot is matched."""
    from htlm_msgs_py.ros import STATE, PoseStamped, pose

    node = Node("test_goal_pose")
    pub = node.create_publisher(PoseStamped, topics.goal_pose(args.agent), STATE)
    matched = _wait_matched(node, [pub], args.subscribers)
    goals = [[float(v) for v in g] for g in json.loads(args.goals)]
    for x, y in goals:
        pub.publish(pose(x, y, args.frame, node.get_clock().now().to_msg()))
        _spin_for(node, args.every)
    Path(args.out).write_text(json.dumps({"sent": len(goals), "matched": matched}))


def odometry(args: argparse.Namespace) -> None:
    from nav_msgs.msg import Odometry

    from htlm_msgs_py.ros import ODOMETRY

    node = Node("test_odometry")
    got: dict[str, dict[str, Any]] = {a: {"count": 0, "nonfinite": 0, "last": None} for a in AGENTS}

    def on_odom(a: str, msg: Odometry) -> None:
        p = msg.pose.pose.position
        g = got[a]
        g["count"] += 1
        values = (p.x, p.y, p.z, msg.twist.twist.linear.x, msg.twist.twist.linear.y)
        if not all(v == v and abs(v) != float("inf") for v in values):
            g["nonfinite"] += 1
        g["last"] = [p.x, p.y] if all(v == v for v in (p.x, p.y)) else [str(p.x), str(p.y)]

    for a in AGENTS:
        node.create_subscription(Odometry, topics.odometry(a), lambda m, a=a: on_odom(a, m), ODOMETRY)
    _spin_and_dump(node, Path(args.out), got)


def listen(args: argparse.Namespace) -> None:
    from rclpy.event_handler import SubscriptionEventCallbacks

    node = Node("test_listener")
    got = {"received": 0, "lost_events": 0, "lost_total": 0}

    def on_lost(status: Any) -> None:
        got["lost_events"] += 1
        got["lost_total"] = int(status.total_count)

    def on_message(_msg: bytes) -> None:
        got["received"] += 1
        if args.cost:
            end = time.perf_counter() + args.cost
            while time.perf_counter() < end:
                pass

    node.create_subscription(
        String,
        args.topic,
        on_message,
        EVENTS,
        raw=True,
        event_callbacks=SubscriptionEventCallbacks(message_lost=on_lost),
    )
    out = Path(args.out)
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    last = 0.0
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() - last > 0.3:
            out.with_suffix(".tmp").write_text(json.dumps(got))
            out.with_suffix(".tmp").replace(out)
            last = time.monotonic()
    out.write_text(json.dumps(got))


def flood(args: argparse.Namespace) -> None:
    """Publish records every receiver of one topic rejects, as fast as one Python process can, from the moment the
    --go file exists until SIGTERM (or --seconds), then write how many went out."""
    import os

    from wire_fuzz import VALID

    topic = args.topic
    schema, qos = subscribed_topics("train")[topic]
    node = Node("test_flooder")
    pub = node.create_publisher(String, topic, qos)
    good = json.dumps({"schema": schema.name, "v": schema.version, **VALID[schema.name]}, separators=(",", ":"))
    bad_field = "agent" if "agent" in VALID[schema.name] else "episode"
    texts = [  # one of each rejection reason, none merely dropped by the protocol
        good[: len(good) // 2],  # json: cut in the middle
        good.replace(schema.name, "htlm/nothing", 1),  # schema
        good.replace(f'"v":{schema.version}', f'"v":{schema.version + 7}', 1),  # version
        json.dumps({"schema": schema.name, "v": schema.version, **VALID[schema.name], bad_field: 10**6}),  # range
    ]
    # and a String whose bytes are not UTF-8, serialized by hand (rclpy's String cannot hold it): encoding
    raw = b'{"schema":"\xff\xfe"}\0'
    msgs: list[Any] = [string(t) for t in texts] + [bytes([0, 1, 0, 0]) + len(raw).to_bytes(4, "little") + raw]
    if args.wrong_key:  # well-formed records signed with a key that is not the team's: rejected for the signature
        wrong = Signer(args.wrong_key.encode())
        msgs = [string(S.encode(schema, {**VALID[schema.name], "step": 1 + i}, wrong)) for i in range(5)]
    end = time.monotonic() + 30
    while time.monotonic() < end and pub.get_subscription_count() < args.subscribers:
        _spin_for(node, 0.1)
    matched = pub.get_subscription_count()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    go = Path(args.go) if args.go else None
    while not stop and go is not None and not go.exists():
        _spin_for(node, 0.02)
    if args.nice:
        os.nice(args.nice)
    sent, t0 = 0, time.monotonic()
    end = t0 + args.seconds
    if args.hog:  # the control: as busy as the flooder, without a record
        while not stop and time.monotonic() < end:
            sum(range(1000))
    elif args.rate:  # at most --rate records/s, in bursts of the five records
        while not stop and (now := time.monotonic()) < end:
            if sent >= (now - t0) * args.rate:
                time.sleep(min(len(msgs) / args.rate, 0.01))
                continue
            for m in msgs:
                pub.publish(m)
            sent += len(msgs)
    else:
        while not stop and time.monotonic() < end:
            for m in msgs:
                pub.publish(m)
            sent += len(msgs)
    took = time.monotonic() - t0
    out = {"sent": sent, "seconds": round(took, 3), "rate": round(sent / max(took, 1e-9)), "matched": matched}
    Path(args.out).write_text(json.dumps(out))


def main() -> None:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("diag")
    d.add_argument("--out", required=True)
    f = sub.add_parser("fuzz")
    f.add_argument("--out", required=True)
    f.add_argument("--mode", default="evaluate")
    f.add_argument("--count", type=int, default=1000)
    f.add_argument("--first", type=int, default=0)
    f.add_argument("--episodes", type=int, default=1)
    f.add_argument("--horizon", type=int, default=30)
    f.add_argument("--pause", type=float, default=0.005)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--topics", default="", help="comma-separated topic name endings to fuzz (default: all)")
    f.add_argument("--batch", type=int, default=50, help="records per topic between two flow-control waits")
    r = sub.add_parser("rogue")
    r.add_argument("--out", required=True)
    r.add_argument("--key", default="", help="the rogue's own (wrong) key; empty: unsigned")
    r.add_argument("--horizon", type=int, default=30)
    r.add_argument("--seconds", type=float, default=60.0)
    r.add_argument("--pause", type=float, default=0.05)
    r.add_argument("--kinds", default="all", help="all, or a comma-separated list of broadcast, action, observation")
    r.add_argument("--wrong-lengths", action="store_true", help="arrays one too short (actions) or long (levels)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--run", default="", help="the run the records name; empty: the team's, from its announcement")
    sp = sub.add_parser("setparam")
    sp.add_argument("--out", required=True)
    sp.add_argument("--node", default="/htlm_world")
    sp.add_argument("--name", required=True)
    sp.add_argument("--value", required=True, help="JSON value")
    ds = sub.add_parser("describe")
    ds.add_argument("--out", required=True)
    ds.add_argument("--nodes", required=True, help="comma-separated node names, e.g. /htlm_world,/htlm_trainer")
    gr = sub.add_parser("graph")
    gr.add_argument("--out", required=True)
    gr.add_argument("--nodes", required=True, help="comma-separated node names without the slash, e.g. htlm_agent1")
    gr.add_argument("--params", default="agent,policy", help="comma-separated string parameters to read")
    mk = sub.add_parser("markers")
    mk.add_argument("--out", required=True)
    rc = sub.add_parser("record")
    rc.add_argument("--out", required=True)
    rc.add_argument("--topic", required=True, help="the topic's last part: scenario, episode_metrics, ...")
    ra = sub.add_parser("record_all")
    ra.add_argument("--out", required=True)
    ra.add_argument("--qos", choices=("state", "events"), default="state")
    ra.add_argument("topics", nargs="+", help="full topic names, e.g. /htlm/agent1/belief")
    pb = sub.add_parser("publish")
    pb.add_argument("--out", required=True)
    pb.add_argument("--topic", required=True, help="the topic's last part: scenario, episode_metrics, ...")
    pb.add_argument("--source", required=True, help="JSON list of record texts (what record writes), read at --go")
    pb.add_argument("--index", type=int, default=0, help="which record of the list (negative: from the end)")
    pb.add_argument("--set", default=None, help="JSON object of fields to change (encoded anew); none: a replay")
    pb.add_argument("--key", default="", help="key to sign a changed record with; empty: unsigned")
    pb.add_argument("--subscribers", type=int, default=1, help="subscribers to wait for (at most 30 s)")
    pb.add_argument("--linger", type=float, default=1.0, help="seconds to stay up after publishing")
    pb.add_argument("--go", default="", help="publish once this file exists (empty: at once)")
    sd = sub.add_parser("send")
    sd.add_argument("--out", required=True)
    sd.add_argument("--topic", default="", help="the full topic name, e.g. /htlm/action")
    sd.add_argument("--topics", default="", help="comma-separated full topic names (--source an object of them)")
    sd.add_argument("--source", required=True, help="JSON list of record texts, or object {topic: [texts]}")
    sd.add_argument("--depth", type=int, default=2000, help="records each writer keeps (reliable delivery)")
    sd.add_argument("--qos", choices=("state", "events"), default="events")
    sd.add_argument("--subscribers", default="1", help='readers to wait for (at most 30 s): N or {"topic": N}')
    sd.add_argument("--go", default="", help="publish once this file exists (empty: at once)")
    sd.add_argument("--pause", type=float, default=0.01, help="seconds of spinning after every 20 records")
    sd.add_argument("--linger", type=float, default=0.5, help="seconds to stay up after the acknowledgements")
    gp = sub.add_parser("goal_pose")
    gp.add_argument("--out", required=True)
    gp.add_argument("--agent", required=True)
    gp.add_argument("--goals", required=True, help='JSON list of [x, y], e.g. [["nan", 0], [1e6, 0]]')
    gp.add_argument("--frame", default="map")
    gp.add_argument("--every", type=float, default=0.5)
    gp.add_argument("--subscribers", type=int, default=1)
    od = sub.add_parser("odometry")
    od.add_argument("--out", required=True)
    ls = sub.add_parser("listen")
    ls.add_argument("--out", required=True)
    ls.add_argument("--topic", default=topics.BROADCAST)
    ls.add_argument("--cost", type=float, default=0.0, help="seconds of busy work per record")
    fl = sub.add_parser("flood")
    fl.add_argument("--out", required=True)
    fl.add_argument("--topic", default=topics.ACTION, help="the full topic name, e.g. /htlm/action")
    fl.add_argument("--subscribers", type=int, default=1, help="subscribers to wait for (at most 30 s)")
    fl.add_argument("--go", default="", help="start once this file exists (empty: at once)")
    fl.add_argument("--seconds", type=float, default=120.0, help="longest flood (SIGTERM ends it sooner)")
    fl.add_argument("--nice", type=int, default=0, help="lower the flooder's CPU priority by this much once it floods")
    fl.add_argument("--rate", type=float, default=0.0, help="records per second at most (0: as fast as it can)")
    fl.add_argument("--hog", action="store_true", help="burn the CPU as the flood would, publishing nothing")
    fl.add_argument("--wrong-key", default="", help="flood well-formed records signed with this (wrong) key instead")
    args = p.parse_args()
    faulthandler.register(signal.SIGUSR1)
    rclpy.init()
    try:
        cmds = {
            "diag": diag,
            "fuzz": fuzz,
            "rogue": rogue,
            "setparam": setparam,
            "describe": describe,
            "graph": graph,
            "markers": markers,
            "flood": flood,
            "send": send,
            "goal_pose": goal_pose,
            "odometry": odometry,
            "listen": listen,
            "record": record,
            "record_all": record_all,
            "publish": publish,
        }
        cmds[args.cmd](args)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
