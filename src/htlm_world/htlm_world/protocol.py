"""The world's side of the lockstep protocol, without ROS: the protocol that sequences batches of episodes and their
steps (`WorldProtocol`) over the episodes of `htlm_world.episode`.

The world node (htlm_world.ros.world_node) only decodes messages, feeds them and the time to `WorldProtocol` and
publishes the records it returns; everything the world decides (phases, deadlines, which agents are present, late
and duplicate answers, the free-running clock, the start and end of episodes and of the run) is decided here, so the
unit tests drive it in one process. The world runs B episodes at once (`LockstepSettings.batch`): batch b holds
episodes b*B .. b*B + B - 1 (the run's last batch may be smaller) and draws from seeds.world(seed, b) exactly as the
in-process Team(scenario, B, seed, b) does (seeds.train_world(seed, b) in train mode, as `htlm train` does), so with
the same actions both runtimes produce the same levels and observations. Every per-step record carries the values of
the batch's episodes as arrays; with B = 1 a batch is one episode.
"""

from __future__ import annotations

import math
import secrets
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.episode import ExternalEpisode, WorldEpisode, batch_index, global_step
from htlm_world.model import Model
from htlm_world.scenario import Scenario

NUDGE = 0.5
"""Seconds between two announcements of an episode's begin while the world waits for the agents."""

ABSENT_LOG_PERIOD = 5.0
"""Least seconds between two warnings about agents that missed a step."""

FIRST_STEP_LEAD = 0.5
"""External operation: the epoch (step 1 of the run) is this many periods after the first begin is over, so that
the announcement carrying it reaches the agents first."""

OBSERVE_AFTER = 0.1
"""External operation: the observer records the joint assignment of a step this many periods after its instant
(the agents sent their actions before it)."""


@dataclass(frozen=True)
class LockstepSettings:
    """What the world's side of the protocol needs to know about the run (the world node's parameters)."""

    seed: int = 0
    """Master seed of the run."""
    mode: str = "evaluate"
    """train, evaluate or deploy (announced to the agents and the trainer)."""
    episodes: int = 10
    """Episodes to run; 0 runs until stopped (read again after every episode)."""
    first_episode: int = 0
    """Index of the first episode."""
    clock: str = "lockstep"
    """lockstep: advance as soon as every live agent answered; free: one step every `period` seconds."""
    period: float = 0.5
    """Step period of the free-running clock, seconds."""
    act_deadline: float = 2.0
    """Longest wait for the agents' actions of a step, seconds."""
    update_deadline: float = 2.0
    """Longest wait for the agents' ready after the last step, seconds."""
    begin_deadline: float = 3.0
    """Longest wait at the start of an episode for every agent to answer, seconds."""
    join_timeout: float = 60.0
    """Longest wait at the start of the first episode for every agent to answer, seconds."""
    linger: float = 1.0
    """Seconds between the end of the last episode and the end of the run."""
    run_id: str = "run"
    """Run identifier announced on /htlm/scenario."""
    batch: int = 1
    """B, episodes run at once; every per-step record carries B values (first_episode must be a multiple of B)."""
    pace: bool = False
    """Wait for the trainer (train mode): step g is applied only once the trainer has finished the gradient updates
    of every step before g - trainer_lag (its /htlm/trainer/progress records)."""
    trainer_lag: int = 1
    """k of the rate limiter: how many steps the trainer's updates may lag behind the world (0: the agents act with
    the networks of every update before the step, exactly as `htlm train`)."""
    trainer_deadline: float = 30.0
    """Longest wait for the trainer's progress, seconds; then the world goes on without it until it is heard."""
    end_hold: float = 60.0
    """With `pace` (training): longest wait after the last step for the trainer to report the updates of every step
    of the run before the run is announced stopped, seconds (so that no agent stops with transitions the trainer has
    not stored, also when the trainer was away and comes back)."""
    operation: str = "simulated"
    """simulated: the world simulates the severities and sends the observations; external: the operation is outside
    (robots observe and publish the observations themselves, an outside source may report the true levels)."""


