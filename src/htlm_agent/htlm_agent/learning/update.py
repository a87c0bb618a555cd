"""The gradient update of the stacked DQN learner without autograd: one forward pass of the online and the target
networks together, the Bellman targets, the Huber loss and its gradient written by hand into the online networks'
flat gradient.

The networks are small (two hidden layers of 64 for 5 agents and minibatches of 128), so an update through autograd
spends most of its time in per-operation overhead rather than arithmetic. Here the online networks (N, P) and the
target networks (N, P) are the two halves of one (2, N, P) tensor, so that every layer of both is one `torch.baddbmm`
over 2N stacked matrices (the first layer two, on the same input), applied to the minibatch's K and K' at once; the
backward pass runs only over the rows that carry a gradient (the online networks on K). Activations, targets and
gradients go into buffers made once, and the views the update reads of them are made once too. The result is the
gradient autograd computes for `Learner.loss` (the same operations, up to rounding: summation order inside the matrix
products, a fused multiply-add); tests/test_learner_update.py checks this.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np
import torch

from htlm_agent.learning.qnet import StackedQ, init_agent_params


@contextmanager
def flush_denormals() -> Iterator[None]:
    """Within the block, this thread's float arithmetic treats denormal numbers (below 1.2e-38 in float32) as zero.

    They turn up in the learner: in knowledge states (marginals of almost impossible levels) and in Adam's first
    moments of parameters whose gradients have stopped. On x86 every operation on one costs about a hundred cycles,
    which made a gradient update about a tenth slower. Values that small never change a sum of float32 numbers of the
    networks' magnitudes (the weights of a run come out the same); only moments that would have been denormal are 0.
    Where torch cannot set the mode, nothing changes.
    """
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


class UpdateBatch:
    """A minibatch of every agent as tensors, ready for `TwinNets.update`. The tensors are views of `Minibatches`'
    storage, which `Learner.update_batches` refills for every update."""

    def __init__(
        self,
        x: torch.Tensor,
        a: torch.Tensor,
        r: torch.Tensor,
        discount: torch.Tensor,
        off: torch.Tensor,
        off2: torch.Tensor,
        weight: torch.Tensor,
    ) -> None:
        """Wrap the tensors (shapes below) and make the views of them that the update needs."""
        n, m = r.shape[0], r.shape[1]
        self.x = x
        """(N, 2M, K) float32: rows 0..M-1 of agent i's block hold its K, rows M..2M-1 its K' (the input of both
        its online and its target network)."""
        self.a = a
        """(2N, M, 1) int64 actions (repeated for the target networks, like x)."""
        self.r = r
        """(N, M, 1) float32 (scaled, possibly n-step) returns."""
        self.discount = discount
        """(N, M, 1) float32 factor of the bootstrap term."""
        self.off = off
        """(N, M, |Ḡ|) float32: 0 on Â(a_o) of K, -inf elsewhere (added to Q-values: a masked max is then a max)."""
        self.off2 = off2
        """(N, M, |Ḡ|) float32: the same for Â(a_o') of K' (0 everywhere on the padding rows of agents that do
        not train)."""
        self.weight = weight
        """(N, 1, 1) float32: 1/M for the agents that train, 0 for the others (the gradient of a mean over M
        rows)."""
        self.a_online = a[:n]
        self.x_rows_t = x[:n, :m].transpose(1, 2)  # the input on the rows with a gradient, transposed


class Minibatches:
    """Storage for `count` minibatches of M transitions of N agents, as numpy arrays to fill and the `UpdateBatch`
    views of them (made once: a new minibatch is a refill, not new tensors)."""

    def __init__(self, count: int, n: int, m: int, knowledge_size: int, n_actions: int, width: int) -> None:
        """Allocate the storage; `width` is the size of a replay record."""
        self.count, self.n, self.m = count, n, m
        self.x = np.zeros((count, n, 2 * m, knowledge_size), dtype=np.float32)
        """Inputs of every minibatch j (agent i: K then K')."""
        self.a = np.zeros((count, 2, n, m, 1), dtype=np.int64)
        self.r = np.zeros((count, n, m, 1), dtype=np.float32)
        self.discount = np.zeros((count, n, m, 1), dtype=np.float32)
        self.offsets = np.zeros((n * count * m, 2, n_actions), dtype=np.float32)
        """Â of K and of K' of the sampled transitions, in the order of the indices (agent, then draw)."""
        self.weight = np.zeros((n, 1, 1), dtype=np.float32)
        self.records = np.zeros((n * count * m, width), dtype=np.float32)
        """The sampled replay records, in the same order."""
        x, a = torch.from_numpy(self.x), torch.from_numpy(self.a)
        r, d = torch.from_numpy(self.r), torch.from_numpy(self.discount)
        off = torch.from_numpy(self.offsets).view(n, count, m, 2, n_actions)
        w = torch.from_numpy(self.weight)
        self.batches = [
            UpdateBatch(
                x=x[j],
                a=a[j].view(2 * n, m, 1),
                r=r[j],
                discount=d[j],
                off=off[:, j, :, 0],
                off2=off[:, j, :, 1],
                weight=w,
            )
            for j in range(count)
        ]


class _Workspace:
    """The activations of one update (for minibatches of M) and the views of them it reads, made once."""

    def __init__(self, n: int, m: int, sizes: Sequence[int]) -> None:
        self.h = [torch.zeros(2 * n, 2 * m, f) for f in sizes[1:]]  # every layer's output, the last: Q-values
        q = self.h[-1]
        self.q_k_both = q[:, :m]  # both networks on K
        self.q_o = q[:n, m:]  # online networks on K' (for Double DQN)
        self.qt_k, self.qt_k2 = q[n:, :m], q[n:, m:]  # target networks on K and K'
        self.rows = [h[:n, :m] for h in self.h[:-1]]  # hidden outputs on the rows with a gradient
        self.rows_t = [r.transpose(1, 2) for r in self.rows]
        self.qa = torch.zeros(2 * n, m, 1)  # Q(K, a) of the online networks, then of the target networks
        self.q_a, self.qt_a = self.qa[:n], self.qa[n:]
        na = sizes[-1]
        self.shifted = torch.zeros(n, m, na)  # Q-values plus offsets
        self.a2 = torch.zeros(n, m, 1, dtype=torch.int64)
        self.nxt = torch.zeros(n, m, 1)
        self.best = torch.zeros(n, m, 1)
        self.y = torch.zeros(n, m, 1)
        self.g = torch.zeros(n, m, 1)
        self.delta = torch.zeros(n, m, na)  # the output layer's gradient
        self.d_hidden = [torch.zeros(n, m, f) for f in sizes[1:-1]]  # gradients of the hidden outputs


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
        self.grad_b: list[torch.Tensor] = []  # (N, 1, out)
        sz = self.online.sizes
        for li in range(len(sz) - 1):
            fin, fout = sz[li], sz[li + 1]
            jw, jb = 2 * li, 2 * li + 1
            self.weights.append(self.both[:, :, o[jw] : o[jw + 1]].view(2 * n, fin, fout))
            self.biases.append(self.both[:, :, o[jb] : o[jb + 1]].view(2 * n, 1, fout))
            self.grad_w.append(self.online.grad[:, o[jw] : o[jw + 1]].view(n, fin, fout))
            self.grad_b.append(self.online.grad[:, o[jb] : o[jb + 1]].view(n, 1, fout))
        self.weights_back = [w[:n].transpose(1, 2) for w in self.weights]  # online W_l^T, for the backward pass
        self._workspaces: dict[int, _Workspace] = {}

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
        n, m = self.n_agents, b.r.shape[1]
        ws = self._workspaces.get(m)
        if ws is None:
            ws = self._workspaces[m] = _Workspace(n, m, self.online.sizes)
        last = len(self.weights) - 1
        h = ws.h[0]  # the first layer reads the same input for both networks: two products, no copy of the input
        torch.baddbmm(self.biases[0][:n], b.x, self.weights[0][:n], out=h[:n])
        torch.baddbmm(self.biases[0][n:], b.x, self.weights[0][n:], out=h[n:])
        for li in range(1, last + 1):
            h.relu_()
            h = torch.baddbmm(self.biases[li], h, self.weights[li], out=ws.h[li])
        torch.gather(ws.q_k_both, -1, b.a, out=ws.qa)  # Q(K, a): online ws.q_a, target ws.qt_a
        if double_dqn:  # a' = masked argmax of the online network (ties to the lowest index, as qnet.masked_argmax)
            torch.argmax(torch.add(ws.q_o, b.off2, out=ws.shifted), dim=-1, keepdim=True, out=ws.a2)
            torch.gather(ws.qt_k2, -1, ws.a2, out=ws.nxt)
        else:
            torch.amax(torch.add(ws.qt_k2, b.off2, out=ws.shifted), dim=-1, keepdim=True, out=ws.nxt)
        y = torch.addcmul(b.r, b.discount, ws.nxt, out=ws.y)  # targets.bellman_targets
        if advantage_learning > 0:  # minus α · targets.advantage_gap
            best = torch.amax(torch.add(ws.qt_k, b.off, out=ws.shifted), dim=-1, keepdim=True, out=ws.best)
            y.sub_(best.sub_(ws.qt_a).mul_(advantage_learning))
        per_agent = torch.nn.functional.huber_loss(ws.q_a, y, reduction="none", delta=huber_delta).mean(dim=(1, 2))
        if not all_active:
            per_agent = per_agent * active.to(per_agent.dtype)
        # d(sum_i active_i · mean_m huber(q_a - y)) / d q_a = active_i / M · clamp(q_a - y, ±δ)
        g = torch.sub(ws.q_a, y, out=ws.g).clamp_(-huber_delta, huber_delta).mul_(b.weight)
        delta = ws.delta.zero_().scatter_(-1, b.a_online, g)  # the output layer's gradient
        for li in range(last, -1, -1):
            below_t = ws.rows_t[li - 1] if li > 0 else b.x_rows_t  # the layer's input on the rows with a gradient
            torch.bmm(below_t, delta, out=self.grad_w[li])
            torch.sum(delta, dim=1, keepdim=True, out=self.grad_b[li])
            if li > 0:  # through the layer and the ReLU below it
                d_below = torch.bmm(delta, self.weights_back[li], out=ws.d_hidden[li - 1])
                delta = torch.ops.aten.threshold_backward.grad_input(d_below, ws.rows[li - 1], 0.0, grad_input=d_below)
        return per_agent
