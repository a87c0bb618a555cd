"""The sequential single-item auction an agent runs in its head (docs/model.md, Baselines): the one definition, used
by the auction baseline (`baselines.heuristics.AuctionPolicy`) and by the token learner, whose tokens carry the
auction's choice made from the agent's own belief (`learning.tokens`)."""

from __future__ import annotations

import numpy as np

from htlm_agent.mind import knowledge
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.travel import arrival_steps
from htlm_world.types import BoolArray, FloatArray, IntArray


def allocate(model: Model, lv: IntArray, present: BoolArray | None = None, drive: IntArray | None = None) -> IntArray:
    """The auction of every auctioneer: (B, M, p) confident levels (auctioneer m's belief) -> (B, M, N) the task
    every agent k gets in auctioneer m's auction, -1 for none. `present` (B, M, N): the teammates auctioneer m
    counts on (its roster, `Scenario.roster`); the others get no task and leave their work to the rest (default:
    everyone).

    A task j is open while its confident level l_j > 0, it is not `blocked`, and the capability assigned to it so far
    does not cover l_j; every agent without a task bids its useful capability min(c_kj, need) on every open task it
    has capability for; the highest bid wins (ties: larger need, larger capability, lower agent, lower task), and the
    rounds repeat until nobody bids. With travel, `drive` (B, M, N, p): the steps until agent k could work on task j
    as auctioneer m reckons them (`team_steps`); every bid is then the finish time, the drive plus the need over the
    useful capability rounded up, and the soonest wins (ties as above: the quickest-finish rule of fleet
    dispatchers). Vectorized over the B episodes and the M auctioneers.
    """
    sc = model.scenario
    b, m, p = lv.shape
    n = sc.n_agents
    caps_np = model.agent_caps[:, :p]  # (N, p): c_kj
    need = np.where((lv > 0) & ~model.blocked(lv), lv, 0).astype(np.int64)  # (B, M, p)
    assigned = np.full((b, m, n), -1, dtype=np.int64)
    bidders = np.ones((b, m, n), dtype=bool) if present is None else np.broadcast_to(present, (b, m, n))
    # every bid as one integer, kept up to date: a round changes one agent's bids (it has a task now) and one
    # task's (its need dropped), so only those are worked out again
    key = _bids(sc, caps_np[None, None], need[:, :, None, :], drive)  # (B, M, N, p)
    key[~bidders] = -1
    flat = key.reshape(b, m, n * p)
    for _ in range(n):  # each round assigns at most one agent per auction
        win = flat.argmax(axis=-1)  # the first maximum: lower agent, then lower task
        ok = np.take_along_axis(flat, win[..., None], axis=-1)[..., 0] >= 0  # (B, M)
        if not ok.any():
            break
        bi, mi = np.nonzero(ok)
        k, j = win[bi, mi] // p, win[bi, mi] % p
        assigned[bi, mi, k] = j
        need[bi, mi, j] = np.maximum(need[bi, mi, j] - caps_np[k, j], 0)
        free = assigned[bi, mi] < 0  # (W, N)
        column = _bids(sc, caps_np.T[j][:, :, None], need[bi, mi, j][:, None, None], _column(drive, bi, mi, j))
        key[bi, mi, :, j] = np.where(free & bidders[bi, mi], column[..., 0], -1)
        key[bi, mi, k] = -1
    return assigned


