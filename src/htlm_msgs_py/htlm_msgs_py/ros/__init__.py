"""The ROS-facing half of the wire contract: QoS profiles, message classes, diagnostics, node parameters.

This is the only module of htlm_msgs_py that imports rclpy and the message classes of common_interfaces; the
rest of the package (and the whole model core) imports without them.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import gc
import math
import os
import sys
import time
import typing
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from std_msgs.msg import String

from .. import qos as _qos
from ..params import INT64_MAX, Constraint, constraints, field_docs
from ..schema import Schema, WireError, decode, encode, record_text
from ..signing import Signer
from ..validation import ConversionError, convert, convert_value
from . import exit_timer

T = TypeVar("T")

__all__ = [
    "WEIGHTS",
    "DiagnosticArray",
    "Health",
    "PoseStamped",
    "SettingsError",
    "String",
    "WorldWatch",
    "declare_settings",
    "field_docs",
    "make_executor",
    "parameter_descriptor",
    "pose",
    "qos_profile",
    "say_unsigned",
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


def make_executor(kind: str) -> Executor:
    """The executor a node spins in: "events" (rclpy's EventsExecutor, fastest) or "single"."""
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:  # an rclpy without it
            return SingleThreadedExecutor()
        return EventsExecutor()
    return SingleThreadedExecutor()


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

    def publish(self) -> None:
        """Publish the status and every counter on /diagnostics."""
        st = DiagnosticStatus()
        st.level = self.level
        st.name = self.name
        st.message = self.message
        st.hardware_id = self.hardware_id
        vals = {"uptime_s": f"{time.monotonic() - self.started:.1f}", **self.values}
        vals.update({k: str(v) for k, v in sorted(self.counters.items())})
        st.values = [KeyValue(key=k, value=v) for k, v in vals.items()]
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


class WorldWatch:
    """Whether the world is heard: its records (`heard()`) or its status on /diagnostics ("htlm: world"). A node
    that follows a run says on its /diagnostics (WARN, with the seconds) and in its log (every `period` seconds at
    most) when the world has been silent for longer than `timeout` seconds."""

    def __init__(self, node: Node, health: Health, timeout: float, period: float = 10.0) -> None:
        """Listen to /diagnostics for the world's status."""
        self.node, self.health, self.timeout, self.period = node, health, timeout, period
        self.last = time.monotonic()
        self.logged = -math.inf
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, DIAGNOSTICS)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if any(st.name == "htlm: world" for st in msg.status):
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


# ----- node parameters from a settings dataclass ------------------------------------------------------------------


class SettingsError(ValueError):
    """A node parameter with a bad value (names the parameter and the value)."""


_PARAMETER_TYPES = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}
"""The ROS parameter type of each field type a settings dataclass may use."""


def parameter_descriptor(name: str, tp: type, doc: str, c: Constraint) -> ParameterDescriptor:
    """The descriptor of the parameter of a settings field: its type, description, range, choices, read-only."""
    d = ParameterDescriptor(
        name=name,
        type=_PARAMETER_TYPES[tp],
        description=doc,
        additional_constraints=c.describe(),
        read_only=not c.tunable,
    )
    if tp is float and (c.lo is not None or c.hi is not None):
        lo = -sys.float_info.max if c.lo is None else float(c.lo)
        hi = sys.float_info.max if c.hi is None else float(c.hi)
        d.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    elif tp is int and (c.lo is not None or c.hi is not None):
        lo_i = -INT64_MAX - 1 if c.lo is None else int(c.lo)
        hi_i = INT64_MAX if c.hi is None else int(c.hi)
        d.integer_range = [IntegerRange(from_value=lo_i, to_value=hi_i, step=0)]
    return d


