"""One agent's decision rule and ε-greedy exploration (docs/model.md, Reduced action space), shared by every runtime.

`team_epsilon_greedy` is the one definition of exploration: the in-process learner (`Learner.act`) calls it for the
whole team, and the agent processes over ROS (`AgentMind`, through `choose`) and `DecentralizedPolicy` (the ROS
agents' rule inside `team.rollout`) call it for one agent (`epsilon_greedy`), each agent with its own generator from
`htlm_world.seeds`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from htlm_agent.mind.context import Context, RowsPolicy
from htlm_agent.mind.knowledge import split as split_knowledge
from htlm_world import seeds
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray


class AgentPolicy(Protocol):
    """One agent's decision rule on its own knowledge: (B, K) knowledge and (B, |G|) mask -> (B,) actions."""

    def act(self, knowledge: FloatArray, mask: BoolArray) -> IntArray:
        """Choose an action in the mask for every row."""
        ...


def epsilon_greedy(
    greedy: IntArray, mask: BoolArray, epsilon: float | FloatArray, rng: np.random.Generator
) -> IntArray:
    """ε-greedy over the reduced action space Â(a_o) for one agent: with probability ε a uniform action of the mask,
    else the greedy one.

    Two uniforms (u_explore, u_action) are drawn per row whatever ε is, so the generator stays in step: the row
    explores when u_explore < ε and then takes the ⌊u_action · |Â|⌋-th allowed action.

    Args:
        greedy: (B,) the policy's actions (in the mask).
        mask: (B, |Ḡ|) Â(a_o) of every row.
        epsilon: ε, one number or one per row (B,).
        rng: this agent's exploration generator.

    Returns:
        (B,) actions.
    """
    greedy = np.asarray(greedy, dtype=np.int64)
    return team_epsilon_greedy(greedy[:, None], mask[:, None], epsilon, [rng])[:, 0]


def team_epsilon_greedy(
    greedy: IntArray, mask: BoolArray, epsilon: float | FloatArray, rngs: Sequence[np.random.Generator]
) -> IntArray:
    """`epsilon_greedy` for N agents at once, agent i with its own generator rngs[i] (the same draws and actions as
    N calls): greedy (B, N), mask (B, N, |Ḡ|), ε one number or one per row (B,) -> (B, N) actions."""
    greedy = np.asarray(greedy, dtype=np.int64)
    b, n = greedy.shape
    u = np.empty((n, b, 2))
    for i, rng in enumerate(rngs):
        rng.random(out=u[i])  # what rng.random((B, 2)) draws
    eps = epsilon if np.ndim(epsilon) == 0 else np.asarray(epsilon)[:, None]
    allowed = mask.sum(axis=-1)  # (B, N)
    nth = np.minimum((u[..., 1].T * allowed).astype(np.int64), allowed - 1)
    uniform = (np.cumsum(mask, axis=-1) > nth[..., None]).argmax(axis=-1)
    out = np.where(np.less(u[..., 0].T, eps), uniform, greedy).astype(np.int64)
    assert np.take_along_axis(mask, out[..., None], axis=-1).all(), f"policy chose {out} outside the mask {mask}"
    return out


def choose(
    policy: AgentPolicy, knowledge: FloatArray, mask: BoolArray, epsilon: float | FloatArray, rng: np.random.Generator
) -> IntArray:
    """`epsilon_greedy` around an agent policy: (B, K) knowledge and (B, |Ḡ|) masks -> (B,) actions."""
    return epsilon_greedy(np.asarray(policy.act(knowledge, mask), dtype=np.int64), mask, epsilon, rng)


class RowPolicy:
    """Agent `agent`'s column of a decentralized team policy (a `RowsPolicy`, whose agent i reads only row i of the
    Context, such as `GreedyPolicy` and `AuctionPolicy`), fed with that agent's own knowledge state and mask: only
    that agent's action is worked out, so an agent's step does not grow with its teammates' work."""

    def __init__(self, scenario: Scenario, policy: RowsPolicy, agent: int) -> None:
        """Wrap `policy` for agent index `agent`."""
        self.scenario = scenario
        self.policy = policy
        self.agent = agent

    def context(self, knowledge: FloatArray, mask: BoolArray) -> Context:
        """The team policy's Context with the agent's own (B, K) knowledge and (B, |Ḡ|) mask in every row."""
        n = self.scenario.n_agents
        return knowledge_context(
            self.scenario, np.repeat(knowledge[:, None], n, axis=1), np.repeat(mask[:, None], n, axis=1)
        )

    def act(self, knowledge: FloatArray, mask: BoolArray) -> IntArray:
        """See AgentPolicy.act: read the agent's marginals and a_o from K = {b, a_o} and ask the team policy."""
        who = np.array([self.agent])
        return np.asarray(self.policy.act_rows(self.context(knowledge, mask), who)[:, 0], dtype=np.int64)


def knowledge_context(scenario: Scenario, knowledge: FloatArray, mask: BoolArray) -> Context:
    """The Context of a decentralized team policy read from knowledge states alone: (B, N, K) knowledge and
    (B, N, |G|) masks; agent i's row holds its marginals and a_o from its own K = {b, a_o} (what every agent process
    has), no step count and no true levels (decentralized policies read neither)."""
    marg, prev = split_knowledge(knowledge, scenario)
    return Context(
        knowledge=knowledge,
        mask=mask,
        marginals=np.asarray(marg, dtype=np.float64),
        prev=prev,
        t=0,
        true_levels=np.zeros((knowledge.shape[0], scenario.n_tasks), dtype=np.int64),
    )


class DecentralizedPolicy:
    """The in-process Team policy made of independent per-agent policies, each on its own row of the context,
    with ε-greedy from `seeds.explore(seed, agent, episode)`: what the agent processes do over ROS."""

    def __init__(self, policies: list[AgentPolicy], seed: int, epsilon: float | list[float] = 0.0) -> None:
        """One policy per agent; call `begin(episode)` before each `team.rollout` of batch 1."""
        self.policies = policies
        self.seed = seed
        self.epsilon = [epsilon] * len(policies) if isinstance(epsilon, float) else list(epsilon)
        self.rngs: list[np.random.Generator] = []

    def begin(self, episode: int) -> None:
        """Take every agent's exploration generator of `episode`."""
        self.rngs = [seeds.explore(self.seed, i, episode) for i in range(len(self.policies))]

    def act(self, ctx: Context) -> IntArray:
        """Every agent's action from its own knowledge and mask (B, N)."""
        assert self.rngs, "call begin(episode) first"
        cols = [
            choose(pol, ctx.knowledge[:, i], ctx.mask[:, i], self.epsilon[i], self.rngs[i])
            for i, pol in enumerate(self.policies)
        ]
        return np.stack(cols, axis=1)
