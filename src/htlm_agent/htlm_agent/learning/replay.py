"""Replay memories D of Algorithm 1: one ring buffer per agent, in preallocated arrays.

The memories of the N agents live in arrays with a leading agent axis (N, capacity, ...) so that a minibatch of every
agent is gathered in one indexing operation, but each agent has its own fill level, write position and sampling
generator: agents never see each other's transitions. A transition is X = <K, a, K', f_R> plus the reduced action
space Â(a_o') of K' (for the max of the Bellman target) and the discount of the bootstrap term: γ^n for an n-step
return that continues, 0 where K' is terminal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from htlm_world.types import BoolArray, FloatArray, IntArray


@dataclass
class Batch:
    """A minibatch of every agent: arrays (N, M, ...)."""

    k: NDArray[np.float32]  # (N, M, K)
    a: IntArray  # (N, M)
    r: NDArray[np.float32]  # (N, M)
    k2: NDArray[np.float32]  # (N, M, K)
    mask2: BoolArray  # (N, M, |G|)
    discount: NDArray[np.float32]  # (N, M) factor of the bootstrap term: γ^n, 0 when terminal


class Replay:
    """Per-agent ring buffers of capacity C each, as one float32 array (N, C, D) of records
    [K (K), K' (K), a, r, Â(K') (|G|), discount] so that a minibatch of every agent is a single gather."""

    def __init__(
        self,
        n_agents: int,
        capacity: int,
        knowledge_size: int,
        n_actions: int,
        seeds: list[int],
        knowledge_mask: Callable[[NDArray[np.float32]], BoolArray] | None = None,
    ) -> None:
        """Allocate the memories.

        Args:
            n_agents: N.
            capacity: C transitions per agent; the oldest is overwritten when full.
            knowledge_size: K.
            n_actions: |Ḡ|.
            seeds: one sampling seed per agent.
            knowledge_mask: Â(a_o) (..., |Ḡ|) of knowledge states (..., K); when given, the memories also keep, per
                transition, Â of K and of K' as masks (see `allowed`), derived from the records and never saved.
        """
        assert capacity >= 1 and len(seeds) == n_agents
        self.n_agents, self.capacity = n_agents, capacity
        self.ks, self.na = knowledge_size, n_actions
        ks = knowledge_size
        self.cols = {
            "k": slice(0, ks),
            "k2": slice(ks, 2 * ks),
            "a": slice(2 * ks, 2 * ks + 1),
            "r": slice(2 * ks + 1, 2 * ks + 2),
            "mask2": slice(2 * ks + 2, 2 * ks + 2 + n_actions),
            "discount": slice(2 * ks + 2 + n_actions, 2 * ks + 3 + n_actions),
        }
        self.width = 2 * ks + 3 + n_actions
        self.data = np.zeros((n_agents, capacity, self.width), dtype=np.float32)
        self.size = np.zeros(n_agents, dtype=np.int64)
        self.pos = np.zeros(n_agents, dtype=np.int64)
        self.rngs = [np.random.default_rng(s) for s in seeds]
        self.agent_rows = np.arange(n_agents)[:, None]
        self.knowledge_mask = knowledge_mask
        self.allowed: BoolArray | None = None
        """(N, C, 2, |Ḡ|): Â(K) (row 0) and Â(K') (row 1) of every stored transition (with `knowledge_mask`
        only)."""
        if knowledge_mask is not None:
            self.allowed = np.zeros((n_agents, capacity, 2, n_actions), dtype=np.bool_)

    def _store_allowed(self, flat: Any, rec: NDArray[np.float32]) -> None:
        """Derive Â of K and K' of records `rec` (J, D) stored in the slots `flat` (J,) of the flattened memories."""
        if self.allowed is None or self.knowledge_mask is None:
            return
        c = self.cols
        allowed = np.stack([self.knowledge_mask(rec[..., c["k"]]), rec[..., c["mask2"]] > 0.5], axis=-2)
        self.allowed.reshape(-1, 2, self.na)[flat] = allowed

    def _allowed_into(self, out: BoolArray, rec: NDArray[np.float32]) -> None:
        """Write Â of K and K' (..., 2, |Ḡ|) of records `rec` (..., D) into `out`."""
        if self.knowledge_mask is None:
            return
        c = self.cols
        out[..., 0, :] = self.knowledge_mask(rec[..., c["k"]])
        np.greater(rec[..., c["mask2"]], 0.5, out=out[..., 1, :])

    def _records(
        self,
        k: FloatArray,
        a: Any,
        r: Any,
        k2: FloatArray,
        mask2: BoolArray,
        discount: Any,
        out: NDArray[np.float32] | None = None,
    ) -> NDArray[np.float32]:
        lead = np.shape(a)
        rec = np.empty((*lead, self.width), dtype=np.float32) if out is None else out
        c = self.cols
        rec[..., c["k"]] = k
        rec[..., c["k2"]] = k2
        rec[..., c["a"]] = np.asarray(a)[..., None]
        rec[..., c["r"]] = np.asarray(r)[..., None]
        rec[..., c["mask2"]] = mask2
        rec[..., c["discount"]] = np.asarray(discount)[..., None]
        return rec

    def add(
        self, agent: int, k: FloatArray, a: int, r: float, k2: FloatArray, mask2: BoolArray, discount: float
    ) -> None:
        """Store one transition of one agent."""
        i = int(self.pos[agent])
        rec = self._records(k, a, r, k2, mask2, discount)
        self.data[agent, i] = rec
        self._store_allowed(agent * self.capacity + i, rec)
        self.pos[agent] = (i + 1) % self.capacity
        self.size[agent] = min(self.size[agent] + 1, self.capacity)

    def add_batch(
        self, k: FloatArray, a: IntArray, r: FloatArray, k2: FloatArray, mask2: BoolArray, discount: FloatArray | float
    ) -> None:
        """Store B transitions of every agent at once: k, k2 (B, N, K), a, r (B, N), mask2 (B, N, |G|), discount
        (B, N) or a scalar. Every agent's transitions go to its own memory."""
        b = a.shape[0]
        assert b <= self.capacity
        disc = np.broadcast_to(np.asarray(discount, dtype=np.float32), (b, self.n_agents))
        p = int(self.pos[0])
        if p + b <= self.capacity and (self.pos == p).all():  # the same run of slots p .. p+B-1 in every memory
            block = self.data[:, p : p + b]  # (N, B, D): the records go straight into place
            self._records(k.swapaxes(0, 1), a.T, r.T, k2.swapaxes(0, 1), mask2.swapaxes(0, 1), disc.T, out=block)
            if self.allowed is not None:
                self._allowed_into(self.allowed[:, p : p + b], block)
            self.pos[:] = (p + b) % self.capacity
            np.minimum(self.size + b, self.capacity, out=self.size)
            return
        rec = self._records(k, a, r, k2, mask2, disc)  # (B, N, D)
        idx = (self.pos[:, None] + np.arange(b)) % self.capacity  # (N, B): each agent's own write positions
        flat = (self.agent_rows * self.capacity + idx).T.reshape(-1)  # (B · N), in the order of rec's rows
        rec = rec.reshape(b * self.n_agents, self.width)
        self.data.reshape(-1, self.width)[flat] = rec
        self._store_allowed(flat, rec)
        self.pos[:] = (self.pos + b) % self.capacity
        np.minimum(self.size + b, self.capacity, out=self.size)

    def sample_indices(self, batch: int, agents: NDArray[np.bool_], count: int = 1) -> IntArray:
        """(N, count · batch) indices: `count` draws of `batch` indices, each uniform with replacement from each marked
        agent's own memory with its own generator (one call of `integers` per draw); unmarked agents get index 0 and
        draw nothing."""
        idx = np.zeros((self.n_agents, count * batch), dtype=np.int64)
        for agent in range(self.n_agents):
            if agents[agent]:
                # one call: numpy's bounded integers draw each value afresh from the bit generator (no buffer kept
                # between values outside it), so this is the same stream as `count` calls of `batch` values
                idx[agent] = self.rngs[agent].integers(0, self.size[agent], count * batch)
        return idx

    def sample_records(self, batch: int, agents: NDArray[np.bool_], count: int = 1) -> NDArray[np.float32]:
        """The records (N, count · batch, D) of `count` minibatches of every agent marked in `agents` (N,) bool from
        its own memory (`sample_indices`; columns in `cols`); other agents' rows are padding the caller ignores."""
        return self.take(self.data, self.sample_indices(batch, agents, count))

    def slots(self, idx: IntArray) -> IntArray:
        """Indices (N, J) into every agent's own memory as indices into the flattened memories (N · C)."""
        out: IntArray = self.agent_rows * self.capacity + idx
        return out

    def take(self, per_slot: NDArray[Any], idx: IntArray) -> NDArray[Any]:
        """per_slot[i, idx[i, j]] for an array (N, C, ...) of every agent's slots and indices (N, J): (N, J, ...).
        (`numpy.take` on the flattened slots: much quicker than fancy indexing with two index arrays.)"""
        n, c = per_slot.shape[:2]
        out = np.take(per_slot.reshape(n * c, *per_slot.shape[2:]), self.slots(idx).reshape(-1), axis=0)
        return out.reshape(*idx.shape, *per_slot.shape[2:])

    def sample(self, batch: int, agents: NDArray[np.bool_]) -> Batch:
        """A minibatch of `batch` transitions of every agent marked in `agents` (N,) bool from its own memory
        (`sample_indices`); other agents' rows are padding the caller ignores."""
        rec = self.sample_records(batch, agents)  # (N, M, D)
        c = self.cols
        return Batch(
            k=rec[..., c["k"]],
            a=rec[..., c["a"]][..., 0].astype(np.int64),
            r=np.ascontiguousarray(rec[..., c["r"]][..., 0]),
            k2=rec[..., c["k2"]],
            mask2=rec[..., c["mask2"]] > 0.5,
            discount=np.ascontiguousarray(rec[..., c["discount"]][..., 0]),
        )

    # ----- persistence (for resuming a run exactly) ------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Arrays and generator states (only the filled part of the memories)."""
        n = int(self.size.max()) if self.n_agents else 0
        return {
            "data": self.data[:, :n],
            "size": self.size.copy(),
            "pos": self.pos.copy(),
            "rngs": [g.bit_generator.state for g in self.rngs],
        }

    def load_state(self, st: dict[str, Any]) -> None:
        """Restore from `state()`."""
        data = st["data"]
        n = data.shape[1]
        if n > self.capacity or data.shape[0] != self.n_agents or data.shape[2] != self.width:
            raise ValueError(f"replay state of shape {data.shape} does not fit memories of {self.data.shape}")
        self.data[:, :n] = data
        slots = (self.agent_rows * self.capacity + np.arange(n)).reshape(-1)
        self._store_allowed(slots, self.data[:, :n].reshape(-1, self.width))
        self.size[:] = st["size"]
        self.pos[:] = st["pos"]
        for g, s in zip(self.rngs, st["rngs"], strict=True):
            g.bit_generator.state = s


