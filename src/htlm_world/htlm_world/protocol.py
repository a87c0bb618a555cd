"""The world's side of the lockstep protocol, without ROS: settings of the world node and one episode's state.

The world node (world_node.py) only moves messages and deadlines; this module applies the model. One episode
of batch 1 draws from seeds.world(seed, episode) exactly as the in-process Team(scenario, 1, seed, episode) does,
so with the same actions both runtimes produce the same levels and observations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from htlm_world.metrics import episode_metrics
from htlm_world.model import Model
from htlm_world.scenario import TEAMS, Scenario, ScenarioError, builtin, load
from htlm_world import seeds
from htlm_world.simulator import sample_world_step
from htlm_world.types import IntArray


@dataclass(frozen=True)
class WorldSettings:
    """Parameters of the world node (one ROS parameter per field)."""

    scenario: str = ""
    """Scenario YAML file; empty: the built-in scenario "paper" with `team`."""
    team: str = "heterogeneous"
    """Built-in team when `scenario` is empty."""
    seed: int = 0
    """Master seed of the run: the world and every agent derive their generators from it."""
    mode: str = "evaluate"
    """train (agents explore and send transitions), evaluate or deploy (greedy policies)."""
    episodes: int = 10
    """Episodes to run; 0 runs until stopped (may be changed while running: the run ends after that many)."""
    first_episode: int = 0
    """Index of the first episode (seeds are derived from the episode index)."""
    clock: str = "lockstep"
    """lockstep: advance as soon as every live agent answered; free: one step every `period` seconds."""
    period: float = 0.5
    """Step period of the free-running clock, seconds."""
    act_deadline: float = 2.0
    """Longest wait for the agents' actions of a step, seconds; a silent agent is idle for that step."""
    update_deadline: float = 2.0
    """Longest wait for the agents' ready after their belief update, seconds."""
    begin_deadline: float = 3.0
    """Longest wait at the start of an episode for agents to reset (a restarted agent rejoins here), seconds."""
    join_timeout: float = 60.0
    """Longest wait at the start of the run for every agent to be up, seconds."""
    linger: float = 1.0
    """Seconds to keep running after the last episode so every node sees the run stop."""
    run_id: str = ""
    """Run identifier announced on /htlm/scenario; empty: derived from the seed and the clock."""
    run_dir: str = ""
    """Directory for the world's episode log (world.jsonl); empty: no file."""
    diagnostics_period: float = 1.0
    """Seconds between /diagnostics messages."""
    executor: str = "events"
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


def validate_world_settings(s: WorldSettings) -> list[str]:
    """Problems of a WorldSettings, each naming the parameter and the value (empty when valid)."""
    bad: list[str] = []
    if s.scenario == "" and s.team not in TEAMS:
        bad.append(f"team: {s.team!r} is not one of {sorted(TEAMS)}")
    if s.seed < 0:
        bad.append(f"seed: {s.seed!r} must be >= 0")
    if s.mode not in ("train", "evaluate", "deploy"):
        bad.append(f"mode: {s.mode!r} is not one of train, evaluate, deploy")
    if s.episodes < 0:
        bad.append(f"episodes: {s.episodes!r} must be >= 0")
    if s.first_episode < 0:
        bad.append(f"first_episode: {s.first_episode!r} must be >= 0")
    if s.clock not in ("lockstep", "free"):
        bad.append(f"clock: {s.clock!r} is not one of lockstep, free")
    for name in ("period", "act_deadline", "update_deadline", "begin_deadline", "join_timeout", "diagnostics_period"):
        v = getattr(s, name)
        if not 0.0 < v <= 3600.0:
            bad.append(f"{name}: {v!r} must be in (0, 3600] seconds")
    if not 0.0 <= s.linger <= 60.0:
        bad.append(f"linger: {s.linger!r} must be in [0, 60] seconds")
    if s.run_id and not all(c.isalnum() or c in "_.:-" for c in s.run_id):
        bad.append(f"run_id: {s.run_id!r} may hold only letters, digits and _.:-")
    if s.executor not in ("events", "single"):
        bad.append(f"executor: {s.executor!r} is not one of events, single")
    return bad