@dataclass
class WorldEffects:
    """What the node must do after feeding the protocol one message or one look at the clock, in this order."""

    publish: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    """Records to publish, in order, as (kind, fields): kind is scenario, step, observation (fields name the
    agent), ground_truth (only worth publishing when someone listens) or episode_metrics."""
    log: list[tuple[str, str]] = field(default_factory=list)
    """Log lines as (level, text), level info or warning."""
    counters: Counter[str] = field(default_factory=Counter)
    """Counters to add to the node's diagnostics (absent_agent_steps, late_ready)."""
    drops: list[tuple[str, str]] = field(default_factory=list)
    """Well-formed records the protocol dropped, as (topic, reason): past, future, duplicate."""
    rejects: list[tuple[str, str, str]] = field(default_factory=list)
    """Records refused as invalid for the state of the episode, as (topic, reason, detail)."""
    episode_log: list[dict[str, Any]] = field(default_factory=list)
    """Finished episodes for the world's episode log (world.jsonl): run, metrics, levels, actions, observations."""
    status_changed: bool = False
    """The run ended (or stopped): publish the node's status now."""


class WorldProtocol:
    """The world's side of the lockstep protocol (docs/ros.md), fed with decoded messages and the time.

    Per batch of B episodes: announce `begin` (again every NUDGE seconds) until every agent answered with its
    actions for step 1 and listens to its observations, or the begin deadline (`join_timeout` for the first batch);
    per step t: wait for the actions of the live agents until `act_deadline` (a silent agent idles at its site in
    every episode of the step, is counted absent, and is no longer waited for until it is heard again), apply T,
    send every agent its observations, announce the step (with the agents whose actions were applied) and the
    ground truth; each agent's next actions, sent after its belief update, are also its "ready"; after the last
    step wait for the agents' ready (`update_deadline`), then publish `end` and the metrics of every episode. With
    the free-running clock, a step is applied every `period` seconds whoever answered. A record of a past or future
    step is dropped and counted, a repeated one too; an agent heard one step late is waited for again from then on.
    With `pace` (training), step g waits until the trainer reports its updates of the steps before g - trainer_lag
    done (`on_trainer`); the deadlines of the agents start once the trainer has caught up.

    Every method takes `now` (monotonic seconds) and returns the `WorldEffects` to carry out; `next_wakeup` says
    when the protocol next needs a `tick` even if no message arrives.
    """

    def __init__(
        self,
        scenario: Scenario,
        settings: LockstepSettings,
        model: Model | None = None,
        listening: Callable[[int], bool] | None = None,
    ) -> None:
        """The protocol of one run; `listening(agent)` tells whether the agent's observations have a reader (the
        begin of an episode waits for it; None: always)."""
        self.scenario = scenario
        self.model = model if model is not None else Model.build(scenario)
        self.settings = settings
        self.listening = listening if listening is not None else (lambda _agent: True)
        self.layout = scenario.layout_hash()
        self.scenario_dict = scenario.to_dict()
        self.phase = "idle"
        """idle (not started), act (waiting for the actions of step t), end (waiting for the readies after the
        last step), stopped (the run is over)."""
        self.joining = False
        """Whether the episode's begin is being announced (phase act, step 1)."""
        self.episode = -1
        self.t = 0
        self.ep: WorldEpisode | None = None
        self.answers: dict[int, Any] = {}
        """What each agent answered in the current phase: its actions (B,), or 0 for a ready."""
        self.present: set[int] = set()
        """The agents heard lately: the live agents a lockstep step waits for."""
        self.waiting: set[int] = set()
        """The agents the current phase waits for (the live set `present` itself while it grows)."""
        self.deadline = math.inf
        self.nudge_at = math.inf
        self.clock_at = 0.0
        self.linger_until = math.inf
        self.first = True
        self.done = False
        self.nonce = secrets.token_hex(8)
        """This world process's nonce in its announcements (a restarted world has another)."""
        self.seq = 0
        """Sequence number of the next announcement; a restarted world continues it (`resume`)."""
        self.resume_at: int | None = None
        """The episode a restarted world continues at (None: the run's first)."""
        self.next_unlogged = settings.first_episode
        self.hold_until = math.inf
        self.holding_for_trainer = False
        """The first episode whose metrics are not yet out (the episode log is complete before it)."""
        self.size = 1
        """Episodes in the current batch (B, or fewer in the run's last batch)."""
        self.trained = -1
        """The trainer's progress: every step with a global index below it has had its updates (-1: not heard)."""
        self.trainer_live = True
        """Whether the world waits for the trainer (it is heard, or has not yet been given up on)."""
        self.gate_since: float | None = None
        """Since when the current step waits for the trainer (None: it does not)."""
        self.episodes_done = 0
        self.absent_total = 0
        self._absent_warned = -math.inf
        self.decentral = settings.operation == "external"
        """External operation (deployment): the agents keep the step clock themselves and the world only observes."""
        self.epoch = 0.0
        """The wall-clock instant of the run's first step (external operation; 0 until fixed)."""
        self.wall_offset = 0.0
        """Wall-clock seconds minus `now` (the node sets it: time.time() - time.monotonic())."""
        self.heard: dict[tuple[int, int], dict[int, Any]] = {}
        """External operation: the actions heard per (episode, step), kept until the observer records the step."""
        self.early: list[tuple[str, dict[str, Any]]] = []
        """External operation: severity and observation records of steps not yet recorded, as (kind, record)."""

    # ----- the run ------------------------------------------------------------------------------------------------
    def resume(self, seq: int, next_episode: int, epoch: float = 0.0) -> None:
        """Continue a run an earlier world process of the same run announced up to sequence number `seq` and logged
        up to (excluding) `next_episode` (its durable progress), under the step clock of `epoch` (external
        operation; 0: not fixed yet)."""
        self.seq = seq + 1
        self.resume_at = self.next_unlogged = next_episode
        if self.decentral:
            self.epoch = epoch

    def progress(self) -> dict[str, Any]:
        """What a restarted world needs to continue the run: its id, the last sequence number announced, the next
        episode not yet logged, the epoch of the step clock."""
        return {
            "run": self.settings.run_id,
            "seq": self.seq - 1,
            "next_episode": self.next_unlogged,
            "epoch": self.epoch,
        }

    def clock(self) -> StepClock | None:
        """The run's step clock (external operation, once the epoch is fixed)."""
        if not (self.decentral and self.epoch > 0.0):
            return None
        s = self.settings
        return StepClock(self.epoch, s.period, self.scenario.horizon, s.first_episode, s.episodes)

    def _mono(self, wall: float) -> float:
        return wall - self.wall_offset

    def start(self, now: float) -> WorldEffects:
        """Announce the run and the begin of its first episode (a restarted world's next one)."""
        out = WorldEffects()
        out.publish.append(("scenario", self.scenario_record("running")))
        first = self.settings.first_episode if self.resume_at is None else self.resume_at
        clock = self.clock()
        if clock is not None:  # the agents keep the clock: observe from the step in progress on
            i = max(clock.last(now + self.wall_offset) + 1, clock.index(first, 1))
            e, t = clock.step(i)
            self.first = False
            if e > first and clock.in_run(i):
                out.log.append(("warning", f"episodes {first}..{e - 1} passed while the world was down; not logged"))
                self.next_unlogged = e
            self._next_episode(e, now, out)
            out.log.append(("info", f"observing the agents' clock from episode {e} step {t}"))
            if self.ep is not None and t > 1:
                assert isinstance(self.ep, ExternalEpisode)
                self.ep.skip(t - 1)
                self.t = t
                self.deadline = self._mono(clock.at(e, t)) + OBSERVE_AFTER * self.settings.period
                out.log.append(("warning", f"episode {e}: steps 1..{t - 1} passed unobserved; logged as idle"))
            self._progress(now, out)
            return out
        self._next_episode(first, now, out)
        self._progress(now, out)
        return out

    def stop(self, now: float) -> WorldEffects:
        """The node was told to stop: end the run at once (the scenario's state turns to stopped)."""
        out = WorldEffects()
        if self.phase != "stopped":
            self.phase = "stopped"
            self.joining = False
            out.publish.append(("scenario", self.scenario_record("stopped")))
            out.status_changed = True
        self.done = True
        return out

    def in_run(self, episode: int) -> bool:
        """Whether `episode` is one of the run's (with the current `episodes`)."""
        s = self.settings
        return s.episodes == 0 or episode < s.first_episode + s.episodes

    def batch_size(self, episode: int) -> int:
        """Episodes of the batch starting at `episode`: B, fewer when the run ends before."""
        s = self.settings
        return s.batch if s.episodes == 0 else max(0, min(s.batch, s.first_episode + s.episodes - episode))

    def next_wakeup(self) -> float:
        """The monotonic time of the next deadline, announcement or clock tick (inf: none)."""
        if self.done:
            return math.inf
        if self.phase == "stopped":
            return self.linger_until
        if self.phase == "holding":
            return self.hold_until
        if self.gate_since is not None:  # waiting for the trainer: the agents' deadline does not run meanwhile
            gate = self.gate_since + self.settings.trainer_deadline
            return min(self.nudge_at, gate) if self.joining else gate
        if self.joining:
            return min(self.deadline, self.nudge_at)
        return self.deadline

    def tick(self, now: float) -> WorldEffects:
        """Look at the clock (and, while an episode begins, at who listens): apply what is due."""
        out = WorldEffects()
        self._progress(now, out)
        return out

    # ----- messages in --------------------------------------------------------------------------------------------
    def on_action(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded action record {agent, episode, step, action}."""
        out = WorldEffects()
        if self.decentral and self.epoch > 0.0:  # the agents' clock: keep it for the step's instant
            ep = self.ep
            before = rec["before"]
            if (
                isinstance(ep, ExternalEpisode)
                and ep.unheard
                and rec["episode"] == self.episode
                and len(before) == rec["step"] - 1
            ):  # what the agent did at the steps recorded without its action, this one included if it is late
                late, missed = ep.rebuild(rec["agent"], [*before, int(rec["actions"][0])])
                out.counters["absent_rebuilt"] += late
                if missed:
                    out.log.append(
                        (
                            "info",
                            f"episode {self.episode}: {missed} missed steps of agent {rec['agent']} rebuilt from "
                            "its record",
                        )
                    )
            key = (rec["episode"], rec["step"])
            if key <= (self.episode, self.t - 1) or (self.phase != "act" and key <= (self.episode, self.t)):
                out.drops.append(("action", "past"))
                return out
            clock = self.clock()
            if clock is not None and clock.ahead(*key, now + self.wall_offset) > FUTURE_STEPS:
                out.rejects.append(("action", "future", f"agent {rec['agent']}: episode {key[0]} step {key[1]}"))
                return out
            self.heard.setdefault(key, {})[rec["agent"]] = np.asarray(rec["actions"], dtype=np.int64)
            while len(self.heard) > 64:
                del self.heard[min(self.heard)]
            self._progress(now, out)
            return out
        if not self._accept("action", rec, "act", out):
            return out
        k, a = rec["agent"], rec["actions"]
        if k in self.answers:
            out.drops.append(("action", "duplicate"))
            return out
        arr = self._valid(k, a, out)
        if arr is None:
            return out
        self.answers[k] = arr
        self.present.add(k)
        self._progress(now, out)
        return out

    def _valid(self, k: int, a: Any, out: WorldEffects) -> Any:
        """Agent k's actions of the current step as an array, or None (rejected: a wrong length, or an idle
        location away from the site of a_o). The observer of a deployed team (the agents' clock) does not judge
        Â(a_o): the agent's own a_o is the truth, and the observer's may be stale (a step it did not hear, or
        steps it missed while down)."""
        assert self.ep is not None
        if len(a) != self.size:
            out.rejects.append(("action", "length", f"agent {k}: {len(a)} actions for a batch of {self.size}"))
            return None
        arr = np.asarray(a, dtype=np.int64)
        if self.clock() is not None:
            return arr
        prev = self.ep.prev[:, k]
        ok = self.model.action_mask(prev)[np.arange(self.size), arr]
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            out.rejects.append(
                (
                    "action",
                    "range",
                    f"agent {k} action {int(arr[i])} of episode {self.episode + i} is not in Â(a_o) "
                    f"of a_o {int(prev[i])}",
                )
            )
            return None
        return arr

    def on_ready(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded ready record {agent, episode, step}."""
        out = WorldEffects()
        if self.decentral and self.epoch > 0.0:
            return out  # the agents' clock does not wait for anyone
        if not self._accept("ready", rec, "end", out):
            return out
        k = rec["agent"]
        if k in self.answers:
            out.drops.append(("ready", "duplicate"))
            return out
        self.answers[k] = 0
        self.present.add(k)
        self._progress(now, out)
        return out

    def on_trainer(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded trainer progress record {run, trained, updates}: the trainer's updates so far."""
        out = WorldEffects()
        if rec["run"] != self.settings.run_id:
            out.drops.append(("trainer_progress", "other_run"))
            return out
        self.trained = max(self.trained, int(rec["trained"]))
        if not self.trainer_live:
            self.trainer_live = True
            out.log.append(("info", f"the trainer is back (trained up to step {self.trained})"))
        self._progress(now, out)
        return out

    def on_severity(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded severity record {episode, step, levels} of an outside source (external operation only): the
        true levels after a step of the current episode, logged and published as the step's ground truth."""
        out = WorldEffects()
        ep = self.ep
        if not isinstance(ep, ExternalEpisode):
            out.drops.append(("severity", "simulated"))
            return out
        e, t = rec["episode"], rec["step"]
        if self._soon(e, t, ep) and len(rec["levels"]) == 1:
            self._keep_early("severity", rec)  # the operation applied the step before we recorded it
            return out
        if e != self.episode or len(rec["levels"]) != 1:
            out.drops.append(("severity", "past" if e < self.episode else "future" if e > self.episode else "length"))
            return out
        if t == 0:
            return out  # the initial levels are the scenario's
        if not ep.report_levels(t, rec["levels"][0]):
            out.drops.append(("severity", "future"))
            return out
        actions = ep.action_log[t - 1].tolist()
        out.publish.append(
            ("ground_truth", {"episode": e, "step": t, "levels": rec["levels"], "actions": actions, "events": [[]]})
        )
        return out

    def on_observation(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded observation record a robot published (external operation only): kept for the episode log."""
        out = WorldEffects()
        ep = self.ep
        if isinstance(ep, ExternalEpisode) and self._soon(rec["episode"], rec["step"], ep):
            self._keep_early("observation", rec)
        elif isinstance(ep, ExternalEpisode) and rec["episode"] == self.episode and 1 <= rec["step"] <= ep.t:
            ep.report_observation(rec["agent"], rec["step"], rec["levels"][0])
        return out

    def _soon(self, e: int, t: int, ep: ExternalEpisode) -> bool:
        """Under the agents' clock: whether step t of episode e is the next one the observer will record (its
        reports may come first)."""
        if not (self.decentral and self.epoch > 0.0) or (e, t) <= (self.episode, ep.t):
            return False
        h = self.scenario.horizon
        nxt = (e - self.episode) * h + t - ep.t
        return nxt == 1

    def _keep_early(self, kind: str, rec: dict[str, Any]) -> None:
        """A report of a step the observer has not recorded yet (the agents' clock runs ahead of its record by
        OBSERVE_AFTER): taken when it records the step."""
        self.early.append((kind, rec))
        del self.early[: max(0, len(self.early) - 64 * self.scenario.n_agents)]

    def _take_early(self, now: float, out: WorldEffects) -> None:
        """The early reports of the steps recorded by now."""
        ready = [(k, r) for k, r in self.early if (r["episode"], r["step"]) <= (self.episode, self.t)]
        self.early = [(k, r) for k, r in self.early if (r["episode"], r["step"]) > (self.episode, self.t)]
        for kind, rec in ready:
            got = self.on_severity(rec, now) if kind == "severity" else self.on_observation(rec, now)
            out.publish += got.publish
            out.drops += got.drops

    def _gate_closed(self, now: float, out: WorldEffects) -> bool:
        """Whether the next step must wait for the trainer (pace): the steps before g - trainer_lag are not all
        trained. Gives up on a silent trainer after trainer_deadline; once the gate opens, the agents' deadline of
        the phase starts."""
        s = self.settings
        if not s.pace or s.clock != "lockstep" or not self.trainer_live:
            return False
        g = global_step(self.episode, s.batch, self.t, self.scenario.horizon)
        if self.trained >= g - s.trainer_lag:
            if self.gate_since is not None:
                self.gate_since = None
                self.deadline = max(self.deadline, now + (self._begin_wait() if self.joining else s.act_deadline))
            return False
        if self.gate_since is None:
            self.gate_since = now
        if now >= self.gate_since + s.trainer_deadline:
            self.trainer_live = False
            self.gate_since = None
            out.counters["trainer_timeouts"] += 1
            out.log.append(
                (
                    "warning",
                    f"no progress from the trainer for {s.trainer_deadline:g} s (trained up to step "
                    f"{self.trained}, step {g} waits for {g - s.trainer_lag}); going on without it",
                )
            )
            self.deadline = max(self.deadline, now + (self._begin_wait() if self.joining else s.act_deadline))
            return False
        return True

    def _hold(self, now: float, out: WorldEffects) -> None:
        """The run's last step is done: announce the stop once the trainer has reported the updates of every step
        (training with pace), or at once, or when `end_hold` is over (said in the log)."""
        s = self.settings
        if self.phase != "holding":
            return
        if s.pace and s.mode == "train" and self.episode >= 0:
            last = global_step(self.episode, s.batch, self.scenario.horizon, self.scenario.horizon)
            if self.trained < last + 1:
                if now < self.hold_until:
                    self.holding_for_trainer = True
                    return
                out.counters["end_hold_timeouts"] += 1
                out.log.append(
                    (
                        "warning",
                        f"the trainer reported updates up to step {self.trained}, not the run's last ({last}), within "
                        f"end_hold {s.end_hold:g} s; stopping the run",
                    )
                )
        self.holding_for_trainer = False
        self.phase = "stopped"
        out.publish.append(("scenario", self.scenario_record("stopped")))
        out.status_changed = True
        self.linger_until = now + s.linger

    def _begin_wait(self) -> float:
        return self.settings.join_timeout if self.first else self.settings.begin_deadline

    def _accept(self, topic: str, rec: dict[str, Any], phase: str, out: WorldEffects) -> bool:
        e, t = rec["episode"], rec["step"]
        if self.phase == phase and e == self.episode and t == self.t:
            return True
        if (e, t) <= (self.episode, self.t):
            out.drops.append((topic, "past"))
            if e == self.episode and t == self.t - 1:
                # alive but slow: wait for it again from the next phase on, or it would lose every race
                self.present.add(rec["agent"])
        else:
            out.drops.append((topic, "future"))
        return False

    # ----- phases -------------------------------------------------------------------------------------------------
    def _progress(self, now: float, out: WorldEffects) -> None:
        """Carry out whatever the answers so far and the time allow (several steps when the clock is behind)."""
        while not self.done and self._advance(now, out):
            pass

    def _advance(self, now: float, out: WorldEffects) -> bool:
        """Take the next transition that is due, if any; returns whether one was taken."""
        s = self.settings
        if self.phase == "stopped":
            self.done = now >= self.linger_until
            return False
        if self.phase == "holding":
            self._hold(now, out)
            return False
        if self.joining:
            everyone = set(range(self.scenario.n_agents))
            if self._gate_closed(now, out):  # agents wait for the trainer's weights too: no deadline meanwhile
                if now >= self.nudge_at:
                    self._announce_begin(now, out)
                return False
            if (everyone <= self.answers.keys() and all(self.listening(k) for k in self.answers)) or (
                now >= self.deadline
            ):
                self._start_steps(now, out)
                return True
            if now >= self.nudge_at:
                self._announce_begin(now, out)
            return False
        if self.phase == "act":
            if s.clock == "free":
                if now < self.deadline:
                    return False
                self.clock_at = self.deadline
            elif self._gate_closed(now, out) or not (self.waiting <= self.answers.keys() or now >= self.deadline):
                return False
            self._apply_step(now, out)
            return True
        if self.phase == "end" and (self.waiting <= self.answers.keys() or now >= self.deadline):
            self._finish_episode(now, out)
            return True
        return False

    def _next_episode(self, e: int, now: float, out: WorldEffects) -> None:
        s = self.settings
        if not self.in_run(e) or self.batch_size(e) < 1:
            self.phase, self.hold_until = "holding", now + s.end_hold
            self._hold(now, out)
            return
        self.size = self.batch_size(e)
        if s.operation == "external":
            self.ep = ExternalEpisode(self.scenario, self.model, e, started=now)
        else:
            self.ep = WorldEpisode(
                self.scenario,
                self.model,
                s.seed,
                e,
                started=now,
                size=self.size,
                b=batch_index(e, s.batch),
                mode=s.mode,
            )
        self.episode, self.t, self.phase = e, 1, "act"
        self.answers = {}
        clock = self.clock()
        if clock is not None:  # nobody waits for anybody: step 1 is recorded at its instant
            self.joining = False
            self.present = set(range(self.scenario.n_agents))
            self.deadline = self._mono(clock.at(e, 1)) + OBSERVE_AFTER * s.period
            out.publish.append(self._step_record(0, "begin", []))
            return
        self.joining = True
        self.gate_since = None
        self.deadline = now + self._begin_wait()
        self._announce_begin(now, out)

    def _announce_begin(self, now: float, out: WorldEffects) -> None:
        out.publish.append(self._step_record(0, "begin", []))
        self.nudge_at = now + NUDGE if self.deadline <= now else min(self.deadline, now + NUDGE)

    def _step_record(self, t: int, phase: str, acted: list[int]) -> tuple[str, dict[str, Any]]:
        return ("step", {"episode": self.episode, "size": self.size, "step": t, "phase": phase, "acted": acted})

    def _start_steps(self, now: float, out: WorldEffects) -> None:
        """The begin is over: those who answered are the live agents; step 1 goes at once."""
        n = self.scenario.n_agents
        self.joining = False
        self.present = set(self.answers)
        if self.first and len(self.present) < n:
            out.log.append(("warning", f"starting without agents {sorted(set(range(n)) - self.present)}"))
        self.first = False
        self.clock_at = self.deadline = now  # step 1 goes at once, also on the free clock
        self.waiting = set()
        if self.decentral and self.epoch == 0.0:  # from here on every agent keeps the clock itself
            lead = FIRST_STEP_LEAD * self.settings.period
            self.epoch = round(now + self.wall_offset + lead, 6)
            out.publish.append(("scenario", self.scenario_record("running")))
            out.log.append(
                ("info", f"the step clock starts at epoch {self.epoch:.6f} (period {self.settings.period:g} s)")
            )
            self.heard[(self.episode, 1)] = dict(self.answers)
            self.answers = {}
            self.clock_at = self.deadline = now + lead + OBSERVE_AFTER * self.settings.period

    def _apply_step(self, now: float, out: WorldEffects) -> None:
        """Apply T to the answers of step t (missing live agents idle), publish the results, wait for the next."""
        assert self.ep is not None
        s, sc = self.settings, self.scenario
        e, t, h = self.episode, self.t, sc.horizon
        clock = self.clock()
        if clock is not None:  # every agent is expected at every step: a silent one is absent each time
            heard = self.heard.pop((e, t), {})
            self.answers = {k: v for k, a in heard.items() if (v := self._valid(k, a, out)) is not None}
            self.present = set(range(sc.n_agents))
        chosen = dict(self.answers)
        missing = self.present - chosen.keys()
        if missing:
            self.absent_total += len(missing)
            out.counters["absent_agent_steps"] += len(missing)
            if now - self._absent_warned >= ABSENT_LOG_PERIOD:
                self._absent_warned = now
                out.log.append(
                    (
                        "warning",
                        f"episode {e} step {t}: no action from agents {sorted(missing)} within the deadline; idle",
                    )
                )
        self.present = set(chosen)
        res = self.ep.step(chosen)
        if clock is not None:  # the reports of this step that came before we recorded it
            self._take_early(now, out)
        self.answers = {}  # from here on, the agents' answers are their actions of step t + 1 (ready after step h)
        external = isinstance(self.ep, ExternalEpisode)
        if not external:  # in an external operation the robots observe and publish the observations themselves
            observed, _cls = self.model.observes(res.actions, t)
            tasks = np.where(res.observations >= 0, observed, -1).T.tolist()
            levels = res.observations.T.tolist()
            for k in range(sc.n_agents):
                out.publish.append(
                    (
                        "observation",
                        {
                            "agent": k,
                            "episode": e,
                            "step": t,
                            "tasks": tasks[k],
                            "levels": levels[k],
                            "acted": res.acted,
                        },
                    )
                )
        out.publish.append(self._step_record(t, "step", res.acted))
        if not external:  # external: published when the outside source reports the levels (on_severity)
            out.publish.append(
                (
                    "ground_truth",
                    {
                        "episode": e,
                        "step": t,
                        "levels": res.levels.tolist(),
                        "actions": res.actions.tolist(),
                        "events": res.events,
                    },
                )
            )
            counts = Counter(j for happened in res.events for j in happened)
            for j, k in sorted(counts.items()):
                where = f"episode {e}" if self.size == 1 else f"{k} of episodes {e}..{e + self.size - 1}"
                out.log.append(("info", f"{where}, step {t}: event {sc.events[j].label!r}"))
        if clock is not None:  # the observer: the next step at its instant, or the end of the episode
            if t < h:
                self.t, self.phase = t + 1, "act"
                self.deadline = self._mono(clock.at(e, t + 1)) + OBSERVE_AFTER * s.period
            else:
                self.t, self.phase = h, "end"
                self.waiting = set()
                self.deadline = self._mono(clock.at(e, h)) + 0.5 * s.period  # the levels of step h come in
        elif t < h:
            self.t, self.phase = t + 1, "act"
            if s.clock == "free":
                self.deadline = self.clock_at + s.period
            else:  # the live agents; with none live, anyone until the deadline (never race ahead)
                self.waiting = self.present if self.present else set(range(sc.n_agents))
                self.deadline = now + s.act_deadline
        else:
            self.t, self.phase = h, "end"
            self.waiting = set(res.acted)
            self.deadline = now + s.update_deadline

    def _finish_episode(self, now: float, out: WorldEffects) -> None:
        assert self.ep is not None
        late = self.waiting - self.answers.keys()
        if late:
            out.counters["late_ready"] += len(late)
        out.publish.append(self._step_record(self.scenario.horizon, "end", []))
        ms = [{"run": self.settings.run_id, **m} for m in self.ep.metrics(now)]
        self.next_unlogged = self.episode + self.size
        out.publish.extend(("episode_metrics", m) for m in ms)
        self.episodes_done += len(ms)
        m = ms[0]
        if m["severity"] == "unknown":
            out.log.append(
                (
                    "info",
                    f"episode {m['episode']}: completion unknown (no outside source reported every level), "
                    f"absent {m['absent']}, {m['seconds']:.2f} s",
                )
            )
        elif len(ms) == 1:
            out.log.append(
                (
                    "info",
                    f"episode {m['episode']}: completion {m['completion']}{' (failed)' if m['failed'] else ''}, "
                    f"idle {m['idle_before']}, reassign {m['reassign_before']}, absent {m['absent']}, "
                    f"{m['seconds']:.2f} s",
                )
            )
        else:
            comp = np.array([x["completion"] for x in ms], dtype=np.float64)
            fails = sum(x["failed"] for x in ms)
            out.log.append(
                (
                    "info",
                    f"episodes {m['episode']}..{ms[-1]['episode']}: completion {comp.mean():.2f} (mean), "
                    f"{fails} failed, absent {m['absent']}, {m['seconds']:.2f} s",
                )
            )
        for i, mi in enumerate(ms):
            out.episode_log.append({"run": self.settings.run_id, "metrics": mi, **self.ep.trajectory(i)})
        self._next_episode(self.episode + self.size, now, out)

    # ----- records and status -------------------------------------------------------------------------------------
    def scenario_record(self, state: str) -> dict[str, Any]:
        """The fields of the /htlm/scenario record announcing the run in `state` (running or stopped)."""
        s = self.settings
        self.seq += 1
        return {
            "run": s.run_id,
            "nonce": self.nonce,
            "seq": self.seq - 1,
            "seed": s.seed,
            "mode": s.mode,
            "clock": s.clock,
            "period": s.period,
            "epoch": self.epoch,
            "operation": s.operation,
            "first_episode": s.first_episode,
            "episodes": s.episodes,
            "batch": s.batch,
            "trainer_lag": s.trainer_lag,
            "state": state,
            "layout": self.layout,
            "scenario": self.scenario_dict,
        }

    def status(self) -> tuple[bool, str]:
        """(healthy, message) of the world for its diagnostics: not healthy while live agents are missing."""
        n = self.scenario.n_agents
        text = f"{self.phase} episode {self.episode} step {self.t}"
        if self.holding_for_trainer:
            return True, f"the run is over: waiting for the trainer's updates (trained up to step {self.trained})"
        if self.joining:
            return (
                True,
                f"episode {self.episode}: waiting for agents {sorted(set(range(n)) - self.answers.keys())} to begin",
            )
        if self.gate_since is not None:
            return True, f"{text}: waiting for the trainer (trained up to step {self.trained})"
        if self.phase in ("act", "end") and len(self.present) < n:
            return False, f"{text}: agents {sorted(set(range(n)) - self.present)} absent"
        return True, text

    def values(self) -> dict[str, str]:
        """The protocol's state for the node's diagnostics."""
        return {
            "phase": self.phase,
            "episode": str(self.episode),
            "step": str(self.t),
            "present": ",".join(str(k) for k in sorted(self.present)),
            "episodes_done": str(self.episodes_done),
            "absent_agent_steps": str(self.absent_total),
            "batch": str(self.size),
            "trainer_trained": str(self.trained),
        }