class ExpertMemory:
    """The warm start's expert choices (`Settings.imitate_updates`): whole team steps of knowledge (float32, as
    stored everywhere), masks and the expert's actions, oldest overwritten first, sampled uniformly."""

    def __init__(self, capacity: int, n_agents: int, k_size: int, n_actions: int, rng: np.random.Generator) -> None:
        """Room for `capacity` team steps (rows of N agents)."""
        self.k = np.zeros((capacity, n_agents, k_size), dtype=np.float32)
        self.mask = np.zeros((capacity, n_agents, n_actions), dtype=bool)
        self.action = np.zeros((capacity, n_agents), dtype=np.int64)
        self.size = 0
        self.next = 0
        self.rng = rng

    def add(self, k: FloatArray, mask: BoolArray, action: IntArray) -> None:
        """Store B team steps: (B, N, K) knowledge, (B, N, |Ḡ|) masks, (B, N) the expert's actions."""
        cap = self.k.shape[0]
        k, mask, action = k[-cap:], mask[-cap:], action[-cap:]  # a batch larger than the memory keeps its last rows
        idx = (self.next + np.arange(k.shape[0])) % cap
        self.k[idx], self.mask[idx], self.action[idx] = k, mask, action
        self.next = int((self.next + k.shape[0]) % cap)
        self.size = min(cap, self.size + k.shape[0])

    def sample(self, rows: int) -> tuple[FloatArray, BoolArray, IntArray]:
        """`rows` team steps drawn uniformly (with replacement) from what is stored."""
        idx = self.rng.integers(0, self.size, size=rows)
        return self.k[idx].astype(np.float64), self.mask[idx], self.action[idx]
