"""The transition T, observation O and information I models of docs/model.md, as probability tables.

Each model is defined once, as a table; the simulator samples from the very same tables that the belief filter
and the optimal baseline use (inverse-CDF sampling), so the three can never disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray


def p_drop_table(sc: Scenario) -> FloatArray:
    """p_drop(c, l) for c in 0..capability_max and l in 0..L-1 (docs/model.md, Transition T)."""
    cm, L = sc.capability_max, sc.levels
    table = np.zeros((cm + 1, L))
    for c in range(1, cm + 1):
        for lv in range(1, L):
            margin = c - lv
            k = 0 if margin >= 0 else min(-margin, len(sc.p_drop) - 1)
            table[c, lv] = sc.p_drop[k]
    return table


def fire_table(sc: Scenario) -> FloatArray:
    """T_fire[c, f, f']: next fire level given joint fire capability c and level f (docs/model.md)."""
    cm, L = sc.capability_max, sc.levels
    pd = p_drop_table(sc)
    t = np.zeros((cm + 1, L, L))
    for c in range(cm + 1):
        t[c, 0, 0] = 1.0
        for f in range(1, L):
            if c == 0:
                up = min(L - 1, f + 1)
                t[c, f, up] += sc.fire_growth
                t[c, f, f] += 1.0 - sc.fire_growth
            else:
                t[c, f, f - 1] += pd[c, f]
                t[c, f, f] += 1.0 - pd[c, f]
    return t


def rescue_table(sc: Scenario) -> FloatArray:
    """T_rescue[c, f, r, r']: next rescue level given capability c, the site's fire f and rescue level r."""
    cm, L = sc.capability_max, sc.levels
    pd = p_drop_table(sc)
    t = np.zeros((cm + 1, L, L, L))
    for c in range(cm + 1):
        for f in range(L):
            t[c, f, 0, 0] = 1.0
            for r in range(1, L):
                p = pd[c, r]
                if f > sc.rescue_block_fire or c == 0:
                    t[c, f, r, r] = 1.0
                elif f <= sc.rescue_double_fire and c >= r and r >= sc.rescue_double_min_level:
                    t[c, f, r, r - 2] += sc.rescue_double_share * p
                    t[c, f, r, r - 1] += (1.0 - sc.rescue_double_share) * p
                    t[c, f, r, r] += 1.0 - p
                else:
                    t[c, f, r, r - 1] += p
                    t[c, f, r, r] += 1.0 - p
    return t


def observation_table(sc: Scenario) -> FloatArray:
    """O[s, l, z]: probability of observing z when the true level is l, for sensing s (docs/model.md)."""
    cm, L = sc.capability_max, sc.levels
    t = np.zeros((cm + 1, L, L))
    for s in range(cm + 1):
        acc = min(1.0, sc.sensing_base + sc.sensing_slope * s)
        for lv in range(L):
            nbrs = [n for n in (lv - 1, lv + 1) if 0 <= n < L]
            t[s, lv, lv] = acc
            for n in nbrs:
                t[s, lv, n] += (1.0 - acc) / len(nbrs)
    return t


def keep_probability(sc: Scenario, comm: int) -> float:
    """tau = min(1, channel_base + comm / capability_max): probability that a broadcast level passes intact."""
    return min(1.0, sc.channel_base + comm / sc.capability_max) if sc.channel else 1.0


def information_table(sc: Scenario) -> FloatArray:
    """I[s, comm, l, m] = tau O_s(m | l) + (1 - tau) / L: likelihood of a teammate's message (docs/model.md)."""
    cm, L = sc.capability_max, sc.levels
    obs = observation_table(sc)
    t = np.zeros((cm + 1, cm + 1, L, L))
    for comm in range(cm + 1):
        tau = keep_probability(sc, comm)
        t[:, comm] = tau * obs + (1.0 - tau) / L
    return t


@dataclass(frozen=True)
class Model:
    """All tables of one scenario, computed once."""

    scenario: Scenario
    fire: FloatArray  # (C+1, L, L)
    rescue: FloatArray  # (C+1, L, L, L)
    obs: FloatArray  # (C+1, L, L)
    info: FloatArray  # (C+1, C+1, L, L)
    fire_cdf: FloatArray  # cumulative fire rows, for inverse-CDF sampling
    rescue_cdf: FloatArray
    obs_cdf: FloatArray
    transition_cdf: FloatArray  # (rows, L): the fire rows (c, f), then the rescue rows (c, f, r), flat
    agent_caps: IntArray  # (N, |G|) capability each agent brings to each element of G-bar (0 for idle)
    task_caps: IntArray  # (N, |G|+1, p) capability agent i brings to every task under action a (row |G|: none)
    sensing: IntArray  # (N,)
    comm: IntArray  # (N,)
    keep: FloatArray  # (N,) tau of each agent's channel
    task_type: IntArray  # (p,) 0 fire, 1 rescue
    task_site: IntArray  # (p,)
    action_site: IntArray  # (|G|,)

    @staticmethod
    def build(sc: Scenario) -> Model:
        """Compute every table of scenario sc."""
        fire, rescue, obs = fire_table(sc), rescue_table(sc), observation_table(sc)
        p, na = sc.n_tasks, sc.n_actions
        caps = np.zeros((sc.n_agents, na), dtype=np.int64)
        for i, a in enumerate(sc.agents):
            for j in range(p):
                caps[i, j] = a.fire if j % 2 == 0 else a.rescue
        task_caps = np.zeros((sc.n_agents, na + 1, p), dtype=np.int64)
        task_caps[:, np.arange(p), np.arange(p)] = caps[:, :p]
        return Model(
            scenario=sc,
            fire=fire,
            rescue=rescue,
            obs=obs,
            info=information_table(sc),
            fire_cdf=_cdf(fire),
            rescue_cdf=_cdf(rescue),
            obs_cdf=_cdf(obs),
            transition_cdf=np.concatenate([_cdf(fire).reshape(-1, sc.levels), _cdf(rescue).reshape(-1, sc.levels)]),
            agent_caps=caps,
            task_caps=task_caps,
            sensing=np.array([a.sensing for a in sc.agents], dtype=np.int64),
            comm=np.array([a.comm for a in sc.agents], dtype=np.int64),
            keep=np.array([keep_probability(sc, a.comm) for a in sc.agents]),
            task_type=np.arange(p, dtype=np.int64) % 2,
            task_site=np.arange(p, dtype=np.int64) // 2,
            action_site=np.array(sc.action_sites, dtype=np.int64),
        )

    def idle_action(self, prev: IntArray) -> IntArray:
        """The idle location at the site of the previous assignment a_o (site 1 before any assignment, a_o = -1):
        where an agent idles, and what an absent agent is taken to do. HT mode (no idle locations): -1, no action.
        Works element-wise on any shape of previous assignments; the one definition of this rule."""
        prev = np.asarray(prev, dtype=np.int64)
        if self.scenario.n_idle == 0:
            return np.full(prev.shape, -1, dtype=np.int64)
        site = np.where(prev >= 0, self.action_site[np.maximum(prev, 0)], 0)
        return (self.scenario.n_tasks + site).astype(np.int64)

    def action_mask(self, prev: IntArray) -> BoolArray:
        """Â(a_o), the reduced action space (docs/model.md): the p tasks and the idle location at the site of a_o
        (HT mode: the p tasks). (...,) previous assignments -> (..., |G|) mask."""
        prev = np.asarray(prev, dtype=np.int64)
        p = self.scenario.n_tasks
        mask = np.zeros(prev.shape + (self.scenario.n_actions,), dtype=bool)
        mask[..., :p] = True
        if self.scenario.n_idle:
            np.put_along_axis(mask, self.idle_action(prev)[..., None], True, axis=-1)
        return mask

    def joint_capability(self, actions: IntArray) -> IntArray:
        """Joint capability on every task, capped: (..., N) actions -> (..., p) capabilities."""
        sc = self.scenario
        n, na = actions.shape[-1], sc.n_actions
        flat = actions.reshape(-1, n)
        if flat.size and int(flat.max()) >= na:
            raise IndexError(f"action {int(flat.max())} is out of range -1..{na - 1}")
        rows = np.where(flat >= 0, flat, na)  # a negative action brings nothing (row |G|)
        if flat.shape[0] < 64:  # few rows: one gather
            caps = self.task_caps.reshape(-1, sc.n_tasks)[rows + (na + 1) * np.arange(n)].sum(axis=1)
        else:  # many rows: one long gather per agent
            caps = self.task_caps[0].take(rows[:, 0], axis=0)
            for i in range(1, n):
                caps += self.task_caps[i].take(rows[:, i], axis=0)
        out: IntArray = np.minimum(caps, sc.capability_max).reshape(actions.shape[:-1] + (sc.n_tasks,))
        return out

    def transition_rows(self, levels: IntArray, caps: IntArray) -> FloatArray:
        """Distribution of every task's next level: (..., p) levels and capabilities -> (..., p, L)."""
        fire_lv = levels[..., 0::2]
        out = np.empty(levels.shape + (self.scenario.levels,))
        out[..., 0::2, :] = self.fire[caps[..., 0::2], fire_lv]
        out[..., 1::2, :] = self.rescue[caps[..., 1::2], fire_lv, levels[..., 1::2]]
        return out

    def sample_transition(self, levels: IntArray, caps: IntArray, u: FloatArray) -> IntArray:
        """Next levels of T by inverse CDF from uniforms u of shape (..., p) (docs/model.md, Transition T)."""
        L = self.scenario.levels
        fire_lv = levels[..., 0::2]
        rows = np.empty_like(levels)  # every task's row of transition_cdf
        rows[..., 0::2] = caps[..., 0::2] * L + fire_lv
        rows[..., 1::2] = (caps[..., 1::2] * L + fire_lv) * L + levels[..., 1::2] + self.fire_cdf.shape[0] * L
        return _inverse_cdf(self.transition_cdf, rows, u)

    def sample_observation(self, true_level: IntArray, sensing: IntArray, u: FloatArray) -> IntArray:
        """Observed levels of O by inverse CDF: true levels, sensing and uniforms of one shape."""
        return _inverse_cdf(self.obs_cdf, sensing * self.scenario.levels + true_level, u)

    def apply_channel(self, level: IntArray, keep: FloatArray, u_keep: FloatArray, u_level: FloatArray) -> IntArray:
        """The simulated channel: with probability 1 - tau replace the level by a uniformly random one."""
        L = self.scenario.levels
        random_level = np.minimum((u_level * L).astype(np.int64), L - 1)
        return np.where(u_keep < keep, level, random_level)


def _inverse_cdf(cdf: FloatArray, row: IntArray, u: FloatArray) -> IntArray:
    """The level drawn by inverse CDF from uniforms u, in flat row `row` of the cumulative table `cdf` (..., L):
    the number of cumulative entries <= u, at most L - 1. The entries of a row never decrease, so counting the first
    L - 1 of them caps the level."""
    L = cdf.shape[-1]
    flat = cdf.reshape(-1, L)
    z = np.zeros(np.shape(row), dtype=np.int8 if L <= 128 else np.int64)
    for lv in range(L - 1):
        z += u >= flat[:, lv][row]
    return z.astype(np.int64)


def _cdf(t: FloatArray) -> FloatArray:
    c = np.cumsum(t, axis=-1)
    # guard against round-off: once the cumulative sum reaches 1, no further (zero-probability) level is drawn
    c[c >= 1.0 - 1e-9] = np.inf
    return c
