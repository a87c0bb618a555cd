"""The belief filter of docs/model.md (Eq. 2 of the paper): per-site joint belief over the levels of the site's tasks.

A site's belief is a joint distribution over one level per "slot" (K of them, `FilterTables.slots`). When a site may
hold a task of every kind (the scenario's kinds are no more than the most tasks at one site), slot k is kind k, in
the order of `Scenario.kinds`, and a kind the site has no task of is a slot certain of level 0 that nothing changes.
When the scenario has more kinds than any site holds (five kinds, at most three at a site), slot j of a site is its
j-th task (its kinds in the order the prediction applies them), so a site's belief holds L^3 numbers, not L^5.
Vectorized over a batch of episodes and the agents of a team: beliefs have shape (B, N, S, L, ..., L) with K level
axes.

Every number is computed with the same floating-point operations in the same order as the plain formulas (a
prediction applies each kind's factor of T in turn, the kinds that depend on another first, each the sum over the
previous level, in increasing order, of belief x T; the posterior is prediction x the likelihood of every slot in
slot order, normalised by numpy's pairwise sum of the site's L^K entries; marginals as numpy sums them), so results
do not depend on the batch shape: one agent's row at batch 1 (the ROS agents, `AgentMind`) equals its row in a
batch of the in-process `Team` bit for bit. What makes it fast keeps those numbers:

- the site-major layout (L^K, S, ...) of `to_sites`: every operation runs over long contiguous rows of episodes;
- T is banded (a level moves by at most a few steps), so a prediction adds only the terms whose table entry can be
  non-zero; the others are exact zeros, and adding +0.0 to a non-negative sum changes no bit;
- the likelihood of any combination of evidence comes from a table computed once with the same products
  (`FilterTables.evidence`), indexed by an integer code of who reported which level.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import Belief, BoolArray, FloatArray, IntArray, Marginals

EVIDENCE_TABLE_LIMIT = 1 << 21
"""Largest evidence table (classes · N · (L+1)^N · L entries) kept in memory; beyond it the likelihood is
multiplied out."""


@dataclass(frozen=True)
class Band:
    """The terms of a prediction whose input is `offset` units away from the output in a site's L·L block."""

    offset: int
    """Unit of the input term minus unit of the output entry."""
    lo: int
    """First output unit where the coefficient can be non-zero for some capability."""
    hi: int
    """One past the last such output unit."""
    row: int
    """Row of `Bands.coefficients` holding the coefficient of output unit lo (hi - lo rows)."""


