"""Episode metrics of docs/model.md and agent importance (Eqs. 6-9 of the paper), from recorded trajectories."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from htlm_world.scenario import Scenario
from htlm_world.travel import TravelState
from htlm_world.types import FloatArray, IntArray


def completion_step(levels: IntArray) -> tuple[IntArray, np.ndarray]:
    """The step after which every true level is 0 and stays 0 until the horizon, per episode; h (and failed=True)
    when the last step still has a task above 0. Without events (a surge can reopen a finished mission) and without a
    hazard, all tasks at 0 is absorbing, so this is the first step at which every level is 0.

    Args:
        levels: (h+1, B, p) true levels, levels[0] the initial ones.

    Returns:
        (B,) completion steps and (B,) failure mask.
    """
    h = levels.shape[0] - 1
    done = (levels[1:] == 0).all(axis=-1)  # (h, B)
    failed = ~done[-1]
    stays = np.logical_and.accumulate(done[::-1], axis=0)[::-1]  # done from this step to the horizon
    first = stays.argmax(axis=0) + 1
    return np.where(failed, h, first).astype(np.int64), failed


@dataclass(frozen=True)
class EpisodeMetrics:
    """Per-episode metrics of docs/model.md for B episodes."""

    completion: IntArray  # (B,)
    failed: np.ndarray  # (B,) bool
    unused_capability: FloatArray  # (B,) per agent per step
    unused_fraction: FloatArray  # (B,) unused capability / mean total capability per agent
    unused_open: FloatArray  # (B,) the same over the steps up to completion only (the load while the mission is open)
    idle_before: IntArray  # (B,) team idle decisions at steps <= completion
    reassign_before: IntArray  # (B,) team decisions changing site at steps <= completion
    agent_unused: FloatArray  # (B, N) unused capability of each agent per step
    agent_idle_before: IntArray  # (B, N)
    agent_reassign_before: IntArray  # (B, N)
    agent_metres: FloatArray | None = None  # (B, N) metres each agent drove (travel only: docs/model.md, Travel)
    agent_driving: IntArray | None = None  # (B, N) steps each agent spent on its way (travel only)


def episode_metrics(sc: Scenario, levels: IntArray, actions: IntArray) -> EpisodeMetrics:
    """Metrics of docs/model.md from (h+1, B, p) true levels and (h, B, N) actions (-1 counts as idle)."""
    h, b, n = actions.shape
    p = sc.n_tasks
    comp, failed = completion_step(levels)
    idle = (actions >= p) | (actions < 0)  # (h, B, N)
    total_cap = np.array([sc.total_capability(i) for i in range(n)], dtype=np.float64)  # (N,)
    agent_unused = (idle * total_cap).sum(axis=0) / h  # (B, N)
    unused = agent_unused.sum(axis=1) / n
    mean_cap = total_cap.mean()
    before = (np.arange(1, h + 1)[:, None] <= comp[None, :])[..., None]  # (h, B, 1)
    sites = np.array(sc.action_sites)
    start = sc.start_assignment
    prev = np.concatenate([np.full((1, b, n), start, dtype=np.int64), actions[:-1]], axis=0)
    # a "previous decision" that was no decision (-1) keeps the one before it
    for t in range(1, h):
        prev[t] = np.where(prev[t] >= 0, prev[t], prev[t - 1])
    moved = (prev >= 0) & (actions >= 0) & (sites[np.maximum(prev, 0)] != sites[np.maximum(actions, 0)])
    agent_idle = (idle & before).sum(axis=0)
    agent_moves = (moved & before).sum(axis=0)
    metres, driving = drives(sc, actions) if sc.travel else (None, None)
    return EpisodeMetrics(
        completion=comp,
        failed=failed,
        unused_capability=unused,
        unused_fraction=unused / mean_cap if mean_cap > 0 else np.zeros_like(unused),
        unused_open=_open_share(idle, total_cap, before[..., 0]),
        idle_before=agent_idle.sum(axis=1),
        reassign_before=agent_moves.sum(axis=1),
        agent_unused=agent_unused,
        agent_idle_before=agent_idle,
        agent_reassign_before=agent_moves,
        agent_metres=metres,
        agent_driving=driving,
    )


def drives(sc: Scenario, actions: IntArray) -> tuple[FloatArray, IntArray]:
    """Metres driven (B, N) and steps spent on the way (B, N) by every agent over (h, B, N) joint assignments, the
    drives of `htlm_world.travel` replayed."""
    state = TravelState(sc, actions.shape[1])
    on_way = np.zeros(actions.shape[1:], dtype=np.int64)
    for a in actions:
        on_way += ~state.step(a)
    return state.driven.copy(), on_way


def _open_share(idle: np.ndarray, total_cap: FloatArray, before: np.ndarray) -> FloatArray:
    """Per episode, the share of the team's capability left unused over the steps up to completion (h, B) `before`."""
    team = max(float(total_cap.sum()), 1e-12)
    per_step = (idle * total_cap).sum(axis=2) / team  # (h, B)
    steps = np.maximum(before.sum(axis=0), 1)
    out: FloatArray = (per_step * before).sum(axis=0) / steps
    return out


