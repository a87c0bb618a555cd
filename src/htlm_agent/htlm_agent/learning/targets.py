"""The Bellman targets of the DQN update (Eq. 10 of the paper), the advantage-learning gap and n-step returns.

Shapes follow the stacked learner: a leading agent axis (N, M, ...) for minibatches of every agent.
"""

from __future__ import annotations

from typing import Any

import torch

from htlm_agent.learning.qnet import masked_argmax, masked_max


def bellman_targets(
    r: torch.Tensor,
    discount: torch.Tensor,
    q_next_target: torch.Tensor,
    mask2: torch.Tensor,
    q_next_online: torch.Tensor | None = None,
) -> torch.Tensor:
    """y = r + d · max_{a' ∈ Â(K')} Q(K', a'; θ̂) (Eq. 10 of the paper, the Bellman target), with d = γ (one step),
    γ^n (an n-step return r), or 0 (terminal K').

    With `q_next_online` (Double DQN) the maximising a' is chosen by the online network and valued by the target
    network. Shapes: r, discount (..., M); q's and mask2 (..., M, |Ḡ|).
    """
    if q_next_online is None:
        nxt = masked_max(q_next_target, mask2)
    else:
        a2 = masked_argmax(q_next_online, mask2)
        nxt = q_next_target.gather(-1, a2[..., None])[..., 0]
    return torch.addcmul(r, discount, nxt)


def advantage_gap(q_target: torch.Tensor, mask: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """max_{b ∈ Â(K)} Q̂(K, b) − Q̂(K, a) >= 0, the term advantage learning subtracts (scaled by α) from the target."""
    return masked_max(q_target, mask) - q_target.gather(-1, a[..., None])[..., 0]


class NStep:
    """Turns a stream of one-step transitions (of one agent, or of arrays of agents and episodes advancing in
    lockstep) into n-step transitions <K_t, a_t, Σ_{j<m} γ^j r_{t+j}, K_{t+m}, Â(K_{t+m}), d> with m = n, or fewer at
    the end of an episode, and d = γ^m, or 0 when the episode ends in a terminal state. Rewards are scaled here."""

    def __init__(self, n: int, gamma: float, scale: float = 1.0) -> None:
        """An empty window of n steps."""
        self.n, self.gamma, self.scale = n, gamma, scale
        self.items: list[tuple[Any, Any, Any]] = []

    def _emit(self, k2: Any, mask2: Any, terminal: bool) -> tuple[Any, ...]:
        k, a, _ = self.items[0]
        ret = sum((self.gamma**j) * r for j, (_, _, r) in enumerate(self.items))
        disc = 0.0 if terminal else self.gamma ** len(self.items)
        self.items.pop(0)
        return k, a, ret * self.scale, k2, mask2, disc

    def push(self, k: Any, a: Any, r: Any, k2: Any, mask2: Any, end: bool, terminal: bool) -> list[tuple[Any, ...]]:
        """Add the step (K, a, r, K', Â(K')); returns the transitions complete now (all pending ones at the end of an
        episode, `end`), each (K, a, return, K', Â(K'), discount)."""
        self.items.append((k, a, r))
        out = []
        if end:
            while self.items:
                out.append(self._emit(k2, mask2, terminal))
        elif len(self.items) == self.n:
            out.append(self._emit(k2, mask2, False))
        return out

    def clear(self) -> None:
        """Forget a partial episode."""
        self.items.clear()
