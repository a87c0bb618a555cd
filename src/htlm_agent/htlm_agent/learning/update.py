"""The gradient update of the stacked DQN learner without autograd: one forward pass of the online and the target
networks together, the Bellman targets, the Huber loss and its gradient written by hand into the online networks'
flat gradient.

The networks are small (two hidden layers of 64 for 5 agents and minibatches of 128), so an update through autograd
spends most of its time in per-operation overhead rather than arithmetic. Here the online networks (N, P) and the
target networks (N, P) are the two halves of one (2, N, P) tensor, so that every layer of both is a single
`torch.baddbmm` over 2N stacked matrices, applied to the minibatch's K and K' at once; the backward pass runs only
over the rows that carry a gradient (the online networks on K). The result is the gradient autograd computes for
`Learner.loss` (the same operations, up to the summation order inside the matrix products);
tests/test_learner_update.py checks this.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from htlm_agent.learning.qnet import StackedQ, init_agent_params


@dataclass
class UpdateBatch:
    """A minibatch of every agent as tensors, ready for `TwinNets.update`."""

    x: torch.Tensor
    """(2N, 2M, K) float32: rows 0..M-1 of agent i's block hold its K, rows M..2M-1 its K'; the block is repeated for
    the target networks (blocks N..2N-1)."""
    a: torch.Tensor
    """(2N, M, 1) int64 actions (repeated for the target networks, like x)."""
    r: torch.Tensor
    """(N, M) float32 (scaled, possibly n-step) returns."""
    discount: torch.Tensor
    """(N, M) float32 factor of the bootstrap term."""
    off: torch.Tensor
    """(N, M, |Ḡ|) float32: 0 on Â(a_o) of K, -inf elsewhere (added to Q-values: a masked max is then a max)."""
    off2: torch.Tensor
    """(N, M, |Ḡ|) float32: the same for Â(a_o') of K' (0 everywhere on the padding rows of agents that do not
    train)."""
    weight: torch.Tensor
    """(N, 1) float32: 1/M for the agents that train, 0 for the others (the gradient of a mean over M rows)."""


class TwinNets:
    """The online and target networks of N agents in one (2, N, P) tensor, and the hand-written DQN update."""

    def __init__(self, sizes: Sequence[int], init_seeds: Sequence[int]) -> None:
        """Online networks initialised from `init_seeds` (one per agent), target networks equal to them."""
        n = len(init_seeds)
        online = [init_agent_params(sizes, s) for s in init_seeds]
        p = sum(t.numel() for t in online[0])
        self.n_agents = n
        self.both = torch.zeros(2, n, p, dtype=torch.float32)
        self.online = StackedQ(sizes, online, storage=self.both[0])
        self.target = StackedQ(sizes, online, storage=self.both[1])
        self.target.requires_grad_(False)
        o = self.online.offsets
        self.weights: list[torch.Tensor] = []  # (2N, in, out): online rows then target rows
        self.biases: list[torch.Tensor] = []  # (2N, 1, out)
        self.grad_w: list[torch.Tensor] = []  # (N, in, out) views of the online gradient
        self.grad_b: list[torch.Tensor] = []  # (N, out)
        sz = self.online.sizes
        for li in range(len(sz) - 1):
            fin, fout = sz[li], sz[li + 1]
            jw, jb = 2 * li, 2 * li + 1
            self.weights.append(self.both[:, :, o[jw] : o[jw + 1]].view(2 * n, fin, fout))
            self.biases.append(self.both[:, :, o[jb] : o[jb + 1]].view(2 * n, 1, fout))
            self.grad_w.append(self.online.grad[:, o[jw] : o[jw + 1]].view(n, fin, fout))
            self.grad_b.append(self.online.grad[:, o[jb] : o[jb + 1]].view(n, fout))

    @torch.no_grad()
    def update(
        self,
        b: UpdateBatch,
        active: torch.Tensor,
        all_active: bool,
        advantage_learning: float,
        huber_delta: float,
        double_dqn: bool,
    ) -> torch.Tensor:
        """The loss of `Learner.loss` and its gradient: forward both networks, form the targets, and write the
        gradient of the sum over the agents marked in `active` of their mean Huber losses into `online.grad` (the
        whole of it: no need to clear it first).

        Args:
            b: the minibatch.
            active: (N,) bool, the agents that train (the others get zero gradients and losses).
            all_active: `active` is all True.
            advantage_learning: α of `Settings.advantage_learning` (0: plain Q-learning targets).
            huber_delta: δ of the Huber loss.
            double_dqn: Double DQN targets (else the max of the target network).

        Returns:
            The per-agent losses (N,).
        """
        n = self.n_agents
        m = b.r.shape[1]
        acts = [b.x]
        h = b.x
        last = len(self.weights) - 1
        for li, (w, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.baddbmm(bias, h, w)
            if li < last:
                h = h.relu_()
                acts.append(h)
        q_o = h[:n, m:]  # online networks on K' (for Double DQN)
        qt_k, qt_k2 = h[n:, :m], h[n:, m:]  # target networks on K and K'
        q_both_a = h[:, :m].gather(-1, b.a)[..., 0]  # Q(K, a) of the online networks, then of the target networks
        q_a, qt_a = q_both_a[:n], q_both_a[n:]
        if double_dqn:  # a' = masked argmax of the online network (ties to the lowest index, as qnet.masked_argmax)
            nxt = qt_k2.gather(-1, (q_o + b.off2).argmax(dim=-1, keepdim=True))[..., 0]
        else:
            nxt = (qt_k2 + b.off2).amax(dim=-1)
        y = b.r + b.discount * nxt  # targets.bellman_targets
        if advantage_learning > 0:  # minus α · targets.advantage_gap
            y = y - advantage_learning * ((qt_k + b.off).amax(dim=-1) - qt_a)
        per_agent = torch.nn.functional.huber_loss(q_a, y, reduction="none", delta=huber_delta).mean(dim=1)
        if not all_active:
            per_agent = per_agent * active.to(per_agent.dtype)
        # d(sum_i active_i · mean_m huber(q_a - y)) / d q_a = active_i / M · clamp(q_a - y, ±δ)
        g = (q_a - y).clamp_(-huber_delta, huber_delta).mul_(b.weight)
        delta = torch.zeros_like(h[:n, :m]).scatter_(-1, b.a[:n], g[..., None])  # output layer's gradient
        for li in range(last, -1, -1):
            below = acts[li][:n, :m]  # the layer's input on the rows with a gradient (online networks, K)
            self.grad_w[li].copy_(torch.bmm(below.transpose(1, 2), delta))
            torch.sum(delta, dim=1, out=self.grad_b[li])
            if li > 0:  # through the layer and the ReLU below it
                delta = torch.ops.aten.threshold_backward(
                    torch.bmm(delta, self.weights[li][:n].transpose(1, 2)), below, 0.0
                )
        return per_agent
