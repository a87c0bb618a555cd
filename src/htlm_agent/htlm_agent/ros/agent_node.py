"""agent_node: one agent of the team as its own process over ROS 2 (docs/architecture.md, data flow of one step).

A thin adapter around the ROS-free `htlm_agent.session.core.AgentSession`, which decides everything (the run it
follows, rejoining a restarted world, the policy and the trainer's weights, the trainer-lag gate, the outbox of
transitions with acknowledgements and resends) around the agent's `AgentMind`: the node decodes messages, feeds
them and the time to the session and publishes what it returns: the action, the broadcast, the ready, the
transition, the belief summary and, when the site of its assignment changes, a geometry_msgs/PoseStamped goal pose.
The policy comes from a checkpoint (evaluate, deploy), from the trainer's weights (train), or is a built-in one
(greedy, auction, qmdp, lookahead, random). An agent a person plays (`person:=true`) also serves the person's page
(htlm_agent.people): the node moves the person's reports from the page to the ROS-free `PersonDesk` and publishes
what it returns (a level report as the signed observation record of the step), and the agent's view to the page.
Run: `ros2 run htlm_agent agent_node --ros-args -p agent:=agent1` or `python -m htlm_agent.ros.agent_node ...`.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.node import Node

from htlm_agent.people.desk import PersonDesk
from htlm_agent.ros.settings import AgentSettings, validate_agent_settings
from htlm_agent.session.core import AgentSession, SessionEffects
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.files import write_atomic
from htlm_msgs_py.ros import (
    EVENTS,
    POSE_READER,
    STATE,
    STATE_READER,
    Health,
    PoseStamped,
    String,
    WorldWatch,
    pose,
    run_node,
    say_unsigned,
    spin_until_finished,
    start_node,
    string,
    subscribe_records,
)
from htlm_msgs_py.ros.parameters import SettingsError
from htlm_msgs_py.schema import record_text


class AgentNode(Node):
    """One agent: alone in its process (`main`), or one of several in a composed one (`htlm_agent.ros.agents_node`)."""

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """Declare parameters, create publishers, subscriptions and timers; the rest waits for /htlm/scenario.

        `cli_args`: this node's own ROS arguments (`--ros-args -r __node:=NAME --params-file FILE`), which take
        precedence over the process's: how a composed process gives each of its agents its name and parameters."""
        super().__init__("htlm_agent", cli_args=cli_args)
        self.settings, self.signer = start_node(self, AgentSettings, validate_agent_settings)
        s = self.settings
        self.name = s.agent
        self.health = Health(self, f"htlm: {self.name}", self.signer)
        self.session = AgentSession(s.session(), self.signer, self._readers, time.time() - time.monotonic())
        self.stop_signal = 0
        self.fatal: str | None = None
        self.log_file: Any = None
        # publishers
        self.pub_action = self.create_publisher(String, topics.ACTION, EVENTS)
        self.pub_broadcast = self.create_publisher(String, topics.BROADCAST, EVENTS)
        self.pub_ready = self.create_publisher(String, topics.READY, EVENTS)
        self.pub_transition = self.create_publisher(String, topics.TRANSITIONS, EVENTS)
        self.pub_goal = self.create_publisher(PoseStamped, topics.goal_pose(self.name), STATE)
        self.pub_goal_record = self.create_publisher(String, topics.goal(self.name), STATE)  # its signed twin
        self.pub_belief = self.create_publisher(String, topics.belief(self.name), STATE)
        self.publishers_by_kind = {
            "action": self.pub_action,
            "broadcast": self.pub_broadcast,
            "ready": self.pub_ready,
            "transition": self.pub_transition,
            "belief": self.pub_belief,
        }
        # subscriptions
        subscribe_records(self, topics.SCENARIO, STATE_READER, self._on_scenario)
        subscribe_records(self, topics.STEP, EVENTS, self._on_step)
        subscribe_records(self, topics.observation(self.name), EVENTS, self._on_observation)
        subscribe_records(self, topics.BROADCAST, EVENTS, self._on_broadcast)
        subscribe_records(self, topics.TRANSITION_ACK, EVENTS, self._on_ack)
        self.sub_weights: Any = None
        if s.pose_topic:
            if s.pose_type == "odometry":
                from nav_msgs.msg import Odometry

                self.create_subscription(Odometry, s.pose_topic, self._on_pose, POSE_READER)
            else:
                self.create_subscription(PoseStamped, s.pose_topic, self._on_pose, POSE_READER)
        self.world = WorldWatch(self, self.health, s.world_timeout)
        say_unsigned(self, self.signer)
        # timers
        self.create_timer(s.diagnostics_period, self._publish_health)
        self.create_timer(s.resend_period, lambda: self._apply(self.session.resend(time.monotonic())))
        self.create_timer(min(0.1, s.broadcast_timeout / 4), self._tick)
        self.desk: PersonDesk | None = None
        self.page: Any = None
        if s.person:
            self._start_page()
        self.run_file = Path(s.run_dir) / f"{self.name}.run.json" if s.run_dir else None
        """A deployed team: the run announcement this agent steps by, kept so that a restart needs no world."""
        if self.run_file is not None and self.run_file.exists():
            self.get_logger().info(f"taking the run announcement kept in {self.run_file}")
            self._on_scenario(self.run_file.read_text(encoding="utf-8"), kept=True)

    def _start_page(self) -> None:
        """A person plays this agent: serve the person's page and move its reports (htlm_agent.people)."""
        from htlm_agent.people.web import Bridge, PageError, page, serve

        s = self.settings
        self.desk = PersonDesk(self.session)
        self.bridge = Bridge()
        self.pub_observation = self.create_publisher(String, topics.observation(self.name), EVENTS)
        self.person_log = Path(s.run_dir) / f"{self.name}.person.jsonl" if s.run_dir else None
        try:
            self.page = serve(self.bridge, s.page_token_file, page("person.html"), s.page_address, s.page_port)
        except PageError as e:  # exit 2 naming it, as a bad parameter does
            raise SettingsError(str(e)) from None
        self.get_logger().info(f"person's page of {self.name}: http://{s.page_address}:{self.page.port}/?token=...")
        self.create_timer(0.1, self._serve_person)

    def _serve_person(self) -> None:
        """The person's reports in (each answered), the agent's view out."""
        desk = self.desk
        assert desk is not None
        for body, fut in self.bridge.take():
            got = desk.report(body, time.monotonic(), time.time())
            self._apply(got.effects)
            if got.observation is not None:
                self.pub_observation.publish(string(S.encode(S.OBSERVATION, got.observation, self.signer)))
            if self.person_log is not None:
                with open(self.person_log, "a", encoding="utf-8") as f:
                    f.write(json.dumps({"agent": self.name, **got.log}) + "\n")
            fut.set_result((got.ok, got.message))
        self.bridge.show(desk.view(time.time()))

    def _tick(self) -> None:
        self.session.wall_offset = time.time() - time.monotonic()  # the step clock follows the wall clock
        self._apply(self.session.tick(time.monotonic()))

    def _readers(self, kind: str) -> int:
        """How many readers our records of `kind` have (the session's discovery and belief summaries ask)."""
        return int(self.publishers_by_kind[kind].get_subscription_count())

    def finished(self) -> bool:
        """Whether the process should exit: fatal error, or the run stopped and the outbox is flushed."""
        return self.fatal is not None or self.session.finished(time.monotonic())

    # ----- messages in ------------------------------------------------------------------------------------------
    def _on_scenario(self, msg: bytes | str, kept: bool = False) -> None:
        rec = self.health.decode("scenario", msg, S.SCENARIO)
        if rec is None:
            return
        self._apply(self.session.on_scenario(rec, time.monotonic(), kept))
        se = self.session
        if self.run_file is not None and se.deploy is not None and rec["run"] == se.run and rec["epoch"] > 0.0:
            text = msg if isinstance(msg, str) else record_text(msg)
            write_atomic(self.run_file, text)

    def _on_step(self, msg: bytes) -> None:
        rec = self.health.decode("step", msg, S.STEP, self.session.lim)
        if rec is not None:
            self._apply(self.session.on_step(rec, time.monotonic()))

    def _on_observation(self, msg: bytes) -> None:
        rec = self.health.decode("observation", msg, S.OBSERVATION, self.session.lim)
        if rec is not None:
            self._apply(self.session.on_observation(rec, time.monotonic()))

    def _on_broadcast(self, msg: bytes) -> None:
        rec = self.health.decode("broadcast", msg, S.BROADCAST, self.session.lim)
        if rec is not None:
            self._apply(self.session.on_broadcast(rec, time.monotonic()))

    def _on_ack(self, msg: bytes) -> None:
        rec = self.health.decode("transition_ack", msg, S.TRANSITION_ACK, self.session.lim)
        if rec is not None:
            self._apply(self.session.on_ack(rec, time.monotonic()))

    def _on_weights(self, msg: bytes) -> None:
        rec = self.health.decode("weights", msg, S.WEIGHTS, self.session.lim)
        if rec is not None:
            self._apply(self.session.on_weights(rec, time.monotonic()))

    def _on_pose(self, msg: Any) -> None:
        p = msg.pose.pose.position if hasattr(msg, "twist") else msg.pose.position
        x, y = float(p.x), float(p.y)
        if not (math.isfinite(x) and math.isfinite(y)):
            self.health.reject("pose", "range", f"position ({x}, {y})")
            return
        self._apply(self.session.on_pose(x, y, time.monotonic()))

    # ----- effects out ------------------------------------------------------------------------------------------
    def _apply(self, eff: SessionEffects) -> None:
        h = self.health
        h.take(eff.drops, eff.rejects, eff.counters)
        if eff.heard_world:
            self.world.heard()
        log = self.get_logger()
        for level, text in eff.log:  # one call site per severity: rclpy's logger refuses to mix them on one line
            if level == "error":
                log.error(text)
            elif level == "warning":
                log.warning(text)
            else:
                log.info(text)
        if eff.fatal is not None:
            self.fatal = eff.fatal
            h.error(eff.fatal)
        if eff.subscribe_weights and self.sub_weights is None:
            self.sub_weights = subscribe_records(self, topics.weights(self.name), STATE_READER, self._on_weights)
        for kind, text in eff.publish:
            self.publishers_by_kind[kind].publish(string(text))
        if eff.episode_log and self.settings.run_dir:
            if self.log_file is None:  # opened with the first finished batch
                Path(self.settings.run_dir).mkdir(parents=True, exist_ok=True)
                self.log_file = open(Path(self.settings.run_dir) / f"{self.name}.jsonl", "a", encoding="utf-8")  # noqa: SIM115
            self.log_file.write("\n".join(json.dumps(line) for line in eff.episode_log) + "\n")
            self.log_file.flush()
        for x, y in eff.goals:
            self.pub_goal.publish(pose(x, y, self.settings.frame_id, self.get_clock().now().to_msg()))
            fields = {"agent": self.session.index, "x": x, "y": y, "frame": self.settings.frame_id, "sent": time.time()}
            self.pub_goal_record.publish(string(S.encode(S.GOAL, fields, self.signer)))

    def _publish_health(self) -> None:
        h = self.health
        se = self.session
        h.values.update({**se.values(), "signed": str(self.signer.enabled).lower()})
        if self.desk is not None:
            d = self.desk
            h.values.update({"person_available": str(d.available).lower(), "person_reports": str(d.taken)})
            h.values["person_refused"] = str(d.refused)
        if self.fatal is None:
            off = se.clock_warning()
            if off is None:
                h.ok(se.status())
            else:
                h.warn(f"{se.status()}; {off}")
            if se.run is not None and not se.stopping:
                self.world.check()
        h.publish()


def cleanup(node: AgentNode) -> None:
    """The agent's last diagnostics and its episode log closed, before the node goes."""
    node._publish_health()
    if node.page is not None:
        node.page.stop()
    if node.log_file is not None:
        node.log_file.close()


def main(args: list[str] | None = None) -> int:
    """Entry point of `agent_node` (exit code: 0 done, 2 bad parameters or policy, 130/143 SIGINT/SIGTERM)."""
    return run_node("agent_node", AgentNode, spin_until_finished, cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
