"""The centralized, fully observed optimum: value iteration over the joint state of every site with every joint
action (docs/model.md, Reference figures). Joint actions are grouped by the capability vector they produce, since T
depends on the assignment only through it.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from htlm_agent.runtime.team import Context
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import FloatArray, IntArray


@dataclass(frozen=True)
class OptimalSolution:
    """Finite-horizon value iteration result."""

    scenario: Scenario
    values: FloatArray  # (h+1, L^p) expected completion step with k steps left (capped at h), by state index
    best: IntArray  # (h+1, L^p) index of the best capability vector with k steps left
    cap_vectors: IntArray  # (C, p) distinct capability vectors
    joint_actions: IntArray  # (C, N) a cheapest joint action producing each capability vector

    @property
    def expected_completion(self) -> float:
        """Expected completion step from the initial state (failures count as h)."""
        return float(self.values[self.scenario.horizon, state_index(self.scenario, self.scenario.initial_levels)])


def state_index(sc: Scenario, levels: tuple[int, ...] | IntArray) -> int:
    """Index of a joint state: site-major, (fire, rescue) per site, base L."""
    idx = 0
    for lv in levels:
        idx = idx * sc.levels + int(lv)
    return idx


def capability_vectors(model: Model) -> tuple[IntArray, IntArray]:
    """Distinct capped capability vectors over all joint task assignments, each with a joint action of least
    total committed capability that produces it (idle agents where they add nothing)."""
    sc = model.scenario
    p = sc.n_tasks
    choices = list(range(p)) + [-1]  # -1: contributes nothing (idle)
    best: dict[tuple[int, ...], tuple[float, tuple[int, ...]]] = {}
    for joint in itertools.product(choices, repeat=sc.n_agents):
        arr = np.array(joint, dtype=np.int64)
        caps = tuple(int(c) for c in model.joint_capability(arr[None])[0])
        cost = sum(model.agent_caps[i, a] for i, a in enumerate(joint) if a >= 0)
        if caps not in best or cost < best[caps][0]:
            best[caps] = (cost, joint)
    keys = sorted(best)
    return np.array(keys, dtype=np.int64), np.array([best[k][1] for k in keys], dtype=np.int64)


def solve(sc: Scenario) -> OptimalSolution:
    """Finite-horizon value iteration for the expected completion step (docs/model.md, Reference figures).

    V_0(s) = 0; V_k(s) = 0 if s is complete, else 1 + min_c sum_s' T_c(s, s') V_{k-1}(s'). V_h(s0) is the
    expected completion step with never-completed episodes counted as h.
    """
    model = Model.build(sc)
    L, S = sc.levels, sc.n_sites
    caps, joints = capability_vectors(model)
    # site transition matrices T_site[c_fire, c_rescue][(f, r), (f', r')]
    site_t = np.einsum("afg,bfrs->abfrgs", model.fire, model.rescue).reshape(
        model.fire.shape[0], model.rescue.shape[0], L * L, L * L
    )
    mats = [site_t[caps[:, 2 * s], caps[:, 2 * s + 1]] for s in range(S)]  # each (C, L^2, L^2)
    n_states = L ** (2 * S)
    complete = np.zeros(n_states, dtype=bool)
    complete[0] = True
    values = np.zeros((sc.horizon + 1, n_states))
    best = np.zeros((sc.horizon + 1, n_states), dtype=np.int64)
    for k in range(1, sc.horizon + 1):
        v = values[k - 1].reshape((L * L,) * S)
        # expected next value for every capability vector: contract each site's axis with its matrix
        ev = np.broadcast_to(v, (caps.shape[0],) + v.shape)
        for s in range(S):
            ev = _contract(ev, mats[s], s + 1)
        q = ev.reshape(caps.shape[0], n_states)
        best[k] = q.argmin(axis=0)
        values[k] = np.where(complete, 0.0, 1.0 + q.min(axis=0))
    return OptimalSolution(sc, values, best, caps, joints)


def _contract(ev: FloatArray, mat: FloatArray, axis: int) -> FloatArray:
    """out[c, ..., i, ...] = sum_j mat[c, i, j] ev[c, ..., j, ...] along `axis`."""
    moved = np.moveaxis(ev, axis, -1)  # (C, ..., j)
    out = np.einsum("c...j,cij->c...i", moved, mat)
    return np.moveaxis(out, -1, axis)


class OptimalPolicy:
    """Acts on the true state with the optimal joint action (the centralized floor, not a decentralized agent)."""

    def __init__(self, sc: Scenario) -> None:
        """Solve the scenario once."""
        self.sol = solve(sc)
        self.sc = sc
        self.model = Model.build(sc)
        self.weights = np.array([sc.levels ** (sc.n_tasks - 1 - j) for j in range(sc.n_tasks)], dtype=np.int64)

    def act(self, ctx: Context) -> IntArray:
        """Joint action for every episode from its true levels; idle agents idle at their current site."""
        sc = self.sc
        k = max(sc.horizon - ctx.t, 1)
        idx = ctx.true_levels @ self.weights
        joint = self.sol.joint_actions[self.sol.best[k, idx]]  # (B, N), -1 where idle
        if sc.n_idle:
            done = (ctx.true_levels == 0).all(axis=1)[:, None]
            joint = np.where((joint < 0) | done, self.model.idle_action(ctx.prev), joint)
        return np.asarray(joint, dtype=np.int64)
