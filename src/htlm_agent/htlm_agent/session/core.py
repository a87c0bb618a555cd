"""One agent process's side of the protocol without ROS: the run it follows, its policy, and the routing of records
between its `AgentMind` and the parts that keep the rest of its state (docs/ros.md).

The agent node (htlm_agent.ros.agent_node) only decodes messages, feeds them and the time to `AgentSession` and
publishes what it returns, as the world node does with its protocol and the trainer node with `TrainerCore`. The
session decides which run to follow and when the world restarted (rejoin at its next begin, or at once when the
world is ahead of a batch we cannot finish) and which policy to act with (a checkpoint, a built-in baseline, or the
trainer's weights); its parts keep the rest: the trainer's weights and the lag gate (`weights.WeightsClient`), the
transitions until acknowledged and the action until applied (`outbox`), the deployed team's step clock
(`deploy_clock.DeployClock`), the teammates' clock offsets (`offsets.ClockOffsets`), the robot's arrival at its
site (`arrival.ArrivalTracker`), and the records the mind's effects become (`carry.EffectCarrier`, encoded by
`records.RecordWriter`). Every method takes `now` (monotonic seconds, the only clock the session reads) and returns
the `SessionEffects` to carry out.
"""

from __future__ import annotations

from typing import Any

from htlm_agent.mind.agent import AgentMind, Effects
from htlm_agent.mind.deploy import DeployObservations, Observed
from htlm_agent.mind.policies import AgentPolicy
from htlm_agent.session.arrival import ArrivalTracker
from htlm_agent.session.carry import EffectCarrier
from htlm_agent.session.deploy_clock import DeployClock
from htlm_agent.session.effects import Readers, SessionEffects
from htlm_agent.session.offsets import ClockOffsets
from htlm_agent.session.outbox import ActionResend, Outbox
from htlm_agent.session.policy import PolicySource
from htlm_agent.session.records import RecordWriter
from htlm_agent.session.run import JoinedRun, NotInTeamError
from htlm_agent.session.settings import SessionSettings
from htlm_msgs_py.run_control import REFUSED, RunControl, Verdict
from htlm_msgs_py.schema import Arrival
from htlm_msgs_py.signing import Signer
from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.scenario import ScenarioRecordError

__all__ = ["AgentSession", "Readers", "SessionEffects", "SessionSettings"]


