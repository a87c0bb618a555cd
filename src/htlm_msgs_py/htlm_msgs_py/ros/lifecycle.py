"""A node process from start to exit, the same for every HTLM node: its start-up (`start_node`: the parameters of
its settings dataclass, checked, and the team key), its main (`run_node`: SIGINT and SIGTERM into a clean stop, the
executor, the garbage collector switched off for the teardown, and the exit watchdog that ends a teardown that hangs)
and the loop most nodes spin in (`spin_until_finished`)."""

from __future__ import annotations

import faulthandler
import gc
import math
import sys
import time
from collections.abc import Callable
from typing import Any, TypeVar

import rclpy
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node

from ..signing import Signer, SigningError, signer_from_env
from . import exit_timer
from .parameters import SettingsError, declare_settings

T = TypeVar("T")


def start_node(
    node: Node,
    cls: type[T],
    validate: Callable[[T], list[str]],
    on_change: Callable[[T], None] | None = None,
) -> tuple[T, Signer]:
    """The start-up every HTLM node shares: declare one parameter per field of the settings dataclass `cls`
    (`declare_settings`; later changes of tunable ones go to `on_change`), checked by `validate`, which lists the
    problems of a whole settings object, and read the team key from the environment (`signer_from_env`).

    Returns:
        The node's settings and its signer.

    Raises:
        SettingsError: a parameter or the team key is bad (the message names it; `run_node` exits with 2).
    """

    def check(settings: T) -> None:
        bad = validate(settings)
        if bad:
            raise SettingsError("; ".join(bad))

    settings = declare_settings(node, cls, check, on_change)
    try:
        signer = signer_from_env()
    except SigningError as e:
        raise SettingsError(str(e)) from None
    return settings, signer


def make_executor(kind: str) -> Executor:
    """The executor a node spins in: "events" (rclpy's EventsExecutor, fastest) or "single"."""
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:  # an rclpy without it
            return SingleThreadedExecutor()
        return EventsExecutor()
    return SingleThreadedExecutor()


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


CHECK_SECONDS = 0.05
"""How often a process of several nodes (`run_nodes`) looks at every node's state (finished, fatal) between
callbacks: each look costs a call per node, and a composed process runs many callbacks a step."""

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


