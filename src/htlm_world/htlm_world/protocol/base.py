"""What the world's two protocols share, without ROS (`WorldProtocol`): the run's announcements, the episode log
(metrics, trajectories, the progress a restarted world continues from), the begin of an episode that waits for
every agent's first actions, and the end of the run."""

from __future__ import annotations

import math
import secrets
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import numpy as np

from htlm_world.episode import WorldEpisode, global_step
from htlm_world.model import Model
from htlm_world.protocol.settings import LockstepSettings, Phase, WorldEffects
from htlm_world.scenario import Scenario

NUDGE = 0.5
"""Seconds between two announcements of an episode's begin while the world waits for the agents."""

ABSENT_LOG_PERIOD = 5.0
"""Least seconds between two warnings about agents that missed a step."""


class WorldProtocol(ABC):
    """The world's side of the protocol (docs/ros.md), fed with decoded messages and the time: the part both the
    lockstep sequencer (`LockstepProtocol`) and the observer of a deployed team (`DeployProtocol`) run.

    An episode begins by announcing `begin` (again every NUDGE seconds) until every agent answered with its actions
    for step 1 and listens to its observations, or the begin deadline (`join_timeout` for the first batch); the
    subclass then runs the steps (`_advance_steps`, `_apply_step`); after the last one the metrics and trajectories
    of the batch's episodes are logged (`_finish_episode`) and the next batch begins, until the run is over and
    announced stopped (after the trainer's updates of every step, with `pace`).

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
        self.phase = Phase.IDLE
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
        """The first episode whose metrics are not yet out (the episode log is complete before it)."""
        self.hold_until = math.inf
        self.holding_for_trainer = False
        self.size = 1
        """Episodes in the current batch (B, or fewer in the run's last batch)."""
        self.trained = -1
        """The trainer's progress: every step with a global index below it has had its updates (-1: not heard)."""
        self.trainer_live = True
        """Whether the world waits for the trainer (it is heard, or has not yet been given up on)."""
        self.gate_since: float | None = None
        """Since when the current step waits for the trainer (None: it does not); a progress record starts the wait
        again (the trainer is silent for trainer_deadline before it is given up)."""
        self.trainer_finished = False
        """Whether the trainer said it needs no more of the run (a training run ends after the batch in progress)."""
        self.episodes_done = 0
        self.absent_total = 0
        self._absent_warned = -math.inf
        self.epoch = 0.0
        """The wall-clock instant of the run's first step (a deployed team; 0 until fixed)."""
        self.wall_offset = 0.0
        """Wall-clock seconds minus `now` (the node sets it: time.time() - time.monotonic())."""

    # ----- the run ------------------------------------------------------------------------------------------------
    def resume(self, seq: int, next_episode: int, epoch: float = 0.0) -> None:
        """Continue a run an earlier world process of the same run announced up to sequence number `seq` and logged
        up to (excluding) `next_episode` (its durable progress); `epoch`: the step clock of a deployed team."""
        self.seq = seq + 1
        self.resume_at = self.next_unlogged = next_episode

    def progress(self) -> dict[str, Any]:
        """What a restarted world needs to continue the run: its id, the last sequence number announced, the next
        episode not yet logged, the epoch of the step clock."""
        return {
            "run": self.settings.run_id,
            "seq": self.seq - 1,
            "next_episode": self.next_unlogged,
            "epoch": self.epoch,
        }

    def start(self, now: float) -> WorldEffects:
        """Announce the run and the begin of its first episode (a restarted world's next one)."""
        out = WorldEffects()
        out.publish.append(("scenario", self.scenario_record("running")))
        self._next_episode(self.settings.first_episode if self.resume_at is None else self.resume_at, now, out)
        self._progress(now, out)
        return out

    def stop(self, now: float) -> WorldEffects:
        """The node was told to stop: end the run at once (the scenario's state turns to stopped)."""
        out = WorldEffects()
        if self.phase != Phase.STOPPED:
            self.phase = Phase.STOPPED
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
        if self.phase == Phase.STOPPED:
            return self.linger_until
        if self.phase == Phase.HOLDING:
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
        """A decoded action record {agent, episode, step, actions}: the answer of the agent in the current phase."""
        out = WorldEffects()
        if not self._accept("action", rec, Phase.ACT, out):
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

    def _valid(self, k: int, a: Any, out: WorldEffects, judge: bool = True) -> Any:
        """Agent k's actions of the current step as an array, or None (rejected: a wrong length, or, when `judge`,
        an idle location away from the site of a_o)."""
        assert self.ep is not None
        if len(a) != self.size:
            out.rejects.append(("action", "length", f"agent {k}: {len(a)} actions for a batch of {self.size}"))
            return None
        arr = np.asarray(a, dtype=np.int64)
        if not judge:
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
        if not self._accept("ready", rec, Phase.END, out):
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
        if self.gate_since is not None:  # heard: the wait for a silent trainer starts again
            self.gate_since = now
        if self.holding_for_trainer:
            self.hold_until = max(self.hold_until, now + self.settings.end_hold)
        if rec["finished"] and self.settings.mode == "train" and not self.trainer_finished:
            self.trainer_finished = True
            out.log.append(
                ("info", f"the trainer has finished learning (trained up to step {self.trained}): the run ends")
            )
            if self.joining and self.phase == Phase.ACT:  # the batch beginning has not started: it is not run
                self.joining = False
                self.gate_since = None
                self.phase, self.hold_until = Phase.HOLDING, now
        self._progress(now, out)
        return out

    def on_severity(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded severity record of an outside source: only a deployed team's world takes one."""
        out = WorldEffects()
        out.drops.append(("severity", "simulated"))
        return out

    def on_observation(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded observation record a robot published: only a deployed team's world takes one."""
        return WorldEffects()

    def _accept(self, topic: str, rec: dict[str, Any], phase: Phase, out: WorldEffects) -> bool:
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
        if self.phase == Phase.STOPPED:
            self.done = now >= self.linger_until
            return False
        if self.phase == Phase.HOLDING:
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
        return self._advance_steps(now, out)

    @abstractmethod
    def _advance_steps(self, now: float, out: WorldEffects) -> bool:
        """Past the begin: apply the next step or finish the batch if due; returns whether it did."""

    def _gate_closed(self, now: float, out: WorldEffects) -> bool:
        """Whether the next step must wait for the trainer (only the lockstep sequencer paces the run)."""
        return False

    def _hold(self, now: float, out: WorldEffects) -> None:
        """The run's last step is done: announce the stop once the trainer has reported the updates of every step
        (training with pace), or at once, or when `end_hold` is over (said in the log)."""
        s = self.settings
        if self.phase != Phase.HOLDING:
            return
        if s.pace and s.mode == "train" and self.episode >= 0 and not self.trainer_finished:
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
        self.phase = Phase.STOPPED
        out.publish.append(("scenario", self.scenario_record("stopped")))
        out.status_changed = True
        self.linger_until = now + s.linger

    def _begin_wait(self) -> float:
        return self.settings.join_timeout if self.first else self.settings.begin_deadline

    def _next_episode(self, e: int, now: float, out: WorldEffects) -> None:
        """The batch from episode e on begins (or the run is over)."""
        if not self.in_run(e) or self.batch_size(e) < 1 or self.trainer_finished:
            self.phase, self.hold_until = Phase.HOLDING, now + self.settings.end_hold
            self._hold(now, out)
            return
        self.size = self.batch_size(e)
        self.ep = self._new_episode(e, now)
        self.episode, self.t, self.phase = e, 1, Phase.ACT
        self.answers = {}
        self._begin(now, out)

    @abstractmethod
    def _new_episode(self, e: int, now: float) -> WorldEpisode:
        """The episodes of the batch from e on, as this protocol runs them."""

    def _begin(self, now: float, out: WorldEffects) -> None:
        """Announce the begin of the batch and wait for the agents' first actions."""
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
        missing = sorted(set(range(n)) - self.present)
        if self.first and missing:
            out.log.append(("warning", f"starting without agents {missing}"))
        elif missing and now - self._absent_warned >= ABSENT_LOG_PERIOD:  # counted absent in step 1
            self._absent_warned = now
            text = f"episode {self.episode} begin: no first action from agents {missing} within the deadline; idle"
            out.log.append(("warning", text))
        self.first = False
        self.clock_at = self.deadline = now  # step 1 goes at once, also on the free clock
        self.waiting = set()

    def _take_answers(self, now: float, out: WorldEffects) -> dict[int, Any]:
        """The answers of step t to apply: live agents that did not answer are counted absent (and warned about,
        at most every ABSENT_LOG_PERIOD seconds); those who answered are the live agents from now on."""
        chosen = dict(self.answers)
        missing = self.present - chosen.keys()
        if missing:
            self.absent_total += len(missing)
            out.counters["absent_agent_steps"] += len(missing)
            if now - self._absent_warned >= ABSENT_LOG_PERIOD:
                self._absent_warned = now
                e, t = self.episode, self.t
                text = f"episode {e} step {t}: no action from agents {sorted(missing)} within the deadline; idle"
                out.log.append(("warning", text))
        self.present = set(chosen)
        return chosen

    def _finish_episode(self, now: float, out: WorldEffects) -> None:
        """The batch is over: log the metrics and trajectories of its episodes, then begin the next batch."""
        assert self.ep is not None
        late = self.waiting - self.answers.keys()
        if late:
            out.counters["late_ready"] += len(late)
        out.publish.append(self._step_record(self.scenario.horizon, "end", []))
        ms = [{"run": self.settings.run_id, **m} for m in self.ep.metrics(now)]
        self.next_unlogged = self.episode + self.size
        out.publish.extend(("episode_metrics", m) for m in ms)
        self.episodes_done += len(ms)
        out.log.append(("info", _summary(ms)))
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
        if self.phase in (Phase.ACT, Phase.END) and len(self.present) < n:
            return False, f"{text}: agents {sorted(set(range(n)) - self.present)} absent"
        return True, text

    def values(self) -> dict[str, str]:
        """The protocol's state for the node's diagnostics."""
        return {
            "phase": self.phase.value,
            "episode": str(self.episode),
            "step": str(self.t),
            "present": ",".join(str(k) for k in sorted(self.present)),
            "episodes_done": str(self.episodes_done),
            "absent_agent_steps": str(self.absent_total),
            "batch": str(self.size),
            "trainer_trained": str(self.trained),
        }


def _summary(ms: list[dict[str, Any]]) -> str:
    """The log line of a finished batch, from the metrics of its episodes."""
    m = ms[0]
    if m["severity"] == "unknown":
        return (
            f"episode {m['episode']}: completion unknown (no outside source reported every level), "
            f"absent {m['absent']}, {m['seconds']:.2f} s"
        )
    if len(ms) == 1:
        return (
            f"episode {m['episode']}: completion {m['completion']}{' (failed)' if m['failed'] else ''}, "
            f"idle {m['idle_before']}, reassign {m['reassign_before']}, absent {m['absent']}, {m['seconds']:.2f} s"
        )
    comp = np.array([x["completion"] for x in ms], dtype=np.float64)
    fails = sum(x["failed"] for x in ms)
    return (
        f"episodes {m['episode']}..{ms[-1]['episode']}: completion {comp.mean():.2f} (mean), "
        f"{fails} failed, absent {m['absent']}, {m['seconds']:.2f} s"
    )