class AgentSession:
    """One agent process's side of the protocol (docs/ros.md), fed with decoded records and the time.

    `on_scenario` joins a run (or notes a stop, a restart of the world, an announcement of another run); the world's
    step records begin and end batches (`on_step`: the mind answers a begin with its actions for step 1; a begin
    after a long silence, after a restart of the world, or while the world is ahead of a batch we cannot finish is
    taken even if it interrupts ours); `on_observation`, `on_broadcast` and `tick` go through the mind, whose
    effects become records: the action (sent again while the world has not applied its step), the broadcast, the
    ready, the transition (kept in the outbox until `on_ack`, sent again by `resend`), the belief summary and the
    goal pose. In training the trainer's weights (`on_weights`) act through the lag gate of `WeightsClient`: the
    mind's actions wait until the weights of their step arrive, or `weights_timeout`, then go with the newest
    (counted as stale_weights).

    In a deployed team, once the announcement carries the epoch, the session steps on its own clock
    (`DeployClock`): the world's step records are no longer read, every instant applies our action of its step, and
    a session started mid-run joins at the next instant.
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
        is wall-clock seconds minus `now` (a deployed team's step clock is on the wall clock)."""
        s = settings
        self.settings = settings
        self.wall_offset = wall_offset
        self.signer = signer if signer is not None else Signer(None)
        self.readers: Readers = readers if readers is not None else (lambda _kind: 1 << 30)
        self.name = s.agent
        self.now = 0.0
        """The time of the message or tick being handled (the gate reads it)."""
        self.fatal: str | None = None
        self.control = RunControl(s.run)
        self.kept: tuple[str, str, int] | None = None
        """(run, nonce, seq) of the announcement taken from disk."""
        self.joined: JoinedRun | None = None
        """The run followed (None before the first announcement taken)."""
        self.observations: DeployObservations | None = None
        """A deployed team: pairs the steps with the robot's observations."""
        self.deploy: DeployClock | None = None
        """A deployed team, once the run's epoch is announced: the step clock this agent keeps itself."""
        self.mind: AgentMind | None = None
        # the parts
        self.policies = PolicySource(s.agent, s.policy, s.checkpoint, s.epsilon, s.weights_timeout)
        self.weights = self.policies.weights
        self.outbox = Outbox(s.outbox_limit, s.resend_period, s.resend_batch)
        self.action_resend = ActionResend(s.action_resend)
        self.arrival = ArrivalTracker(s.arrival_radius)
        self.offsets = ClockOffsets()
        self.records = RecordWriter(self.signer, self.outbox.session)
        self.carrier = EffectCarrier(
            s, self.records, self.outbox, self.action_resend, self.arrival, self.readers, wall_offset
        )
        self.id = self.outbox.session
        """This process's session id in its transition records (the trainer acknowledges per session)."""
        # joining and rejoining
        self.scenario_at = 0.0
        self.last_accept = 0.0
        self.world_ahead = (-1, -1)
        """(episode, step) of the newest step record the world sent."""
        self.rejoin = False
        """The world restarted: take its next begin even if it interrupts our batch."""
        self.stopping = False
        self.stop_deadline = 0.0

    @property
    def run(self) -> str | None:
        """The id of the run followed (None before the first announcement taken)."""
        return self.joined.run if self.joined is not None else None

    @property
    def index(self) -> int:
        """This agent's index in the scenario's team (-1 before the first announcement taken)."""
        return self.joined.index if self.joined is not None else -1

    @property
    def lim(self) -> dict[str, int] | None:
        """The run's bounds for decoding records (None before the scenario)."""
        return self.joined.lim if self.joined is not None else None

    # ----- the run ------------------------------------------------------------------------------------------------
    def on_scenario(self, rec: dict[str, Any], now: float, kept: bool = False) -> SessionEffects:
        """The world's announcement of a run (a decoded scenario record); `kept`: the one this agent kept on disk
        (a deployed team), taken at a restart so that it needs no world to step on."""
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
        if verdict == Verdict.STOP:
            if not self.stopping and (self.deploy is None or self.deploy.stop_after is None):
                self._stop_on_deploy_clock(now, out)
            return out
        deploy_epoch = self.deploy is None and rec["epoch"] > 0.0 and self.joined is not None
        if verdict in (Verdict.UPDATE, Verdict.RESTART) and deploy_epoch:
            self._start_clock(rec, now, out)
            return out
        if verdict == Verdict.UPDATE:
            return out
        if verdict == Verdict.RESTART and self.deploy is not None:  # the world is back; our clock never stopped
            text = f"run {self.run}: the world (deploy observer) restarted (announcement {rec['seq']})"
            out.log.append(("info", text))
            return out
        if verdict == Verdict.RESTART:  # the same run from a restarted world: take its next begin whatever our state
            # The announcement (a transient-local sample, sent to a newly matched reader on the writer's heartbeat)
            # may come seconds after the restarted world's first step records: by then we may already be playing
            # its batch, which replays ours exactly (same seed and streams). So the mind is kept (dropping it would
            # leave us deaf to the batch the world is playing: every action missing until the next begin) and the
            # next begin is taken even if it interrupts a batch (the world began again from step 0).
            out.log.append(("warning", f"run {self.run}: the world restarted (announcement {rec['seq']}); rejoining"))
            self.rejoin = True
            self.stopping = False
            if self.deploy is not None:
                self.deploy.stop_after = None
            return out
        self._join(rec, now, out)
        return out

    def _join(self, rec: dict[str, Any], now: float, out: SessionEffects) -> None:
        """Join the run `rec` announces (the first, or the next after ours stopped)."""
        try:
            run = JoinedRun.from_record(rec, self.name)
        except ScenarioRecordError as e:
            out.rejects.append(("scenario", e.reason, str(e)))
            return
        except NotInTeamError as e:
            self._fail(str(e), out)
            return
        sc = run.scenario
        self.joined = run
        self.signer.run = run.run  # what we send carries it; records of other runs are rejected
        self.observations = DeployObservations(run.batch) if run.deployed else None
        self.scenario_at = now
        self.arrival.scenario = sc
        self.records.index = run.index
        self.mind = None
        self.stopping = False
        if self.deploy is not None:
            self.deploy.stop_after = None
        s = self.settings
        self.carrier.send_transitions = s.transitions == "on" or (s.transitions == "auto" and run.mode == "train")
        why = self.policies.choose(run, out)
        if why is not None:
            self._fail(why, out)
            return
        out.log.append(
            (
                "info",
                f"run {self.run}: agent {self.name} (index {run.index}) of {sc.name}/{sc.team}, mode {run.mode}, "
                f"policy {self.policies.kind}, transitions {'on' if self.carrier.send_transitions else 'off'}"
                + (", operation external: observations from the robot" if run.deployed else ""),
            )
        )
        if rec["state"] == "stopped":
            self.stop_run(now, out)
        elif run.deployed and rec["epoch"] > 0.0:
            self._start_clock(rec, now, out)

    def _start_clock(self, rec: dict[str, Any], now: float, out: SessionEffects) -> None:
        """The run's epoch is known: from now on this agent steps on its own clock (htlm_world.clock)."""
        run = self.joined
        assert run is not None and self.observations is not None
        clock = StepClock(rec["epoch"], run.period, run.scenario.horizon, run.first_episode, run.episodes)
        self.deploy = DeployClock(clock, self.observations, self.observation_wait(), self)
        out.log.append(
            ("info", f"run {self.run}: stepping on our own clock (epoch {rec['epoch']:.6f}, period {run.period:g} s)")
        )
        self._run_clock(now, out)

    def _fail(self, why: str, out: SessionEffects) -> None:
        self.fatal = why
        out.fatal = why
        out.log.append(("error", why))

    def _stop_on_deploy_clock(self, now: float, out: SessionEffects) -> None:
        """The world announced the run stopped: on our own clock, finish the steps in progress first
        (`DeployClock.stop_at`); else stop at once."""
        d = self.deploy
        if d is None or self.policies.policy is None or self.fatal is not None:
            self.stop_run(now, out)
            return
        finishing = d.stop_at(now + self.wall_offset)
        if finishing is not None:
            e, t = finishing
            out.log.append(("info", f"run {self.run} stopped by the world: finishing episode {e} step {t} first"))
        self._run_clock(now, out)

    def stop_run(self, now: float, out: SessionEffects, why: str = "stopped by the world") -> None:
        """The run is over for this agent: wait for the trainer's acknowledgements at most `stop_timeout`."""
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
        return not (self.carrier.send_transitions and len(self.outbox)) or now >= self.stop_deadline

    # ----- the policy ---------------------------------------------------------------------------------------------
    def epsilon(self, episode: int, size: int) -> Any:
        """ε of the batch from `episode` on (`PolicySource.epsilon`)."""
        return self.policies.epsilon(episode, size)

    def _gate(self, episode: int, t: int) -> AgentPolicy | None:
        """The policy to act with at step t of the batch from `episode` on (`WeightsClient.gate`); a step that
        starts waiting for its weights is timed from now."""
        policy = self.weights.gate(episode, t)
        if policy is None and self.mind is not None and self.mind.deferred is None:
            self.weights.hold(self.now)
        return policy

    def on_weights(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The trainer's weights for this agent (a decoded weights record): cache them by the step they were taken
        after, act with them, and release actions that waited for them."""
        out = SessionEffects()
        self.now = now
        if self.joined is None:
            return out
        net = self.policies.take(rec, out)
        if net is not None and self.mind is not None:
            self.mind.policy = net
            if self.mind.deferred is not None:
                self.carry("weights", self.mind.act_now(), out)
        return out

    # ----- the world and the team -----------------------------------------------------------------------------
    def _discovered(self, now: float) -> bool:
        """Every teammate and the world are matched on the topics of a step (or the grace period is over)."""
        if now - self.scenario_at > self.settings.discovery_grace:
            return True
        assert self.joined is not None
        return self.readers("action") > 0 and self.readers("broadcast") >= self.joined.scenario.n_agents

    def on_step(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The world's step record: the begin of a batch (answered with our actions for step 1), a step it applied
        (a deployed team: paired with the robot's observation), or the end of an episode."""
        out = SessionEffects()
        self.now = now
        run = self.joined
        if run is None:
            return out
        out.heard_world = True
        if self.deploy is not None:  # we keep the clock ourselves: the world's step records are for observers
            return out
        e, t, phase = rec["episode"], rec["step"], rec["phase"]
        if phase == "begin":
            if t != 0:
                out.rejects.append(("step", "range", f"begin at step {t}"))
                return out
            if not run.in_run(e):
                out.drops.append(("step", "outside_run"))
                return out
            if self.policies.policy is None or not self._discovered(now):
                return out  # not ready yet: the world asks again
            m = self.the_mind()
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
            if size > run.batch:
                out.rejects.append(("step", "length", f"batch of {size} episodes > the run's batch {run.batch}"))
                return out
            eff = m.begin(e, self.epsilon(e, size), force=force, size=size)
            self.rejoin = False
        elif self.mind is None:
            return out
        else:
            self.world_ahead = max(self.world_ahead, (e, t))
            if phase == "step":
                if self.observations is not None:  # the step was applied: pair it with the robot's observation
                    if self._future(e, t, now):
                        out.rejects.append(("step", "future", f"episode {e} step {t}"))
                        return out
                    ready = self.observations.on_step(e, t, rec["acted"], now, self.observation_wait())
                    self.observe_deployed(ready, now, out)
                return out
            eff = self.mind.end(e, t)
        if eff.drop is None:
            self.last_accept = now
        self.carry("step", eff, out)
        return out

    def the_mind(self) -> AgentMind:
        """The mind, made with the policy at the first batch."""
        if self.mind is None:
            run = self.joined
            policy = self.policies.policy
            assert run is not None and policy is not None
            gate = self._gate if self.policies.gated(run) else None
            self.mind = AgentMind(run.scenario, run.index, run.seed, policy, run.model, run.batch, run.mode, gate)
        return self.mind

    def on_observation(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The world's observations of a step for this agent (a deployed team: the robot's observation)."""
        out = SessionEffects()
        self.now = now
        if self.mind is None:
            return out
        if rec["agent"] != self.index:
            out.rejects.append(("observation", "agent", f"observation for agent {rec['agent']} on {self.name}'s topic"))
            return out
        if self.observations is not None:  # from the robot's perception
            if len(rec["levels"]) != self.mind.size:
                out.rejects.append(("observation", "length", f"{len(rec['levels'])} levels for {self.mind.size}"))
                return out
            if self._future(rec["episode"], rec["step"], now):
                out.rejects.append(("observation", "future", f"episode {rec['episode']} step {rec['step']}"))
                return out
            ready = self.observations.on_robot(rec["episode"], rec["step"], rec["levels"])
            self.observe_deployed(ready, now, out)
            self._run_clock(now, out)
            return out
        eff = self.mind.observe(rec["episode"], rec["step"], rec["levels"], rec["acted"], now, tasks=rec["tasks"])
        if eff.drop is None:
            self.last_accept = now
        self.carry("observation", eff, out)
        return out

    def _future(self, e: int, t: int, now: float) -> bool:
        """Whether step t of episode e lies more than FUTURE_STEPS ahead of our own step clock (a deployed team;
        before it runs: of the step the mind is in, 0 before a begin), so its record must not take a place in the
        table of steps."""
        if self.deploy is not None:
            return self.deploy.future(e, t, now + self.wall_offset)
        run, m = self.joined, self.mind
        if run is None:
            return False
        joined = 0
        if m is not None and m.episode is not None:
            joined = (m.episode - run.first_episode) * run.scenario.horizon + max(m.current, 0)
        return (e - run.first_episode) * run.scenario.horizon + t - 1 >= FUTURE_STEPS + joined

    def on_broadcast(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """A teammate's broadcast (our own, looped back, is ignored)."""
        out = SessionEffects()
        self.now = now
        if rec["agent"] == self.index:
            return out
        self.offsets.sample(rec["agent"], now + self.wall_offset - rec["sent"])
        if self.mind is None:
            return out
        eff = self.mind.hear(rec["agent"], rec["episode"], rec["step"], rec["actions"], rec["levels"])
        self.carry("broadcast", eff, out)
        self._run_clock(now, out)
        return out

    def clock_offsets(self) -> dict[int, float]:
        """Per teammate heard, how far our wall clock is ahead of its, seconds (`ClockOffsets.offsets`)."""
        return self.offsets.offsets()

    def clock_warning(self) -> str | None:
        """On our own step clock: which teammates' clocks differ from ours by more than a quarter of the period
        (the tolerance, docs/ros.md, Connecting your robots), or None."""
        if self.deploy is None or self.joined is None:
            return None
        return self.offsets.warning(self.joined.names, self.joined.period)

    def on_ack(self, rec: dict[str, Any], now: float) -> SessionEffects:
        """The trainer's acknowledgement of our transitions up to `upto`: they leave the outbox."""
        out = SessionEffects()
        self.now = now
        if rec["agent"] == self.index:
            self.outbox.ack(rec["session"], rec["upto"], out)
        return out

    def on_pose(self, x: float, y: float, now: float) -> SessionEffects:
        """The robot's position (finite, map frame): log when it reaches the site of its assignment or leaves it."""
        out = SessionEffects()
        self.now = now
        self.arrival.on_pose(x, y, out)
        return out

    def _broadcast_wait(self) -> float:
        """Seconds to wait for a teammate's broadcast: broadcast_timeout, and under the free clock at most 40 % of
        the period (the rest is for the update and the next action, so a dead teammate costs no one a step)."""
        w = self.settings.broadcast_timeout
        run = self.joined
        return min(w, 0.4 * run.period) if run is not None and run.clock == "free" else w

    def observation_wait(self) -> float:
        """Seconds to wait for the robot's observation of a step (a deployed team)."""
        w, run = self.settings.observation_wait, self.joined
        assert run is not None
        return w if w >= 0.0 else 0.25 * run.period

    def observe_deployed(self, ready: list[Observed], now: float, out: SessionEffects) -> None:
        """Feed the mind the steps of a deployed team whose robot observation is in (or overdue)."""
        for ob in ready:
            if self.mind is None:
                return
            # a robot still on its way did not work on its task this step
            worked = self.arrival.arrival()[0] != Arrival.NO
            eff = self.mind.observe(
                ob.episode, ob.step, ob.levels, ob.acted, now, worked, position=self.arrival.position
            )
            if eff.drop is None:
                self.last_accept = now
            self.carry("observation", eff, out)

    # ----- the clock ----------------------------------------------------------------------------------------------
    def tick(self, now: float) -> SessionEffects:
        """A look at the clock (every 0.1 s at most): the robot's observations that are due, the action resent while
        the world has not applied its step, actions released after `weights_timeout`, and a step finished without
        the broadcast of a teammate that died after acting."""
        out = SessionEffects()
        self.now = now
        self._run_clock(now, out)
        if self.observations is not None:
            self.observe_deployed(self.observations.due(now), now, out)
        m = self.mind
        if self.deploy is None and m is not None and m.pending is not None and m.pending.observed_at is None:
            self.action_resend.due(m.episode, m.pending.t, now, out)  # nobody waits for it on our own clock
        if m is not None and m.deferred is not None:
            if self.weights.overdue(now) and m.policy is not None:
                out.counters["stale_weights"] += 1
                out.log.append(
                    (
                        "warning",
                        f"no weights for step {m.deferred} of episode {m.episode} within "
                        f"{self.settings.weights_timeout:g} s; acting with the newest ({self.weights.version})",
                    )
                )
                self.carry("tick", m.act_now(force=True), out)
            return out
        if m is not None and m.pending is not None:
            eff = m.tick(now, self._broadcast_wait())
            if eff.transition is not None:
                self.carry("tick", eff, out)
        self._run_clock(now, out)
        return out

    def _run_clock(self, now: float, out: SessionEffects) -> None:
        """Our own step clock (a deployed team), while the run goes on for us (`DeployClock.run`)."""
        if self.deploy is None or self.policies.policy is None or self.stopping or self.fatal is not None:
            return
        self.deploy.run(now, now + self.wall_offset, out)

    def resend(self, now: float) -> SessionEffects:
        """One pass over the outbox (every `resend_period`, `Outbox.resend`)."""
        out = SessionEffects()
        self.now = now
        self.outbox.resend(now, out)
        return out

    # ----- records out --------------------------------------------------------------------------------------------
    def carry(self, topic: str, eff: Effects, out: SessionEffects) -> None:
        """Turn the mind's effects of a record on `topic` into records (`EffectCarrier.carry`)."""
        self.carrier.carry(topic, eff, self.mind, self.joined, self.now, self.deploy is not None, out)

    @property
    def episodes_done(self) -> int:
        """Episodes this process has finished, over all its runs."""
        return self.carrier.episodes_done

    # ----- status ---------------------------------------------------------------------------------------------
    def values(self) -> dict[str, str]:
        """The session's values for the node's /diagnostics."""
        m, run = self.mind, self.joined
        vals = {
            "run": str(self.run),
            "agent": self.name,
            "index": str(self.index),
            "session": self.id,
            "mode": run.mode if run is not None else "",
            "policy": self.policies.kind,
            "weights_version": str(self.weights.version),
            "episode": str(m.episode if m else -1),
            "step": str(m.current if m else 0),
            "episodes_done": str(self.episodes_done),
            "missed_steps": str(m.missed_steps if m else 0),
            "impossible_evidence": str(m.impossible if m else 0),
            **self.outbox.values(),
            "operation": run.operation if run is not None else "simulated",
            "clock": "own" if self.deploy is not None else "world",
        }
        if run is not None:
            vals.update(self.offsets.values(run.names, run.period if self.deploy is not None else None))
        vals.update(self.arrival.values())
        if self.observations is not None:
            vals.update(self.observations.values())
        return vals

    def status(self) -> str:
        """The node's status message while it is healthy."""
        m = self.mind
        return "waiting for the world" if m is None else f"episode {m.episode} step {m.current}"