def run_nodes(
    name: str,
    make_nodes: Callable[[], list[Any]],
    cleanup: Callable[[Any], None],
    args: list[str] | None = None,
) -> int:
    """The skeleton of a process that hosts several nodes in one executor (as a ROS 2 component container hosts
    components), each the node `run_node` would run alone, with that process's rules kept for the whole process.

    `make_nodes()` constructs every hosted node in one rclpy context (each with its own name, parameters and
    entities); a bad parameter of any of them exits with code 2, as `run_node` does, naming the node. The nodes
    spin in one executor (the first node's `settings.executor`) until:

    - a node is `finished()` (its run is over and its work flushed): it stops at once (`cleanup`, its counters
      logged, `flush`, removed from the executor) while the others go on; when the last one has finished, the
      process exits 0. A finished node is destroyed, and leaves the graph, with the process: the EventsExecutor
      may still hold events of a node it no longer runs, and one that came for a destroyed node's subscription
      raised InvalidHandle out of `spin_once` (a training run's last acknowledgements, seen in
      tests/ros/test_compose.py);
    - a node has a `fatal` error (the process alone would exit 2: a bad policy or checkpoint, which would fail the
      same way again): every node stops and the process exits 2;
    - SIGINT or SIGTERM: every node stops (each node's `stop_signal` is set), exit 128 + signal;
    - an exception escapes a callback: every node is torn down as below and the exception ends the process (exit 1
      with its traceback), as it would end a process of one node.

    The teardown of the nodes still up is `run_node`'s: `cleanup`, counters, one `flush` budget for all of them,
    the garbage collector off, the exit watchdog, every node removed and destroyed, rclpy shut down. Call it only
    as the process's main.
    """
    import signal
    import traceback

    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    faulthandler.register(signal.SIGUSR1)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        nodes = make_nodes()
    except SettingsError as e:
        print(f"{name}: {e}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    stop_signal: list[int] = []

    def on_signal(signum: int, _frame: Any) -> None:
        stop_signal.append(signum)
        for n in nodes:
            n.stop_signal = signum

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    executor = make_executor(nodes[0].settings.executor)
    for n in nodes:
        executor.add_node(n)
    live = list(nodes)
    retired: list[Any] = []

    def counters(node: Any) -> None:
        health = getattr(node, "health", None)
        if health is not None and health.counters:
            counts = ", ".join(f"{k} {v}" for k, v in sorted(health.counters.items()))
            node.get_logger().info(f"counters at exit: {counts}")

    def retire(node: Any) -> None:
        """A finished node stops now, as its own process would exit, while the others go on."""
        live.remove(node)
        retired.append(node)
        try:
            cleanup(node)
            counters(node)
            flush(node, FLUSH_SECONDS)
        finally:
            executor.remove_node(node)

    code = 1
    checked = -math.inf
    try:
        while True:
            if stop_signal:
                code = 128 + int(stop_signal[0])
                break
            now = time.monotonic()
            if now - checked >= CHECK_SECONDS:  # every node's state, not after each of the many callbacks
                checked = now
                fatal = [n for n in live if n.fatal is not None]
                if fatal:
                    for n in fatal:
                        n.get_logger().error(f"fatal in {n.get_name()}: {n.fatal}; stopping every node of this process")
                    code = 2
                    break
                for n in [n for n in live if n.finished()]:
                    retire(n)
                if not live:
                    code = 0
                    break
            executor.spin_once(timeout_sec=CHECK_SECONDS)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 130
    finally:  # an exception from a callback propagates after this (exit 1, its traceback at the end of the log)
        for n in live:
            try:
                cleanup(n)
                counters(n)
            except Exception:  # one node's cleanup must not keep the others from theirs
                traceback.print_exc()
        end = time.monotonic() + FLUSH_SECONDS
        for n in live:
            flush(n, max(0.0, end - time.monotonic()))
        gc.disable()
        gc.freeze()
        timed = exit_timer.exit_after(TEARDOWN_SECONDS + 0.5, code)
        faulthandler.dump_traceback_later(TEARDOWN_SECONDS, exit=not timed)
        try:
            for n in live:
                executor.remove_node(n)
            executor.shutdown()
        finally:
            for n in live + retired:
                n.destroy_node()
            rclpy.try_shutdown()
    return code


def parse_hosted(words: list[str], what: str = "agent") -> list[tuple[str, str]]:
    """(node name, parameters file) of every node a composed process hosts, from its words before `--ros-args`
    (NODE=PARAMETERS_FILE each).

    Raises:
        ValueError: no node, a word that is not NODE=FILE, or a node named twice.
    """
    hosted: list[tuple[str, str]] = []
    for w in words:
        node, sep, path = w.partition("=")
        if not sep or not node or not path:
            raise ValueError(f"{w!r}: expected NODE=PARAMETERS_FILE")
        if node in (n for n, _ in hosted):
            raise ValueError(f"{node}: named twice")
        hosted.append((node, path))
    if not hosted:
        raise ValueError(f"no {what} to host")
    return hosted


def node_args(node: str, params_file: str) -> list[str]:
    """The ROS arguments of one hosted node: its name and its parameters file."""
    return ["--ros-args", "-r", f"__node:={node}", "--params-file", params_file]


def host_nodes(
    name: str, what: str, make: Callable[[list[str]], Any], cleanup: Callable[[Any], None], args: list[str] | None
) -> int:
    """The `main` of a composed process (`run_nodes`): every NODE=PARAMETERS_FILE word before `--ros-args` becomes
    one node, `make(its ROS arguments)`, named after `what` it hosts in the log line and the errors."""
    from rclpy.utilities import remove_ros_args

    argv = sys.argv if args is None else args
    try:
        hosted = parse_hosted(remove_ros_args(argv)[1:], what)
    except ValueError as e:
        usage = f"usage: {name} NODE=PARAMETERS_FILE [NODE=PARAMETERS_FILE ...] [--ros-args ...]"
        print(f"{name}: {e}\n{usage}", file=sys.stderr)
        return 2

    def make_nodes() -> list[Any]:
        rclpy.logging.get_logger(f"htlm_{what}s").info(
            f"hosting {len(hosted)} {what}s in one process: {', '.join(n for n, _ in hosted)}"
        )
        nodes: list[Any] = []
        try:
            for node, path in hosted:
                try:
                    nodes.append(make(node_args(node, path)))
                except SettingsError as e:
                    raise SettingsError(f"{node}: {e}") from None
        except BaseException:
            for n in nodes:  # the ones already made, so rclpy shuts down cleanly
                n.destroy_node()
            raise
        return nodes

    return run_nodes(name, make_nodes, cleanup, argv)
