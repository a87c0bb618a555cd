"""watch_node: `htlm watch`, a live terminal view of a running team.

A thin node: it subscribes to the monitoring topics (/htlm/scenario, /htlm/step, /htlm/ground_truth, every agent's
/htlm/<agent>/belief once the scenario names them, /htlm/episode_metrics, /diagnostics), hands every record to the
ROS-free `htlm_agent.experiments.watch_view.WatchState` (which decodes and validates it, counting rejects) and
draws it with `watch_view.show` (in place with rich, or plain snapshots with `plain`, `once`, or when stdout is not
a terminal). Its subscriptions are what make the world publish the ground truth and the agents their beliefs.
"""

from __future__ import annotations

import functools
import time
from typing import IO, Any

from rclpy.executors import Executor
from rclpy.node import Node

from htlm_agent.experiments.watch_view import WatchSettings, WatchState, feed, show
from htlm_msgs_py import topics
from htlm_msgs_py.ros import DIAGNOSTICS, EVENTS, STATE_READER, DiagnosticArray, String, run_node
from htlm_msgs_py.signing import Signer


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
        feed(self.state, topics.DIAGNOSTICS, msg, time.monotonic())


def watch(node: WatchNode, executor: Executor, out: IO[str]) -> int:
    """Spin and show the state until `duration` elapses or a signal arrives; returns 0."""

    def pump(timeout: float) -> bool:
        executor.spin_once(timeout_sec=timeout)
        return not node.stop_signal

    return show(node.state, node.settings, out, pump)


def main(settings: WatchSettings, signer: Signer, out: IO[str]) -> int:
    """Run the watch (exit code 0 after `duration` or Ctrl-C / SIGTERM)."""
    return run_node(
        "htlm watch",
        lambda: WatchNode(settings, signer),
        lambda node, executor: watch(node, executor, out),
        lambda node: None,
        [],
    )
