"""commander_node: the commander's page of a whole operation, read-only (docs/usage.md, A person in the team).

A thin node: it reads the team's records (/htlm/scenario, /htlm/ground_truth, /htlm/episode_metrics, /diagnostics,
/htlm/action, every agent's /htlm/<agent>/belief and the observation records of the agents people play), hands them
to the ROS-free `htlm_agent.people.commander.CommanderDesk`, and puts its view where the page's API (Starlette,
uvicorn in a thread of this process, `htlm_agent.people.web`) reads it. Its subscriptions make the world publish the
ground truth and the agents their beliefs, as `htlm watch` does.
Run: `python -m htlm_agent.ros.commander_node --ros-args -p page_token_file:=FILE -p people:=nurse`.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Any

from rclpy.node import Node

from htlm_agent.people.commander import CommanderDesk
from htlm_agent.people.web import Bridge, PageError, page, serve
from htlm_agent.ros.settings import CommanderSettings, validate_commander_settings
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    DIAGNOSTICS,
    EVENTS,
    STATE_READER,
    DiagnosticArray,
    String,
    run_node,
    spin_until_finished,
    start_node,
)
from htlm_msgs_py.ros.parameters import SettingsError


def _text(msg: Any) -> str:
    return str(msg.data)


class CommanderNode(Node):
    """The team's records in, the commander's view out to the page."""

    def __init__(self) -> None:
        """Parameters, the page, the subscriptions (the beliefs' once the scenario names the agents)."""
        super().__init__("htlm_commander")
        self.settings, self.signer = start_node(self, CommanderSettings, validate_commander_settings)
        s = self.settings
        people = tuple(x.strip() for x in s.people.split(",") if x.strip())
        self.desk = CommanderDesk(people, self.signer)
        self.stop_signal = 0
        self.fatal: str | None = None
        self._subscribed: set[str] = set()
        self.create_subscription(String, topics.SCENARIO, self._on_scenario, STATE_READER)
        st = self.desk.state
        self.create_subscription(String, topics.GROUND_TRUTH, lambda m: st.on_ground_truth(_text(m)), EVENTS)
        self.create_subscription(String, topics.EPISODE_METRICS, lambda m: st.on_metrics(_text(m)), EVENTS)
        self.create_subscription(String, topics.ACTION, lambda m: self.desk.on_action(_text(m)), EVENTS)
        self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS)
        self.bridge = Bridge()
        try:
            self.page = serve(
                self.bridge, s.page_token_file, page("commander.html"), s.page_address, s.page_port, reports=False
            )
        except PageError as e:  # exit 2 naming it, as a bad parameter does
            raise SettingsError(str(e)) from None
        self.get_logger().info(f"commander's page: http://{s.page_address}:{self.page.port}/?token=...")
        self.create_timer(0.25, lambda: self.bridge.show(self.desk.view(time.time())))

    def _on_scenario(self, msg: String) -> None:
        st = self.desk.state
        st.on_scenario(msg.data)
        for name in st.agent_names:
            if name in self._subscribed:
                continue
            self._subscribed.add(name)
            self.create_subscription(
                String, topics.belief(name), functools.partial(self._on_belief, name), STATE_READER
            )
            if name in self.desk.people:
                self.create_subscription(
                    String, topics.observation(name), functools.partial(self._on_report, name), EVENTS
                )

    def _on_belief(self, name: str, msg: String) -> None:
        self.desk.state.on_belief(name, msg.data)

    def _on_report(self, name: str, msg: String) -> None:
        self.desk.on_report(name, msg.data)

    def _on_diagnostics(self, msg: Any) -> None:
        from htlm_agent.experiments.watch_view import feed

        feed(self.desk.state, topics.DIAGNOSTICS, msg, time.monotonic())

    def finished(self) -> bool:
        """Whether the process should exit: the run the world announced has stopped (with exit_on_stop)."""
        run = self.desk.state.run
        return self.settings.exit_on_stop and run is not None and run.get("state") == "stopped"


def cleanup(node: CommanderNode) -> None:
    """Stop serving the page."""
    node.page.stop()


def main(args: list[str] | None = None) -> int:
    """Entry point of `commander_node` (exit code: 0 the run stopped, 2 bad parameters, 130/143 SIGINT/SIGTERM)."""
    return run_node("commander_node", CommanderNode, spin_until_finished, cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
