"""The world of a deployed team, without ROS (`DeployProtocol`): the operation is outside (the robots observe and
publish their observations, an outside source may report the true levels), the agents keep the step clock
themselves (htlm_world.clock), and the world only observes and logs (docs/ros.md, Connecting your robots)."""

from __future__ import annotations

from typing import Any

import numpy as np

from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.episode import DeployEpisode, WorldEpisode
from htlm_world.protocol.base import WorldProtocol
from htlm_world.protocol.settings import Phase, WorldEffects

FIRST_STEP_LEAD = 0.5
"""The epoch (step 1 of the run) is this many periods after the first begin is over, so that the announcement
carrying it reaches the agents first."""

OBSERVE_AFTER = 0.1
"""The observer records the joint assignment of a step this many periods after its instant (the agents sent their
actions before it)."""

HEARD_KEPT = 64
"""Most steps whose heard actions the observer keeps."""


class DeployProtocol(WorldProtocol):
    """The observer of a deployed team (operation external: clock free, batch 1).

    The run's first episode begins as every run does (`WorldProtocol`: every agent's actions for step 1, or the
    join timeout); then the world fixes the epoch of the step clock, announces it, and from then on nobody waits for
    anybody: at OBSERVE_AFTER periods past each step's instant the world records the actions heard for that step (a
    silent agent is absent), takes the robots' observations and the outside source's levels as they come, and logs
    the episodes. An action heard after its step was recorded still tells what the agent did (its `before`), and
    the steps a world missed while it was down are rebuilt from it. A world restarted mid-run observes from the step
    in progress on.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """The observer of one run (the arguments of `WorldProtocol`)."""
        super().__init__(*args, **kwargs)
        self.heard: dict[tuple[int, int], dict[int, Any]] = {}
        """The actions heard per (episode, step), kept until the observer records the step."""
        self.early: list[tuple[str, dict[str, Any]]] = []
        """Severity and observation records of steps not yet recorded, as (kind, record)."""

    # ----- the run ------------------------------------------------------------------------------------------------
    def resume(self, seq: int, next_episode: int, epoch: float = 0.0) -> None:
        """Continue a run (`WorldProtocol.resume`) under the step clock of `epoch` (0: not fixed yet)."""
        super().resume(seq, next_episode, epoch)
        self.epoch = epoch

    def clock(self) -> StepClock | None:
        """The run's step clock (once the epoch is fixed)."""
        if self.epoch <= 0.0:
            return None
        s = self.settings
        return StepClock(self.epoch, s.period, self.scenario.horizon, s.first_episode, s.episodes)

    def _mono(self, wall: float) -> float:
        return wall - self.wall_offset

    def start(self, now: float) -> WorldEffects:
        """Announce the run; with the epoch fixed (a restarted world), observe from the step in progress on, else
        begin the first episode (`WorldProtocol.start`)."""
        clock = self.clock()
        if clock is None:
            return super().start(now)
        out = WorldEffects()
        out.publish.append(("scenario", self.scenario_record("running")))
        first = self.settings.first_episode if self.resume_at is None else self.resume_at
        i = max(clock.last(now + self.wall_offset) + 1, clock.index(first, 1))
        e, t = clock.step(i)
        self.first = False
        if e > first and clock.in_run(i):
            out.log.append(("warning", f"episodes {first}..{e - 1} passed while the world was down; not logged"))
            self.next_unlogged = e
        self._next_episode(e, now, out)
        out.log.append(("info", f"observing the agents' clock from episode {e} step {t}"))
        if self.ep is not None and t > 1:
            assert isinstance(self.ep, DeployEpisode)
            self.ep.skip(t - 1)
            self.t = t
            self.deadline = self._mono(clock.at(e, t)) + OBSERVE_AFTER * self.settings.period
            out.log.append(("warning", f"episode {e}: steps 1..{t - 1} passed unobserved; logged as idle"))
        self._progress(now, out)
        return out

    # ----- messages in --------------------------------------------------------------------------------------------
    def on_action(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded action record {agent, episode, step, actions, before}: kept for the step's instant (before the
        epoch, the answer to the first begin)."""
        clock = self.clock()
        if clock is None:
            return super().on_action(rec, now)
        out = WorldEffects()
        ep = self.ep
        before = rec["before"]
        if (
            isinstance(ep, DeployEpisode)
            and ep.unheard
            and rec["episode"] == self.episode
            and len(before) == rec["step"] - 1
        ):  # what the agent did at the steps recorded without its action, this one included if it is late
            late, missed = ep.rebuild(rec["agent"], [*before, int(rec["actions"][0])])
            out.counters["absent_rebuilt"] += late
            if missed:
                text = f"episode {self.episode}: {missed} missed steps of agent {rec['agent']} rebuilt from its record"
                out.log.append(("info", text))
        key = (rec["episode"], rec["step"])
        if key <= (self.episode, self.t - 1) or (self.phase != Phase.ACT and key <= (self.episode, self.t)):
            out.drops.append(("action", "past"))
            return out
        if clock.ahead(*key, now + self.wall_offset) > FUTURE_STEPS:
            out.rejects.append(("action", "future", f"agent {rec['agent']}: episode {key[0]} step {key[1]}"))
            return out
        self.heard.setdefault(key, {})[rec["agent"]] = np.asarray(rec["actions"], dtype=np.int64)
        while len(self.heard) > HEARD_KEPT:
            del self.heard[min(self.heard)]
        self._progress(now, out)
        return out

    def on_ready(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded ready record: the agents' clock does not wait for anyone (before the epoch, as every run)."""
        return super().on_ready(rec, now) if self.clock() is None else WorldEffects()

    def on_severity(self, rec: dict[str, Any], now: float) -> WorldEffects:
        """A decoded severity record {episode, step, levels} of an outside source: the true levels after a step of
        the current episode, logged and published as the step's ground truth."""
        out = WorldEffects()
        ep = self.ep
        if not isinstance(ep, DeployEpisode):
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
        """A decoded observation record a robot published: kept for the episode log."""
        out = WorldEffects()
        ep = self.ep
        if isinstance(ep, DeployEpisode) and self._soon(rec["episode"], rec["step"], ep):
            self._keep_early("observation", rec)
        elif isinstance(ep, DeployEpisode) and rec["episode"] == self.episode and 1 <= rec["step"] <= ep.t:
            ep.report_observation(rec["agent"], rec["step"], rec["levels"][0])
        return out

    def _soon(self, e: int, t: int, ep: DeployEpisode) -> bool:
        """Under the agents' clock: whether step t of episode e is the next one the observer will record (its
        reports may come first)."""
        if self.epoch <= 0.0 or (e, t) <= (self.episode, ep.t):
            return False
        h = self.scenario.horizon
        nxt = (e - self.episode) * h + t - ep.t
        return nxt == 1

    def _keep_early(self, kind: str, rec: dict[str, Any]) -> None:
        """A report of a step the observer has not recorded yet (the agents' clock runs ahead of its record by
        OBSERVE_AFTER): taken when it records the step."""
        self.early.append((kind, rec))
        del self.early[: max(0, len(self.early) - HEARD_KEPT * self.scenario.n_agents)]

    def _take_early(self, now: float, out: WorldEffects) -> None:
        """The early reports of the steps recorded by now."""
        ready = [(k, r) for k, r in self.early if (r["episode"], r["step"]) <= (self.episode, self.t)]
        self.early = [(k, r) for k, r in self.early if (r["episode"], r["step"]) > (self.episode, self.t)]
        for kind, rec in ready:
            got = self.on_severity(rec, now) if kind == "severity" else self.on_observation(rec, now)
            out.publish += got.publish
            out.drops += got.drops

    # ----- phases -------------------------------------------------------------------------------------------------
    def _new_episode(self, e: int, now: float) -> WorldEpisode:
        return DeployEpisode(self.scenario, self.model, e, started=now)

    def _begin(self, now: float, out: WorldEffects) -> None:
        """Under the agents' clock nobody waits for anybody: step 1 is recorded at its instant (before the epoch,
        the begin waits for the agents as every run's does)."""
        clock = self.clock()
        if clock is None:
            super()._begin(now, out)
            return
        self.joining = False
        self.present = set(range(self.scenario.n_agents))
        self.deadline = self._mono(clock.at(self.episode, 1)) + OBSERVE_AFTER * self.settings.period
        out.publish.append(self._step_record(0, "begin", []))

    def _start_steps(self, now: float, out: WorldEffects) -> None:
        """The first begin is over: fix the epoch and announce it; from here on every agent keeps the clock."""
        super()._start_steps(now, out)
        if self.epoch != 0.0:
            return
        period = self.settings.period
        lead = FIRST_STEP_LEAD * period
        self.epoch = round(now + self.wall_offset + lead, 6)
        out.publish.append(("scenario", self.scenario_record("running")))
        out.log.append(("info", f"the step clock starts at epoch {self.epoch:.6f} (period {period:g} s)"))
        self.heard[(self.episode, 1)] = dict(self.answers)
        self.answers = {}
        self.clock_at = self.deadline = now + lead + OBSERVE_AFTER * period

    def _advance_steps(self, now: float, out: WorldEffects) -> bool:
        if self.phase == Phase.ACT:
            if now < self.deadline:
                return False
            self.clock_at = self.deadline
            self._apply_step(now, out)
            return True
        if self.phase == Phase.END and (self.waiting <= self.answers.keys() or now >= self.deadline):
            self._finish_episode(now, out)
            return True
        return False

    def _apply_step(self, now: float, out: WorldEffects) -> None:
        """Record step t at its instant: the actions heard for it (every agent is expected at every step: a silent
        one is absent each time), the reports that came before, then wait for the next instant."""
        assert self.ep is not None
        clock = self.clock()
        assert clock is not None
        s, sc = self.settings, self.scenario
        e, t, h = self.episode, self.t, sc.horizon
        heard = self.heard.pop((e, t), {})
        self.answers = {k: v for k, a in heard.items() if (v := self._valid(k, a, out, judge=False)) is not None}
        self.present = set(range(sc.n_agents))
        res = self.ep.step(self._take_answers(now, out))
        self._take_early(now, out)  # the reports of this step that came before we recorded it
        self.answers = {}
        out.publish.append(self._step_record(t, "step", res.acted))
        # the ground truth is published when the outside source reports the levels (on_severity)
        if t < h:
            self.t, self.phase = t + 1, Phase.ACT
            self.deadline = self._mono(clock.at(e, t + 1)) + OBSERVE_AFTER * s.period
        else:
            self.t, self.phase = h, Phase.END
            self.waiting = set()
            self.deadline = self._mono(clock.at(e, h)) + 0.5 * s.period  # the levels of step h come in