def declare_settings(
    node: Node, cls: type[T], validate: Callable[[T], None], on_change: Callable[[T], None] | None = None
) -> T:
    """Declare one parameter per field of the frozen settings dataclass `cls` and return the settings.

    Every parameter is statically typed and gets a descriptor (`parameter_descriptor`) with the field's docstring,
    its range (`floating_point_range` / `integer_range`) and choices from the field's `htlm_msgs_py.params`
    constraint, and `read_only` unless the field is tunable, so `ros2 param describe` shows them. The values
    (defaults, or given with `--ros-args -p name:=value` or a parameters file; an integer is taken for a float) are
    converted with `htlm_msgs_py.validation.convert` and checked with `validate(settings)` before anything is
    declared; both raise SettingsError naming the parameter and the value. Later changes of tunable parameters go
    through rclpy's type and range checks and then the same `validate`; a refusal is a
    SetParametersResult(successful=False, reason=...) naming the parameter and the value, and an accepted change
    calls `on_change(new settings)`.
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)  # type: ignore[arg-type]
    cons = constraints(cls)
    # rclpy keeps the values given on the command line and in parameter files here until they are declared
    overrides: dict[str, Any] = getattr(node, "_parameter_overrides", {})
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name in overrides:
            values[f.name] = overrides[f.name].value
        else:
            values[f.name] = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[operator]
    try:
        settings = convert(values, cls, "parameters")
    except ConversionError as e:
        raise SettingsError(str(e)) from None
    validate(settings)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        desc = parameter_descriptor(f.name, hints[f.name], docs.get(f.name, ""), cons[f.name])
        node.declare_parameter(f.name, getattr(settings, f.name), desc, ignore_override=True)
    floats = {name for name, tp in hints.items() if tp is float}
    state = {"settings": settings}

    def widen(params: list[Parameter]) -> list[Parameter]:
        """An integer given for a float parameter (`ros2 param set /node period 1`) is taken as that float."""
        return [
            Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
            if p.name in floats and p.type_ == Parameter.Type.INTEGER
            else p
            for p in params
        ]

    def on_set(params: list[Parameter]) -> SetParametersResult:
        try:
            changes = {
                p.name: convert_value(p.value, hints[p.name], p.name, "parameters") for p in params if p.name in hints
            }
            new = dataclasses.replace(state["settings"], **changes)  # type: ignore[type-var]
            validate(new)
        except (ConversionError, SettingsError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        state["settings"] = new
        if on_change is not None:
            on_change(new)
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(widen)
    node.add_on_set_parameters_callback(on_set)
    return settings


def spin_until(executor: Executor, done: Callable[[], bool], deadline: float) -> bool:
    """Spin until `done()` or the monotonic `deadline`; returns done(). Raises if the context shuts down."""
    while not done():
        now = time.monotonic()
        if now >= deadline:
            return done()
        executor.spin_once(timeout_sec=min(deadline - now, 0.25))
        if not rclpy.ok():
            from rclpy.executors import ExternalShutdownException

            raise ExternalShutdownException()
    return True


def spin_until_finished(node: Any, executor: Executor) -> int:
    """Spin until the node says it is finished or a signal arrived; exit code 128 + signal, 2 fatal, 0 done.

    `node` has `stop_signal` (0 or the signal number), `fatal` (None or a reason) and `finished()`.
    """
    while not node.stop_signal and not node.finished():
        executor.spin_once(timeout_sec=0.25)
    if node.stop_signal:
        return 128 + int(node.stop_signal)
    return 2 if node.fatal else 0


FLUSH_SECONDS = 1.0
"""Longest a node process waits at exit for its reliable readers to acknowledge what it published (`flush`)."""


def flush(node: Node, seconds: float) -> bool:
    """Wait until every reliable reader matched with the node's publishers has acknowledged every message they
    published, at most `seconds` in all; returns whether all were.

    Without it a node's last messages can be lost to a reader that had not received them yet when the node left:
    its goodbye may be handled before the data (another socket, another thread), and the data of a writer that is
    gone is dropped. A recorder missed an agent's last belief and ready that way.
    """
    from rclpy.duration import Duration

    end = time.monotonic() + seconds
    for pub in list(node.publishers):
        left = end - time.monotonic()
        if left <= 0 or not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            return False
    return True


TEARDOWN_SECONDS = 10.0
"""Longest a node process may take to tear rclpy down after its work is done (`run_node`); usually well under 1 s."""


def run_node(
    name: str,
    make_node: Callable[[], Any],
    run: Callable[[Any, Executor], int],
    cleanup: Callable[[Any], None],
    args: list[str] | None = None,
) -> int:
    """The Jazzy node skeleton shared by every HTLM node's `main`.

    Construct the node before `try` (bad parameters exit with code 2 and the reason on stderr), route SIGINT and
    SIGTERM into `node.stop_signal` so `run` can stop cleanly, let SIGUSR1 dump every thread's stack to the log,
    then `cleanup(node)`, the executor's release of the node, `destroy_node()` and `try_shutdown()` whatever
    happened, with the cyclic garbage collector off and every live object frozen; a teardown (up to the
    interpreter's own exit) that takes longer than TEARDOWN_SECONDS prints every thread's stack and ends the
    process with the code it returns (`exit_timer`). Call it only as the process's main: the teardown's watchdog
    outlives the call.

    Returns the process exit code: what `run` returned, 130 on KeyboardInterrupt / external shutdown.
    """
    import signal

    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    faulthandler.register(signal.SIGUSR1)  # `kill -USR1 <pid>` prints every thread's stack to the log, from the start
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = make_node()
    except SettingsError as e:
        print(f"{name}: {e}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2

    def on_signal(signum: int, _frame: Any) -> None:
        node.stop_signal = signum

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    executor = make_executor(node.settings.executor)
    executor.add_node(node)
    code = 1
    try:
        code = run(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 130
    finally:
        cleanup(node)
        health = getattr(node, "health", None)
        if health is not None and health.counters:
            counts = ", ".join(f"{k} {v}" for k, v in sorted(health.counters.items()))
            node.get_logger().info(f"counters at exit: {counts}")
        flush(node, FLUSH_SECONDS)
        # The node's work is done and logged, and its exit code decided. Tearing rclpy down can hang: a Fast DDS
        # participant's destruction can spin with the GIL held while a discovery callback starves (exit_timer says
        # how; 15 of about 14,500 node exits in this project's ROS tests). Then, after TEARDOWN_SECONDS,
        # faulthandler's own thread prints every thread's stack to the log, and half a second later a timer ends
        # the process with the code it would have had: the run's result stands, the stacks say where it hung
        # (without the timer, where the platform lacks it, faulthandler exits with code 1). Both stay armed through
        # the interpreter's exit (every node's `main` is the process's); neither needs the GIL.
        # No cyclic collection runs from here on either (gdb caught one in the interpreter's exit, over rclpy's
        # torn-down objects): the collector is off, and what is alive is frozen, which the collection at exit skips.
        gc.disable()
        gc.freeze()
        timed = exit_timer.exit_after(TEARDOWN_SECONDS + 0.5, code)
        faulthandler.dump_traceback_later(TEARDOWN_SECONDS, exit=not timed)
        try:  # the executor lets go of the node's entities before they are destroyed, not while Python tears it down
            executor.remove_node(node)  # (there a node's QoS event handler hung the exit: tests/ros saw it 4 times)
            executor.shutdown()
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
    return code
