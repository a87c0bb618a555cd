"""Events of an operation (docs/model.md, Events): what happens from outside the model T, step by step, in B
episodes at once. Both runtimes call it the same way with the same generator (`seeds.events`, `seeds.train_events`),
so the same seed gives the same events: the in-process Team and the world node.

In step t (1..h), before the joint assignment is applied: every event that has not yet happened in an episode and
whose step has come draws whether it happens (its probability), and it happens only if its condition holds on the
true levels before the step (`once_done`). A surge or a new task raises its task's level to at least the event's
level, and the transition of step t starts from there; a dropout makes the agent idle (at the site of its previous
assignment, as an absent agent) from step t on, until a return. Every episode draws (B, E) uniforms per step, whatever
happens, so the events of one episode never change another's draws.
"""

from __future__ import annotations

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import EventSpec, Scenario, ScenarioError
from htlm_world.types import BoolArray, IntArray

SURGE, DROPOUT, RETURN = 0, 1, 2
"""Event codes: a level that rises (surge, new_task), an agent that stops, an agent that returns."""


def resolve_agent(sc: Scenario, events: tuple[EventSpec, ...], agent: str) -> tuple[EventSpec, ...]:
    """The events with the placeholder agent `most_important` replaced by `agent` (a name of the team)."""
    if agent not in [a.name for a in sc.agents]:
        raise ScenarioError(f"agent {agent!r} is not an agent of the team")
    return tuple(EventSpec(**{**ev.__dict__, "agent": agent}) if ev.agent == "most_important" else ev for ev in events)


class EventRun:
    """The events of a batch of B episodes, decided step by step (`begin_step`)."""

    def __init__(self, scenario: Scenario, batch: int, rng: np.random.Generator) -> None:
        """Events of `scenario` in `batch` episodes, drawing from `rng` (one (B, E) draw per step)."""
        self.scenario = scenario
        self.batch = batch
        self.rng = rng
        sites = list(scenario.site_names)
        kinds = list(scenario.kind_names)
        agents = [a.name for a in scenario.agents]
        task_of = {(s, k): j for j, (s, k) in enumerate(scenario.tasks)}
        evs = scenario.events
        for ev in evs:
            if ev.event in ("dropout", "return") and ev.agent not in agents:
                raise ScenarioError(f"event {ev.label!r}: agent {ev.agent!r} is not an agent of the team {agents}")
        self.labels = [ev.label for ev in evs]
        codes = {"surge": SURGE, "new_task": SURGE, "dropout": DROPOUT, "return": RETURN}
        self.code = np.array([codes[ev.event] for ev in evs], dtype=np.int64)
        self.target = np.array(
            [
                task_of[(sites.index(ev.site), kinds.index(ev.task))] if code == SURGE else agents.index(ev.agent)
                for ev, code in zip(evs, self.code, strict=True)
            ],
            dtype=np.int64,
        )
        self.level = np.array([ev.level for ev in evs], dtype=np.int64)
        self.at = np.array([ev.at for ev in evs], dtype=np.int64)
        self.probability = np.array([ev.probability for ev in evs], dtype=np.float64)
        self.done_tasks = [
            [j for j, (s, _) in enumerate(scenario.tasks) if s == sites.index(ev.once_done)] if ev.once_done else None
            for ev in evs
        ]
        """Per event, the tasks of its `once_done` site (None: no condition)."""
        self.happened: BoolArray = np.zeros((batch, len(evs)), dtype=np.bool_)
        """(B, E) which events have happened in each episode."""
        self.out: BoolArray = np.zeros((batch, scenario.n_agents), dtype=np.bool_)
        """(B, N) agents out (dropped out and not returned) in each episode."""
        self.log: list[tuple[int, int, int]] = []
        """(step, episode of the batch, event) of every event that happened, in order."""

    @property
    def count(self) -> int:
        """E, the number of events."""
        return len(self.labels)

    def begin_step(self, t: int, levels: IntArray) -> tuple[IntArray, BoolArray]:
        """Decide the events of step t on the true levels (B, p) before it; returns the levels the transition starts
        from and (B, E) the events that happened now. Updates `out`, the agents out in step t."""
        e = self.count
        fired: BoolArray = np.zeros((self.batch, e), dtype=np.bool_)
        if e == 0:
            return levels, fired
        u = self.rng.random((self.batch, e))
        fired = ~self.happened & (t >= self.at) & (u < self.probability)
        for j, tasks in enumerate(self.done_tasks):
            if tasks is not None:
                fired[:, j] &= (levels[:, tasks] == 0).all(axis=1)
        if not fired.any():
            return levels, fired
        levels = levels.copy()
        for j in range(e):
            now = fired[:, j]
            if not now.any():
                continue
            target = self.target[j]
            if self.code[j] == SURGE:
                levels[:, target] = np.where(now, np.maximum(levels[:, target], self.level[j]), levels[:, target])
            else:
                self.out[:, target] = np.where(now, self.code[j] == DROPOUT, self.out[:, target])
            self.log.extend((t, int(i), j) for i in np.flatnonzero(now))
        self.happened |= fired
        return levels, fired

    def force(self, model: Model, actions: IntArray, prev: IntArray) -> IntArray:
        """The joint assignment (B, N) with the agents out idle at the site of their previous assignment (HT: -1)."""
        if not self.out.any():
            return actions
        return np.where(self.out, model.idle_action(prev), actions)

    @staticmethod
    def records(fired: BoolArray) -> list[list[int]]:
        """Per episode of the batch, the indices of the events that happened (`begin_step`'s second result)."""
        return [np.flatnonzero(row).tolist() for row in fired]