@dataclass(frozen=True)
class Bands:
    """One slot's factor of T as bands, in the order their terms are added. The L^K entries of a site (row-major
    over the slots) are grouped in units of `width` consecutive entries that share their coefficients (entries that
    differ only in slots after both the kind's own and the one it depends on)."""

    width: int
    """Entries per unit (a power of L)."""
    bands: tuple[Band, ...]
    """The bands whose coefficients can be non-zero, in the order their terms are added."""
    starts: bool
    """True: the first band has offset 0 and its terms start the sum; False: the sum starts at zero."""
    ones: int
    """From this unit on, the first band's coefficient is 1.0 for every capability: its terms are copies."""
    table: FloatArray
    """(codes, rows) the coefficients of every band's output units, by capability code (`FilterTables.slot_caps`:
    the joint capability 0..C, C+1 for no task (1.0), plus C+2 times the slot's variant at the site)."""
    by_row: FloatArray
    """`table` transposed, (rows, codes): what `coefficients` gathers from."""

    @staticmethod
    def build(tabs: list[tuple[int, FloatArray]], levels: int) -> Bands:
        """Bands of a factor given as its coefficient rows.

        Args:
            tabs: (offset, tab) in the order of the original sum (increasing summed level): tab[c, out] is the
                coefficient of input entry out + offset in output entry out, for every capability c.
            levels: L.
        """
        n = tabs[0][1].shape[1] if tabs else 1
        width = 1
        w = n // levels
        while w > 1:
            if all(off % w == 0 for off, _ in tabs) and all(
                (t.reshape(t.shape[0], -1, w) == t.reshape(t.shape[0], -1, w)[..., :1]).all() for _, t in tabs
            ):
                width = w
                break
            w //= levels
        found: list[tuple[int, int, int, FloatArray]] = []
        for off, tab in tabs:
            units = tab[:, ::width]
            nz = np.flatnonzero((units != 0.0).any(axis=0))
            if nz.size:
                lo, hi = int(nz[0]), int(nz[-1]) + 1
                found.append((off // width, lo, hi, units[:, lo:hi]))
        # addition is commutative: the sum may start with the offset-0 band when it is one of the first two terms
        starts = any(f[0] == 0 for f in found[:2])
        if starts:
            found.sort(key=lambda f: f[0] != 0)  # stable: the others keep their order
        ones = n // width
        if starts:  # x * 1.0 is x: the first band's trailing units of coefficient 1.0 need no table
            off, lo, hi, tab = found[0]
            while ones > lo and ones == hi and (tab[:, ones - 1 - lo] == 1.0).all():
                ones -= 1
                hi -= 1
            found[0] = (off, lo, hi, tab[:, : hi - lo])
        bands, row = [], 0
        for off, lo, hi, _ in found:
            bands.append(Band(off, lo, hi, row))
            row += hi - lo
        rows = tabs[0][1].shape[0] if tabs else 1
        table = np.concatenate([f[3] for f in found], axis=1) if found else np.zeros((rows, 0))
        return Bands(width, tuple(bands), starts, ones, np.ascontiguousarray(table), np.ascontiguousarray(table.T))

    def coefficients(self, caps: IntArray) -> FloatArray:
        """Every band's coefficients for capabilities caps (...): (rows, 1, ...), unit-major, for `apply`."""
        flat = np.take(self.by_row, caps.reshape(-1), axis=1)  # (rows, caps.size)
        out: FloatArray = flat.reshape((self.table.shape[1], 1) + caps.shape)
        return out

    def apply(self, x: FloatArray, coef: FloatArray, out: FloatArray, part: FloatArray) -> FloatArray:
        """sum over the input entries of coefficient x input for site-major x (L·L, ...), with `coefficients`
        broadcastable against x[0], written into `out` (shaped like x) with `part` (as large) as scratch."""
        units = (x.shape[0] // self.width, self.width) + x.shape[1:]
        xu, ou, pu = x.reshape(units), out.reshape(units), part.reshape(units)
        todo = self.bands
        if self.starts:
            b = todo[0]
            np.multiply(xu[b.lo : b.hi], coef[b.row : b.row + b.hi - b.lo], out=ou[b.lo : b.hi])
            ou[: b.lo] = 0.0
            ou[b.hi : self.ones] = 0.0
            np.copyto(ou[self.ones :], xu[self.ones :])
            todo = todo[1:]
        else:
            out[...] = 0.0
        for b in todo:
            k = b.hi - b.lo
            np.multiply(xu[b.lo + b.offset : b.hi + b.offset], coef[b.row : b.row + k], out=pu[:k])
            np.add(ou[b.lo : b.hi], pu[:k], out=ou[b.lo : b.hi])
        return out


@dataclass(frozen=True)
class FilterTables:
    """Everything of one model the filter precomputes (`filter_tables` keeps one per model)."""

    levels: int
    """L."""
    slots: int
    """K, the level axes of a site's joint belief: the scenario's kinds, or the most tasks at one site when fewer
    (module docstring)."""
    factors: tuple[tuple[int, Bands], ...]
    """(slot, its factor of T) in the order the prediction applies them: a kind before the kind it depends on
    (whose slot still holds the current level when the dependent's factor reads it)."""
    slot_task: IntArray
    """(K, S) the task of every slot of every site; p (a stand-in: capability C+1, likelihood 1) where the site has
    no task there."""
    slot_code: IntArray
    """(K, S) what `slot_caps` adds to a slot's capability at every site: C+2 times the index of the slot's variant
    there (the kind of its task and the slot that kind depends on), 0 where slot k is kind k."""
    task_slot: IntArray
    """(p,) the slot of every task at its site."""
    absent: int
    """The capability index of a slot without a task (C+1): its factor is the identity."""
    stand_in: bool
    """Some site lacks a kind: `slot_task` names the stand-in task p, which the slot functions append."""
    base: int
    """L + 1: the evidence code of a task holds one digit per agent, 0 for no report, else the level + 1."""
    powers: IntArray
    """(N,) base^k, the place of agent k's digit."""
    evidence: FloatArray | None
    """(classes · N · base^N, L) likelihood of every code for every receiving agent and accuracy class (row
    (class · N + i) · base^N + code), the product of the reports' likelihood rows in increasing agent order (O for the
    receiver's own report, I for others'); None when larger than EVIDENCE_TABLE_LIMIT."""
    by_level: FloatArray | None
    """(L, classes · N · base^N) the evidence table, level-major."""

    @staticmethod
    def build(model: Model) -> FilterTables:
        """Compute the tables of `model`."""
        sc = model.scenario
        L, n, K = sc.levels, sc.n_agents, sc.n_kinds
        gate = sc.kind_dependencies
        depth = []
        for k in range(K):
            d, g = 0, gate[k]
            while g >= 0:
                d, g = d + 1, gate[g]
            depth.append(d)
        order = sorted(range(K), key=lambda k: (-depth[k], -k))
        S, p, codes = sc.n_sites, sc.n_tasks, sc.capability_max + 2
        most = max(len(site.tasks) for site in sc.sites)
        if most >= K:  # slot k is kind k at every site; its factor is the kind's, applied in `order`
            slots, applied = K, order
            slot_kind = np.repeat(np.arange(K)[:, None], S, axis=1)  # (K, S)
            slot_gate = np.repeat(np.asarray(gate, dtype=np.int64)[:, None], S, axis=1)
        else:  # slot j of a site is its j-th task in `order`: a dependent's slot comes before its gate's
            slots, applied = most, list(range(most))
            slot_kind = np.full((most, S), -1, dtype=np.int64)
            slot_gate = np.full((most, S), -1, dtype=np.int64)
            for s in range(S):
                here = [k for k in order if model.site_task[s, k] >= 0]
                for j, k in enumerate(here):
                    slot_kind[j, s] = k
                    slot_gate[j, s] = here.index(gate[k]) if gate[k] in here else -1
        slot_task = np.full((slots, S), p, dtype=np.int64)
        slot_code = np.zeros((slots, S), dtype=np.int64)
        task_slot = np.zeros(p, dtype=np.int64)
        factor_of: dict[int, Bands] = {}
        for j in range(slots):
            variants = list(dict.fromkeys(zip(slot_kind[j].tolist(), slot_gate[j].tolist(), strict=True)))
            variants = [v for v in variants if v[0] >= 0] or [(0, -1)]  # a slot no site fills: the identity
            for s in range(S):
                k = int(slot_kind[j, s])
                if k >= 0:
                    t = int(model.site_task[s, k])
                    slot_task[j, s] = t if t >= 0 else p
                    if t >= 0:
                        task_slot[t] = j
                    slot_code[j, s] = variants.index((k, int(slot_gate[j, s]))) * codes
            factor_of[j] = _factor_bands([(model.kind_tables[k], g) for k, g in variants], j, slots, L)
        factors = tuple((j, factor_of[j]) for j in applied)
        base = L + 1
        powers = base ** np.arange(n, dtype=np.int64)
        size = model.obs.shape[0] * n * base**n * L
        ev = _evidence_table(model, base) if size <= EVIDENCE_TABLE_LIMIT else None
        return FilterTables(
            levels=L,
            slots=slots,
            factors=factors,
            slot_task=slot_task,
            slot_code=slot_code,
            task_slot=task_slot,
            absent=sc.capability_max + 1,
            stand_in=bool((slot_task == sc.n_tasks).any()),
            base=base,
            powers=powers,
            evidence=ev,
            by_level=None if ev is None else np.ascontiguousarray(ev.T),
        )

    def slot_caps(self, caps: IntArray) -> list[IntArray]:
        """Every slot's capability codes (S, ...) of task-major joint capabilities (p, ...): the joint capability on
        the slot's task (C+1 where it has none), plus the slot's `slot_code` at every site."""
        if self.stand_in:
            caps = np.concatenate([caps, np.full((1,) + caps.shape[1:], self.absent, dtype=caps.dtype)])
        out = [caps[self.slot_task[k]] for k in range(self.slots)]
        for k in range(self.slots):
            if self.slot_code[k].any():
                out[k] = out[k] + self.slot_code[k].reshape((-1,) + (1,) * (caps.ndim - 1))
        return out

    def slot_likelihoods(self, lik: FloatArray, axis: int) -> list[FloatArray]:
        """Every slot's likelihood of task-major likelihoods: the task axis `axis` of `lik` replaced by the sites
        (S), a slot without a task weighing every level 1."""
        if self.stand_in:
            lik = np.concatenate([lik, np.ones(lik.shape[:axis] + (1,) + lik.shape[axis + 1 :])], axis=axis)
        return [np.take(lik, self.slot_task[k], axis=axis) for k in range(self.slots)]


def _factor_bands(variants: list[tuple[FloatArray, int]], slot: int, slots: int, levels: int) -> Bands:
    """The bands of one slot's factor of T over a site's L^K entries, for each of its variants (a kind's table
    T[c, g, l, l'] and the slot `gate` holding the level g of the task it depends on; -1: none, g = 0): output entry
    (.., l', ..) takes the input entries (.., l, ..) of the same other levels with coefficient T[c, g, l, l']. The
    rows of variant v are the codes v (C+2) + c, c = 0..C+1; row C+1 is the identity (a site without this task)."""
    L, K = levels, slots
    idx = np.indices((L,) * K).reshape(K, -1)
    out_level = idx[slot]
    stride = L ** (K - 1 - slot)
    fulls = [np.concatenate([t, np.broadcast_to(np.eye(L), (1,) + t.shape[1:])], axis=0) for t, _ in variants]
    gates = [idx[gate] if gate >= 0 else np.zeros_like(out_level) for _, gate in variants]
    codes = fulls[0].shape[0]
    tabs = []
    for delta in range(-(L - 1), L):
        in_level = out_level + delta
        ok = (in_level >= 0) & (in_level < L)
        tab = np.zeros((codes * len(variants), out_level.size))
        for v, (full, g) in enumerate(zip(fulls, gates, strict=True)):
            tab[v * codes : (v + 1) * codes, ok] = full[:, g[ok], in_level[ok], out_level[ok]]
        if (tab != 0.0).any():
            tabs.append((delta * stride, tab))
    return Bands.build(tabs, L)


def _evidence_table(model: Model, base: int) -> FloatArray:
    n, L = model.scenario.n_agents, model.scenario.levels
    codes = np.arange(base**n, dtype=np.int64)
    ones = np.ones((L, 1))
    classes = model.obs.shape[0]
    out = np.empty((classes, n, codes.size, L))
    for c in range(classes):
        # every agent's report row of every code, as a teammate's message (I) and as the receiver's own observation
        # (O); digit 0 (no report) gives a row of ones, and x * 1.0 is x
        heard, own = [], []
        for k in range(n):
            digit = (codes // base**k) % base
            heard.append(np.hstack([ones, model.info[c, model.sensing[k], model.comm[k]]])[:, digit].T)
            own.append(np.hstack([ones, model.obs[c, model.sensing[k]]])[:, digit].T)
        for i in range(n):
            lik = np.ones((codes.size, L))
            for k in range(n):
                lik *= own[k] if k == i else heard[k]
            out[c, i] = lik
    return out.reshape(classes * n * codes.size, L)


_BY_MODEL: dict[int, tuple[weakref.ref[Model], FilterTables]] = {}
_BY_SCENARIO: dict[Scenario, tuple[Model, FilterTables]] = {}
_SCENARIOS_KEPT = 16


def filter_tables(model: Model) -> FilterTables:
    """The `FilterTables` of `model`, computed once per scenario (models of one scenario share them) and kept while
    the model lives."""
    key = id(model)
    hit = _BY_MODEL.get(key)
    if hit is not None and hit[0]() is model:
        return hit[1]
    known = _BY_SCENARIO.get(model.scenario)
    if known is not None and _same_tables(known[0], model):
        tables = known[1]
    else:
        tables = FilterTables.build(model)
        _BY_SCENARIO[model.scenario] = (model, tables)
        while len(_BY_SCENARIO) > _SCENARIOS_KEPT:
            del _BY_SCENARIO[next(iter(_BY_SCENARIO))]
    _BY_MODEL[key] = (weakref.ref(model, lambda _ref: _BY_MODEL.pop(key, None)), tables)
    return tables


def _same_tables(a: Model, b: Model) -> bool:
    """Whether two models hold the tables the filter is computed from."""
    return all(
        np.array_equal(getattr(a, name), getattr(b, name))
        for name in ("transition_pdf", "obs", "info", "sensing", "comm", "site_task")
    )


# ----- layouts --------------------------------------------------------------------------------------------------


def to_sites(belief: Belief, kinds: int) -> FloatArray:
    """The site-major view (L^K, S, ...) of beliefs (..., S, L, ..., L) with K level axes (a view when the layout
    allows)."""
    k = belief.ndim - kinds - 1
    flat = belief.reshape(belief.shape[: k + 1] + (-1,))
    return flat.transpose(k + 1, k, *range(k))


def from_sites(x: FloatArray, levels: int, kinds: int) -> Belief:
    """The inverse of `to_sites`: beliefs (..., S, L, ..., L) of site-major x (L^K, S, ...), a view of x."""
    k = x.ndim - 2
    grid = x.reshape((levels,) * kinds + x.shape[1:])
    return grid.transpose(*range(kinds + 1, kinds + 1 + k), kinds, *range(kinds))


def initial_belief(model: Model, batch: int, agents: int | None = None) -> Belief:
    """b0: certain of the initial levels (level 0 in the slots without a task), for every agent of every episode:
    (batch, agents, S, L, ..., L), `agents` the scenario's unless given (every agent's b0 is the same: an agent
    alone asks for 1). (Also computes the model's `filter_tables` if not yet done, so that the first step of an
    episode does not wait for them.)"""
    tables = filter_tables(model)
    sc = model.scenario
    L = sc.levels
    n = sc.n_agents if agents is None else agents
    b = np.zeros((batch, n, sc.n_sites) + (L,) * tables.slots)
    start = (*sc.initial_levels, 0)  # the stand-in task p: level 0
    for s in range(sc.n_sites):
        at = tuple(start[j] for j in tables.slot_task[:, s])
        b[(slice(None), slice(None), s, *at)] = 1.0
    return b


# ----- the filter on the site-major layout --------------------------------------------------------------------


def predict_sites(
    tables: FilterTables,
    x: FloatArray,
    caps: list[IntArray],
    out: FloatArray | None = None,
    work: tuple[FloatArray, FloatArray] | None = None,
) -> FloatArray:
    """`predict` on site-major beliefs x (L^K, S, ...) with every slot's capabilities (S, ...) broadcastable
    against x[0] (`FilterTables.slot_caps`).

    Args:
        out: where to write the prediction (shaped like x); a new array when None.
        work: two scratch arrays shaped like x; new ones when None.
    """
    tmp, part = work if work is not None else (np.empty_like(x), np.empty_like(x))
    pred = np.empty_like(x) if out is None else out
    src = x
    last = len(tables.factors) - 1
    for i, (slot, bands) in enumerate(tables.factors):
        dst = pred if (last - i) % 2 == 0 else tmp  # the last factor writes into pred
        src = bands.apply(src, bands.coefficients(caps[slot]), dst, part)
    return pred


def pairwise_sum(x: FloatArray, lo: int = 0, n: int | None = None, out: FloatArray | None = None) -> FloatArray:
    """x[lo] + ... + x[lo + n - 1] in the order of numpy's pairwise summation (what `ndarray.sum` does along a
    contiguous axis): one by one below 8 terms, 8 interleaved partial sums up to 128, halves beyond. Written into
    `out` when given."""
    n = x.shape[0] - lo if n is None else n
    res: FloatArray = np.empty(x.shape[1:]) if out is None else out
    if n < 8:
        if n < 2:
            np.copyto(res, x[lo])
        else:
            np.add(x[lo], x[lo + 1], out=res)
        for i in range(lo + 2, lo + n):
            res += x[i]
        return res
    if n <= 128:
        r = x[lo : lo + 8] + x[lo + 8 : lo + 16] if n >= 16 else x[lo : lo + 8].copy()
        i = 16 if n >= 16 else 8
        while i < n - n % 8:
            r += x[lo + i : lo + i + 8]
            i += 8
        q = r[0::2] + r[1::2]
        np.add(q[0] + q[1], q[2] + q[3], out=res)
        for j in range(i, n):
            res += x[lo + j]
        return res
    half = n // 2
    half -= half % 8
    return np.add(pairwise_sum(x, lo, half), pairwise_sum(x, lo + half, n - half), out=res)


def pairwise_sum_rows(rows: list[FloatArray]) -> FloatArray:
    """`pairwise_sum` of the stacked rows, without stacking them: the same additions in the same order, row by
    row (for rows that are views no reshape can stack without a copy)."""

    def block(lo: int, n: int) -> FloatArray:
        if n < 8:
            res = rows[lo].copy() if n < 2 else rows[lo] + rows[lo + 1]
            for i in range(lo + 2, lo + n):
                res += rows[i]
            return res
        if n <= 128:
            r = [rows[lo + j] + rows[lo + 8 + j] if n >= 16 else rows[lo + j].copy() for j in range(8)]
            i = 16 if n >= 16 else 8
            while i < n - n % 8:
                for j in range(8):
                    r[j] += rows[lo + i + j]
                i += 8
            q = [r[2 * j] + r[2 * j + 1] for j in range(4)]
            res = (q[0] + q[1]) + (q[2] + q[3])
            for j in range(i, n):
                res += rows[lo + j]
            return res
        half = n // 2
        half -= half % 8
        return block(lo, half) + block(lo + half, n - half)

    return block(0, len(rows))


def update_sites(
    tables: FilterTables,
    x: FloatArray,
    caps: list[IntArray],
    liks: list[FloatArray],
    out: FloatArray | None = None,
    work: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, BoolArray]:
    """`update` on site-major beliefs x (L^K, S, ...).

    Args:
        caps: every slot's (S, ...) joint capabilities, broadcastable against x[0].
        liks: every slot's (L, S, ...) likelihood of every level, broadcastable against x[0].
        out: where to write the new beliefs (shaped like x, not overlapping it); a new array when None.
        work: two scratch arrays shaped like x; new ones when None.

    Returns:
        The new site-major beliefs and the (S, ...) mask of sites whose evidence had zero probability (they keep
        the prediction).
    """
    L, K = tables.levels, tables.slots
    post, part = work if work is not None else (np.empty_like(x), np.empty_like(x))
    pred = np.empty_like(x) if out is None else out  # the prediction, then the posterior
    predict_sites(tables, x, caps, pred, (post, part))
    grid = (L,) * K + x.shape[1:]
    # prediction x every slot's likelihood in slot order, in one pass: einsum multiplies its operands left to right
    axes = "gstuvwxyz"[:K]
    spec = ",".join([f"{axes}...", *[f"{a}..." for a in axes]]) + f"->{axes}..."
    np.einsum(spec, pred.reshape(grid), *liks, out=post.reshape(grid))
    z = pairwise_sum(post)
    bad: BoolArray = z <= 0.0
    if bad.any():  # those sites keep the prediction
        np.divide(post, np.where(bad, 1.0, z), out=pred, where=np.broadcast_to(~bad, post.shape))
    else:
        np.divide(post, z, out=pred)
    return pred, bad


def marginals_sites(x: FloatArray, levels: int, kinds: int) -> list[FloatArray]:
    """Every slot's marginals (L, S, ...) of site-major beliefs x (L^K, S, ...), summed over the other slots'
    entries in row-major order as numpy sums a site's belief: pairwise, but one entry after the other for the last
    slot (whose entries are not contiguous)."""
    L, K = levels, kinds
    grid = x.reshape((L,) * K + x.shape[1:])
    rest = tuple(range(K, grid.ndim))
    out = []
    for k in range(K - 1):  # slot k last among the level axes, the others flattened in front
        order = (*range(k), *range(k + 1, K), k, *rest)
        moved = grid.transpose(order)
        if k == 0:  # the other slots' axes are adjacent: one view of rows
            out.append(pairwise_sum(moved.reshape((L ** (K - 1), L) + x.shape[1:])))
        else:  # flattening them would copy every belief: their entries one by one instead
            out.append(pairwise_sum_rows([moved[i] for i in np.ndindex((L,) * (K - 1))]))
    last = grid.reshape((L ** (K - 1), L) + x.shape[1:])  # the last slot's entries: one after the other
    total = last[0].copy()
    for i in range(1, last.shape[0]):
        total += last[i]
    out.append(total)
    return out


def task_marginals(model: Model, slots: list[FloatArray]) -> FloatArray:
    """The marginals (L, p, ...) of every task, in task order, of every slot's marginals (L, S, ...) (contiguous)."""
    first = slots[0]
    task_slot = filter_tables(model).task_slot
    out: FloatArray = np.empty((first.shape[0], task_slot.size) + first.shape[2:])
    for j, (slot, site) in enumerate(zip(task_slot.tolist(), model.task_site.tolist(), strict=True)):
        out[:, j] = slots[slot][:, site]
    return out


# ----- the evidence ---------------------------------------------------------------------------------------------


def _check_levels(levels: IntArray, used: BoolArray, n_levels: int) -> None:
    if used.any() and int(levels[used].max()) >= n_levels:
        raise IndexError(f"reported level {int(levels[used].max())} is out of range 0..{n_levels - 1}")


def _report_groups(model: Model, actions: IntArray, t: int | None) -> list[tuple[IntArray, IntArray | int]]:
    """The reports of a step in groups that each take one row of the evidence table per task: (the task every
    agent reports on, -1 for none, shaped like `actions`; the accuracy class of the group's rows, per task (p,) or
    one for all). The workers' reports, by their tasks' classes; with standby (`Model.observes`), the standing-by
    agents' reports, by the standby class."""
    task, _cls = model.observes(actions, t)
    if model.standby_class < 0:
        return [(task, model.task_class)]
    standby = actions >= model.scenario.n_tasks
    return [(np.where(standby, -1, task), model.task_class), (np.where(standby, task, -1), model.standby_class)]


def evidence_codes(
    model: Model,
    actions: IntArray,
    observations: IntArray,
    messages: IntArray,
    t: int | None = None,
    tasks: IntArray | None = None,
) -> list[IntArray]:
    """Every agent's evidence codes of every task, all messages delivered: (B, N) -> one (p, N, B) array of rows of
    `FilterTables.evidence` (receiver i's code plus (class · N + i) · base^N) per group of reports
    (`_report_groups`); a task's likelihood is the product of its groups' rows, in group order.

    With `tasks` (task indices of any shape, p for none: `FilterTables.slot_task`), the codes of those tasks
    instead, (tasks.shape..., N, B); the code of "none" is that of no report (a likelihood of 1)."""
    sc = model.scenario
    tab = filter_tables(model)
    p, n = sc.n_tasks, sc.n_agents
    sel = np.arange(p) if tasks is None else tasks
    obs, msgs = observations.T, messages.T  # (N, B)
    powers = tab.powers[:, None]
    msg_digit = np.where(msgs >= 0, msgs + 1, 0) * powers  # (N, B)
    own_digit = np.where(obs >= 0, obs + 1, 0) * powers
    receiver = np.arange(n, dtype=np.int64)[:, None] * tab.base**n  # (N, 1)
    out = []
    for target, cls in _report_groups(model, actions, t):
        reporting = target.T  # (N, B)
        if obs.size and max(int(obs.max()), int(msgs.max())) >= sc.levels:
            _check_levels(msgs, (reporting >= 0) & (msgs >= 0), sc.levels)
            _check_levels(obs, (reporting >= 0) & (obs >= 0), sc.levels)
        hit = reporting == sel[..., None, None]  # (..., N, B): agent k reports on the task
        shared = np.einsum("...kb,kb->...b", hit, msg_digit)  # every report weighed as a teammate's
        codes: IntArray = hit * (own_digit - msg_digit)  # the receiver's own report weighed as its own
        codes += shared[..., None, :]
        codes += receiver
        if model.obs.shape[0] > 1:
            task_cls = np.append(np.broadcast_to(np.asarray(cls), (p,)), 0)  # "none": any class, no digits
            codes += (task_cls[sel] * (n * tab.base**n))[..., None, None]
        out.append(codes)
    return out


def agent_codes(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None = None,
    t: int | None = None,
) -> list[IntArray]:
    """Agent `agent`'s evidence codes of every task (B, p), one array per group of reports (`evidence_codes`):
    rows of `FilterTables.evidence` (see `agent_evidence`)."""
    sc = model.scenario
    tab = filter_tables(model)
    p, n = sc.n_tasks, sc.n_agents
    levels = messages.copy()
    levels[:, agent] = own_observation
    ok = levels >= 0
    if heard is not None:
        mine = np.zeros(ok.shape[1], dtype=bool)
        mine[agent] = True
        ok &= heard | mine
    digit = np.where(ok, levels + 1, 0) * tab.powers
    out = []
    for target, cls in _report_groups(model, actions, t):
        onehot = target[..., None] == np.arange(p)  # (B, N, p): agent k reports on task j
        if levels.size and int(levels.max()) >= sc.levels:
            _check_levels(levels, ok & (target >= 0), sc.levels)
        codes: IntArray = np.einsum("bkj,bk->bj", onehot, digit)
        codes += agent * tab.base**n
        if model.obs.shape[0] > 1:
            codes += np.asarray(cls) * (n * tab.base**n)
        out.append(codes)
    return out


def _agent_evidence_product(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None,
    t: int | None,
) -> FloatArray:
    """`agent_evidence` multiplied out report by report (for teams too large for the evidence table): every report's
    row of its table gathered at once, and multiplied into its task's likelihood in increasing agent order."""
    sc = model.scenario
    b, n = actions.shape
    lik = np.ones((b, sc.n_tasks, sc.levels))
    target, target_cls = model.observes(actions, t)  # (B, N)
    level = np.array(messages, dtype=np.int64)
    level[:, agent] = own_observation
    reports = (target >= 0) & (level >= 0)
    if heard is not None:
        reports &= np.asarray(heard, dtype=bool) | (np.arange(n) == agent)
    who, row = np.nonzero(reports.T)  # by agent, then by episode: the order of the products
    tables = model.info[:, model.sensing, model.comm]  # (C, N, L, L) every teammate's report as I weighs it
    tables[:, agent] = model.obs[:, model.sensing[agent]]  # the agent's own observation, weighed with O
    rows = tables[target_cls[row, who], who, :, level[row, who]]  # (M, L)
    np.multiply.at(lik, (row, target[row, who]), rows)
    return lik


def agent_evidence(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None = None,
    t: int | None = None,
) -> FloatArray:
    """Likelihood of agent `agent`'s evidence of step t for every task level: (B, p, L).

    Its own observation is weighed with O, teammate k's message with I_k (docs/model.md, Information I), each of
    the accuracy class of the report (`Model.observes`: the task's kind's for a worker, the standby class for an
    agent standing by); the likelihood of a task is the product of its reports' rows in increasing agent order (with
    standby: the workers', then the standing-by agents').

    Args:
        actions: (B, N) the joint assignment of the step (as the agent knows it).
        own_observation: (B,) the agent's own observation, -1 when none.
        messages: (B, N) levels received from each teammate after its channel, -1 when none or not sent.
        heard: optional (B, N) mask of teammates whose message arrived; all when None.
        t: the step (1..h); needed when the scenario has standby (which task an idle agent observes).
    """
    tables = filter_tables(model)
    if tables.evidence is None:
        return _agent_evidence_product(model, agent, actions, own_observation, messages, heard, t)
    groups = agent_codes(model, agent, actions, own_observation, messages, heard, t)
    out: FloatArray = tables.evidence[groups[0]]
    for codes in groups[1:]:
        out *= tables.evidence[codes]
    return out


def evidence_sites(
    model: Model, actions: IntArray, observations: IntArray, messages: IntArray, t: int | None = None
) -> list[FloatArray]:
    """Every agent's evidence of step t, all messages delivered, for `update_sites`: every slot's likelihoods
    (L, S, N, B) of (B, N) actions, observations and messages."""
    tables = filter_tables(model)
    if tables.by_level is None:
        lik = evidence(model, actions, observations, messages, t)  # (B, N, p, L)
        sites = np.ascontiguousarray(lik.transpose(3, 1, 2, 0))  # (L, N, p, B)
        return [x.swapaxes(1, 2) for x in tables.slot_likelihoods(sites, axis=2)]  # (L, S, N, B)
    groups = evidence_codes(model, actions, observations, messages, t, tables.slot_task)  # each (K, S, N, B)
    slots = np.take(tables.by_level, groups[0], axis=1)  # (L, K, S, N, B)
    for codes in groups[1:]:
        slots *= np.take(tables.by_level, codes, axis=1)
    return [slots[:, k] for k in range(tables.slots)]


def evidence(
    model: Model, actions: IntArray, observations: IntArray, messages: IntArray, t: int | None = None
) -> FloatArray:
    """Likelihood of every agent's evidence of step t, all messages delivered: (B, N, p, L) (see
    `agent_evidence`)."""
    tables = filter_tables(model)
    n = actions.shape[1]
    if tables.evidence is None:
        rows = [_agent_evidence_product(model, i, actions, observations[:, i], messages, None, t) for i in range(n)]
        return np.stack(rows, axis=1)
    groups = evidence_codes(model, actions, observations, messages, t)  # each (p, N, B)
    out: FloatArray = tables.evidence[groups[0].transpose(2, 1, 0)]
    for codes in groups[1:]:
        out *= tables.evidence[codes.transpose(2, 1, 0)]
    return out


# ----- the filter on (..., S, L, ..., L) beliefs ----------------------------------------------------------------


def predict(model: Model, belief: Belief, caps: IntArray) -> Belief:
    """Predict every site's belief with T (Eq. 2, sum over s of T(s, a, s') b(s)).

    Args:
        belief: (..., S, L, ..., L) with K level axes.
        caps: (..., p) joint capabilities each belief assumes for the step.
    """
    sc = model.scenario
    tables = filter_tables(model)
    k = caps.ndim - 1
    x = predict_sites(tables, to_sites(belief, tables.slots), tables.slot_caps(caps.transpose(k, *range(k))))
    return np.ascontiguousarray(from_sites(x, sc.levels, tables.slots))


def update(model: Model, belief: Belief, caps: IntArray, likelihood: FloatArray) -> tuple[Belief, np.ndarray]:
    """One step of Eq. 2: predict with T, multiply by the evidence, normalise.

    Args:
        belief: (..., S, L, ..., L), e.g. (B, N, S, L, L) for a team or (B, S, L, L) for one agent (K = 2).
        caps: (..., p) joint capabilities each belief assumes for the step.
        likelihood: (..., p, L) from `evidence` or `agent_evidence`.

    Returns:
        The new belief and a (...) mask of agents whose evidence had zero probability: they keep the prediction
        (docs/model.md), and the caller counts the event.
    """
    sc = model.scenario
    tables = filter_tables(model)
    k = caps.ndim - 1
    to_levels = (k + 1, k, *range(k))  # (..., p, L) -> (L, p, ...)
    post, bad = update_sites(
        tables,
        to_sites(belief, tables.slots),
        tables.slot_caps(caps.transpose(k, *range(k))),
        tables.slot_likelihoods(likelihood.transpose(to_levels), axis=1),
    )
    return np.ascontiguousarray(from_sites(post, sc.levels, tables.slots)), np.asarray(bad.any(axis=0), dtype=np.bool_)


def marginals(model: Model, belief: Belief) -> Marginals:
    """Per-task marginals (..., p, L) in task order (`Scenario.tasks`)."""
    sc, k = model.scenario, filter_tables(model).slots
    slots = marginals_sites(to_sites(belief, k), sc.levels, k)  # each (L, S, ...)
    out = task_marginals(model, slots)  # (L, p, ...)
    k = out.ndim - 2
    return np.ascontiguousarray(out.transpose(*range(2, 2 + k), 1, 0))
