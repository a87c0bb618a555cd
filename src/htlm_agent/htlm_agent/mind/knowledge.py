"""The knowledge state K = {b, a_o} as a vector (docs/model.md, Knowledge state): the one place that builds and reads
its layout.

Layout of the last axis (K = p·L + |Ḡ| entries): the per-task marginals of the belief, task-major (p rows of L
levels, tasks in task order, `Scenario.tasks`), then the one-hot previous assignment a_o over
Ḡ; a_o = -1 (no assignment yet) is all zeros. With `Scenario.roster`, N more entries: 1 for every teammate heard
from at the last step (the agent itself always; everyone before the first step). With `Scenario.teammates`, |Ḡ|
more entries (`teammates`): where the agent's teammates were at the last step by their last known assignments.
With `Scenario.travel`, 2N more (`travel`): every agent's place (the index of the site it is at or drives to) and
then every agent's steps until it arrives there (docs/model.md, Travel). `Scenario.knowledge_size` is its length
and `Scenario.layout_hash` its fingerprint.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import FloatArray, IntArray, Knowledge, Marginals

AnyFloats = NDArray[np.floating[Any]]
"""Knowledge states as stored anywhere: float64 in the runtimes, float32 in the replay memories."""


def build(
    marg: Marginals,
    prev: IntArray,
    n_actions: int,
    roster: NDArray[np.bool_] | None = None,
    mates: FloatArray | None = None,
    places: FloatArray | None = None,
) -> Knowledge:
    """K from marginals (..., p, L) and previous assignments (...,): (..., p·L + |Ḡ|), followed with `roster`
    (..., N) by 1 for every teammate heard from at the last step, 0 for the others (`Scenario.roster`), then with
    `mates` (..., |Ḡ|) by where the teammates were (`Scenario.teammates`, `teammates_of`), then with `places`
    (..., 2N) by every agent's place and steps to arrival (`Scenario.travel`, `places_of`)."""
    lead, size = marg.shape[:-2], marg.shape[-2] * marg.shape[-1]
    if roster is not None or mates is not None or places is not None:
        parts = [build(marg, prev, n_actions)]
        for extra in (roster, mates, places):
            if extra is not None:
                parts.append(np.broadcast_to(extra, lead + extra.shape[-1:]).astype(parts[0].dtype))
        return np.concatenate(parts, axis=-1)
    out: Knowledge = np.empty(lead + (size + n_actions,))
    dst = out[..., :size].reshape(marg.shape)  # a view of out (its last axis split)
    if marg.strides[-1] == marg.itemsize or marg[..., 0, 0].size < 2048:
        dst[...] = marg
    else:  # level-major marginals (`Team.marg`): numpy copies them faster one task and level at a time
        for j in range(marg.shape[-2]):
            for level in range(marg.shape[-1]):
                dst[..., j, level] = marg[..., j, level]
    out[..., size:] = 0.0  # the one-hot a_o: a 1 where 0 <= a_o < |Ḡ|
    flat = np.broadcast_to(prev, lead).reshape(-1)
    rows = np.flatnonzero((flat >= 0) & (flat < n_actions))
    out.reshape(-1, size + n_actions)[rows, size + flat[rows]] = 1.0
    return out


def marginals(k: AnyFloats, scenario: Scenario) -> AnyFloats:
    """The marginals (..., p, L) held in knowledge states (..., K)."""
    p, levels = scenario.n_tasks, scenario.levels
    return k[..., : p * levels].reshape(k.shape[:-1] + (p, levels))


def previous(k: AnyFloats, scenario: Scenario) -> IntArray:
    """The previous assignments a_o (...,) held in knowledge states (..., K): the index of the one-hot entry, -1 when
    there is none."""
    start = scenario.n_tasks * scenario.levels
    onehot = k[..., start : start + scenario.n_actions] > 0.5
    return np.where(onehot.any(axis=-1), onehot.argmax(axis=-1), -1).astype(np.int64)


def roster(k: AnyFloats, scenario: Scenario) -> NDArray[np.bool_]:
    """The teammates heard from at the last step (..., N) held in knowledge states (..., K); every teammate when
    the scenario keeps no roster."""
    if not scenario.roster:
        return np.ones(k.shape[:-1] + (scenario.n_agents,), dtype=bool)
    start = scenario.n_tasks * scenario.levels + scenario.n_actions
    out: NDArray[np.bool_] = k[..., start : start + scenario.n_agents] > 0.5
    return out


def teammates_of(model: Model, joint: IntArray) -> FloatArray:
    """Where each agent's teammates were (..., N, |Ḡ|), from the last known assignments of the whole team
    (..., N) (`Scenario.teammates`, docs/model.md, Knowledge state): for task j the capability the agent's teammates
    brought to it, over capability_max · (N − 1); for an idle location the number of teammates idling there, over
    N − 1. An assignment of -1 (none) counts nowhere."""
    sc = model.scenario
    n, g = sc.n_agents, sc.n_actions
    onehot = (joint[..., None] == np.arange(g)).astype(np.float64)  # (..., N, |Ḡ|)
    caps = np.where(np.arange(g) < sc.n_tasks, model.agent_caps / sc.capability_max, 1.0)  # (N, |Ḡ|)
    brought = onehot * caps  # what each agent brings to where it is
    out: FloatArray = (brought.sum(axis=-2, keepdims=True) - brought) / max(1, n - 1)
    return out


def teammates(k: AnyFloats, scenario: Scenario) -> AnyFloats:
    """The teammates' places (..., |Ḡ|) held in knowledge states (..., K) (`teammates_of`); zeros when the scenario
    keeps none."""
    if not scenario.teammates:
        return np.zeros(k.shape[:-1] + (scenario.n_actions,), dtype=k.dtype)
    start = scenario.n_tasks * scenario.levels + scenario.n_actions + (scenario.n_agents if scenario.roster else 0)
    return k[..., start : start + scenario.n_actions]


def places_of(goal: IntArray, eta: IntArray) -> FloatArray:
    """The travel entries (..., 2N) of every agent's place (the site it is at or drives to, (..., N)) and steps to
    arrival (..., N) (`Scenario.travel`)."""
    out: FloatArray = np.concatenate([goal, eta], axis=-1).astype(np.float64)
    return out


def places(k: AnyFloats, scenario: Scenario) -> tuple[IntArray, IntArray]:
    """Every agent's place (..., N) and steps to arrival (..., N) held in knowledge states (..., K) (`places_of`);
    everyone at site 0 and arrived when the scenario has no travel."""
    n = scenario.n_agents
    if not scenario.travel:
        zero = np.zeros(k.shape[:-1] + (n,), dtype=np.int64)
        return zero, zero.copy()
    block = np.rint(k[..., scenario.knowledge_size - 2 * n :]).astype(np.int64)
    return block[..., :n], block[..., n:]


def split(k: AnyFloats, scenario: Scenario) -> tuple[AnyFloats, IntArray]:
    """The inverse of `build`: marginals (..., p, L) and previous assignments (...,) of knowledge states (..., K)."""
    return marginals(k, scenario), previous(k, scenario)
