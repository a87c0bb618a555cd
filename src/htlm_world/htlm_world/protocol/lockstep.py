"""The world of a simulated operation, without ROS (`LockstepProtocol`): it sequences batches of episodes and their
steps, simulates them (htlm_world.episode.WorldEpisode) and sends every agent its observations.

The world runs B episodes at once (`LockstepSettings.batch`): batch b holds episodes b*B .. b*B + B - 1 (the run's
last batch may be smaller) and draws from seeds.world(seed, b) exactly as the in-process Team(scenario, B, seed, b)
does (seeds.train_world(seed, b) in train mode, as `htlm train` does), so with the same actions both runtimes
produce the same levels and observations. Every per-step record carries the values of the batch's episodes as
arrays; with B = 1 a batch is one episode.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from htlm_world.episode import WorldEpisode, batch_index, global_step
from htlm_world.protocol.base import WorldProtocol
from htlm_world.protocol.settings import Phase, WorldEffects


class LockstepProtocol(WorldProtocol):
    """The world's side of the lockstep protocol (docs/ros.md) for a simulated operation.

    Per batch of B episodes: the begin (`WorldProtocol`); per step t: wait for the actions of the live agents until
    `act_deadline` (a silent agent idles at its site in every episode of the step, is counted absent, and is no
    longer waited for until it is heard again), apply T, send every agent its observations, announce the step (with
    the agents whose actions were applied) and the ground truth; each agent's next actions, sent after its belief
    update, are also its "ready"; after the last step wait for the agents' ready (`update_deadline`), then publish
    `end` and the metrics of every episode. With the free-running clock, a step is applied every `period` seconds
    whoever answered. A record of a past or future step is dropped and counted, a repeated one too; an agent heard
    one step late is waited for again from then on. With `pace` (training), step g waits until the trainer reports
    its updates of the steps before g - trainer_lag done (`on_trainer`); the deadlines of the agents start once the
    trainer has caught up.
    """

    def _new_episode(self, e: int, now: float) -> WorldEpisode:
        s = self.settings
        b = batch_index(e, s.batch)
        return WorldEpisode(self.scenario, self.model, s.seed, e, started=now, size=self.size, b=b, mode=s.mode)

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

    def _advance_steps(self, now: float, out: WorldEffects) -> bool:
        if self.phase == Phase.ACT:
            if self.settings.clock == "free":
                if now < self.deadline:
                    return False
                self.clock_at = self.deadline
            elif self._gate_closed(now, out) or not (self.waiting <= self.answers.keys() or now >= self.deadline):
                return False
            self._apply_step(now, out)
            return True
        if self.phase == Phase.END and (self.waiting <= self.answers.keys() or now >= self.deadline):
            self._finish_episode(now, out)
            return True
        return False

    def _apply_step(self, now: float, out: WorldEffects) -> None:
        """Apply T to the answers of step t (missing live agents idle), publish the results, wait for the next."""
        assert self.ep is not None
        s, sc = self.settings, self.scenario
        e, t, h = self.episode, self.t, sc.horizon
        res = self.ep.step(self._take_answers(now, out))
        self.answers = {}  # from here on, the agents' answers are their actions of step t + 1 (ready after step h)
        observed, _cls = self.model.observes(res.actions, t)
        tasks = np.where(res.observations >= 0, observed, -1).T.tolist()
        levels = res.observations.T.tolist()
        for k in range(sc.n_agents):
            fields = {"agent": k, "episode": e, "step": t, "tasks": tasks[k], "levels": levels[k], "acted": res.acted}
            out.publish.append(("observation", fields))
        out.publish.append(self._step_record(t, "step", res.acted))
        truth = {
            "episode": e,
            "step": t,
            "levels": res.levels.tolist(),
            "actions": res.actions.tolist(),
            "events": res.events,
        }
        out.publish.append(("ground_truth", truth))
        counts = Counter(j for happened in res.events for j in happened)
        for j, k in sorted(counts.items()):
            where = f"episode {e}" if self.size == 1 else f"{k} of episodes {e}..{e + self.size - 1}"
            out.log.append(("info", f"{where}, step {t}: event {sc.events[j].label!r}"))
        if t < h:
            self.t, self.phase = t + 1, Phase.ACT
            if s.clock == "free":
                self.deadline = self.clock_at + s.period
            else:  # the live agents; with none live, anyone until the deadline (never race ahead)
                self.waiting = self.present if self.present else set(range(sc.n_agents))
                self.deadline = now + s.act_deadline
        else:
            self.t, self.phase = h, Phase.END
            self.waiting = set(res.acted)
            self.deadline = now + s.update_deadline
