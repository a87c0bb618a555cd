"""The policies an agent process runs by name, without a trained network (the agent node's `policy:=NAME`,
`htlm launch --policy NAME`): the heuristics of `baselines.heuristics`, QMDP where the optimum can be computed, and
the lookahead with its value network fitted on the spot."""

from __future__ import annotations

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy
from htlm_agent.mind.policies import AgentPolicy, RowPolicy
from htlm_world.scenario import Scenario

BUILTIN_POLICIES = ("greedy", "auction", "qmdp", "lookahead", "random")
"""The names of `builtin_policy`."""


def builtin_policy(scenario: Scenario, name: str, agent: int) -> tuple[AgentPolicy, float]:
    """A policy that needs no network, and its ε (one of `BUILTIN_POLICIES`): "greedy" (`GreedyPolicy` on the
    agent's own row), "auction" (`AuctionPolicy`: the auction the agent runs on its own belief, keeping its own
    assignment), "qmdp" (`QmdpPolicy`, where the optimum can be computed), "lookahead" (`LookaheadPolicy`: its value
    network fitted here, a few seconds, the same in every process) or "random" (uniform over Â(a_o) from the agent's
    exploration generator, ε = 1)."""
    if name not in BUILTIN_POLICIES:
        raise ValueError(f"unknown built-in policy {name!r}; choose one of {', '.join(BUILTIN_POLICIES)}")
    if name == "auction":
        return RowPolicy(scenario, AuctionPolicy(scenario), agent), 0.0
    if name == "qmdp":
        from htlm_agent.baselines.optimal import QmdpPolicy  # the optimum's code: only when asked for

        return RowPolicy(scenario, QmdpPolicy(scenario), agent), 0.0
    if name == "lookahead":
        from htlm_agent.learning.lookahead import AgentLookahead, LookaheadPolicy  # torch: only when asked for

        return AgentLookahead(scenario, LookaheadPolicy(scenario), agent), 0.0
    return RowPolicy(scenario, GreedyPolicy(scenario), agent), (1.0 if name == "random" else 0.0)
