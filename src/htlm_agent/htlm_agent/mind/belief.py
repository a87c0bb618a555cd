"""The belief filter of docs/model.md (Eq. 2 of the paper): per-site joint belief over (fire, rescue) levels.

Vectorized over a batch of episodes and the agents of a team: beliefs have shape (B, N, S, L, L).

Every number is computed with the same floating-point operations in the same order as the plain formulas (a
prediction is the sum over the previous level, in increasing order, of belief x T; the posterior is prediction x
fire likelihood x rescue likelihood, normalised by numpy's pairwise sum of the site's L·L entries; marginals as
numpy sums them), so results do not depend on the batch shape: one agent's row at batch 1 (the ROS agents,
`AgentMind`) equals its row in a batch of the in-process `Team` bit for bit. What makes it fast keeps those numbers:

- the site-major layout (L·L, S, ...) of `to_sites`: every operation runs over long contiguous rows of episodes;
- T is banded (a level moves by at most a few steps), so a prediction adds only the terms whose table entry can be
  non-zero; the others are exact zeros, and adding +0.0 to a non-negative sum changes no bit;
- the likelihood of any combination of evidence comes from a table computed once with the same products
  (`FilterTables.evidence`), indexed by an integer code of who reported which level.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import Belief, BoolArray, FloatArray, IntArray, Marginals

EVIDENCE_TABLE_LIMIT = 1 << 21
"""Largest evidence table (N · (L+1)^N · L entries) kept in memory; beyond it the likelihood is multiplied out."""


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
    """One factor of T (rescue or fire) as bands, in the order their terms are added. The L·L entries of a site
    (row-major (first level, second level)) are grouped in units of `width` consecutive entries that share their
    coefficients: single entries for rescue, whole rows of one fire level for fire (its T ignores the rescue level)."""

    width: int
    """Entries per unit (1 or L)."""
    bands: tuple[Band, ...]
    """The bands whose coefficients can be non-zero, in the order their terms are added."""
    starts: bool
    """True: the first band has offset 0 and its terms start the sum; False: the sum starts at zero."""
    ones: int
    """From this unit on, the first band's coefficient is 1.0 for every capability: its terms are copies."""
    table: FloatArray
    """(C+1, rows) the coefficients of every band's output units, by joint capability."""

    @staticmethod
    def build(coef: FloatArray, offsets: list[int], levels: int) -> Bands:
        """Bands of a factor given as coef[c, out, in] over flat entries of a site's L·L block.

        Args:
            coef: (C+1, L·L, L·L) coefficient of input entry `in` in output entry `out`.
            offsets: the flat offsets in the order of the original sum (increasing summed level).
            levels: L.
        """
        n = levels * levels
        tabs = []
        for off in offsets:
            tab = np.zeros((coef.shape[0], n))
            for out in range(n):
                if 0 <= out + off < n:
                    tab[:, out] = coef[:, out, out + off]
            tabs.append(tab)
        rows_shared = all(off % levels == 0 for off in offsets) and all(
            (t.reshape(t.shape[0], levels, levels) == t.reshape(t.shape[0], levels, levels)[..., :1]).all()
            for t in tabs
        )
        width = levels if rows_shared else 1
        found: list[tuple[int, int, int, FloatArray]] = []
        for off, tab in zip(offsets, tabs, strict=True):
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
        table = np.concatenate([f[3] for f in found], axis=1) if found else np.zeros((coef.shape[0], 0))
        return Bands(width, tuple(bands), starts, ones, np.ascontiguousarray(table))

    def coefficients(self, caps: IntArray) -> FloatArray:
        """Every band's coefficients for capabilities caps (...): (rows, 1, ...), unit-major, for `apply`."""
        flat = np.ascontiguousarray(self.table[caps.reshape(-1)].T)
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
    rescue: Bands
    """The rescue factor of T: entry (f, r') from entries (f, r), summed over r in increasing order."""
    fire: Bands
    """The fire factor of T: entry (f', r') from entries (f, r'), summed over f in increasing order."""
    base: int
    """L + 1: the evidence code of a task holds one digit per agent, 0 for no report, else the level + 1."""
    powers: IntArray
    """(N,) base^k, the place of agent k's digit."""
    evidence: FloatArray | None
    """(N · base^N, L) likelihood of every code for every receiving agent (row i · base^N + code), the product of
    the reports' likelihood rows in increasing agent order (O for the receiver's own report, I for others');
    None when larger than EVIDENCE_TABLE_LIMIT."""
    by_level: FloatArray | None
    """(L, N · base^N) the evidence table, level-major."""

    @staticmethod
    def build(model: Model) -> FilterTables:
        """Compute the tables of `model`."""
        sc = model.scenario
        L, n = sc.levels, sc.n_agents
        cmax = model.rescue.shape[0]
        eye = np.eye(L)
        # rescue: out (f, r'), in (f, r), coefficient T_rescue[c, f, r, r']
        rescue = np.einsum("cfrs,fg->cfsgr", model.rescue, eye).reshape(cmax, L * L, L * L)
        # fire: out (f', r'), in (f, r'), coefficient T_fire[c, f, f']
        fire = np.einsum("cfg,sr->cgsfr", model.fire, eye).reshape(cmax, L * L, L * L)
        r_off = sorted({d for d in range(-(L - 1), L) if _band_nonzero(rescue, d)})
        f_off = sorted({d for d in range(-(L - 1) * L, L * L, L) if _band_nonzero(fire, d)})
        base = L + 1
        powers = base ** np.arange(n, dtype=np.int64)
        size = n * base**n * L
        ev = _evidence_table(model, base) if size <= EVIDENCE_TABLE_LIMIT else None
        return FilterTables(
            levels=L,
            rescue=Bands.build(rescue, r_off, L),
            fire=Bands.build(fire, f_off, L),
            base=base,
            powers=powers,
            evidence=ev,
            by_level=None if ev is None else np.ascontiguousarray(ev.T),
        )


