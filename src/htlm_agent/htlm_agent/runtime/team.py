"""The in-process runtime: a batch of episodes of a whole team, simulator + every agent's belief and reward.

This is the same model code the ROS nodes call; here all agents and B episodes advance as arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.mind.context import Context, Policy
from htlm_agent.mind.reward import RewardTables, reward
from htlm_world import seeds
from htlm_world.events import EventRun
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.simulator import BatchSim, StepResult
from htlm_world.travel import TravelState, working_actions
from htlm_world.types import BoolArray, FloatArray, IntArray


@dataclass
class StepInfo:
    """Side results of one team step."""

    levels: IntArray  # (B, p) true levels after the step
    observations: IntArray
    messages: IntArray
    parts: dict[str, FloatArray]
    impossible: BoolArray  # (B, N) zero-probability evidence events
    actions: IntArray  # (B, N) the joint assignment applied (inactive and dropped-out agents idle)
    events: BoolArray  # (B, E) the scenario's events that happened in the step
    working: IntArray | None = None  # (B, N) the assignment as applied with travel: -1 for an agent on its way


class Team:
    """B episodes of a team in one process."""

    def __init__(
        self,
        scenario: Scenario,
        batch: int,
        seed: int,
        episode: int = 0,
        inactive: tuple[int, ...] = (),
    ) -> None:
        """Create the team.

        Args:
            scenario: the operation and the team.
            batch: B episodes advanced together.
            seed: master seed; the world and every channel take their streams from it and `episode` (`seeds`).
            episode: index of this batch (episode index when batch = 1), for seed derivation.
            inactive: agents forced to idle (at the site of their previous assignment) whatever they choose.
        """
        self.scenario = scenario
        self.model = Model.build(scenario)
        self.tables = RewardTables.build(scenario)
        self.batch = batch
        self.inactive = tuple(inactive)
        self.dropped: BoolArray | None = None
        """(B, N) agents that sit out single episodes (training for resilience); None: nobody."""
        for k in self.inactive:
            if not 0 <= k < scenario.n_agents:
                raise ValueError(f"inactive agent index {k!r} is out of range 0..{scenario.n_agents - 1}")
        self.sim = BatchSim(
            scenario,
            batch,
            seeds.world(seed, episode),
            [seeds.channel(seed, k, episode) for k in range(scenario.n_agents)],
        )
        self.event_rng = seeds.events(seed, episode)
        """The generator of the scenario's events (`htlm_world.events`); training sets its own per batch."""
        self.travel = TravelState(scenario, batch) if scenario.travel else None
        """Where every agent is (`htlm_world.travel`); None without travel."""
        self.filter = bf.filter_tables(self.model)
        self._work = (self._new_sites(), self._new_sites())  # scratch of the filter
        self._spare = self._new_sites()  # where the next step writes its beliefs (the step after swaps them back)
        self.impossible_count = 0
        self.reset()

    def _new_sites(self) -> FloatArray:
        """Site-major beliefs (L^K, S, N, B): the episodes innermost, so that every operation of the filter runs
        over long contiguous rows and the capability coefficients of a step (L^K, S, 1, B) broadcast over agents."""
        sc = self.scenario
        return np.empty((sc.levels**self.filter.slots, sc.n_sites, sc.n_agents, self.batch))

    @property
    def belief(self) -> FloatArray:
        """Every agent's belief (B, N, S, L, ..., L): a view of the site-major beliefs the filter keeps
        (`belief.to_sites` of the (N, B) agent-major batch), so writing into it changes the team's beliefs until the
        next step. The team keeps two such arrays and writes a step's beliefs into the one its step before last
        left: copy a view to keep it beyond the next step."""
        sc = self.scenario
        view: FloatArray = bf.from_sites(self.sites, sc.levels, self.filter.slots).swapaxes(0, 1)
        return view

    def reset(self) -> FloatArray:
        """Start B new episodes; returns the knowledge states (B, N, K)."""
        sc = self.scenario
        self.sim.reset()
        if self.travel is not None:
            self.travel.reset()
        self.events = EventRun(sc, self.batch, self.event_rng)
        self._fired: BoolArray | None = None
        b0 = bf.initial_belief(self.model, self.batch)
        self.sites = self._new_sites()
        self.sites[...] = bf.to_sites(b0.swapaxes(0, 1), self.filter.slots)
        self.prev = np.full((self.batch, sc.n_agents), sc.start_assignment, dtype=np.int64)
        self.heard = np.ones((self.batch, sc.n_agents), dtype=bool)
        """(B, N) the teammates whose broadcast arrived at the last step (in process every message arrives: all but
        those sitting out); everyone before the first step."""
        self.marg = self._marginals()
        self.t = 0
        self._knowledge = self._build_knowledge()
        return self.knowledge()

    def _marginals(self) -> FloatArray:
        """Per-task marginals (B, N, p, L) of the beliefs (`belief.marginals`), as a view of level-major (L, p, N, B)
        ones: the reward's passes over levels and tasks then run over long contiguous rows."""
        sc = self.scenario
        slots = bf.marginals_sites(self.sites, sc.levels, self.filter.slots)  # each (L, S, N, B)
        marg: FloatArray = bf.task_marginals(self.model, slots).transpose(3, 2, 1, 0)
        return marg

    def _build_knowledge(self) -> FloatArray:
        """K of every agent (B, N, K) from the marginals, a_o and (with `Scenario.roster`) who was heard from, (with
        `Scenario.teammates`) where the teammates were: in process every broadcast arrives, so every agent knows the
        whole joint assignment of the last step."""
        sc = self.scenario
        roster = self.heard[:, None, :] | np.eye(sc.n_agents, dtype=bool)[None] if sc.roster else None
        mates = knowledge.teammates_of(self.model, self.prev) if sc.teammates else None
        places = None
        if self.travel is not None:  # every broadcast carries its sender's place and arrival
            places = knowledge.places_of(self.travel.goal, self.travel.eta())[:, None, :]
        return knowledge.build(self.marg, self.prev, sc.n_actions, roster, mates, places)

    def _sitting_out(self) -> BoolArray:
        """(B, N) the agents that sit out the step: kept out by an event, inactivated or dropped."""
        out = self.events.out.copy()
        out[:, list(self.inactive)] = True
        if self.dropped is not None:
            out |= self.dropped
        return out

    def knowledge(self) -> FloatArray:
        """Current knowledge states (B, N, K)."""
        return self._knowledge.copy()

    def mask(self) -> BoolArray:
        """Current A-hat(a_o) of every agent (B, N, |G|)."""
        return self.model.action_mask(self.prev)

    def context(self) -> Context:
        """What policies see now."""
        return Context(self.knowledge(), self.mask(), self.marg, self.prev.copy(), self.t, self.sim.levels.copy())

    def _next_events(self) -> BoolArray:
        """The events of the next step, decided once on the true levels now (`EventRun.begin_step`) by the first
        of `force_inactive` and `step` that needs them: who is out and the levels its transition starts from."""
        if self._fired is None:
            self._start, self._fired = self.events.begin_step(self.sim.t + 1, self.sim.levels)
        return self._fired

    def force_inactive(self, actions: IntArray) -> IntArray:
        """Replace the actions of inactivated agents by idling at their current site (HT mode: no action): the
        agents of `inactive` in every episode, those `dropped` (B, N) marks in single episodes and those the
        scenario's events keep out."""
        self._next_events()
        actions = self.events.force(self.model, actions, self.prev)
        if not self.inactive and self.dropped is None:
            return actions
        actions = actions.copy()
        for k in self.inactive:
            actions[:, k] = self.model.idle_action(self.prev[:, k])
        if self.dropped is not None:
            idle = self.model.idle_action(self.prev)
            actions = np.where(self.dropped, idle, actions)
        return actions

    def _sit_out(self, actions: IntArray, res: StepResult) -> None:
        """Inactivated and dropped agents and those an event keeps out observe nothing and broadcast no level,
        standing by or not (as an absent agent over ROS: `WorldEpisode.step`); the simulator's draws stay as they
        were."""
        out = self._sitting_out()
        res.observations[out] = -1
        res.messages[out] = -1

    def step(self, actions: IntArray) -> tuple[FloatArray, FloatArray, StepInfo]:
        """One step of the data flow of docs/architecture.md for every agent of every episode.

        Returns the next knowledge states (B, N, K), rewards (B, N) and side results.
        """
        actions = self.force_inactive(np.asarray(actions, dtype=np.int64))
        fired = self._next_events()
        self.sim.levels = self._start
        self._fired = None
        working = None
        if self.travel is not None:  # an agent on its way works on nothing and observes nothing
            working = working_actions(actions, self.travel.step(actions))
        applied = actions if working is None else working
        res = self.sim.step(applied)
        if self.model.standby_class >= 0:
            self._sit_out(applied, res)
        liks = bf.evidence_sites(self.model, applied, res.observations, res.messages, self.t + 1)  # (L, S, N, B)
        caps = self.filter.slot_caps(res.caps.T[:, None, :])  # (S, 1, B): every agent assumes the step's joint
        new, bad_site = bf.update_sites(self.filter, self.sites, caps, liks, self._spare, self._work)
        self.sites, self._spare = new, self.sites
        bad = np.asarray(bad_site.any(axis=0).T, dtype=np.bool_)  # (B, N)
        self.impossible_count += int(bad.sum())
        prior = self.marg.copy() if self.tables.difference.any() else None
        self.marg = self._marginals()
        r, parts = reward(self.model, self.tables, self.prev, self.marg, actions, prior)
        self.prev = np.where(actions >= 0, actions, self.prev)
        self.t += 1
        if self.scenario.roster:
            self.heard = ~self._sitting_out()
        info = StepInfo(res.levels, res.observations, res.messages, parts, bad, actions, fired, working)
        self._knowledge = self._build_knowledge()
        return self.knowledge(), r, info


@dataclass
class Trajectory:
    """Everything of B episodes, for metrics, plots and equivalence checks."""

    levels: IntArray  # (h+1, B, p) true levels, levels[0] the initial ones
    actions: IntArray  # (h, B, N)
    observations: IntArray  # (h, B, N)
    messages: IntArray  # (h, B, N)
    rewards: FloatArray  # (h, B, N)
    extra: dict[str, FloatArray] = field(default_factory=dict)


def rollout(team: Team, policy: Policy) -> Trajectory:
    """Run the B episodes of `team` for the whole horizon under `policy`."""
    sc = team.scenario
    team.reset()
    levels = [team.sim.levels.copy()]
    acts, obs, msgs, rews = [], [], [], []
    for _ in range(sc.horizon):
        a = team.force_inactive(policy.act(team.context()))
        _, r, info = team.step(a)
        levels.append(info.levels)
        acts.append(a)
        obs.append(info.observations)
        msgs.append(info.messages)
        rews.append(r)
    return Trajectory(np.stack(levels), np.stack(acts), np.stack(obs), np.stack(msgs), np.stack(rews))
