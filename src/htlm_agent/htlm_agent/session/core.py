"""One agent process's side of the protocol without ROS: the run it follows, its policy, and everything around its
`AgentMind` that the lockstep protocol asks of an agent (docs/ros.md).

The agent node (htlm_agent.ros.agent_node) only decodes messages, feeds them and the time to `AgentSession` and
publishes what it returns, as the world node does with `WorldProtocol` and the trainer node with `TrainerCore`. The
session decides: which run to follow and when the world restarted (rejoin at its next begin, or at once when the
world is ahead of a batch we cannot finish); which policy to act with (a checkpoint, a built-in baseline, or the
trainer's weights, kept per step in a small cache); the trainer-lag gate that holds our actions until the weights
of their step arrive (or `weights_timeout` is over); the outbox of transitions, kept until the trainer acknowledges
them and sent again on `resend_period`; the resend of an action the world has not applied; the belief summaries,
goal poses and episode log; and the counters and log lines of those decisions. Every method takes `now`
(monotonic seconds, the only clock the session reads) and returns the `SessionEffects` to carry out.
"""

from __future__ import annotations

import secrets
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from htlm_agent.baselines.heuristics import BUILTIN_POLICIES, builtin_policy
from htlm_agent.mind.agent import AgentMind, Effects, Transition
from htlm_agent.mind.external import ExternalObservations, Observed
from htlm_agent.mind.policies import AgentPolicy
from htlm_msgs_py import schema as S
from htlm_msgs_py.payload import PayloadError, unseal
from htlm_msgs_py.run_control import REFUSED, RunControl
from htlm_msgs_py.schema import encode, limits
from htlm_msgs_py.signing import Signer
from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.episode import acting_weights, global_step
from htlm_world.model import Model
from htlm_world.robots import site_distance
from htlm_world.scenario import Scenario, ScenarioRecordError, from_record

CLOCK_SAMPLES = 20
"""Broadcasts per teammate from which its clock offset is measured (the least of them)."""

CLOCK_TOLERANCE = 0.25
"""The clock offset between two agents tolerated under the deployed team's own clock, in periods."""

WEIGHTS_KEPT = 16
"""Most weight versions the session keeps (the newest; the gate picks one per step)."""


@dataclass(frozen=True)
class SessionSettings:
    """The agent node's parameters the session reads (htlm_agent.ros.settings.AgentSettings documents each)."""

    agent: str
    """This agent's name in the scenario."""
    run: str
    """The run to join (empty: the first announced)."""
    policy: str
    """auto, checkpoint, trainer, or a built-in baseline."""
    checkpoint: str
    """Checkpoint directory of `htlm train`."""
    epsilon: float
    """ε of ε-greedy; -1: the learner's schedule while training, the policy's own otherwise."""
    transitions: str
    """Send transitions to the trainer: auto, on, off."""
    resend_period: float
    """Seconds before an unacknowledged transition is sent again."""
    resend_batch: int
    """Most transitions sent again per resend pass."""
    outbox_limit: int
    """Most unacknowledged transitions kept."""
    belief_every: int
    """Publish the belief summary every this many steps (0: never)."""
    belief_episode: int
    """Which episode of a batch the belief summary and the goal pose follow."""
    broadcast_timeout: float
    """Seconds to wait for the teammates' broadcasts."""
    action_resend: float
    """Seconds after which an action the world has not applied is sent again."""
    resync_timeout: float
    """Seconds without an accepted world message after which the agent rejoins at the next begin."""
    discovery_grace: float
    """Seconds after the scenario during which the agent answers only once matched with world and team."""
    stop_timeout: float
    """Seconds to wait for the trainer's acknowledgements when the run stops."""
    exit_on_stop: bool
    """Exit when the world announces the end of the run."""
    weights_timeout: float
    """Training: longest wait for the trainer's weights of a step, seconds."""
    arrival_radius: float
    """Metres from the site within which the robot has arrived."""
    observation_wait: float
    """External operation: seconds to wait for the robot's observation of a step; -1: a quarter of the period."""


@dataclass
class SessionEffects:
    """What the node must do after feeding the session one message or one look at the clock, in this order."""

    publish: list[tuple[str, str]] = field(default_factory=list)
    """Records to publish, in order, as (kind, record text signed with the session's signer): kind is action,
    broadcast, ready, transition or belief (on the agent's own belief topic)."""
    goals: list[tuple[float, float]] = field(default_factory=list)
    """Goal poses (x, y) in the map frame to publish: the site of the assignment changed."""
    log: list[tuple[str, str]] = field(default_factory=list)
    """Log lines as (level, text), level info, warning or error."""
    counters: Counter[str] = field(default_factory=Counter)
    """Counters to add to the node's diagnostics (resent, actions_resent, outbox_dropped, stale_weights)."""
    drops: list[tuple[str, str]] = field(default_factory=list)
    """Well-formed records the protocol dropped, as (topic, reason): past, future, duplicate, outside_run, ..."""
    rejects: list[tuple[str, str, str]] = field(default_factory=list)
    """Records refused as invalid for the run, as (topic, reason, detail)."""
    episode_log: list[dict[str, Any]] = field(default_factory=list)
    """Finished episodes for the agent's episode log (<agent>.jsonl): run, episode, actions, messages, rewards."""
    heard_world: bool = False
    """A record of the world was taken (the node's watch of a silent world)."""
    subscribe_weights: bool = False
    """The policy comes from the trainer: subscribe to this agent's weights topic (once)."""
    fatal: str | None = None
    """The agent cannot go on (not in the team, no usable policy): why."""