def spearman(x: FloatArray | list[float], y: FloatArray | list[float]) -> float:
    """Spearman's rank correlation of two samples (ties share their average rank); nan when either is constant."""
    rx, ry = (_ranks(np.asarray(v, dtype=np.float64)) for v in (x, y))
    if rx.std() == 0 or ry.std() == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def _ranks(v: FloatArray) -> FloatArray:
    order = np.argsort(v, kind="stable")
    ranks = np.empty(len(v))
    ranks[order] = np.arange(len(v), dtype=np.float64)
    for value in np.unique(v):  # ties: the mean of their ranks
        same = v == value
        ranks[same] = ranks[same].mean()
    return ranks


def mean_se(x: FloatArray | IntArray) -> tuple[float, float]:
    """Mean and standard error of the mean."""
    x = np.asarray(x, dtype=np.float64)
    if x.size <= 1:
        return float(x.mean()) if x.size else float("nan"), 0.0
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(x.size))


@dataclass(frozen=True)
class Importance:
    """Agent importance (Eqs. 6-9): per agent capabilities C, usage U, score zeta; per kind of task omega."""

    capability: FloatArray  # (N, K) C_k, the agent's capability on every kind
    usage: FloatArray  # (N, K) u_k (Eq. 7)
    omega: FloatArray  # (K,) task urgency weights (Eqs. 8-9)
    zeta: FloatArray  # (N,) importance (Eq. 6)


def importance(sc: Scenario, actions: IntArray) -> Importance:
    """Agent importance from the greedy policy's actions (h, E, N) over E episodes (Eqs. 6-9, over the K kinds)."""
    e = actions.shape[1]
    p, kinds = sc.n_tasks, sc.n_kinds
    task_kind = np.array([k for _, k in sc.tasks] + [-1], dtype=np.int64)  # [-1]: not working on a task
    working = (actions >= 0) & (actions < p)
    ttype = task_kind[np.where(working, actions, p)]  # the kind worked on, -1 when idle
    caps = np.array(sc.capability_table(), dtype=np.float64).reshape(sc.n_agents, kinds)  # (N, K)
    counts = np.stack([(ttype == k).sum(axis=(0, 1)) for k in range(kinds)], axis=1)  # (N, K) over episodes, steps
    usage = caps * counts / e  # Eq. 7
    omega_bar = counts.sum(axis=0).astype(np.float64)  # Eq. 8
    omega = omega_bar / omega_bar.sum() if omega_bar.sum() > 0 else np.zeros(kinds)  # Eq. 9
    zeta = usage @ omega  # Eq. 6
    return Importance(capability=caps, usage=usage, omega=omega, zeta=zeta)
