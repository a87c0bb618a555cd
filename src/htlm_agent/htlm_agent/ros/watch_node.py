"""watch_node: `htlm watch`, a live terminal view of a running team.

A thin node: it subscribes to the monitoring topics (/htlm/scenario, /htlm/step, /htlm/ground_truth, every agent's
/htlm/<agent>/belief once the scenario names them, /htlm/episode_metrics, /diagnostics), hands every record to the
ROS-free `htlm_agent.experiments.watch_view.WatchState` (which decodes and validates it, counting rejects) and
redraws `watch_view.render` in place with rich, or prints plain snapshots (`plain`, `once`, or when stdout is not a
terminal). Its subscriptions are what make the world publish the ground truth and the agents their beliefs.
"""

from __future__ import annotations

import functools
import time
from typing import IO, Any

from rclpy.executors import Executor
from rclpy.node import Node
from rich.console import Console
from rich.live import Live

from htlm_agent.experiments.watch_view import WatchSettings, WatchState, render, snapshot
from htlm_msgs_py import topics
from htlm_msgs_py.ros import DIAGNOSTICS, EVENTS, STATE_READER, DiagnosticArray, String, run_node
from htlm_msgs_py.signing import Signer


def _level(raw: Any) -> int:
    """A DiagnosticStatus level (rclpy gives it as one byte)."""
    if isinstance(raw, bytes | bytearray):
        return raw[0] if raw else 0
    return int(raw)


class WatchNode(Node):
    """Subscriptions that feed a WatchState."""

    def __init__(self, settings: WatchSettings, signer: Signer) -> None:
        """Create the subscriptions (the beliefs' come once the scenario names the agents)."""
        super().__init__("htlm_watch")
        self.settings = settings
        self.state = WatchState(settings.episode_in_batch, signer, settings.stale_after)
        self.stop_signal = 0
        self._beliefs: dict[str, Any] = {}
        self.create_subscription(String, topics.SCENARIO, self._on_scenario, STATE_READER)
        self.create_subscription(String, topics.STEP, self._on_step, EVENTS)
        self.create_subscription(String, topics.GROUND_TRUTH, self._on_ground_truth, EVENTS)
        self.create_subscription(String, topics.EPISODE_METRICS, self._on_metrics, EVENTS)
        self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS)

    def _on_step(self, msg: String) -> None:
        self.state.on_step(msg.data)

    def _on_ground_truth(self, msg: String) -> None:
        self.state.on_ground_truth(msg.data)

    def _on_metrics(self, msg: String) -> None:
        self.state.on_metrics(msg.data)

    def _on_scenario(self, msg: String) -> None:
        self.state.on_scenario(msg.data)
        for name in self.state.agent_names:
            if name not in self._beliefs:
                self._beliefs[name] = self.create_subscription(
                    String, topics.belief(name), functools.partial(self._on_belief, name), STATE_READER
                )

    def _on_belief(self, name: str, msg: String) -> None:
        self.state.on_belief(name, msg.data)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        statuses = [(s.name, _level(s.level), s.message, {kv.key: kv.value for kv in s.values}) for s in msg.status]
        self.state.on_diagnostics(statuses, time.monotonic())


def watch(node: WatchNode, executor: Executor, out: IO[str]) -> int:
    """Spin and show the state until `duration` elapses or a signal arrives; returns 0."""
    s = node.settings
    console = Console(file=out)
    interactive = not (s.plain or s.once) and console.is_terminal
    start = time.monotonic()
    end = start + s.duration if s.duration > 0 else float("inf")
    next_print = start + s.every

    def plain(now: float) -> None:
        out.write(f"--- htlm watch, {now - start:.1f} s ---\n")
        out.write(snapshot(node.state, now, s.width))
        out.flush()

    live = Live(render(node.state, start), console=console, auto_refresh=False) if interactive else None
    if live is not None:
        live.start()
    next_draw = start
    try:
        while not node.stop_signal:
            now = time.monotonic()
            if now >= end:
                break
            executor.spin_once(timeout_sec=min(1.0 / s.refresh, end - now, 0.25))
            now = time.monotonic()
            if live is not None and now >= next_draw:
                live.update(render(node.state, now), refresh=True)
                next_draw = now + 1.0 / s.refresh
            elif live is None and not s.once and now >= next_print:
                plain(now)
                next_print = now + s.every
    finally:
        now = time.monotonic()
        if live is not None:
            live.update(render(node.state, now), refresh=True)
            live.stop()
        else:
            plain(now)
    return 0


def main(settings: WatchSettings, signer: Signer, out: IO[str]) -> int:
    """Run the watch (exit code 0 after `duration` or Ctrl-C / SIGTERM)."""
    return run_node(
        "htlm watch",
        lambda: WatchNode(settings, signer),
        lambda node, executor: watch(node, executor, out),
        lambda node: None,
        [],
    )