Readers = Callable[[str], int]
"""kind (action, broadcast, belief) -> how many readers the agent's records of that kind have."""


class AgentSession:
    """One agent process's side of the protocol (docs/ros.md), fed with decoded records and the time.

    `on_scenario` joins a run (or notes a stop, a restart of the world, an announcement of another run); the world's
    step records begin and end batches (`on_step`: the mind answers a begin with its actions for step 1; a begin
    after a long silence, after a restart of the world, or while the world is ahead of a batch we cannot finish is
    taken even if it interrupts ours); `on_observation`, `on_broadcast` and `tick` go through the mind, whose
    effects become records: the action (kept to be sent again while the world has not applied its step), the
    broadcast, the ready, the transition (kept in the outbox until `on_ack`, sent again by `resend`), the belief
    summary and the goal pose. In training the trainer's weights (`on_weights`) are cached by the step they were
    taken after, and the mind acts at step g only with those of the fixed cadence (`trainer_lag`, `every`): its
    actions wait until they arrive, or `weights_timeout`, then go with the newest (counted as stale_weights).

    In an external operation (deployment), once the announcement carries the epoch, the session keeps the step clock
    itself (`_run_clock`, htlm_world.clock): the world's step records are no longer read, every instant applies our
    action of its step, and a session started mid-run joins at the next instant.
    """

    def __init__(
        self,
        settings: SessionSettings,
        signer: Signer | None = None,
        readers: Readers | None = None,
        wall_offset: float = 0.0,
    ) -> None:
        """The session of agent `settings.agent` (its run comes with the first announcement); `signer` signs every
        record; `readers(kind)` tells how many readers a kind of record has (None: always enough); `wall_offset`
        is wall-clock seconds minus `now` (the step clock of an external operation is on the wall clock)."""
        self.settings = settings
        self.wall_offset = wall_offset
        self.own_clock: StepClock | None = None
        """External operation, once the run's epoch is announced: the step clock this agent keeps itself."""
        self.applied = -1
        """The run-wide index of the newest step whose instant this agent has passed on its own clock."""
        self.clock_samples: dict[int, deque[float]] = {}
        """Per teammate, its latest broadcasts' arrival minus send time on the two wall clocks (`clock_offsets`)."""
        self.kept: tuple[str, str, int] | None = None
        """(run, nonce, seq) of the announcement taken from disk."""
        self.joined_at: tuple[int, int] | None = None
        """(episode, step) at which this process joined the step clock."""
        self.signer = signer if signer is not None else Signer(None)
        self.readers: Readers = readers if readers is not None else (lambda _kind: 1 << 30)
        self.name = settings.agent
        self.id = secrets.token_hex(8)
        """This process's session id in its transition records (the trainer acknowledges per session)."""
        self.now = 0.0
        """The time of the message or tick being handled (the gate reads it)."""
        self.fatal: str | None = None
        self.control = RunControl(settings.run)
        self.run: str | None = None
        self.mode = ""
        self.seed = 0
        self.scenario: Scenario | None = None
        self.model: Model | None = None
        self.index = -1
        self.lim: dict[str, int] | None = None
        """The run's bounds for decoding records (None before the scenario)."""
        self.first_episode = 0
        self.episodes = 0
        self.batch = 1
        self.trainer_lag = 0
        self.first_step = 0
        self.operation = "simulated"
        self.period = 0.5
        self.clock = "lockstep"
        self.external: ExternalObservations | None = None
        self.mind: AgentMind | None = None
        # the policy
        self.policy: AgentPolicy | None = None
        self.expert: AgentPolicy | None = None
        """The baseline the agent acts with in the warm start of a training run (`Settings.imitate`)."""
        self.policy_kind = ""
        self.policy_epsilon = 0.0
        self.learner_settings: Any = None
        self._settings_data: Any = None
        self.weights_version = -1
        self.weights_every = 1
        self.versions: dict[int, AgentPolicy] = {}
        """trained -> AgentQ: the weights the trainer took after the updates of the steps before `trained`."""
        self.deferred_since = 0.0
        # joining and rejoining
        self.scenario_at = 0.0
        self.last_accept = 0.0
        self.world_ahead = (-1, -1)
        """(episode, step) of the newest step record the world sent."""
        self.rejoin = False
        """The world restarted: take its next begin even if it interrupts our batch."""
        self.stopping = False
        self.stop_deadline = 0.0
        self.stop_after: int | None = None
        """Under our own clock, once the world announced the run stopped: the run-wide index of the last step we
        finish before stopping (`_stop_on_our_clock`)."""
        # what was sent
        self.send_transitions = False
        self.seq = 0
        self.outbox: dict[int, list[Any]] = {}
        """seq -> [record text, last sent]: the transitions the trainer has not acknowledged, oldest first."""
        self.acked = 0
        self.last_action: tuple[int, int, str, float] | None = None
        """(episode, step, record text, sent at) of our newest action."""
        self.episodes_done = 0
        self.last_site = -1
        self.position: tuple[float, float] | None = None
        """The robot's (x, y) in the map frame, from its pose topic."""
        self.arrived_logged = "unknown"

    # ----- the run ------------------------------------------------------------------------------------------------
    def on_scenario(self, rec: dict[str, Any], now: float, kept: bool = False) -> SessionEffects:
        """The world's announcement of a run (a decoded scenario record); `kept`: the one this agent kept on disk
        (external operation), taken at a restart so that it needs no world to step on."""
        out = SessionEffects()
        self.now = now
        key = (rec["run"], rec["nonce"], rec["seq"])
        if kept:
            self.kept = key
        elif key == self.kept:  # the announcement we took from disk, now also from the world
            out.heard_world = True
            return out
        verdict = self.control.take(rec)
        if verdict in REFUSED:  # nobody but our run's world stops or switches us
            out.rejects.append(("scenario", verdict, self.control.refused(rec)))
            return out
        out.heard_world = True
        if verdict == "stop":
            if not self.stopping and self.stop_after is None:
                self._stop_on_our_clock(now, out)
            return out
        if (
            verdict in ("update", "restart")
            and self.own_clock is None
            and rec["epoch"] > 0.0
            and self.scenario is not None
        ):
            self._start_clock(rec, now, out)
            return out
        if verdict == "update":
            return out
        if verdict == "restart" and self.own_clock is not None:  # the observer is back; our clock never stopped
            out.log.append(("info", f"run {self.run}: the world (observer) restarted (announcement {rec['seq']})"))
            return out
        if verdict == "restart":  # the same run from a restarted world: take its next begin whatever our state
            # The announcement (a transient-local sample, sent to a newly matched reader on the writer's heartbeat)
            # may come seconds after the restarted world's first step records: by then we may already be playing
            # its batch, which replays ours exactly (same seed and streams). So the mind is kept (dropping it would
            # leave us deaf to the batch the world is playing: every action missing until the next begin) and the
            # next begin is taken even if it interrupts a batch (the world began again from step 0).
            out.log.append(("warning", f"run {self.run}: the world restarted (announcement {rec['seq']}); rejoining"))
            self.rejoin = True
            self.stopping = False
            self.stop_after = None
            return out
        try:
            sc = from_record(rec)
        except ScenarioRecordError as e:
            out.rejects.append(("scenario", e.reason, str(e)))
            return out
        names = [a.name for a in sc.agents]
        if self.name not in names:
            self._fail(f"agent {self.name!r} is not in the scenario's team {names}", out)
            return out
        self.run = rec["run"]
        self.signer.run = self.run  # what we send carries it; records of other runs are rejected
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
        self.scenario_at = now
        self.model = Model.build(sc)
        self.index = names.index(self.name)
        self.lim = limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, self.batch, sc.knowledge_size)
        self.mind = None
        self.stopping = False
        self.stop_after = None
        s = self.settings
        self.send_transitions = s.transitions == "on" or (s.transitions == "auto" and self.mode == "train")
        kind = s.policy
        if kind == "auto":
            kind = "trainer" if self.mode == "train" else ("checkpoint" if s.checkpoint else "")
            if not kind:
                self._fail(
                    f"mode {self.mode}: no policy: set checkpoint:=DIR, or policy:=greedy, auction or random", out
                )
                return out
        self.policy_kind = kind
        try:
            self._make_policy(kind, out)
        except Exception as e:  # a checkpoint that cannot be used is fatal for this process
            self._fail(f"policy {kind}: {e}", out)
            return out
        out.log.append(
            (
                "info",
                f"run {self.run}: agent {self.name} (index {self.index}) of {sc.name}/{sc.team}, mode {self.mode}, "
                f"policy {kind}, transitions {'on' if self.send_transitions else 'off'}"
                + (", operation external: observations from the robot" if self.external is not None else ""),
            )
        )
        if rec["state"] == "stopped":
            self._stop_run(now, out)
        elif self.operation == "external" and rec["epoch"] > 0.0:
            self._start_clock(rec, now, out)
        return out

    def _start_clock(self, rec: dict[str, Any], now: float, out: SessionEffects) -> None:
        """The run's epoch is known: from now on this agent steps on its own clock (htlm_world.clock)."""
        assert self.scenario is not None
        self.own_clock = StepClock(rec["epoch"], self.period, self.scenario.horizon, self.first_episode, self.episodes)
        out.log.append(
            ("info", f"run {self.run}: stepping on our own clock (epoch {rec['epoch']:.6f}, period {self.period:g} s)")
        )
        self._run_clock(now, out)

    def _make_policy(self, kind: str, out: SessionEffects) -> None:
        sc = self.scenario
        assert sc is not None and self.model is not None
        if kind in BUILTIN_POLICIES:
            self.policy, self.policy_epsilon = builtin_policy(sc, kind, self.index)
        elif kind == "checkpoint":
            from htlm_agent.learning.checkpoint import load_checkpoint  # torch only for the policies that need it
            from htlm_agent.learning.qnet import AgentQ

            ck = load_checkpoint(self.settings.checkpoint, sc)
            self.policy = AgentQ.from_checkpoint(ck, self.index)
            self.learner_settings = ck.settings
            self.policy_epsilon = 0.0
        else:  # trainer: the first weights record creates the network
            self.policy = None
            out.subscribe_weights = True

    def _fail(self, why: str, out: SessionEffects) -> None:
        self.fatal = why
        out.fatal = why
        out.log.append(("error", why))

    def _stop_on_our_clock(self, now: float, out: SessionEffects) -> None:
        """The world announced the run stopped. Under our own clock we first finish the steps whose instants are
        at most a quarter period (the clocks' tolerance) ahead of our clock, then stop: the world announces the end
        of the run 0.05 s after the last instant on its clock, which may be ahead of ours, and a busy host may read
        the announcement before its timer has applied that instant; stopping at once would leave the last episode
        unlogged. A stop in mid-run (the world shut down) costs at most the step in progress."""
        c = self.own_clock
        if c is None or self.policy is None or self.fatal is not None:
            self._stop_run(now, out)
            return
        last = c.last(now + self.wall_offset + CLOCK_TOLERANCE * self.period)
        self.stop_after = min(last, c.episodes * c.horizon - 1) if c.episodes else last  # (0 episodes: until stopped)
        if self.stop_after >= 0:
            e, t = c.step(self.stop_after)
            out.log.append(("info", f"run {self.run} stopped by the world: finishing episode {e} step {t} first"))
        self._run_clock(now, out)

    def _stop_run(self, now: float, out: SessionEffects, why: str = "stopped by the world") -> None:
        self.stopping = True
        self.stop_deadline = now + self.settings.stop_timeout
        out.log.append(("info", f"run {self.run} {why}; {len(self.outbox)} transitions unacknowledged"))

    def finished(self, now: float) -> bool:
        """Whether the process should exit: fatal error, or the run stopped and the outbox is flushed (or the wait
        for the trainer's acknowledgements is over)."""
        if self.fatal is not None:
            return True
        if not (self.stopping and self.settings.exit_on_stop):
            return False
        return not (self.send_transitions and self.outbox) or now >= self.stop_deadline

    # ----- the policy ---------------------------------------------------------------------------------------------
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
        newest at or below T is older than the cadence's last version R <= T (they are on their way). In the warm
        start of a training run (`Settings.warm_start`) the baseline it imitates, as `htlm train` acts."""
        assert self.scenario is not None
        ls = self.learner_settings
        if ls is not None and self.mode == "train" and ls.warm_start(episode):  # episode: as `_epsilon` counts
            return self._expert(ls.imitate)  # the warm start: the baseline acts, no weights needed
        g = global_step(episode, self.batch, t, self.scenario.horizon)
        target, need = acting_weights(g, self.first_step, self.trainer_lag, self.weights_every)
        have = [v for v in self.versions if v <= target]
        if not have or max(have) < need:
            if self.mind is not None and self.mind.deferred is None:
                self.deferred_since = self.now
            return None
        return self.versions[max(have)]

    def _expert(self, name: str) -> AgentPolicy:
        """The warm start's baseline `name` as this agent runs it on its own knowledge (made once)."""
        if self.expert is None:
            assert self.scenario is not None
            self.expert = builtin_policy(self.scenario, name, self.index)[0]
        return self.expert

    def on_weights(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The trainer's weights for this agent (a decoded weights record): cache them by the step they were taken
        after, act with them, and release actions that waited for them."""
        out = SessionEffects()
        self.now = now
        if self.scenario is None:
            return out
        if rec["agent"] != self.index:
            out.rejects.append(("weights", "agent", f"weights for agent {rec['agent']} on {self.name}'s topic"))
            return out
        if rec["version"] <= self.weights_version:
            out.drops.append(("weights", "past"))
            return out
        try:
            data = unseal(rec)
        except PayloadError as e:
            out.rejects.append(("weights", "data", str(e)))
            return out
        try:
            from htlm_agent.learning.qnet import AgentQ, network_shapes, unpack_weights
            from htlm_agent.learning.settings import Settings

            if self.learner_settings is None or rec["settings"] != self._settings_data:
                ls = Settings.from_dict(rec["settings"], "weights.settings")
                self._settings_data = rec["settings"]
            else:
                ls = self.learner_settings
            params = unpack_weights(data, network_shapes(self.scenario, ls))
            net = AgentQ.for_agent(self.scenario, ls, self.index, params)  # every version its own network
        except ValueError as e:
            out.rejects.append(("weights", "data", str(e)))
            return out
        self.learner_settings = ls
        self.weights_version = rec["version"]
        self.weights_every = rec["every"]
        self.versions[rec["trained"]] = net
        while len(self.versions) > WEIGHTS_KEPT:
            del self.versions[min(self.versions)]
        if self.policy_kind == "trainer":
            self.policy = net
            if self.mind is not None:
                self.mind.policy = net
                if self.mind.deferred is not None:
                    self._carry("weights", self.mind.act_now(), out)
        return out

    # ----- the world and the team -----------------------------------------------------------------------------
    def _discovered(self, now: float) -> bool:
        """Every teammate and the world are matched on the topics of a step (or the grace period is over)."""
        if now - self.scenario_at > self.settings.discovery_grace:
            return True
        assert self.scenario is not None
        return self.readers("action") > 0 and self.readers("broadcast") >= self.scenario.n_agents

    def _in_run(self, episode: int) -> bool:
        return episode >= self.first_episode and (self.episodes == 0 or episode < self.first_episode + self.episodes)

    def on_step(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The world's step record: the begin of a batch (answered with our actions for step 1), a step it applied
        (external operation: paired with the robot's observation), or the end of an episode."""
        out = SessionEffects()
        self.now = now
        if self.scenario is None:
            return out
        out.heard_world = True
        if self.own_clock is not None:  # we keep the clock ourselves: the world's step records are for observers
            return out
        e, t, phase = rec["episode"], rec["step"], rec["phase"]
        if phase == "begin":
            if t != 0:
                out.rejects.append(("step", "range", f"begin at step {t}"))
                return out
            if not self._in_run(e):
                out.drops.append(("step", "outside_run"))
                return out
            if self.policy is None or not self._discovered(now):
                return out  # not ready yet: the world asks again
            m = self._the_mind()
            force = m.episode is not None and (self.rejoin or now - self.last_accept > self.settings.resync_timeout)
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
                out.rejects.append(("step", "length", f"batch of {size} episodes > the run's batch {self.batch}"))
                return out
            eff = m.begin(e, self._epsilon(e, size), force=force, size=size)
            self.rejoin = False
        elif self.mind is None:
            return out
        else:
            self.world_ahead = max(self.world_ahead, (e, t))
            if phase == "step":
                if self.external is not None:  # the step was applied: pair it with the robot's observation
                    if self._future(e, t, now):
                        out.rejects.append(("step", "future", f"episode {e} step {t}"))
                        return out
                    ready = self.external.on_step(e, t, rec["acted"], now, self._wait())
                    self._observe_external(ready, now, out)
                return out
            eff = self.mind.end(e, t)
        if eff.drop is None:
            self.last_accept = now
        self._carry("step", eff, out)
        return out

    def _the_mind(self) -> AgentMind:
        """The mind, made with the policy at the first batch."""
        if self.mind is None:
            assert self.scenario is not None and self.policy is not None
            gate = self._gate if self.policy_kind == "trainer" and self.mode == "train" else None
            self.mind = AgentMind(
                self.scenario, self.index, self.seed, self.policy, self.model, self.batch, self.mode, gate
            )
        return self.mind

    def on_observation(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The world's observations of a step for this agent (external operation: the robot's observation)."""
        out = SessionEffects()
        self.now = now
        if self.mind is None:
            return out
        if rec["agent"] != self.index:
            out.rejects.append(("observation", "agent", f"observation for agent {rec['agent']} on {self.name}'s topic"))
            return out
        if self.external is not None:  # from the robot's perception
            if len(rec["levels"]) != self.mind.size:
                out.rejects.append(("observation", "length", f"{len(rec['levels'])} levels for {self.mind.size}"))
                return out
            if self._future(rec["episode"], rec["step"], now):
                out.rejects.append(("observation", "future", f"episode {rec['episode']} step {rec['step']}"))
                return out
            self._observe_external(self.external.on_robot(rec["episode"], rec["step"], rec["levels"]), now, out)
            self._run_clock(now, out)
            return out
        eff = self.mind.observe(rec["episode"], rec["step"], rec["levels"], rec["acted"], now, tasks=rec["tasks"])
        if eff.drop is None:
            self.last_accept = now
        self._carry("observation", eff, out)
        return out

    def _future(self, e: int, t: int, now: float) -> bool:
        """Whether step t of episode e lies more than FUTURE_STEPS ahead of our own step clock (external operation;
        before it runs: of the run's first step), so its record must not take a place in the table of steps."""
        c = self.own_clock
        if c is not None:
            return c.ahead(e, t, now + self.wall_offset) > FUTURE_STEPS
        if self.scenario is None:
            return False
        return (e - self.first_episode) * self.scenario.horizon + t - 1 >= FUTURE_STEPS + self._joined_index()

    def _joined_index(self) -> int:
        """Without our clock yet, how far the run may be: the step the mind is in (0 before a begin)."""
        m = self.mind
        if m is None or m.episode is None or self.scenario is None:
            return 0
        return (m.episode - self.first_episode) * self.scenario.horizon + max(m.current, 0)

    def on_broadcast(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """A teammate's broadcast (our own, looped back, is ignored)."""
        out = SessionEffects()
        self.now = now
        if rec["agent"] == self.index:
            return out
        self._clock_sample(rec["agent"], now + self.wall_offset - rec["sent"])
        if self.mind is None:
            return out
        eff = self.mind.hear(rec["agent"], rec["episode"], rec["step"], rec["actions"], rec["levels"])
        self._carry("broadcast", eff, out)
        self._run_clock(now, out)
        return out

    def _clock_sample(self, k: int, seconds: float) -> None:
        """Arrival minus send time of a broadcast of teammate k on the two wall clocks: the delivery's latency plus
        how far our clock is ahead of k's. The least of the last CLOCK_SAMPLES is the offset (latency on a local
        network is milliseconds, queueing only adds)."""
        q = self.clock_samples.setdefault(k, deque(maxlen=CLOCK_SAMPLES))
        q.append(seconds)

    def clock_offsets(self) -> dict[int, float]:
        """Per teammate heard, how far our wall clock is ahead of its (negative: behind), seconds; /diagnostics
        shows the opposite, `clock_offset/<teammate>`: how far the teammate's clock is ahead of ours."""
        return {k: min(q) for k, q in sorted(self.clock_samples.items()) if q}

    def clock_warning(self) -> str | None:
        """Under our own step clock: which teammates' clocks differ from ours by more than a quarter of the period
        (the tolerance, docs/ros.md, Connecting your robots), or None."""
        if self.own_clock is None or self.scenario is None:
            return None
        limit = CLOCK_TOLERANCE * self.period
        far = {k: x for k, x in self.clock_offsets().items() if abs(x) > limit}
        if not far:
            return None
        names = [a.name for a in self.scenario.agents]
        said = ", ".join(f"{names[k]} {-x:+.3f} s" for k, x in far.items())
        return f"teammates' clocks off ours by more than {limit:g} s (a quarter of the period): {said}"

    def on_ack(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The trainer's acknowledgement of our transitions up to `upto`: they leave the outbox."""
        out = SessionEffects()
        self.now = now
        if rec["agent"] != self.index:
            return out
        if rec["session"] != self.id:
            out.drops.append(("transition_ack", "session"))
            return out
        upto = rec["upto"]
        box = self.outbox
        while box:
            first = next(iter(box))
            if first > upto:
                break
            del box[first]
            self.acked += 1
        return out

    def on_pose(self, x: float, y: float, now: float) -> SessionEffects:
        """The robot's position (finite, map frame): log when it reaches the site of its assignment or leaves it."""
        out = SessionEffects()
        self.now = now
        self.position = (x, y)
        self._log_arrival(out)
        return out

    def _log_arrival(self, out: SessionEffects) -> None:
        """Log when the robot reaches the site of its assignment or leaves it (a change, never per step)."""
        arrived, distance = self.arrival()
        if arrived != self.arrived_logged and arrived != "unknown":
            self.arrived_logged = arrived
            assert self.scenario is not None
            site = self.scenario.site_names[self.last_site]
            out.log.append(
                (
                    "info",
                    f"robot at site {site}"
                    if arrived == "yes"
                    else f"robot on its way to site {site} ({distance:g} m)",
                )
            )

    def arrival(self) -> tuple[str, float]:
        """Whether the robot is at the site of its assignment (yes, no, unknown) and its distance (-1: unknown)."""
        if self.position is None or self.scenario is None or self.last_site < 0:
            return "unknown", -1.0
        d = site_distance(self.scenario, self.last_site, *self.position)
        return ("yes" if d <= self.settings.arrival_radius else "no"), round(d, 3)

    def _broadcast_wait(self) -> float:
        """Seconds to wait for a teammate's broadcast: broadcast_timeout, and under the free clock at most 40 % of
        the period (the rest is for the update and the next action, so a dead teammate costs no one a step)."""
        w = self.settings.broadcast_timeout
        return min(w, 0.4 * self.period) if self.clock == "free" else w

    def _wait(self) -> float:
        """Seconds to wait for the robot's observation of a step (external operation)."""
        w = self.settings.observation_wait
        return w if w >= 0.0 else 0.25 * self.period

    def _observe_external(self, ready: list[Observed], now: float, out: SessionEffects) -> None:
        for ob in ready:
            if self.mind is None:
                return
            worked = self.arrival()[0] != "no"  # a robot still on its way did not work on its task this step
            eff = self.mind.observe(ob.episode, ob.step, ob.levels, ob.acted, now, worked)
            if eff.drop is None:
                self.last_accept = now
            self._carry("observation", eff, out)

    # ----- the clock ----------------------------------------------------------------------------------------------
    def tick(self, now: float) -> SessionEffects:
        """A look at the clock (every 0.1 s at most): the robot's observations that are due, the action resent while
        the world has not applied its step, actions released after `weights_timeout`, and a step finished without
        the broadcast of a teammate that died after acting."""
        out = SessionEffects()
        self.now = now
        self._run_clock(now, out)
        if self.external is not None:
            self._observe_external(self.external.due(now), now, out)
        self._resend_action(now, out)
        m = self.mind
        if m is not None and m.deferred is not None:
            if now - self.deferred_since > self.settings.weights_timeout and m.policy is not None:
                out.counters["stale_weights"] += 1
                out.log.append(
                    (
                        "warning",
                        f"no weights for step {m.deferred} of episode {m.episode} within "
                        f"{self.settings.weights_timeout:g} s; acting with the newest ({self.weights_version})",
                    )
                )
                self._carry("tick", m.act_now(force=True), out)
            return out
        if m is not None and m.pending is not None:
            eff = m.tick(now, self._broadcast_wait())
            if eff.transition is not None:
                self._carry("tick", eff, out)
        self._run_clock(now, out)
        return out

    def _run_clock(self, now: float, out: SessionEffects) -> None:
        """Our own step clock (external operation): every instant that passed applies our action of its step (the
        robot's observation and the teammates' broadcasts then come in as usual), a step still open at the next
        instant is closed with what arrived, and the next episode begins as soon as the last one is done. A process
        that joins mid-run (a restart) joins at the next instant; the steps it was away count as missed."""
        c = self.own_clock
        if c is None or self.policy is None or self.stopping or self.fatal is not None:
            return
        assert self.external is not None
        m = self._the_mind()
        target = c.last(now + self.wall_offset)
        if self.stop_after is not None:
            target = min(target, self.stop_after)
        if self.joined_at is None:  # our first look at the clock: the action of the first begin counts if in time
            p = m.pending
            mine = c.index(m.episode, p.t) if m.episode is not None and p is not None and p.observed_at is None else -1
            self.applied = mine - 1 if mine >= 0 and target <= mine else max(target, c.index(self.first_episode, 1) - 1)
            self.joined_at = c.step(self.applied + 1)
            if self.applied >= 0:
                e, t = self.joined_at
                out.log.append(("info", f"joined the team's clock at episode {e} step {t}"))
        while self.applied < target:
            i = self.applied + 1
            if not c.in_run(i):
                break
            e, t = c.step(i)
            self._act_for(e, t, now, out)
            self.applied = i
            # the step is applied with our action: the robot's observation, or none after the wait
            self._observe_external(self.external.on_step(e, t, list(range(m.n)), now, self._wait()), now, out)
        if self.stop_after is not None:  # stopped by the world: stop once the steps up to stop_after are finished,
            # or at the next instant at the latest (a step still open then is given up: its episode goes unlogged)
            done = c.index(m.episode, m.t) if m.episode is not None else -1
            finished = self.applied >= self.stop_after and done >= self.applied
            if finished or c.last(now + self.wall_offset) > self.stop_after:
                self._stop_run(now, out)
            return
        nxt = self.applied + 1
        if not c.in_run(nxt):
            if m.finished and not self.stopping:
                self._stop_run(now, out, "over on our own clock")
            return
        e, t = c.step(nxt)
        if m.episode != e and m.finished:  # the last episode is done (or we just joined): act for the next step now
            self._act_for(e, t, now, out)

    def _act_for(self, e: int, t: int, now: float, out: SessionEffects) -> None:
        """Make sure the mind has its actions of step t of episode e before the step's instant (closing what is
        still open of earlier steps)."""
        m = self._the_mind()
        if m.episode != e:
            eff = m.begin(e, self._epsilon(e, 1), force=True, size=1)
            if t > 1:  # joining mid-episode: the actions of step 1 are long past
                eff.action = None
            self._carry("clock", eff, out)
            if t == 1:
                return
        p = m.pending
        if p is not None and p.t == t and p.observed_at is None:
            return  # the usual case: acted in time
        assert self.external is not None
        if p is not None and p.t == t - 1:  # the previous step is late: close it with what arrived
            out.counters["late_steps"] += 1
            self._observe_external(self.external.due(float("inf")), now, out)
            if m.pending is not None and m.pending.t == t - 1 and m.pending.observed_at is not None:
                self._carry("clock", m.tick(now, -1.0), out)
            p = m.pending
            if p is not None and p.t == t and p.observed_at is None:
                return
        for eff in m.skip_to(t):
            self._carry("clock", eff, out)

    def _resend_action(self, now: float, out: SessionEffects) -> None:
        """Send our action of the step in progress again while the world has not applied the step (a record lost
        in a reader's queue, e.g. under a flood of other records, costs a resend instead of the world's deadline)."""
        m, last = self.mind, self.last_action
        if self.own_clock is not None:
            return  # nobody waits for our action: it counts when it arrives before the step's instant
        if m is None or last is None or m.pending is None or m.pending.observed_at is not None:
            return
        e, t, text, at = last
        if (e, t) == (m.episode, m.pending.t) and now - at >= self.settings.action_resend:
            out.publish.append(("action", text))
            self.last_action = (e, t, text, now)
            out.counters["actions_resent"] += 1

    def resend(self, now: float) -> SessionEffects:
        """One pass over the outbox (every `resend_period`): send again, oldest first, at most `resend_batch` of
        the transitions not sent for `resend_period`."""
        out = SessionEffects()
        self.now = now
        if not self.outbox:
            return out
        old = now - self.settings.resend_period
        n = 0
        for item in self.outbox.values():
            if item[1] <= old:
                out.publish.append(("transition", item[0]))
                item[1] = now
                n += 1
                if n >= self.settings.resend_batch:
                    break
        out.counters["resent"] += n
        return out

    # ----- records out --------------------------------------------------------------------------------------------
    def _carry(self, topic: str, eff: Effects, out: SessionEffects) -> None:
        """Turn the mind's effects of a record on `topic` into records, in the order the protocol wants them."""
        if eff.drop is not None:
            out.drops.append((topic, eff.drop))
            return
        mind = self.mind
        assert mind is not None and mind.episode is not None
        me, signer = self.index, self.signer
        if eff.broadcast is not None:
            t, a, level = eff.broadcast
            fields = {
                "agent": me,
                "episode": mind.episode,
                "step": t,
                "actions": a.tolist(),
                "levels": level.tolist(),
                "sent": round(max(0.0, self.now + self.wall_offset), 6),
            }
            out.publish.append(("broadcast", encode(S.BROADCAST, fields, signer)))
        if eff.action is not None:  # before the transition: the world and the team wait for it
            t, a = eff.action
            before = mind.history(t) if self.own_clock is not None else []
            fields = {"agent": me, "episode": mind.episode, "step": t, "actions": a.tolist(), "before": before}
            text = encode(S.ACTION, fields, signer)
            out.publish.append(("action", text))
            self.last_action = (mind.episode, t, text, self.now)
        if eff.ready is not None:
            out.publish.append(
                ("ready", encode(S.READY, {"agent": me, "episode": mind.episode, "step": eff.ready}, signer))
            )
        if eff.transition is not None:
            self._finished(eff.transition, out)
        if eff.action is not None:
            self._goal(int(eff.action[1][min(self.settings.belief_episode, len(eff.action[1]) - 1)]), out)

    def _finished(self, tr: Transition, out: SessionEffects) -> None:
        me = self.index
        mind = self.mind
        assert mind is not None
        if self.send_transitions:
            seq = self.seq
            self.seq += 1
            text = encode(
                S.TRANSITION,
                {
                    "agent": me,
                    "session": self.id,
                    "seq": seq,
                    "episode": tr.episode,
                    "step": tr.step,
                    "k": tr.k,
                    "a": tr.a,
                    "r": tr.r,
                    "k2": tr.k2,
                    "mask2": tr.mask2,
                    "done": tr.done,
                },
                self.signer,
            )
            if len(self.outbox) >= self.settings.outbox_limit:
                del self.outbox[next(iter(self.outbox))]
                out.counters["outbox_dropped"] += 1
            self.outbox[seq] = [text, self.now]
            out.publish.append(("transition", text))
        every = self.settings.belief_every
        if every and (tr.done or (tr.step % every == 0 and self.readers("belief") > 0)):
            i = min(self.settings.belief_episode, mind.size - 1)
            marg, conf = mind.belief_summary(i)
            arrived, distance = self.arrival()
            fields = {
                "agent": me,
                "episode": tr.episode + i,
                "step": tr.step,
                "marginals": marg,
                "confident": conf,
                "arrived": arrived,
                "distance": distance,
            }
            out.publish.append(("belief", encode(S.BELIEF, fields, self.signer)))
        if tr.done:
            self._episode_done(tr.episode, out)

    def _episode_done(self, episode: int, out: SessionEffects) -> None:
        """The batch from `episode` on is over: log its episodes (in train mode only the first of each batch)."""
        assert self.mind is not None
        self.episodes_done += self.mind.size
        logged = 1 if self.mode == "train" else self.mind.size
        out.episode_log += [
            {"run": self.run, "episode": episode + i, **self.mind.episode_log(i)} for i in range(logged)
        ]

    def _goal(self, action: int, out: SessionEffects) -> None:
        assert self.model is not None and self.scenario is not None
        site = int(self.model.action_site[action])
        if site != self.last_site:
            self.last_site = site
            x, y = self.scenario.site_positions[site]
            out.goals.append((float(x), float(y)))

    # ----- status ---------------------------------------------------------------------------------------------
    def values(self) -> dict[str, str]:
        """The session's values for the node's /diagnostics."""
        m = self.mind
        vals = {
            "run": str(self.run),
            "agent": self.name,
            "index": str(self.index),
            "session": self.id,
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
            "operation": self.operation,
            "clock": "own" if self.own_clock is not None else "world",
        }
        offsets = self.clock_offsets()
        if offsets and self.scenario is not None:
            names = [a.name for a in self.scenario.agents]
            vals.update({f"clock_offset/{names[k]}": f"{-x:+.3f}" for k, x in offsets.items()})
            vals["clock_offset_max"] = f"{max(abs(x) for x in offsets.values()):.3f}"
            if self.own_clock is not None:
                vals["clock_tolerance"] = f"{CLOCK_TOLERANCE * self.period:g}"
        arrived, distance = self.arrival()
        vals.update({"arrived": arrived, "distance_to_site": f"{distance:g}"})
        if self.external is not None:
            vals.update(
                {"observations_missing": str(self.external.missing), "observations_late": str(self.external.late)}
            )
        return vals

    def status(self) -> str:
        """The node's status message while it is healthy."""
        m = self.mind
        return "waiting for the world" if m is None else f"episode {m.episode} step {m.current}"
