"""The episodes the world runs, without ROS: one batch's state and step (`WorldEpisode`, simulated; `DeployEpisode`,
a deployed team's), and how a run's episodes, batches and steps are numbered (`batch_index`, `global_step`) and
seeded (`world_stream`). `htlm_world.protocol.WorldProtocol` sequences them."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from htlm_world import seeds
from htlm_world.events import EventRun
from htlm_world.metrics import episode_metrics
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.simulator import sample_world_step
from htlm_world.travel import TravelState, working_actions
from htlm_world.types import IntArray

TRAINER_LAG = 1
"""k of the trainer lag unless a run says otherwise: the agents act at step g with the networks updated through
step g − 1 − k, and the world paces step g on the trainer's updates of the steps before g − k (the learner's rule,
`htlm_agent.learning.loop.acting_weights`). The one default of the world node's, the lockstep protocol's and the
learner's `trainer_lag`."""


def batch_index(episode: int, batch: int) -> int:
    """The index b of the batch whose first episode is `episode` (its random streams are keyed by b)."""
    return episode // batch


def global_step(episode: int, batch: int, t: int, horizon: int) -> int:
    """The run-wide index g of step t (1..h) of the batch whose first episode is `episode`: b * h + t - 1. The
    trainer counts its rounds of updates in it (round g: the updates for the transitions of step g)."""
    return batch_index(episode, batch) * horizon + t - 1


def world_stream(seed: int, b: int, mode: str) -> np.random.Generator:
    """The world generator of batch b: `htlm train`'s training stream in train mode, else the evaluation one."""
    return seeds.train_world(seed, b) if mode == "train" else seeds.world(seed, b)


def event_stream(seed: int, b: int, mode: str) -> np.random.Generator:
    """The events generator of batch b: `htlm train`'s training stream in train mode, else the evaluation one."""
    return seeds.train_events(seed, b) if mode == "train" else seeds.events(seed, b)


@dataclass
class StepOutcome:
    """What the world produced in one step of a batch of B episodes."""

    actions: IntArray  # (B, N) joint assignment applied (absent agents idle at their site; -1 in HT mode)
    acted: list[int]  # agents whose own actions were applied
    levels: IntArray  # (B, p) true levels after the transition
    observations: IntArray  # (B, N) observed level of each agent's observed task (`Model.observes`), -1 when none
    # or absent
    events: list[list[int]] = field(default_factory=list)  # per episode, the scenario's events that happened


