"""What a policy sees when it acts (`Context`) and what a policy is (`Policy`): shared by the in-process runtime, the
baselines, the Q-policy and the agent processes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from htlm_world.types import BoolArray, FloatArray, IntArray


@dataclass
class Context:
    """What a policy may look at when it acts (decentralized policies use only their own row)."""

    knowledge: FloatArray  # (B, N, K) each agent's knowledge state
    mask: BoolArray  # (B, N, |G|) the reduced action space A-hat(a_o)
    marginals: FloatArray  # (B, N, p, L)
    prev: IntArray  # (B, N) previous assignments
    t: int  # steps taken so far in the episode
    true_levels: IntArray  # (B, p) ground truth: only the centralized optimum may read it


class Policy(Protocol):
    """Anything that maps a Context to a joint action (B, N)."""

    def act(self, ctx: Context) -> IntArray:
        """Choose every agent's action."""
        ...


class RowsPolicy(Policy, Protocol):
    """A decentralized team policy that can work out some agents' actions alone: agent i reads only row i of the
    Context, so an agent process asks for its own column without computing its teammates' (`RowPolicy`)."""

    def act_rows(self, ctx: Context, who: IntArray) -> IntArray:
        """The actions (B, R) of the agents `who` (R,), each from its own row of the Context (`act` is
        `act_rows` of every agent)."""
        ...