def _bids(sc: Scenario, caps: IntArray, need: IntArray, drive: IntArray | None) -> IntArray:
    """Every bid as one integer (broadcast over caps (..., N, p) and need (..., 1, p)), -1 for no bid: ordered by
    useful capability, then need, then capability; with `drive` (..., N, p), by the soonest finish first."""
    cmax, L = sc.capability_max, sc.levels
    useful = np.minimum(caps, need)
    key = (useful * L + need) * (cmax + 1) + caps
    if drive is not None:  # the finish time: the drive plus the need over the useful capability, rounded up
        cap = 4 * sc.horizon  # finish times beyond it rank alike
        finish = drive + -(-need // np.maximum(useful, 1))
        key = (cap - np.minimum(finish, cap)) * (L * L * (cmax + 1)) + key
    out: IntArray = np.where(useful > 0, key, -1)
    return out


def _column(drive: IntArray | None, bi: IntArray, mi: IntArray, j: IntArray) -> IntArray | None:
    """The drives (W, N, 1) of every agent to task j[w] in auction (bi[w], mi[w]) (None without travel)."""
    if drive is None:
        return None
    out: IntArray = drive[bi, mi, :, j][:, :, None]
    return out


def own_assignment(model: Model, lv: IntArray, agent: IntArray, present: BoolArray | None = None) -> IntArray:
    """What `allocate` gives each auctioneer's own agent, without running the auctions on once it is settled:
    (R, p) confident levels, (R,) the auctioneer of each row, (R, N) its roster -> (R,) its task, -1 for none.

    The same rounds as `allocate`, on the rows still open only: a row stops once its own agent has won a task or
    nobody bids, which for a team of N agents is usually long before N rounds. Within a round, the best bid on a
    task comes from the free agent with the largest capability for it (the lowest index among equals: a useful
    capability min(c, need) never decreases with c), so each task's bidder is the first free agent in the task's
    order of capabilities, and only the p tasks' best bids are compared."""
    sc = model.scenario
    r, p = lv.shape
    n, cmax, L = sc.n_agents, sc.capability_max, sc.levels
    caps_np = model.agent_caps[:, :p]  # (N, p)
    order = np.argsort(-caps_np.T, axis=1, kind="stable")  # (p, N): task j's agents, largest capability first
    ordered_caps = np.take_along_axis(caps_np.T, order, axis=1)  # (p, N)
    need = np.where((lv > 0) & ~model.blocked(lv), lv, 0).astype(np.int64)  # (R, p)
    free = np.ones((r, n), dtype=bool) if present is None else np.array(present, dtype=bool)  # may still bid
    out = np.full(r, -1, dtype=np.int64)
    rows = np.arange(r)
    tasks = np.arange(p)
    for _ in range(n):
        if rows.size == 0:
            break
        bidding = free[rows][:, order] & (ordered_caps > 0)  # (r', p, N): free agents able to, in task order
        first = bidding.argmax(axis=-1)  # (r', p) the best bidder's place in the order
        has = np.take_along_axis(bidding, first[..., None], axis=-1)[..., 0]
        c = ordered_caps[tasks, first]  # (r', p) its capability
        nd = need[rows]
        useful = np.minimum(c, nd)
        bidder = order[tasks, first]  # (r', p) the best bidder's index
        # allocate's order of bids: key, then the lower agent, then the lower task
        key = np.where(has & (useful > 0), ((useful * L + nd) * (cmax + 1) + c) * n + (n - 1 - bidder), -1)
        j = key.argmax(axis=-1)
        ok = key[np.arange(rows.size), j] >= 0
        k = bidder[np.arange(rows.size), j]
        mine = ok & (k == agent[rows])
        out[rows[mine]] = j[mine]
        go = ok & ~mine
        rows, k, j = rows[go], k[go], j[go]
        free[rows, k] = False
        need[rows, j] = np.maximum(need[rows, j] - caps_np[k, j], 0)
    return out


def team_steps(sc: Scenario, k: FloatArray) -> IntArray:
    """The steps until every agent could work on every task (..., N, p), as the agent of each knowledge state (..., K)
    reckons them from the team's places and arrivals it holds (`knowledge.places`, `travel.arrival_steps`)."""
    place, eta = knowledge.places(k, sc)
    per_site = arrival_steps(sc, place, eta)  # (..., N, S)
    out: IntArray = per_site[..., Model.build(sc).task_site]
    return out


def travel_steps(sc: Scenario, k: FloatArray, who: IntArray) -> IntArray:
    """The steps until each of agents `who` (R,) could work on every task (B, R, p), from its own knowledge state
    (B, R, K) (`team_steps`, its own row)."""
    steps = team_steps(sc, k)  # (B, R, N, p)
    out: IntArray = steps[:, np.arange(who.size), who]
    return out