class WorldEpisode:
    """One batch of B episodes of the operation as the world process runs it, with its own world generator."""

    def __init__(
        self,
        scenario: Scenario,
        model: Model,
        seed: int,
        episode: int,
        started: float | None = None,
        size: int = 1,
        b: int | None = None,
        mode: str = "evaluate",
    ) -> None:
        """Start the `size` episodes from `episode` on, batch index `b` (`episode` when None: batch 1), of the run
        with master seed `seed` at the initial levels (at monotonic time `started`, now when None)."""
        self.scenario = scenario
        self.model = model
        self.episode = episode
        self.size = size
        self.b = episode if b is None else b
        self.rng = world_stream(seed, self.b, mode)
        self.events = EventRun(scenario, size, event_stream(seed, self.b, mode))
        n = scenario.n_agents
        self.levels: IntArray = np.tile(np.array(scenario.initial_levels, dtype=np.int64), (size, 1))  # (B, p)
        self.prev: IntArray = np.full((size, n), scenario.start_assignment, dtype=np.int64)
        self.t = 0
        self.travel = TravelState(scenario, size) if scenario.travel else None
        """Where every agent is (`htlm_world.travel`); None without travel."""
        self.absent = np.zeros(n, dtype=np.int64)
        self.level_log: list[IntArray] = [self.levels.copy()]
        self.action_log: list[IntArray] = []
        self.obs_log: list[IntArray] = []
        self.started = time.monotonic() if started is None else started

    def idle_actions(self, agent: int) -> IntArray:
        """What an absent agent does in each episode: idle at the site of its previous assignment (HT mode: -1)."""
        return np.asarray(self.model.idle_action(self.prev[:, agent]), dtype=np.int64)

    def joint(self, chosen: dict[int, IntArray], absent: np.ndarray | None = None) -> tuple[IntArray, list[int]]:
        """The joint assignment (B, N) of a step and the agents that acted: `chosen` maps agent -> its actions (B,);
        every other agent is idle at the site of its previous assignment in every episode, and counted absent unless
        `absent` (N,) says it is out by an event."""
        n = self.scenario.n_agents
        actions = np.empty((self.size, n), dtype=np.int64)
        acted = []
        for k in range(n):
            a = chosen.get(k)
            if a is None:
                actions[:, k] = self.idle_actions(k)
                if absent is None or not absent[k]:
                    self.absent[k] += 1
            else:
                actions[:, k] = a
                acted.append(k)
        return actions, acted

    def step(self, chosen: dict[int, IntArray]) -> StepOutcome:
        """Apply the step's events (`htlm_world.events`) and T to the joint assignment: `chosen` maps agent -> its
        actions (B,); every other agent is absent (idle in every episode). An agent an event keeps out is idle, not
        absent, and is not among those that acted when it is out in every episode of the batch. Absent agents and
        agents out observe nothing, standing by or not."""
        levels, fired = self.events.begin_step(self.t + 1, self.levels)
        out: np.ndarray = np.asarray(self.events.out.all(axis=0))
        actions, acted = self.joint({k: a for k, a in chosen.items() if not out[k]}, absent=out)
        actions = self.events.force(self.model, actions, self.prev)
        applied = actions
        if self.travel is not None:  # an agent on its way works on nothing and observes nothing
            applied = working_actions(actions, self.travel.step(actions))
        nxt, obs, _caps = sample_world_step(self.model, levels, applied, self.rng, self.t + 1)
        if len(acted) < self.scenario.n_agents:
            obs[:, [k for k in range(self.scenario.n_agents) if k not in acted]] = -1
        if self.model.standby_class >= 0:
            obs[self.events.out] = -1
        self.levels = nxt
        self.prev = np.where(actions >= 0, actions, self.prev)
        self.t += 1
        self.level_log.append(nxt.copy())
        self.action_log.append(actions)
        self.obs_log.append(obs.copy())
        return StepOutcome(actions=actions, acted=acted, levels=nxt, observations=obs, events=EventRun.records(fired))

    def metrics(self, now: float | None = None) -> list[dict[str, Any]]:
        """The episode_metrics records of the finished episodes (docs/model.md metrics plus absences), one per
        episode of the batch, finished at monotonic time `now` (now when None)."""
        sc = self.scenario
        levels = np.stack(self.level_log)  # (t+1, B, p)
        actions = np.stack(self.action_log)  # (t, B, N)
        m = episode_metrics(sc, levels, actions)
        seconds = round((time.monotonic() if now is None else now) - self.started, 6)
        absent = [int(x) for x in self.absent]
        return [
            {
                "episode": self.episode + i,
                "severity": "simulated",
                "completion": int(m.completion[i]),
                "failed": bool(m.failed[i]),
                "unused_capability": float(m.unused_capability[i]),
                "unused_fraction": float(m.unused_fraction[i]),
                "idle_before": int(m.idle_before[i]),
                "reassign_before": int(m.reassign_before[i]),
                "absent": absent,
                "seconds": seconds,
            }
            for i in range(self.size)
        ]

    def trajectory(self, i: int = 0) -> dict[str, Any]:
        """Episode i of the batch: levels (t+1, p), applied actions (t, N) and observations (t, N) as lists, and the
        events that happened as [step, label] (when the scenario has events)."""
        out = {
            "levels": np.stack(self.level_log)[:, i].tolist(),
            "actions": np.stack(self.action_log)[:, i].tolist() if self.action_log else [],
            "observations": np.stack(self.obs_log)[:, i].tolist() if self.obs_log else [],
        }
        if self.events.count:
            out["events"] = [[t, self.events.labels[j]] for t, e, j in self.events.log if e == i]
        return out


