"""The decentralized team policy of the agents' Q-networks: every agent acts greedily on its own network, its own
knowledge state and its own Â(a_o)."""

from __future__ import annotations

import numpy as np
import torch

from htlm_agent.learning.checkpoint import Checkpoint
from htlm_agent.learning.qnet import QNetwork, build_network, masked_argmax
from htlm_agent.mind.context import Context
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray


def greedy_actions(net: QNetwork, knowledge: FloatArray, mask: BoolArray) -> IntArray:
    """Every agent's masked argmax of its own network: knowledge (B, N, K) and masks (B, N, |Ḡ|) -> (B, N)."""
    x = torch.from_numpy(np.ascontiguousarray(knowledge.transpose(1, 0, 2), dtype=np.float32))
    m = torch.from_numpy(np.ascontiguousarray(mask.transpose(1, 0, 2)))
    with torch.no_grad():
        a = masked_argmax(net.forward(x), m)  # (N, B)
    return np.ascontiguousarray(a.numpy().T, dtype=np.int64)


class QPolicy:
    """The decentralized team policy of stacked Q-networks: every agent takes the greedy masked argmax of its own
    network over its own knowledge state and Â (its own row of the Context only)."""

    def __init__(self, scenario: Scenario, net: QNetwork) -> None:
        """Wrap networks (not copied: the policy follows later training)."""
        assert net.n_agents == scenario.n_agents and net.sizes[0] == scenario.knowledge_size, "another layout"
        self.scenario = scenario
        self.net = net

    @staticmethod
    def from_checkpoint(ckpt: Checkpoint) -> QPolicy:
        """The policy of a loaded checkpoint."""
        net = build_network(ckpt.scenario, ckpt.settings, ckpt.weights)
        net.requires_grad_(False)
        return QPolicy(ckpt.scenario, net)

    def act(self, ctx: Context) -> IntArray:
        """Greedy actions (B, N)."""
        return greedy_actions(self.net, ctx.knowledge, ctx.mask)
