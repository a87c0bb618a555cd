"""What a gradient update of the DQN learner reads, and the float mode it runs in.

The minibatches of every agent are gathered from the replay memories into storage made once (`Minibatches`) and read
as tensors that view it (`UpdateBatch`): an update allocates no input, and the tensors of K and K' lie side by side so
that a network can score both in one pass.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch


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
    """A minibatch of every agent as tensors (the input of `Learner.batch_loss`): views of `Minibatches`' storage,
    which `Learner.update_batches` refills for every update."""

    def __init__(
        self,
        x: torch.Tensor,
        a: torch.Tensor,
        r: torch.Tensor,
        discount: torch.Tensor,
        allowed: torch.Tensor,
        allowed2: torch.Tensor,
        weight: torch.Tensor,
    ) -> None:
        """Wrap the tensors (shapes below)."""
        self.x = x
        """(N, 2M, K) float32: rows 0..M-1 of agent i's block hold its K, rows M..2M-1 its K'."""
        self.a = a
        """(N, M) int64 actions."""
        self.a_col = a[..., None]
        """(N, M, 1): the actions as an index of Q-values (N, M, |Ḡ|)."""
        self.r = r
        """(N, M) float32 (scaled, possibly n-step) returns."""
        self.discount = discount
        """(N, M) float32 factor of the bootstrap term."""
        self.allowed = allowed
        """(N, M, |Ḡ|) bool: Â(a_o) of K."""
        self.allowed2 = allowed2
        """(N, M, |Ḡ|) bool: Â(a_o') of K' (every action on the padding rows of agents that do not train)."""
        self.weight = weight
        """(N, 1, 1) float32: 1/M for the agents that train, 0 for the others (a mean over M rows, or nothing)."""

    @property
    def m(self) -> int:
        """M, transitions per agent."""
        return int(self.r.shape[1])


class Minibatches:
    """Storage for `count` minibatches of M transitions of N agents, as numpy arrays to fill and the `UpdateBatch`
    views of them (made once: a new minibatch is a refill, not new tensors)."""

    def __init__(self, count: int, n: int, m: int, knowledge_size: int, n_actions: int, width: int) -> None:
        """Allocate the storage; `width` is the size of a replay record."""
        self.count, self.n, self.m = count, n, m
        self.x = np.zeros((count, n, 2 * m, knowledge_size), dtype=np.float32)
        """Inputs of every minibatch j (agent i: K then K')."""
        self.a = np.zeros((count, n, m), dtype=np.int64)
        self.r = np.zeros((count, n, m), dtype=np.float32)
        self.discount = np.zeros((count, n, m), dtype=np.float32)
        self.allowed = np.zeros((n * count * m, 2, n_actions), dtype=np.bool_)
        """Â of K and of K' of the sampled transitions, in the order of the indices (agent, then draw)."""
        self.weight = np.zeros((n, 1, 1), dtype=np.float32)
        self.records = np.zeros((n * count * m, width), dtype=np.float32)
        """The sampled replay records, in the same order."""
        x, a = torch.from_numpy(self.x), torch.from_numpy(self.a)
        r, d = torch.from_numpy(self.r), torch.from_numpy(self.discount)
        allowed = torch.from_numpy(self.allowed).view(n, count, m, 2, n_actions)
        w = torch.from_numpy(self.weight)
        self.batches = [
            UpdateBatch(
                x=x[j],
                a=a[j],
                r=r[j],
                discount=d[j],
                allowed=allowed[:, j, :, 0],
                allowed2=allowed[:, j, :, 1],
                weight=w,
            )
            for j in range(count)
        ]