class DeployEpisode(WorldEpisode):
    """One episode of a deployed team (operation external, B = 1): the world applies nothing and observes nothing;
    it records the joint assignment of every step, the true levels an outside source reports (`report_levels`) and
    the observations the robots publish (`report_observation`), and knows the metrics only when every level is
    known."""

    def __init__(self, scenario: Scenario, model: Model, episode: int, started: float | None = None) -> None:
        """Start episode `episode` (its levels at step 0 are the scenario's initial levels, the rest unknown)."""
        super().__init__(scenario, model, 0, episode, started, size=1)
        self.reported: dict[int, IntArray] = {0: self.levels[0].copy()}
        self.observed: dict[tuple[int, int], int] = {}
        self.unheard: dict[tuple[int, int], bool] = {}
        """(step, agent) whose action the observer did not have when it recorded the step -> whether it counted the
        agent absent there (False: a step that passed unobserved, `skip`); `rebuild` fills them later."""

    def step(self, chosen: dict[int, IntArray]) -> StepOutcome:
        """Record the joint assignment of the step (absent agents idle); nothing is simulated."""
        n = self.scenario.n_agents
        actions, acted = self.joint(chosen)
        self.prev = np.where(actions >= 0, actions, self.prev)
        self.t += 1
        self.action_log.append(actions)
        self.unheard.update({(self.t, k): True for k in range(n) if k not in chosen})
        unknown = np.full((1, n), -1, dtype=np.int64)
        return StepOutcome(
            actions=actions, acted=acted, levels=np.full((1, self.scenario.n_tasks), -1), observations=unknown
        )

    def skip(self, steps: int) -> None:
        """Steps that passed unobserved (a world restarted mid-episode under the agents' clock): recorded as every
        agent idle at its site, each (step, agent) in `unheard`; the levels of those steps stay unknown, so the
        metrics do."""
        for _ in range(steps):
            self.t += 1
            self.action_log.append(np.asarray(self.model.idle_action(self.prev), dtype=np.int64))
            self.unheard.update({(self.t, k): False for k in range(self.scenario.n_agents)})

    def rebuild(self, agent: int, before: list[int]) -> tuple[int, int]:
        """An agent's own assignments of steps 1..len(before) (the `before` of its action record, -1 where it did
        not act): fill them in the steps recorded without its action (late or lost on the way, or passed while the
        observer was down), which then no longer count it absent. Returns (steps filled that had counted it absent,
        steps filled that passed unobserved)."""
        late = missed = 0
        for s in range(1, min(self.t, len(before)) + 1):
            counted = self.unheard.get((s, agent))
            if counted is None or before[s - 1] < 0:
                continue
            del self.unheard[(s, agent)]
            self.action_log[s - 1][0, agent] = before[s - 1]
            if counted:
                self.absent[agent] -= 1
                late += 1
            else:
                missed += 1
        if late + missed and len(before) >= self.t and before[self.t - 1] >= 0:
            self.prev[0, agent] = before[self.t - 1]
        return late, missed

    def report_levels(self, t: int, levels: IntArray) -> bool:
        """The outside source's true levels after step t (1..steps so far); False when t is not a step of it."""
        if not 1 <= t <= self.t:
            return False
        self.reported[t] = np.asarray(levels, dtype=np.int64).reshape(-1)
        return True

    def report_observation(self, agent: int, t: int, level: int) -> None:
        """A robot's observation of its task at step t (kept for the episode log)."""
        self.observed[(t, agent)] = int(level)

    @property
    def levels_known(self) -> bool:
        """Whether the true levels of every step so far were reported."""
        return all(t in self.reported for t in range(self.t + 1))

    def metrics(self, now: float | None = None) -> list[dict[str, Any]]:
        """The episode's metrics: as the simulated world's when every level was reported, else unknown (-1)."""
        if self.levels_known and self.action_log:
            self.level_log = [self.reported[t].reshape(1, -1) for t in range(self.t + 1)]
            out = super().metrics(now)
            out[0]["severity"] = "reported"
            return out
        seconds = round((time.monotonic() if now is None else now) - self.started, 6)
        return [
            {
                "episode": self.episode,
                "severity": "unknown",
                "completion": -1,
                "failed": False,
                "unused_capability": -1.0,
                "unused_fraction": -1.0,
                "idle_before": -1,
                "reassign_before": -1,
                "absent": [int(x) for x in self.absent],
                "seconds": seconds,
            }
        ]

    def trajectory(self, i: int = 0) -> dict[str, Any]:
        """The episode: levels (t+1 rows, None where not reported), applied actions (t, N), the robots'
        observations (t, N; -1 where none arrived)."""
        n = self.scenario.n_agents
        return {
            "levels": [self.reported[t].tolist() if t in self.reported else None for t in range(self.t + 1)],
            "actions": np.stack(self.action_log)[:, 0].tolist() if self.action_log else [],
            "observations": [[self.observed.get((t, k), -1) for k in range(n)] for t in range(1, self.t + 1)],
        }


# ----- the protocol -----------------------------------------------------------------------------------------------
