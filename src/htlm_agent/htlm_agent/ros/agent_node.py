"""agent_node: one agent of the team as its own process over ROS 2 (docs/architecture.md, data flow of one step).

The node decodes messages and feeds them to its `AgentMind` (htlm_agent.mind.agent), which holds the agent's belief,
previous assignment, policy and simulated channel; it publishes what the mind returns: the action, the broadcast,
the ready, the transition (kept in an outbox until the trainer acknowledges it), the belief summary and, when the
site of its assignment changes, a geometry_msgs/PoseStamped goal pose. The policy comes from a checkpoint
(evaluate, deploy), from the trainer's weights (train), or is a built-in one (greedy, auction, random).
Run: `ros2 run htlm_agent agent_node --ros-args -p agent:=agent1` or `python -m htlm_agent.ros.agent_node ...`.
"""

from __future__ import annotations

import json
import math
import secrets
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.node import Node

from htlm_agent.baselines.heuristics import BUILTIN_POLICIES, builtin_policy
from htlm_agent.mind.agent import AgentMind, Effects, Transition
from htlm_agent.mind.external import ExternalObservations, Observed
from htlm_agent.mind.policies import AgentPolicy
from htlm_agent.ros.settings import AgentSettings, validate_agent_settings
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.payload import PayloadError, unseal
from htlm_msgs_py.ros import (
    EVENTS,
    POSE_READER,
    STATE,
    STATE_READER,
    Health,
    PoseStamped,
    SettingsError,
    String,
    WorldWatch,
    declare_settings,
    pose,
    run_node,
    say_unsigned,
    spin_until_finished,
    string,
    subscribe_records,
)
from htlm_msgs_py.run_control import RunControl
from htlm_msgs_py.schema import encode, limits
from htlm_msgs_py.signing import SigningError, signer_from_env
from htlm_world.episode import global_step
from htlm_world.model import Model
from htlm_world.robots import site_distance
from htlm_world.scenario import Scenario, ScenarioRecordError, from_record


def _validate(s: AgentSettings) -> None:
    bad = validate_agent_settings(s)
    if bad:
        raise SettingsError("; ".join(bad))