def load_scenario(s: WorldSettings) -> Scenario:
    """The scenario the settings name (a file, else the built-in one with the team).

    Raises:
        ScenarioError: the file is missing or invalid.
    """
    if s.scenario:
        return load(s.scenario)
    if s.team not in TEAMS:
        raise ScenarioError(f"team: {s.team!r} is not one of {sorted(TEAMS)}")
    return builtin(s.team)


@dataclass
class StepOutcome:
    """What the world produced in one step."""

    actions: IntArray  # (N,) joint assignment applied (absent agents idle at their site; -1 in HT mode)
    acted: list[int]  # agents whose own action was applied
    levels: IntArray  # (p,) true levels after the transition
    observations: IntArray  # (N,) observed level of each agent's task, -1 when idle or absent


class WorldEpisode:
    """One episode of the operation as the world process runs it: batch 1, its own world generator."""

    def __init__(self, scenario: Scenario, model: Model, seed: int, episode: int) -> None:
        """Start episode `episode` of the run with master seed `seed` at the initial levels."""
        self.scenario = scenario
        self.model = model
        self.episode = episode
        self.rng = seeds.world(seed, episode)
        n = scenario.n_agents
        self.levels: IntArray = np.array([scenario.initial_levels], dtype=np.int64)  # (1, p)
        self.prev: IntArray = np.full(n, scenario.start_assignment, dtype=np.int64)
        self.t = 0
        self.absent = np.zeros(n, dtype=np.int64)
        self.level_log: list[IntArray] = [self.levels[0].copy()]
        self.action_log: list[IntArray] = []
        self.obs_log: list[IntArray] = []
        self.started = time.monotonic()

    def idle_action(self, agent: int) -> int:
        """What an absent agent does: idle at the site of its previous assignment (HT mode: nothing, -1)."""
        sc = self.scenario
        if sc.n_idle == 0:
            return -1
        prev = int(self.prev[agent])
        site = int(self.model.action_site[prev]) if prev >= 0 else 0
        return sc.n_tasks + site

    def step(self, chosen: dict[int, int]) -> StepOutcome:
        """Apply T to the joint assignment: `chosen` maps agent -> action; every other agent is absent (idle)."""
        n = self.scenario.n_agents
        actions = np.empty(n, dtype=np.int64)
        acted = []
        for k in range(n):
            a = chosen.get(k)
            if a is None:
                actions[k] = self.idle_action(k)
                self.absent[k] += 1
            else:
                actions[k] = a
                acted.append(k)
        nxt, obs, _caps = sample_world_step(self.model, self.levels, actions[None, :], self.rng)
        self.levels = nxt
        self.prev = np.where(actions >= 0, actions, self.prev)
        self.t += 1
        self.level_log.append(nxt[0].copy())
        self.action_log.append(actions)
        self.obs_log.append(obs[0].copy())
        return StepOutcome(actions=actions, acted=acted, levels=nxt[0], observations=obs[0])

    def metrics(self) -> dict[str, Any]:
        """The episode_metrics record of the finished episode (docs/model.md metrics plus absences)."""
        sc = self.scenario
        levels = np.stack(self.level_log)[:, None, :]  # (t+1, 1, p)
        actions = np.stack(self.action_log)[:, None, :]  # (t, 1, N)
        m = episode_metrics(sc, levels, actions)
        return {
            "episode": self.episode,
            "completion": int(m.completion[0]),
            "failed": bool(m.failed[0]),
            "unused_capability": float(m.unused_capability[0]),
            "unused_fraction": float(m.unused_fraction[0]),
            "idle_before": int(m.idle_before[0]),
            "reassign_before": int(m.reassign_before[0]),
            "absent": [int(x) for x in self.absent],
            "seconds": round(time.monotonic() - self.started, 6),
        }

    def trajectory(self) -> dict[str, Any]:
        """Levels (t+1, p), applied actions (t, N) and observations (t, N) as lists, for the run log."""
        return {
            "levels": np.stack(self.level_log).tolist(),
            "actions": np.stack(self.action_log).tolist() if self.action_log else [],
            "observations": np.stack(self.obs_log).tolist() if self.obs_log else [],
        }