def _band_nonzero(coef: FloatArray, off: int) -> bool:
    n = coef.shape[1]
    return any(bool((coef[:, out, out + off] != 0.0).any()) for out in range(n) if 0 <= out + off < n)


def _report_tables(model: Model, receiver: int) -> list[FloatArray]:
    """The likelihood table (L true levels, L reported levels) of every agent's report as `receiver` weighs it."""
    return [
        model.obs[model.sensing[k]] if k == receiver else model.info[model.sensing[k], model.comm[k]]
        for k in range(model.scenario.n_agents)
    ]


def _evidence_table(model: Model, base: int) -> FloatArray:
    n, L = model.scenario.n_agents, model.scenario.levels
    codes = np.arange(base**n, dtype=np.int64)
    ones = np.ones((L, 1))
    # every agent's report row of every code, as a teammate's message (I) and as the receiver's own observation
    # (O); digit 0 (no report) gives a row of ones, and x * 1.0 is x
    heard, own = [], []
    for k in range(n):
        digit = (codes // base**k) % base
        heard.append(np.hstack([ones, model.info[model.sensing[k], model.comm[k]]])[:, digit].T)
        own.append(np.hstack([ones, model.obs[model.sensing[k]]])[:, digit].T)
    out = np.empty((n, codes.size, L))
    for i in range(n):
        lik = np.ones((codes.size, L))
        for k in range(n):
            lik *= own[k] if k == i else heard[k]
        out[i] = lik
    return out.reshape(n * codes.size, L)


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
        for name in ("fire", "rescue", "obs", "info", "sensing", "comm")
    )


# ----- layouts --------------------------------------------------------------------------------------------------


def to_sites(belief: Belief) -> FloatArray:
    """The site-major view (L·L, S, ...) of beliefs (..., S, L, L) (a view when the layout allows)."""
    k = belief.ndim - 3
    flat = belief.reshape(belief.shape[:-2] + (-1,))
    return flat.transpose(k + 1, k, *range(k))


def from_sites(x: FloatArray) -> Belief:
    """The inverse of `to_sites`: beliefs (..., S, L, L) of site-major x (L·L, S, ...), a view of x."""
    L, k = math.isqrt(x.shape[0]), x.ndim - 2
    return x.reshape((L, L) + x.shape[1:]).transpose(*range(3, 3 + k), 2, 0, 1)