class AgentNode(Node):
    """One agent process."""

    def __init__(self) -> None:
        """Declare parameters, create publishers, subscriptions and timers; the rest waits for /htlm/scenario."""
        super().__init__("htlm_agent")
        self.settings: AgentSettings = declare_settings(self, AgentSettings, _validate)
        s = self.settings
        try:
            self.signer = signer_from_env()
        except SigningError as e:
            raise SettingsError(str(e)) from None
        self.name = s.agent
        self.health = Health(self, f"htlm: {self.name}", self.signer)
        self.session = secrets.token_hex(8)
        self.stop_signal = 0
        self.fatal: str | None = None
        # run state (set by /htlm/scenario)
        self.control = RunControl(s.run)
        self.run: str | None = None
        self.mode = ""
        self.scenario: Scenario | None = None
        self.model: Model | None = None
        self.index = -1
        self.lim: dict[str, int] | None = None
        self.first_episode = 0
        self.episodes = 0
        self.mind: AgentMind | None = None
        self.policy: AgentPolicy | None = None
        self.policy_kind = ""
        self.policy_epsilon = 0.0
        self.learner_settings: Any = None
        self.weights_version = -1
        self.versions: dict[int, AgentPolicy] = {}  # trained -> AgentQ: the weights the trainer took after that step
        self._settings_data: Any = None
        self.weights_every = 1
        self.batch = 1
        self.trainer_lag = 0
        self.first_step = 0
        self.deferred_since = 0.0
        self.send_transitions = False
        self.stopping = False
        self.stop_deadline = 0.0
        self.last_accept = time.monotonic()
        self.world_ahead = (-1, -1)  # (episode, step) of the newest step record the world sent
        self.rejoin = False  # the world restarted: take its next begin even if it interrupts our batch
        self.scenario_at = 0.0
        self.last_site = -1
        self.seq = 0
        self.outbox: dict[int, list[Any]] = {}  # seq -> [text, last sent (monotonic)]
        self.acked = 0
        self.episodes_done = 0
        self.log_file: Any = None
        self.operation = "simulated"
        self.period = 0.5
        self.clock = "lockstep"
        self.external: ExternalObservations | None = None
        self.position: tuple[float, float] | None = None  # the robot's (x, y) in the map frame, from pose_topic
        self.pose_at = 0.0
        self.arrived_logged = "unknown"
        self.last_action: tuple[int, int, str, float] | None = None  # (episode, step, record, sent at)
        # publishers
        self.pub_action = self.create_publisher(String, topics.ACTION, EVENTS)
        self.pub_broadcast = self.create_publisher(String, topics.BROADCAST, EVENTS)
        self.pub_ready = self.create_publisher(String, topics.READY, EVENTS)
        self.pub_transition = self.create_publisher(String, topics.TRANSITIONS, EVENTS)
        self.pub_goal = self.create_publisher(PoseStamped, topics.goal_pose(self.name), STATE)
        self.pub_belief = self.create_publisher(String, topics.belief(self.name), STATE)
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
        self.create_timer(s.resend_period, self._resend)
        self.create_timer(min(0.1, s.broadcast_timeout / 4), self._tick)

    # ----- the run ------------------------------------------------------------------------------------------------
    def _on_scenario(self, msg: bytes) -> None:
        rec = self.health.decode("scenario", msg, S.SCENARIO)
        if rec is None:
            return
        verdict = self.control.take(rec)
        if verdict in ("other_run", "replay"):  # nobody but our run's world stops or switches us
            self.health.reject("scenario", verdict, self.control.refused(rec))
            return
        self.world.heard()
        if verdict == "stop":
            if not self.stopping:
                self._stop_run()
            return
        if verdict == "update":
            return
        if verdict == "restart":  # the same run from a restarted world: take its next begin whatever our state
            # The announcement (a transient-local sample, sent to a newly matched reader on the writer's heartbeat)
            # may come seconds after the restarted world's first step records: by then we may already be playing
            # its batch, which replays ours exactly (same seed and streams). So the mind is kept (dropping it would
            # leave us deaf to the batch the world is playing: every action missing until the next begin) and the
            # next begin is taken even if it interrupts a batch (the world began again from step 0).
            self.get_logger().warning(f"run {self.run}: the world restarted (announcement {rec['seq']}); rejoining")
            self.rejoin = True
            self.stopping = False
            return
        try:
            sc = from_record(rec)
        except ScenarioRecordError as e:
            self.health.reject("scenario", e.reason, str(e))
            return
        names = [a.name for a in sc.agents]
        if self.name not in names:
            self._fail(f"agent {self.name!r} is not in the scenario's team {names}")
            return
        self.run = rec["run"]
        self.mode = rec["mode"]
        self.seed = rec["seed"]
        self.first_episode = rec["first_episode"]
        self.episodes = rec["episodes"]
        self.batch = rec["batch"]
        self.trainer_lag = rec["trainer_lag"]
        self.operation = rec["operation"]
        self.period = rec["period"]
        self.clock = rec["clock"]
        self.external = ExternalObservations(self.batch) if self.operation == "external" else None
        self.first_step = global_step(self.first_episode, self.batch, 1, sc.horizon)
        self.scenario = sc
        self.scenario_at = time.monotonic()
        self.model = Model.build(sc)
        self.index = names.index(self.name)
        self.lim = limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, self.batch)
        self.mind = None
        self.stopping = False
        s = self.settings
        self.send_transitions = s.transitions == "on" or (s.transitions == "auto" and self.mode == "train")
        kind = s.policy
        if kind == "auto":
            kind = "trainer" if self.mode == "train" else ("checkpoint" if s.checkpoint else "")
            if not kind:
                self._fail(f"mode {self.mode}: no policy: set checkpoint:=DIR, or policy:=greedy, auction or random")
                return
        self.policy_kind = kind
        try:
            self._make_policy(kind)
        except Exception as e:  # a checkpoint that cannot be used is fatal for this process
            self._fail(f"policy {kind}: {e}")
            return
        if s.run_dir and self.log_file is None:
            Path(s.run_dir).mkdir(parents=True, exist_ok=True)
            self.log_file = open(Path(s.run_dir) / f"{self.name}.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        self.get_logger().info(
            f"run {self.run}: agent {self.name} (index {self.index}) of {sc.name}/{sc.team}, mode {self.mode}, "
            f"policy {kind}, transitions {'on' if self.send_transitions else 'off'}"
            + (", operation external: observations from the robot" if self.external is not None else "")
        )
        if rec["state"] == "stopped":
            self._stop_run()

    def _make_policy(self, kind: str) -> None:
        sc = self.scenario
        assert sc is not None and self.model is not None
        if kind in BUILTIN_POLICIES:
            self.policy, self.policy_epsilon = builtin_policy(sc, kind, self.index)
        elif kind == "checkpoint":
            from htlm_agent.learning.checkpoint import load_checkpoint
            from htlm_agent.learning.qnet import AgentQ

            ck = load_checkpoint(self.settings.checkpoint, sc)
            self.policy = AgentQ.from_checkpoint(ck, self.index)
            self.learner_settings = ck.settings
            self.policy_epsilon = 0.0
        else:  # trainer: the first weights message creates the network
            self.policy = None
            if self.sub_weights is None:
                self.sub_weights = subscribe_records(self, topics.weights(self.name), STATE_READER, self._on_weights)

    def _fail(self, why: str) -> None:
        self.fatal = why
        self.health.error(why)
        self.get_logger().error(why)

    def _stop_run(self) -> None:
        self.stopping = True
        self.stop_deadline = time.monotonic() + self.settings.stop_timeout
        self.get_logger().info(f"run {self.run} stopped by the world; {len(self.outbox)} transitions unacknowledged")

    def finished(self) -> bool:
        """Whether the process should exit: fatal error, or the run stopped and the outbox is flushed."""
        if self.fatal is not None:
            return True
        if not (self.stopping and self.settings.exit_on_stop):
            return False
        return not (self.send_transitions and self.outbox) or time.monotonic() >= self.stop_deadline

    def _epsilon(self, episode: int, size: int) -> Any:
        """ε of the batch from `episode` on: the parameter, else the learner's schedule while training (per episode
        with eps_spread, as `htlm train` does), else the policy's own."""
        s = self.settings
        if s.epsilon >= 0.0:
            return s.epsilon
        if self.policy_kind == "trainer" and self.learner_settings is not None and self.mode == "train":
            from htlm_agent.learning.loop import episode_epsilons

            return episode_epsilons(self.learner_settings, episode, size)[1]
        return self.policy_epsilon

    def _gate(self, episode: int, t: int) -> AgentPolicy | None:
        """The trainer's weights to act with at step t of the batch from `episode` on (the fixed cadence): those
        taken after the updates of the steps before T = max(g0, g - lag), the newest at or below T; None while the
        newest at or below T is older than the cadence's last version R <= T (they are on their way)."""
        assert self.scenario is not None
        g = global_step(episode, self.batch, t, self.scenario.horizon)
        target = max(self.first_step, g - self.trainer_lag)
        need = self.first_step + (target - self.first_step) // self.weights_every * self.weights_every
        have = [v for v in self.versions if v <= target]
        if not have or max(have) < need:
            if self.mind is not None and self.mind.deferred is None:
                self.deferred_since = time.monotonic()
            return None
        return self.versions[max(have)]

    # ----- messages in ------------------------------------------------------------------------------------------
    def _discovered(self) -> bool:
        """Every teammate and the world are matched on the topics of a step (or the grace period is over)."""
        if time.monotonic() - self.scenario_at > self.settings.discovery_grace:
            return True
        assert self.scenario is not None
        return (
            self.pub_action.get_subscription_count() > 0
            and self.pub_broadcast.get_subscription_count() >= self.scenario.n_agents
        )

    def _in_run(self, episode: int) -> bool:
        return episode >= self.first_episode and (self.episodes == 0 or episode < self.first_episode + self.episodes)

    def _on_step(self, msg: bytes) -> None:
        rec = self.health.decode("step", msg, S.STEP, self.lim)
        if rec is None or self.scenario is None:
            return
        self.world.heard()
        e, t, phase = rec["episode"], rec["step"], rec["phase"]
        if phase == "begin":
            if t != 0:
                self.health.reject("step", "range", f"begin at step {t}")
                return
            if not self._in_run(e):
                self.health.drop("step", "outside_run")
                return
            if self.policy is None or not self._discovered():
                return  # not ready yet: the world asks again
            if self.mind is None:
                gate = self._gate if self.policy_kind == "trainer" and self.mode == "train" else None
                self.mind = AgentMind(
                    self.scenario, self.index, self.seed, self.policy, self.model, self.batch, self.mode, gate
                )
            m = self.mind
            force = m.episode is not None and (
                self.rejoin or time.monotonic() - self.last_accept > self.settings.resync_timeout
            )
            # the world applied steps of our batch that we never observed (an observation lost while a restarted
            # agent's subscriptions were still being matched) and now begins the next batch: we cannot finish ours,
            # so rejoin at once instead of waiting resync_timeout
            force = force or (
                m.episode is not None
                and e == m.episode + m.size
                and m.current < m.h
                and self.world_ahead[0] == m.episode
                and self.world_ahead[1] > m.current + 1
            )
            size = rec["size"]
            if size > self.batch:
                self.health.reject("step", "length", f"batch of {size} episodes > the run's batch {self.batch}")
                return
            eff = self.mind.begin(e, self._epsilon(e, size), force=force, size=size)
            self.rejoin = False
        elif self.mind is None:
            return
        else:
            self.world_ahead = max(self.world_ahead, (e, t))
            if phase == "step":
                if self.external is not None:  # the step was applied: pair it with the robot's observation
                    self._observe_external(self.external.on_step(e, t, rec["acted"], time.monotonic(), self._wait()))
                return
            eff = self.mind.end(e, t)
        if eff.drop is None:
            self.last_accept = time.monotonic()
        self._apply("step", eff)

    def _on_observation(self, msg: bytes) -> None:
        rec = self.health.decode("observation", msg, S.OBSERVATION, self.lim)
        if rec is None or self.mind is None:
            return
        if rec["agent"] != self.index:
            self.health.reject("observation", "agent", f"observation for agent {rec['agent']} on {self.name}'s topic")
            return
        if self.external is not None:  # from the robot's perception
            if len(rec["levels"]) != self.mind.size:
                self.health.reject("observation", "length", f"{len(rec['levels'])} levels for {self.mind.size}")
                return
            self._observe_external(self.external.on_robot(rec["episode"], rec["step"], rec["levels"]))
            return
        eff = self.mind.observe(
            rec["episode"], rec["step"], rec["levels"], rec["acted"], time.monotonic(), tasks=rec["tasks"]
        )
        if eff.drop is None:
            self.last_accept = time.monotonic()
        self._apply("observation", eff)

    def _on_broadcast(self, msg: bytes) -> None:
        rec = self.health.decode("broadcast", msg, S.BROADCAST, self.lim)
        if rec is None or self.mind is None:
            return
        if rec["agent"] == self.index:
            return  # our own broadcast, looped back
        eff = self.mind.hear(rec["agent"], rec["episode"], rec["step"], rec["actions"], rec["levels"])
        self._apply("broadcast", eff)

    def _broadcast_wait(self) -> float:
        """Seconds to wait for a teammate's broadcast: broadcast_timeout, and under the free clock at most 40 % of
        the period (the rest is for the update and the next action, so a dead teammate costs no one a step)."""
        w = self.settings.broadcast_timeout
        return min(w, 0.4 * self.period) if self.clock == "free" else w

    def _wait(self) -> float:
        """Seconds to wait for the robot's observation of a step (external operation)."""
        w = self.settings.observation_wait
        return w if w >= 0.0 else 0.25 * self.period

    def _observe_external(self, ready: list[Observed]) -> None:
        for ob in ready:
            if self.mind is None:
                return
            worked = self.arrival()[0] != "no"  # a robot still on its way did not work on its task this step
            eff = self.mind.observe(ob.episode, ob.step, ob.levels, ob.acted, time.monotonic(), worked)
            if eff.drop is None:
                self.last_accept = time.monotonic()
            self._apply("observation", eff)

    def _on_pose(self, msg: Any) -> None:
        p = msg.pose.pose.position if hasattr(msg, "twist") else msg.pose.position
        x, y = float(p.x), float(p.y)
        if not (math.isfinite(x) and math.isfinite(y)):
            self.health.reject("pose", "range", f"position ({x}, {y})")
            return
        self.position = (x, y)
        self.pose_at = time.monotonic()
        self._log_arrival()

    def _log_arrival(self) -> None:
        """Log when the robot reaches the site of its assignment or leaves it (a change, never per step)."""
        arrived, distance = self.arrival()
        if arrived != self.arrived_logged and arrived != "unknown":
            self.arrived_logged = arrived
            assert self.scenario is not None
            site = self.scenario.site_names[self.last_site]
            self.get_logger().info(
                f"robot at site {site}" if arrived == "yes" else f"robot on its way to site {site} ({distance:g} m)"
            )

    def arrival(self) -> tuple[str, float]:
        """Whether the robot is at the site of its assignment (yes, no, unknown) and its distance (-1: unknown)."""
        if self.position is None or self.scenario is None or self.last_site < 0:
            return "unknown", -1.0
        d = site_distance(self.scenario, self.last_site, *self.position)
        return ("yes" if d <= self.settings.arrival_radius else "no"), round(d, 3)

    def _resend_action(self) -> None:
        """Send our action of the step in progress again while the world has not applied the step (a record lost
        in a reader's queue, e.g. under a flood of other records, costs a resend instead of the world's deadline)."""
        m, last = self.mind, self.last_action
        if m is None or last is None or m.pending is None or m.pending.observed_at is not None:
            return
        e, t, text, at = last
        now = time.monotonic()
        if (e, t) == (m.episode, m.pending.t) and now - at >= self.settings.action_resend:
            self.pub_action.publish(string(text))
            self.last_action = (e, t, text, now)
            self.health.counters["actions_resent"] += 1

    def _tick(self) -> None:
        if self.external is not None:
            self._observe_external(self.external.due(time.monotonic()))
        self._resend_action()
        m = self.mind
        if m is not None and m.deferred is not None:
            if time.monotonic() - self.deferred_since > self.settings.weights_timeout and m.policy is not None:
                self.health.counters["stale_weights"] += 1
                self.get_logger().warning(
                    f"no weights for step {m.deferred} of episode {m.episode} within "
                    f"{self.settings.weights_timeout:g} s; acting with the newest ({self.weights_version})"
                )
                self._apply("tick", m.act_now(force=True))
            return
        if self.mind is not None and self.mind.pending is not None:
            eff = self.mind.tick(time.monotonic(), self._broadcast_wait())
            if eff.transition is not None:
                self._apply("tick", eff)

    def _on_ack(self, msg: bytes) -> None:
        rec = self.health.decode("transition_ack", msg, S.TRANSITION_ACK, self.lim)
        if rec is None or rec["agent"] != self.index:
            return
        if rec["session"] != self.session:
            self.health.drop("transition_ack", "session")
            return
        upto = rec["upto"]
        box = self.outbox
        while box:
            first = next(iter(box))
            if first > upto:
                break
            del box[first]
            self.acked += 1

    def _on_weights(self, msg: bytes) -> None:
        rec = self.health.decode("weights", msg, S.WEIGHTS, self.lim)
        if rec is None or self.scenario is None:
            return
        if rec["agent"] != self.index:
            self.health.reject("weights", "agent", f"weights for agent {rec['agent']} on {self.name}'s topic")
            return
        if rec["version"] <= self.weights_version:
            self.health.drop("weights", "past")
            return
        try:
            data = unseal(rec)
        except PayloadError as e:
            self.health.reject("weights", "data", str(e))
            return
        try:
            from htlm_agent.learning.qnet import AgentQ, layer_sizes, param_shapes, unpack_weights
            from htlm_agent.learning.settings import Settings

            if self.learner_settings is None or rec["settings"] != self._settings_data:
                ls = Settings.from_dict(rec["settings"], "weights.settings")
                self._settings_data = rec["settings"]
            else:
                ls = self.learner_settings
            sizes = layer_sizes(self.scenario, ls.hidden)
            net = AgentQ(sizes, unpack_weights(data, param_shapes(sizes)))  # every version its own network
        except ValueError as e:
            self.health.reject("weights", "data", str(e))
            return
        self.learner_settings = ls
        self.weights_version = rec["version"]
        self.weights_every = rec["every"]
        self.versions[rec["trained"]] = net
        while len(self.versions) > 16:
            del self.versions[min(self.versions)]
        if self.policy_kind == "trainer":
            self.policy = net
            if self.mind is not None:
                self.mind.policy = net
                if self.mind.deferred is not None:
                    self._apply("weights", self.mind.act_now())

    # ----- messages out -----------------------------------------------------------------------------------------
    def _apply(self, topic: str, eff: Effects) -> None:
        if eff.drop is not None:
            self.health.drop(topic, eff.drop)
            return
        mind = self.mind
        assert mind is not None and mind.episode is not None
        me, signer = self.index, self.signer
        if eff.broadcast is not None:
            t, a, level = eff.broadcast
            self.pub_broadcast.publish(
                string(
                    encode(
                        S.BROADCAST,
                        {
                            "agent": me,
                            "episode": mind.episode,
                            "step": t,
                            "actions": a.tolist(),
                            "levels": level.tolist(),
                        },
                        signer,
                    )
                )
            )
        if eff.action is not None:  # before the transition: the world and the team wait for it
            t, a = eff.action
            text = encode(S.ACTION, {"agent": me, "episode": mind.episode, "step": t, "actions": a.tolist()}, signer)
            self.pub_action.publish(string(text))
            self.last_action = (mind.episode, t, text, time.monotonic())
        if eff.ready is not None:
            self.pub_ready.publish(
                string(encode(S.READY, {"agent": me, "episode": mind.episode, "step": eff.ready}, signer))
            )
        if eff.transition is not None:
            self._finished(eff.transition)
        if eff.action is not None:
            self._goal(int(eff.action[1][min(self.settings.belief_episode, len(eff.action[1]) - 1)]))

    def _finished(self, tr: Transition) -> None:
        me = self.index
        if self.send_transitions:
            seq = self.seq
            self.seq += 1
            text = encode(
                S.TRANSITION,
                {
                    "agent": me,
                    "session": self.session,
                    "seq": seq,
                    "episode": tr.episode,
                    "step": tr.step,
                    "k": tr.k.tolist(),
                    "a": tr.a.tolist(),
                    "r": tr.r.tolist(),
                    "k2": tr.k2.tolist(),
                    "mask2": tr.mask2.tolist(),
                    "done": tr.done,
                },
                self.signer,
            )
            if len(self.outbox) >= self.settings.outbox_limit:
                del self.outbox[next(iter(self.outbox))]
                self.health.counters["outbox_dropped"] += 1
            self.outbox[seq] = [text, time.monotonic()]
            self.pub_transition.publish(string(text))
        every = self.settings.belief_every
        if every and (tr.done or (tr.step % every == 0 and self.pub_belief.get_subscription_count() > 0)):
            assert self.mind is not None
            i = min(self.settings.belief_episode, self.mind.size - 1)
            marg, conf = self.mind.belief_summary(i)
            arrived, distance = self.arrival()
            self.pub_belief.publish(
                string(
                    encode(
                        S.BELIEF,
                        {
                            "agent": me,
                            "episode": tr.episode + i,
                            "step": tr.step,
                            "marginals": marg,
                            "confident": conf,
                            "arrived": arrived,
                            "distance": distance,
                        },
                        self.signer,
                    )
                )
            )
        if tr.done:
            self._episode_done(tr.episode)

    def _episode_done(self, episode: int) -> None:
        """The batch from `episode` on is over: log its episodes (in train mode only the first of each batch)."""
        assert self.mind is not None
        self.episodes_done += self.mind.size
        if self.log_file is not None:
            logged = 1 if self.mode == "train" else self.mind.size
            lines = [
                json.dumps({"run": self.run, "episode": episode + i, **self.mind.episode_log(i)}) for i in range(logged)
            ]
            self.log_file.write("\n".join(lines) + "\n")
            self.log_file.flush()

    def _goal(self, action: int) -> None:
        assert self.model is not None and self.scenario is not None
        site = int(self.model.action_site[action])
        if site != self.last_site:
            self.last_site = site
            x, y = self.scenario.site_positions[site]
            self.pub_goal.publish(pose(x, y, self.settings.frame_id, self.get_clock().now().to_msg()))

    def _resend(self) -> None:
        if not self.outbox:
            return
        now = time.monotonic()
        old = now - self.settings.resend_period
        n = 0
        for item in self.outbox.values():
            if item[1] <= old:
                self.pub_transition.publish(string(item[0]))
                item[1] = now
                n += 1
                if n >= self.settings.resend_batch:
                    break
        self.health.counters["resent"] += n

    def _publish_health(self) -> None:
        h = self.health
        m = self.mind
        h.values.update(
            {
                "run": str(self.run),
                "agent": self.name,
                "index": str(self.index),
                "session": self.session,
                "mode": self.mode,
                "policy": self.policy_kind,
                "weights_version": str(self.weights_version),
                "episode": str(m.episode if m else -1),
                "step": str(m.current if m else 0),
                "episodes_done": str(self.episodes_done),
                "missed_steps": str(m.missed_steps if m else 0),
                "impossible_evidence": str(m.impossible if m else 0),
                "transitions_sent": str(self.seq),
                "transitions_acked": str(self.acked),
                "outbox": str(len(self.outbox)),
                "signed": str(self.signer.enabled).lower(),
                "operation": self.operation,
            }
        )
        arrived, distance = self.arrival()
        h.values.update({"arrived": arrived, "distance_to_site": f"{distance:g}"})
        if self.external is not None:
            h.values.update(
                {
                    "observations_missing": str(self.external.missing),
                    "observations_late": str(self.external.late),
                }
            )
        if self.fatal is None:
            h.ok("waiting for the world" if m is None else f"episode {m.episode} step {m.current}")
            if self.run is not None and not self.stopping:
                self.world.check()
        h.publish()


def _cleanup(node: AgentNode) -> None:
    node._publish_health()
    if node.log_file is not None:
        node.log_file.close()


def main(args: list[str] | None = None) -> int:
    """Entry point of `agent_node` (exit code: 0 done, 2 bad parameters or policy, 130/143 SIGINT/SIGTERM)."""
    return run_node("agent_node", AgentNode, spin_until_finished, _cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
