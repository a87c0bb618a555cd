"""The batched simulator: B episodes of the operation advance together in numpy.

Random draws come from generators the caller passes: one for the world (transitions and observations) and one per
agent for its simulated channel, so the ROS runtime (world process + agent processes) can draw the very same numbers
in the very same order. Per step and in this order the world draws u_T (B, p) then u_O (B, N); every agent k draws
(B, 2) from its channel generator whether it worked or not. Runs take these generators from `htlm_world.seeds`
(`seeds.world`, `seeds.channel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import Actions, IntArray, Levels, Messages, Observations


@dataclass
class StepResult:
    """What one step produced."""

    levels: Levels  # (B, p) true levels after the transition
    observations: Observations  # (B, N) z of each observing agent (`Model.observes`), -1 if none
    messages: Messages  # (B, N) level each agent's broadcast carries after its channel, -1 if none
    caps: IntArray  # (B, p) joint capability of the step


def sample_world_step(
    model: Model, levels: Levels, actions: Actions, rng: np.random.Generator, t: int | None = None
) -> tuple[Levels, Observations, IntArray]:
    """Apply T to the joint assignment of step t (1..h) and draw every observing agent's observation O
    (docs/model.md; which task an agent observes: `Model.observes`, which needs t when the scenario has standby).

    Returns the next levels, the observations (-1 for agents that observe nothing) and the joint capabilities.
    """
    sc = model.scenario
    b, n = actions.shape
    p = sc.n_tasks
    caps = model.joint_capability(actions)
    u_t = rng.random((b, p))
    nxt = model.sample_transition(levels, caps, u_t)
    u_o = rng.random((b, n))  # one draw per agent, observing or not: the streams do not depend on who observes
    target, cls = model.observes(actions, t)
    seen = target >= 0
    task = np.where(seen, target, 0)
    true = nxt.reshape(-1)[task + p * np.arange(b)[:, None]]
    z = model.sample_observation(task, true, model.sensing, u_o, None if model.standby_class < 0 else cls)
    return nxt, np.where(seen, z, -1), caps


def sample_channel(model: Model, agent: int, observation: IntArray, rng: np.random.Generator) -> IntArray:
    """Agent `agent`'s broadcast levels after its simulated channel, for a batch of its observations (B,)."""
    u = rng.random((observation.shape[0], 2))
    sent = model.apply_channel(observation, model.keep[agent], u[:, 0], u[:, 1])
    return np.where(observation >= 0, sent, -1)


class BatchSim:
    """B episodes of one scenario, stepped together."""

    def __init__(
        self,
        scenario: Scenario,
        batch: int,
        rng: np.random.Generator,
        channel_rngs: list[np.random.Generator] | None = None,
    ) -> None:
        """Create the simulator.

        Args:
            scenario: the operation.
            batch: B, the number of episodes stepped together (>= 1).
            rng: the world's generator (transitions, observations).
            channel_rngs: one generator per agent for its channel; derived from rng when None.
        """
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch!r}")
        self.scenario = scenario
        self.model = Model.build(scenario)
        self.batch = batch
        self.rng = rng
        if channel_rngs is None:
            channel_rngs = [np.random.default_rng(s) for s in rng.bit_generator.seed_seq.spawn(scenario.n_agents)]  # type: ignore[attr-defined]
        if len(channel_rngs) != scenario.n_agents:
            raise ValueError(f"need {scenario.n_agents} channel generators, got {len(channel_rngs)}")
        self.channel_rngs = channel_rngs
        self.levels: Levels = np.empty((batch, scenario.n_tasks), dtype=np.int64)
        self.t = 0
        self.reset()

    def reset(self) -> Levels:
        """Start B new episodes at the initial levels; returns a copy of the levels."""
        self.levels = np.tile(np.array(self.scenario.initial_levels, dtype=np.int64), (self.batch, 1))
        self.t = 0
        return self.levels.copy()

    def step(self, actions: Actions) -> StepResult:
        """Advance every episode one step under the joint assignment `actions` (B, N)."""
        assert actions.shape == (self.batch, self.scenario.n_agents), actions.shape
        nxt, obs, caps = sample_world_step(self.model, self.levels, actions, self.rng, self.t + 1)
        # every agent's channel draws (B, 2) from its own generator, as `sample_channel` does
        u = np.empty((self.scenario.n_agents, self.batch, 2))
        for k, g in enumerate(self.channel_rngs):
            g.random(out=u[k])
        obs_t = obs.T
        sent = self.model.apply_channel(obs_t, self.model.keep[:, None], u[..., 0], u[..., 1])
        msgs = np.ascontiguousarray(np.where(obs_t >= 0, sent, -1).T)
        self.levels = nxt
        self.t += 1
        return StepResult(levels=nxt.copy(), observations=obs, messages=msgs, caps=caps)

    @property
    def complete(self) -> np.ndarray:
        """(B,) whether every task is at level 0."""
        return np.asarray((self.levels == 0).all(axis=1))
