"""The transition T, observation O and information I models of docs/model.md, as probability tables.

Each model is defined once, as a table; the simulator samples from the very same tables that the belief filter
and the optimal baseline use (inverse-CDF sampling), so the three can never disagree.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from htlm_world.scenario import REOPEN_LEVEL, Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray


def p_drop_table(sc: Scenario, p_drop: tuple[float, ...] | None = None) -> FloatArray:
    """p_drop(c, l) for c in 0..capability_max and l in 0..L-1 (docs/model.md, Transition T), from the drop
    probabilities by margin `p_drop` (default: the scenario's)."""
    cm, L = sc.capability_max, sc.levels
    drops = sc.p_drop if p_drop is None else p_drop
    table = np.zeros((cm + 1, L))
    for c in range(1, cm + 1):
        for lv in range(1, L):
            margin = c - lv
            k = 0 if margin >= 0 else min(-margin, len(drops) - 1)
            table[c, lv] = drops[k]
    return table


def kind_table(sc: Scenario, k: int) -> FloatArray:
    """T_k[c, g, l, l']: next level l' of a task of kind k at level l, given the joint capability c on it and the
    level g of the task it depends on at its site (docs/model.md, Transition T). g has L entries when the kind
    depends on another, else one (g = 0). A finished task reopens at `REOPEN_LEVEL` with the kind's `hazard`,
    whatever c and g are (level 0 is absorbing when the hazard is 0, as in the paper)."""
    kind = sc.kinds[k]
    cm, L = sc.capability_max, sc.levels
    pd = p_drop_table(sc, kind.p_drop or None)
    gates = L if kind.depends_on else 1
    dd = kind.double_drop
    t = np.zeros((cm + 1, gates, L, L))
    for c in range(cm + 1):
        for g in range(gates):
            t[c, g, 0, 0] = 1.0
            if kind.hazard > 0.0:
                t[c, g, 0, 0] -= kind.hazard
                t[c, g, 0, REOPEN_LEVEL] += kind.hazard
            for lv in range(1, L):
                p = pd[c, lv]
                if c == 0:  # unattended: grows with the kind's growth probability
                    up = min(L - 1, lv + 1)
                    t[c, g, lv, up] += kind.growth
                    t[c, g, lv, lv] += 1.0 - kind.growth
                elif kind.blocked_above is not None and g > kind.blocked_above:
                    t[c, g, lv, lv] = 1.0
                elif dd is not None and c >= lv >= dd.min_level and (dd.gate_at_most is None or g <= dd.gate_at_most):
                    t[c, g, lv, lv - 2] += dd.share * p
                    t[c, g, lv, lv - 1] += (1.0 - dd.share) * p
                    t[c, g, lv, lv] += 1.0 - p
                else:
                    t[c, g, lv, lv - 1] += p
                    t[c, g, lv, lv] += 1.0 - p
    return t


def accuracy(sc: Scenario, k: int, sensing: int) -> float:
    """Observation accuracy of an agent with `sensing` on a task of kind k: min(1, base + slope * sensing), with
    the kind's own base and slope where it has them."""
    kind = sc.kinds[k]
    base = sc.sensing_base if kind.sensing_base is None else kind.sensing_base
    slope = sc.sensing_slope if kind.sensing_slope is None else kind.sensing_slope
    return min(1.0, base + slope * sensing)


def accuracies(sc: Scenario, k: int | None) -> tuple[float, ...]:
    """The accuracy of an observation at every sensing 0..capability_max: of a task of kind k by an agent working
    on it, or (k None) of an agent standing by (`standby_accuracy`, whatever its sensing)."""
    if k is None:
        assert sc.standby_accuracy is not None
        return (sc.standby_accuracy,) * (sc.capability_max + 1)
    return tuple(accuracy(sc, k, s) for s in range(sc.capability_max + 1))


def observation_table(sc: Scenario, k: int | None = 0) -> FloatArray:
    """O_k[s, l, z]: probability of observing z when the true level of a task of kind k is l, for sensing s
    (docs/model.md); k None: the observation of an agent standing by."""
    cm, L = sc.capability_max, sc.levels
    t = np.zeros((cm + 1, L, L))
    for s, acc in enumerate(accuracies(sc, k)):
        for lv in range(L):
            nbrs = [n for n in (lv - 1, lv + 1) if 0 <= n < L]
            t[s, lv, lv] = acc
            for n in nbrs:
                t[s, lv, n] += (1.0 - acc) / len(nbrs)
    return t


def keep_probability(sc: Scenario, comm: int) -> float:
    """tau = min(1, channel_base + comm / capability_max): probability that a broadcast level passes intact."""
    return min(1.0, sc.channel_base + comm / sc.capability_max) if sc.channel else 1.0


def information_table(sc: Scenario, obs: FloatArray) -> FloatArray:
    """I[s, comm, l, m] = tau O_s(m | l) + (1 - tau) / L: likelihood of a teammate's message (docs/model.md), for
    the observation table `obs` of one accuracy class."""
    cm, L = sc.capability_max, sc.levels
    t = np.zeros((cm + 1, cm + 1, L, L))
    for comm in range(cm + 1):
        tau = keep_probability(sc, comm)
        t[:, comm] = tau * obs + (1.0 - tau) / L
    return t


@dataclass(frozen=True)
class Model:
    """All tables of one scenario, computed once. Tasks are numbered as `Scenario.tasks`; a task's kind decides
    its transition table and its accuracy class (kinds with the same observation accuracy share one class)."""

    scenario: Scenario
    kind_tables: tuple[FloatArray, ...]  # per kind (C+1, G_k, L, L), G_k = L if the kind depends on another, else 1
    obs: FloatArray  # (classes, C+1, L, L) O of every accuracy class
    info: FloatArray  # (classes, C+1, C+1, L, L) I of every accuracy class
    obs_cdf: FloatArray  # (classes, C+1, L, L) cumulative rows of obs, for inverse-CDF sampling
    transition_cdf: FloatArray  # (rows, L): every kind's cumulative rows (c, g, l), kind after kind, flat
    transition_pdf: FloatArray  # (rows, L): the same rows as probabilities
    agent_caps: IntArray  # (N, |G|) capability each agent brings to each element of G-bar (0 for idle)
    task_caps: IntArray  # (N, |G|+1, p) capability agent i brings to every task under action a (row |G|: none)
    sensing: IntArray  # (N,)
    comm: IntArray  # (N,)
    keep: FloatArray  # (N,) tau of each agent's channel
    task_kind: IntArray  # (p,) kind index
    task_site: IntArray  # (p,)
    task_gate: IntArray  # (p,) the task at the same site this one depends on; p (a level-0 stand-in) when none
    task_block: IntArray  # (p,) no progress while the task it depends on is above this level (L: never blocked)
    task_class: IntArray  # (p,) accuracy class of every task (row block of obs and info)
    task_row: IntArray  # (p,) first row of the task's kind in transition_cdf
    task_gates: IntArray  # (p,) G of the task's kind (1 or L)
    site_task: IntArray  # (S, K) the task of kind k at site s; -1 when the site has none
    action_site: IntArray  # (|G|,)
    standby_class: int  # accuracy class of an observation standing by; -1: idle agents observe nothing (the paper)
    site_first: IntArray  # (S,) the first task of every site (a site's tasks are numbered one after the other)
    site_count: IntArray  # (S,) the number of tasks of every site

    @staticmethod
    def build(sc: Scenario) -> Model:
        """Every table of scenario sc, computed once per scenario: a scenario is frozen and hashable, so equal
        scenarios share one Model (its `scenario` is the first of them it was built for) and no caller needs to hand
        a Model around. The Models of the last MODELS_KEPT scenarios are kept."""
        return _build_cached(sc)

    @staticmethod
    def compute(sc: Scenario) -> Model:
        """Compute every table of scenario sc (`build` keeps the result)."""
        L, p, na = sc.levels, sc.n_tasks, sc.n_actions
        tables = tuple(kind_table(sc, k) for k in range(sc.n_kinds))
        accs = [accuracies(sc, k) for k in range(sc.n_kinds)]
        standby = accuracies(sc, None) if sc.standby_accuracy is not None and sc.n_idle else None
        classes = list(dict.fromkeys(accs if standby is None else [*accs, standby]))
        kind_class = [classes.index(a) for a in accs]
        first_kind: list[int | None] = [kind_class.index(c) if c in kind_class else None for c in range(len(classes))]
        obs = np.stack([observation_table(sc, k) for k in first_kind])
        rows = np.cumsum([0] + [t.shape[0] * t.shape[1] * L for t in tables])
        site_task = np.full((sc.n_sites, sc.n_kinds), -1, dtype=np.int64)
        for j, (s, k) in enumerate(sc.tasks):
            site_task[s, k] = j
        task_kind = np.array([k for _, k in sc.tasks], dtype=np.int64).reshape(p)
        task_site = np.array([s for s, _ in sc.tasks], dtype=np.int64).reshape(p)
        dep = sc.kind_dependencies
        gate = np.array(  # its task at the same site; p (level 0) when the kind depends on none or the site lacks it
            [site_task[s, dep[k]] if dep[k] >= 0 and site_task[s, dep[k]] >= 0 else p for s, k in sc.tasks],
            dtype=np.int64,
        ).reshape(p)
        caps = np.zeros((sc.n_agents, na), dtype=np.int64)
        for i, a in enumerate(sc.agents):
            for j, (_, k) in enumerate(sc.tasks):
                caps[i, j] = a.capability(sc.kinds[k].uses)
        task_caps = np.zeros((sc.n_agents, na + 1, p), dtype=np.int64)
        task_caps[:, np.arange(p), np.arange(p)] = caps[:, :p]
        return Model(
            scenario=sc,
            kind_tables=tables,
            obs=obs,
            info=np.stack([information_table(sc, o) for o in obs]),
            obs_cdf=_cdf(obs),
            transition_cdf=np.concatenate([_cdf(t).reshape(-1, L) for t in tables]),
            transition_pdf=np.concatenate([t.reshape(-1, L) for t in tables]),
            agent_caps=caps,
            task_caps=task_caps,
            sensing=np.array([a.sensing for a in sc.agents], dtype=np.int64),
            comm=np.array([a.comm for a in sc.agents], dtype=np.int64),
            keep=np.array([keep_probability(sc, a.comm) for a in sc.agents]),
            task_kind=task_kind,
            task_site=task_site,
            task_gate=gate,
            task_block=np.array(
                [L if k.blocked_above is None or not k.depends_on else k.blocked_above for k in sc.kinds],
                dtype=np.int64,
            )[task_kind],
            task_class=np.array(kind_class, dtype=np.int64)[task_kind],
            task_row=rows[:-1].astype(np.int64)[task_kind],
            task_gates=np.array([t.shape[1] for t in tables], dtype=np.int64)[task_kind],
            site_task=site_task,
            action_site=np.array(sc.action_sites, dtype=np.int64),
            standby_class=-1 if standby is None else classes.index(standby),
            site_first=np.searchsorted(task_site, np.arange(sc.n_sites)).astype(np.int64),
            site_count=np.bincount(task_site, minlength=sc.n_sites).astype(np.int64),
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

    def rest_action(self, prev: IntArray) -> IntArray:
        """What a baseline agent does when it takes no task: idle at the site of its previous assignment
        (`idle_action`); HT mode (no idle locations): stay on its previous task, task 0 before any."""
        prev = np.asarray(prev, dtype=np.int64)
        return self.idle_action(prev) if self.scenario.n_idle else np.where(prev >= 0, prev, 0)

    def observes(self, actions: IntArray, t: int | None) -> tuple[IntArray, IntArray]:
        """Which task each action observes at step t (1..h), and with which accuracy class (docs/model.md,
        Observation O): an agent working on a task observes it, with its kind's class; with `standby_accuracy`, an
        agent idling at site s observes the site's tasks in turn, task t mod m of its m tasks, with the standby
        class; otherwise -1 (no observation). Every teammate knows it from the action and t, so a standing-by
        agent's broadcast is evidence like a worker's. The one definition of the rule, for the simulator, the world's
        records and every belief. Works element-wise on any shape of actions.

        Raises:
            ValueError: t is None while the scenario has standby (which task depends on the step).
        """
        a = np.asarray(actions, dtype=np.int64)
        p = self.scenario.n_tasks
        working = (a >= 0) & (a < p)
        task = np.where(working, a, -1)
        cls = np.where(working, self.task_class[np.clip(a, 0, p - 1)], -1)
        if self.standby_class >= 0:
            if t is None:
                raise ValueError("the step t is needed: which task a standing-by agent observes depends on it")
            idle = a >= p
            site = np.clip(a - p, 0, self.site_first.size - 1)
            task = np.where(idle, self.site_first[site] + t % self.site_count[site], task)
            cls = np.where(idle, self.standby_class, cls)
        return task.astype(np.int64), cls.astype(np.int64)

    def action_mask(self, prev: IntArray) -> BoolArray:
        """Â(a_o), the reduced action space (docs/model.md): the p tasks and the idle location at the site of a_o
        (HT mode: the p tasks). (...,) previous assignments -> (..., |G|) mask."""
        prev = np.asarray(prev, dtype=np.int64)
        if prev.size and int(prev.min()) >= -1 and int(prev.max()) < self.scenario.n_actions:
            out: BoolArray = self._action_masks[prev]  # row -1, the last, is a_o = -1
            return out
        return self._action_mask_rule(prev)

    @functools.cached_property
    def _action_masks(self) -> BoolArray:
        """`action_mask` of a_o = 0, ..., |G| - 1, then of -1 (none): the rows it reads, made once."""
        return self._action_mask_rule(np.append(np.arange(self.scenario.n_actions, dtype=np.int64), -1))

    def _action_mask_rule(self, prev: IntArray) -> BoolArray:
        """`action_mask` worked out for every element of prev."""
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

    def gate_levels(self, levels: IntArray) -> IntArray:
        """(..., p) levels -> (..., p) the level of the task each task depends on at its site (0 when none)."""
        ext = np.concatenate([levels, np.zeros(levels.shape[:-1] + (1,), dtype=levels.dtype)], axis=-1)
        out: IntArray = ext[..., self.task_gate]
        return out

    def _rows(self, levels: IntArray, caps: IntArray) -> IntArray:
        """Every task's row of the transition tables: (..., p) levels and capabilities -> (..., p) rows."""
        out: IntArray = (caps * self.task_gates + self.gate_levels(levels)) * self.scenario.levels
        return out + levels + self.task_row

    def blocked(self, levels: IntArray) -> BoolArray:
        """(..., p) levels -> (..., p) whether each task is held back by the task it depends on (its level above the
        kind's `blocked_above`): the one definition of the rule for anyone judging levels (true or believed)."""
        out: BoolArray = self.gate_levels(levels) > self.task_block
        return out

    def transition_rows(self, levels: IntArray, caps: IntArray) -> FloatArray:
        """Distribution of every task's next level: (..., p) levels and capabilities -> (..., p, L)."""
        out: FloatArray = self.transition_pdf[self._rows(levels, caps)]
        return out

    def sample_transition(self, levels: IntArray, caps: IntArray, u: FloatArray) -> IntArray:
        """Next levels of T by inverse CDF from uniforms u of shape (..., p) (docs/model.md, Transition T)."""
        return _inverse_cdf(self.transition_cdf, self._rows(levels, caps), u)

    def sample_observation(
        self,
        task: IntArray,
        true_level: IntArray,
        sensing: IntArray,
        u: FloatArray,
        cls: IntArray | None = None,
    ) -> IntArray:
        """Observed levels of O by inverse CDF: the observed tasks, their true levels, the observers' sensing and
        uniforms, all of one shape; `cls` the accuracy classes of the observations (`observes`; None: the tasks'
        own, every observer working)."""
        L, cm = self.scenario.levels, self.scenario.capability_max
        c = self.task_class[task] if cls is None else cls
        return _inverse_cdf(self.obs_cdf, (c * (cm + 1) + sensing) * L + true_level, u)

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


MODELS_KEPT = 32
"""How many scenarios' Models `Model.build` keeps (least recently used first out)."""


@functools.lru_cache(maxsize=MODELS_KEPT)
def _build_cached(sc: Scenario) -> Model:
    """`Model.compute`, kept per scenario (`Model.build`)."""
    return Model.compute(sc)