def initial_belief(model: Model, batch: int) -> Belief:
    """b0: certain of the initial levels, for every agent of every episode. (Also computes the model's
    `filter_tables` if not yet done, so that the first step of an episode does not wait for them.)"""
    filter_tables(model)
    sc = model.scenario
    L = sc.levels
    b = np.zeros((batch, sc.n_agents, sc.n_sites, L, L))
    for s in range(sc.n_sites):
        b[:, :, s, sc.initial_levels[2 * s], sc.initial_levels[2 * s + 1]] = 1.0
    return b


# ----- the filter on the site-major layout --------------------------------------------------------------------


def predict_sites(
    tables: FilterTables,
    x: FloatArray,
    fire_caps: IntArray,
    rescue_caps: IntArray,
    out: FloatArray | None = None,
    work: tuple[FloatArray, FloatArray] | None = None,
) -> FloatArray:
    """`predict` on site-major beliefs x (L·L, S, ...) with capabilities (S, ...) broadcastable against x[0].

    Args:
        out: where to write the prediction (shaped like x); a new array when None.
        work: two scratch arrays shaped like x; new ones when None.
    """
    tmp, part = work if work is not None else (np.empty_like(x), np.empty_like(x))
    tables.rescue.apply(x, tables.rescue.coefficients(rescue_caps), tmp, part)
    pred = np.empty_like(x) if out is None else out
    return tables.fire.apply(tmp, tables.fire.coefficients(fire_caps), pred, part)


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


def update_sites(
    tables: FilterTables,
    x: FloatArray,
    fire_caps: IntArray,
    rescue_caps: IntArray,
    fire_lik: FloatArray,
    rescue_lik: FloatArray,
    out: FloatArray | None = None,
    work: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, BoolArray]:
    """`update` on site-major beliefs x (L·L, S, ...).

    Args:
        fire_caps, rescue_caps: (S, ...) joint capabilities, broadcastable against x[0].
        fire_lik, rescue_lik: (L, S, ...) likelihood of every fire / rescue level, broadcastable against x[0].
        out: where to write the new beliefs (shaped like x, not overlapping it); a new array when None.
        work: two scratch arrays shaped like x; new ones when None.

    Returns:
        The new site-major beliefs and the (S, ...) mask of sites whose evidence had zero probability (they keep
        the prediction).
    """
    L = tables.levels
    post, part = work if work is not None else (np.empty_like(x), np.empty_like(x))
    pred = np.empty_like(x) if out is None else out  # the prediction, then the posterior
    predict_sites(tables, x, fire_caps, rescue_caps, pred, (post, part))
    grid = (L, L) + x.shape[1:]
    # (prediction x fire likelihood) x rescue likelihood in one pass: einsum multiplies its operands left to right
    np.einsum("gs...,g...,s...->gs...", pred.reshape(grid), fire_lik, rescue_lik, out=post.reshape(grid))
    z = pairwise_sum(post)
    bad: BoolArray = z <= 0.0
    if bad.any():  # those sites keep the prediction
        np.divide(post, np.where(bad, 1.0, z), out=pred, where=np.broadcast_to(~bad, post.shape))
    else:
        np.divide(post, z, out=pred)
    return pred, bad


def marginals_sites(x: FloatArray, out: tuple[FloatArray, FloatArray] | None = None) -> tuple[FloatArray, FloatArray]:
    """Fire and rescue marginals (L, S, ...) of site-major beliefs x (L·L, S, ...), summed as `marginals` does;
    written into `out` (fire, rescue) when given."""
    L = math.isqrt(x.shape[0])
    grid = x.reshape((L, L) + x.shape[1:])
    fire_out, rescue = out if out is not None else (None, np.empty(grid.shape[1:]))
    fire = pairwise_sum(grid.swapaxes(0, 1), out=fire_out)  # numpy sums the contiguous last axis pairwise
    np.copyto(rescue, grid[0])  # and the other axis one level after the other
    for f in range(1, L):
        rescue += grid[f]
    return fire, rescue


# ----- the evidence ---------------------------------------------------------------------------------------------


def _check_levels(levels: IntArray, used: BoolArray, n_levels: int) -> None:
    if used.any() and int(levels[used].max()) >= n_levels:
        raise IndexError(f"reported level {int(levels[used].max())} is out of range 0..{n_levels - 1}")


