"""The ROS-facing half of the wire contract: QoS profiles, message classes, diagnostics, node parameters.

This is the only module of htlm_msgs_py that imports rclpy and the message classes of common_interfaces; the
rest of the package (and the whole model core) imports without them.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import time
import typing
from collections import Counter
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from .. import qos as _qos
from ..schema import Schema, WireError, decode, encode
from ..signing import Signer

__all__ = [
    "DiagnosticArray",
    "Health",
    "PoseStamped",
    "SettingsError",
    "String",
    "declare_settings",
    "field_docs",
    "make_executor",
    "pose",
    "qos_profile",
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
DIAGNOSTICS = qos_profile(_qos.DIAGNOSTICS)


def make_executor(kind: str) -> Executor:
    """The executor a node spins in: "events" (rclpy's EventsExecutor, fastest) or "single"."""
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:  # an rclpy without it
            return SingleThreadedExecutor()
        return EventsExecutor()  # type: ignore[no-any-return]
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

    def decode(self, topic: str, msg: Any, schema: Schema, lim: Any = None) -> dict[str, Any] | None:
        """The validated fields of a received String, or None (counted and logged) when it is rejected."""
        self.counters[f"arrived/{topic}"] += 1
        try:
            data = msg.data
            rec = decode(data, schema, lim, self.signer)
        except WireError as e:
            self.reject(topic, e.reason, str(e))
            return None
        except Exception as e:
            self.reject(topic, "error", f"{type(e).__name__}: {e}")
            return None
        self.counters[f"received/{topic}"] += 1
        return rec

    def reject(self, topic: str, reason: str, detail: str) -> None:
        """Count a rejected or dropped record and warn (at most once every 5 s per node)."""
        self.counters["rejected"] += 1
        self.counters[f"rejected/{topic}/{reason}"] += 1
        now = time.monotonic()
        if now - self._warned.get(topic, -1e9) >= 5.0:  # at most one warning per topic every 5 s
            self._warned[topic] = now
            n = self.counters[f"rejected/{topic}/{reason}"]
            self.node.get_logger().warning(f"rejected a record on {topic} ({reason}, {n} so far): {detail[:200]}")

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


def field_docs(cls: type) -> dict[str, str]:
    """The one-line docstring under each field of a dataclass (the attribute docstring convention)."""
    import ast
    import inspect
    import textwrap

    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = ast.parse(src).body[0]
    assert isinstance(body, ast.ClassDef)
    docs: dict[str, str] = {}
    stmts = body.body
    for a, b in itertools.pairwise(stmts):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            docs[a.target.id] = b.value.value.strip().splitlines()[0]
    return docs


def _coerce(name: str, value: Any, tp: Any) -> Any:
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is str and isinstance(value, str):
        return value
    raise SettingsError(f"parameter {name}: expected {tp.__name__}, got {type(value).__name__} {value!r}")


def declare_settings(
    node: Node,
    cls: type,
    validate: Callable[[Any], None],
    tunable: tuple[str, ...] = (),
    on_change: Callable[[Any], None] | None = None,
) -> Any:
    """Declare one parameter per field of the frozen settings dataclass `cls` and return the settings.

    Every parameter gets a descriptor with the field's docstring; fields not in `tunable` are read-only. The values
    (defaults or given with `--ros-args -p name:=value`) are converted to the field's type and checked with
    `validate(settings)`, which raises SettingsError naming the parameter and the value. Later changes of tunable
    parameters go through the same check and are refused with SetParametersResult(successful=False, reason=...).
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        desc = ParameterDescriptor(
            description=docs.get(f.name, ""), read_only=f.name not in tunable, dynamic_typing=True
        )
        param = node.declare_parameter(f.name, default, desc)
        values[f.name] = _coerce(f.name, param.value, hints[f.name])
    settings = cls(**values)
    validate(settings)
    state = {"settings": settings}

    def on_set(params: list[Any]) -> SetParametersResult:
        changes = {}
        try:
            for p in params:
                if p.name not in hints:
                    continue
                changes[p.name] = _coerce(p.name, p.value, hints[p.name])
            new = dataclasses.replace(state["settings"], **changes)
            validate(new)
        except SettingsError as e:
            return SetParametersResult(successful=False, reason=str(e))
        state["settings"] = new
        if on_change is not None:
            on_change(new)
        return SetParametersResult(successful=True)

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


def run_node(
    name: str,
    make_node: Callable[[], Any],
    run: Callable[[Any, Executor], int],
    cleanup: Callable[[Any], None],
    args: list[str] | None = None,
) -> int:
    """The Jazzy node skeleton shared by every HTLM node's `main` (STYLE.md 8).

    Construct the node before `try` (bad parameters exit with code 2 and the reason on stderr), route SIGINT and
    SIGTERM into `node.stop_signal` so `run` can stop cleanly, let SIGUSR1 dump every thread's stack to the log,
    then `cleanup(node)`, `destroy_node()` and `try_shutdown()` whatever happened.

    Returns the process exit code: what `run` returned, 130 on KeyboardInterrupt / external shutdown.
    """
    import faulthandler
    import signal
    import sys

    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

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
    faulthandler.register(signal.SIGUSR1)  # `kill -USR1 <pid>` prints every thread's stack to the log
    executor = make_executor(node.settings.executor)
    executor.add_node(node)
    code = 1
    try:
        code = run(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 130
    finally:
        cleanup(node)
        node.destroy_node()
        rclpy.try_shutdown()
    return code