def evidence_codes(
    model: Model,
    actions: IntArray,
    observations: IntArray,
    messages: IntArray,
) -> IntArray:
    """Every agent's evidence code of every task, all messages delivered: (B, N) -> (N, p, B) rows of
    `FilterTables.evidence` (receiver i's code plus i · base^N)."""
    sc = model.scenario
    t = filter_tables(model)
    p, n = sc.n_tasks, sc.n_agents
    acts, obs, msgs = actions.T, observations.T, messages.T  # (N, B)
    if obs.size and max(int(obs.max()), int(msgs.max())) >= sc.levels:
        works = (acts >= 0) & (acts < p)
        _check_levels(msgs, works & (msgs >= 0), sc.levels)
        _check_levels(obs, works & (obs >= 0), sc.levels)
    powers = t.powers[:, None]
    msg_digit = np.where(msgs >= 0, msgs + 1, 0) * powers  # (N, B)
    own_digit = np.where(obs >= 0, obs + 1, 0) * powers
    onehot = acts[:, None, :] == np.arange(p)[:, None]  # (N, p, B): agent k works on task j
    shared = np.einsum("kjb,kb->jb", onehot, msg_digit)  # (p, B): every report weighed as a teammate's (integers)
    codes: IntArray = np.einsum("kjb,kb->kjb", onehot, own_digit - msg_digit)  # the receiver's own report
    codes += shared
    codes += (np.arange(n, dtype=np.int64) * t.base**n)[:, None, None]
    return codes


def agent_codes(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None = None,
) -> IntArray:
    """Agent `agent`'s evidence code of every task (B, p): rows of `FilterTables.evidence` (see `agent_evidence`)."""
    sc = model.scenario
    t = filter_tables(model)
    p = sc.n_tasks
    levels = messages.copy()
    levels[:, agent] = own_observation
    ok = levels >= 0
    if heard is not None:
        mine = np.zeros(ok.shape[1], dtype=bool)
        mine[agent] = True
        ok &= heard | mine
    onehot = actions[..., None] == np.arange(p)  # (B, N, p): agent k works on task j
    if levels.size and int(levels.max()) >= sc.levels:
        _check_levels(levels, ok & onehot.any(axis=-1), sc.levels)
    digit = np.where(ok, levels + 1, 0) * t.powers
    codes: IntArray = np.einsum("bkj,bk->bj", onehot, digit)
    codes += agent * t.base**sc.n_agents
    return codes


def _agent_evidence_product(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None,
) -> FloatArray:
    """`agent_evidence` multiplied out report by report (for teams too large for the evidence table)."""
    sc = model.scenario
    b = actions.shape[0]
    p = sc.n_tasks
    lik = np.ones((b, p, sc.levels))
    rows = np.arange(b)
    for k, table in enumerate(_report_tables(model, agent)):
        works = (actions[:, k] >= 0) & (actions[:, k] < p)
        task = np.where(works, actions[:, k], 0)
        level = own_observation if k == agent else messages[:, k]
        if k != agent and heard is not None:
            works = works & heard[:, k]
        ok = works & (level >= 0)
        if ok.any():
            lik[rows[ok], task[ok]] *= table[:, level[ok]].T
    return lik


def agent_evidence(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None = None,
) -> FloatArray:
    """Likelihood of agent `agent`'s evidence of one step for every task level: (B, p, L).

    Its own observation is weighed with O, teammate k's message with I_k (docs/model.md, Information I); the
    likelihood of a task is the product of its reports' rows in increasing agent order.

    Args:
        actions: (B, N) the joint assignment of the step (as the agent knows it).
        own_observation: (B,) the agent's own observation, -1 when idle.
        messages: (B, N) levels received from each teammate after its channel, -1 when idle or not sent.
        heard: optional (B, N) mask of teammates whose message arrived; all when None.
    """
    tables = filter_tables(model)
    if tables.evidence is None:
        return _agent_evidence_product(model, agent, actions, own_observation, messages, heard)
    out: FloatArray = tables.evidence[agent_codes(model, agent, actions, own_observation, messages, heard)]
    return out


def evidence_sites(
    model: Model, actions: IntArray, observations: IntArray, messages: IntArray
) -> tuple[FloatArray, FloatArray]:
    """Every agent's evidence, all messages delivered, for `update_sites`: fire and rescue likelihoods
    (L, S, N, B) of (B, N) actions, observations and messages (views of one (L, N, p, B) array)."""
    sc = model.scenario
    tables = filter_tables(model)
    b, n = actions.shape
    if tables.by_level is None:
        lik = evidence(model, actions, observations, messages)  # (B, N, p, L)
        sites = np.ascontiguousarray(lik.transpose(3, 1, 2, 0))  # (L, N, p, B)
    else:
        sites = np.take(tables.by_level, evidence_codes(model, actions, observations, messages), axis=1)
    grid = sites.reshape((sc.levels, n, sc.n_sites, 2, b)).transpose(0, 2, 1, 3, 4)  # (L, S, N, 2, B)
    return grid[:, :, :, 0], grid[:, :, :, 1]


def evidence(model: Model, actions: IntArray, observations: IntArray, messages: IntArray) -> FloatArray:
    """Likelihood of every agent's evidence, all messages delivered: (B, N, p, L) (see `agent_evidence`)."""
    tables = filter_tables(model)
    n = actions.shape[1]
    if tables.evidence is None:
        rows = [_agent_evidence_product(model, i, actions, observations[:, i], messages, None) for i in range(n)]
        return np.stack(rows, axis=1)
    codes = evidence_codes(model, actions, observations, messages)  # (N, p, B)
    out: FloatArray = tables.evidence[codes.transpose(2, 0, 1)]
    return out


# ----- the filter on (..., S, L, L) beliefs -------------------------------------------------------------------


def _site_caps(caps: IntArray) -> tuple[IntArray, IntArray]:
    """Fire and rescue capabilities (S, ...) of (..., p) capabilities."""
    k = caps.ndim - 1
    return caps[..., 0::2].transpose(k, *range(k)), caps[..., 1::2].transpose(k, *range(k))


def predict(model: Model, belief: Belief, caps: IntArray) -> Belief:
    """Predict every site's belief with T (Eq. 2, sum over s of T(s, a, s') b(s)).

    Args:
        belief: (..., S, L, L) over (fire, rescue).
        caps: (..., p) joint capabilities each belief assumes for the step.
    """
    fire_caps, rescue_caps = _site_caps(caps)
    x = predict_sites(filter_tables(model), to_sites(belief), fire_caps, rescue_caps)
    return np.ascontiguousarray(from_sites(x))


def update(model: Model, belief: Belief, caps: IntArray, likelihood: FloatArray) -> tuple[Belief, np.ndarray]:
    """One step of Eq. 2: predict with T, multiply by the evidence, normalise.

    Args:
        belief: (..., S, L, L), e.g. (B, N, S, L, L) for a team or (B, S, L, L) for one agent.
        caps: (..., p) joint capabilities each belief assumes for the step.
        likelihood: (..., p, L) from `evidence` or `agent_evidence`.

    Returns:
        The new belief and a (...) mask of agents whose evidence had zero probability: they keep the prediction
        (docs/model.md), and the caller counts the event.
    """
    fire_caps, rescue_caps = _site_caps(caps)
    k = likelihood.ndim - 2
    to_levels = (k + 1, k, *range(k))  # (..., S, L) -> (L, S, ...)
    post, bad = update_sites(
        filter_tables(model),
        to_sites(belief),
        fire_caps,
        rescue_caps,
        likelihood[..., 0::2, :].transpose(to_levels),
        likelihood[..., 1::2, :].transpose(to_levels),
    )
    return np.ascontiguousarray(from_sites(post)), np.asarray(bad.any(axis=0), dtype=np.bool_)


def marginals(belief: Belief) -> Marginals:
    """Per-task marginals (..., p, L) in task order fire@site1, rescue@site1, fire@site2, ..."""
    fire, rescue = marginals_sites(to_sites(belief))  # (L, S, ...)
    out = np.stack([fire, rescue], axis=2)  # (L, S, 2, ...)
    lead = belief.shape[:-3]
    k = len(lead)
    return np.ascontiguousarray(out.transpose(*range(3, 3 + k), 1, 2, 0)).reshape(lead + (-1, belief.shape[-1]))
