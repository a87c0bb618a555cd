"""The reward f_R(a_o, b, a) = R_comp + R_II + T_RP of docs/model.md (Eqs. 3-5 of the paper). The reduced action space
Â(a_o) is `Model.action_mask`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray, Marginals

LOAD_PRICE = 0.001
"""The steps of expected completion one unit of committed capability is worth to the planners that count steps (QMDP,
the lookahead; `Settings.load_price`): mission first, load second (it decides only between choices whose expected
completions differ by less than the price of the capability they commit: the one that commits less)."""


@dataclass(frozen=True)
class RewardTables:
    """Per-agent reward parameters as arrays over agents (agents may carry their own preferences)."""

    level_rewards: FloatArray  # (N, L)
    threshold: FloatArray  # (N,)
    idle_bonus: FloatArray  # (N,) already scaled by idle_incentive
    excess_penalty: FloatArray  # (N,) already scaled by idle_incentive
    excess_margin: IntArray  # (N,)
    idle_belief: tuple[str, ...]  # (N,) constant, site or mission: how the idle bonus depends on the belief
    reassign_cost: FloatArray  # (N,)
    load_management: bool  # False in HT mode: R_LM = 0
    difference: BoolArray  # (N,) R_comp as a difference reward (`credit: difference`)
    contribution: FloatArray | None  # (N, p, C+1, L, L) expected R_l' after a step from (c, g, l); None: team credit

    @staticmethod
    def build(sc: Scenario) -> RewardTables:
        """Collect every agent's parameters (its own or the shared ones)."""
        rs = [sc.agent_reward(i) for i in range(sc.n_agents)]
        return RewardTables(
            level_rewards=np.array([r.level_rewards for r in rs]),
            threshold=np.array([r.belief_threshold for r in rs]),
            idle_bonus=np.array([r.idle_bonus * r.idle_incentive for r in rs]),
            excess_penalty=np.array([r.excess_penalty * r.idle_incentive for r in rs]),
            excess_margin=np.array([r.excess_margin for r in rs], dtype=np.int64),
            idle_belief=tuple(r.idle_belief for r in rs),
            reassign_cost=np.array([r.reassign_cost for r in rs]),
            load_management=sc.mode == "htlm",
            difference=np.array([r.credit == "difference" for r in rs], dtype=bool),
            contribution=(
                np.einsum("jcglm,im->ijcgl", prediction_table(Model.build(sc)), np.array([r.level_rewards for r in rs]))
                if any(r.credit == "difference" for r in rs)
                else None
            ),
        )


def confident_levels(marg: Marginals, threshold: FloatArray) -> IntArray:
    """Smallest l with P(level <= l) >= b_th, per task: (B, N, p, L) -> (B, N, p); threshold (N,). 0 where no level
    reaches it (the cumulative sum can fall short of b_th by round-off only when b_th is about 1).

    The cumulative sums are added level by level as `np.cumsum` adds them, and they never decrease (marginals are
    not negative), so the level is the number of sums below the threshold. One pass per level over (B, N, p): fast
    whatever the layout of `marg` (the in-process team passes a level-major view, `Team.marg`)."""
    L = marg.shape[-1]
    limit = threshold[:, None] - 1e-9
    cdf = marg[..., 0].copy(order="K")  # every array below in the layout of `marg`
    below = np.empty_like(cdf, dtype=bool)
    count = np.less(cdf, limit).astype(np.int64)
    for level in range(1, L):
        cdf += marg[..., level]
        count += np.less(cdf, limit, out=below)
    out: IntArray = np.where(count < L, count, 0)
    return out


def idle_weight(model: Model, tables: RewardTables, marg: Marginals, actions: IntArray) -> FloatArray:
    """The belief factor of R_II(b) for every agent (B, N) (docs/model.md, Reward): 1 for `constant`; for `site`,
    the agent's believed probability that every task at the site of its action is at level 0; for `mission`, that
    every task is at level 0. Probabilities are products of the per-task marginals (the agent's knowledge state)."""
    weight = np.ones(actions.shape)
    kinds = set(tables.idle_belief)
    if kinds == {"constant"}:
        return weight
    done = marg[..., 0]  # (B, N, p) P(level_j = 0)
    # products of P(level_j = 0) over tasks in task order, as np.prod multiplies (and a factor 1.0 changes nothing)
    mission, site = weight, weight
    if "mission" in kinds:
        mission = done[..., 0].copy(order="K")
        for j in range(1, done.shape[-1]):
            mission *= done[..., j]
    if "site" in kinds:
        at_site: dict[int, FloatArray] = {}  # every site's product
        for j, s in enumerate(model.task_site.tolist()):
            if s in at_site:
                at_site[s] *= done[..., j]
            else:
                at_site[s] = done[..., j].copy(order="K")
        action_site = model.action_site[np.maximum(actions, 0)]  # (B, N)
        site = np.ones(actions.shape)  # a site without tasks: 1
        for s, prod in at_site.items():
            np.copyto(site, prod, where=action_site == s)
    for i, kind in enumerate(tables.idle_belief):
        if kind == "site":
            weight[:, i] = site[:, i]
        elif kind == "mission":
            weight[:, i] = mission[:, i]
    return weight


def prediction_table(model: Model) -> FloatArray:
    """T of every task as one array (p, C+1, L, L, L): [j, c, g, l, l'], the next level l' of task j at level l with
    joint capability c while the task it depends on is at g (every g alike for a kind that depends on none)."""
    sc = model.scenario
    L, cm = sc.levels, sc.capability_max
    out = np.zeros((sc.n_tasks, cm + 1, L, L, L))
    for j, (_, k) in enumerate(sc.tasks):
        table = model.kind_tables[k]  # (C+1, G, L, L)
        out[j] = table if table.shape[1] == L else np.broadcast_to(table, (cm + 1, L, L, L))
    return out


def own_contribution(model: Model, tables: RewardTables, prior: Marginals, joint: IntArray) -> FloatArray:
    """The difference reward's R_comp (docs/model.md, Reward, `credit: difference`) of every agent (B, N): the
    expected completion reward of the task it works on after the step as its belief predicts it with T, from its
    marginals before the step (B, N, p, L), with the step's joint assignment `joint` (B, N), minus the same with the
    agent idle, divided by p (the share of R_comp that task holds) and by 1 − γ: R_comp is paid every step while a
    level lasts, so the progress of one step is worth its completion reward for as long as it lasts, which is what
    the paper's reward pays for it over the following steps. 0 while idle. Tasks are taken as independent of the
    task they depend on (the product of their marginals)."""
    sc = model.scenario
    p, cm = sc.n_tasks, sc.capability_max
    b, n = joint.shape
    working = (joint >= 0) & (joint < p)
    task = np.where(working, joint, 0)
    own = np.where(working, model.agent_caps[np.arange(n)[None, :], task], 0)  # (B, N)
    total = np.zeros((b, p), dtype=np.int64)
    np.add.at(total, (np.repeat(np.arange(b), n), task.reshape(-1)), own.reshape(-1))
    on_task = np.take_along_axis(total, task, axis=1)  # (B, N) the uncapped joint capability on the agent's task
    with_me, without = np.minimum(on_task, cm), np.minimum(on_task - own, cm)
    m = np.take_along_axis(prior, task[..., None, None], axis=2)[:, :, 0]  # (B, N, L)
    gate = model.task_gate[task]  # (B, N): p when none
    ext = np.concatenate([prior, np.zeros(prior.shape[:-2] + (1, prior.shape[-1]))], axis=-2)
    ext[..., p, 0] = 1.0  # the stand-in of no dependency: certain of level 0
    g = np.take_along_axis(ext, gate[..., None, None], axis=2)[:, :, 0]  # (B, N, L)
    value = tables.contribution  # (N, p, C+1, L, L): expected R_l' from (c, g, l), made once
    assert value is not None, "a difference reward needs RewardTables.contribution"
    idx_i = np.broadcast_to(np.arange(n)[None, :], (b, n))
    v_with = value[idx_i, task, with_me]  # (B, N, L, L) over (g, l)
    v_without = value[idx_i, task, without]
    gain = np.einsum("bngl,bng,bnl->bn", v_with - v_without, g, m)
    out: FloatArray = np.where(working, gain / (p * (1.0 - sc.gamma)), 0.0)
    return out


def reward(
    model: Model,
    tables: RewardTables,
    prev: IntArray,
    marg: Marginals,
    actions: IntArray,
    prior: Marginals | None = None,
    joint: IntArray | None = None,
) -> tuple[FloatArray, dict[str, FloatArray]]:
    """f_R for every agent (docs/model.md, Reward), from its own updated belief.

    Args:
        prev: (B, N) previous assignments a_o (-1: none).
        marg: (B, N, p, L) per-task marginals of each agent's updated belief.
        actions: (B, N) the actions taken.
        prior: (B, N, p, L) the marginals before the step; needed where an agent's credit is `difference`.
        joint: (B, N) the joint assignment each agent's prediction used (default: `actions`), for the same.

    Returns:
        (B, N) rewards and their parts {"comp", "idle", "reassign"}.
    """
    sc = model.scenario
    p = sc.n_tasks
    lv = confident_levels(marg, tables.threshold)  # (B, N, p)
    n = actions.shape[1]
    rows = np.arange(n)[:, None] * tables.level_rewards.shape[1]  # (N, 1): agent i's row of level_rewards, flat
    r_levels = tables.level_rewards.reshape(-1)[lv + rows]  # (B, N, p) R_l of every task's confident level
    if p < 8:  # numpy's sum of fewer than 8 numbers adds them one after the other (in any layout): the same here
        total = r_levels[..., 0].copy(order="K")
        for j in range(1, p):
            total += r_levels[..., j]
        comp = total / p
    else:  # pairwise: along a contiguous axis, as numpy's mean
        comp = np.ascontiguousarray(r_levels).mean(axis=-1)
    if tables.difference.any():
        assert prior is not None, "a difference reward needs the marginals before the step"
        own = own_contribution(model, tables, prior, actions if joint is None else joint)
        comp = np.where(tables.difference[None, :], own, comp)
    if not tables.load_management:
        zero = np.zeros_like(comp)
        return comp, {"comp": comp, "idle": zero, "reassign": zero}
    idle = actions >= p
    task = np.where(idle, 0, actions)
    my_cap = model.agent_caps[np.arange(n)[None, :], task]  # (B, N)
    task_level = np.take_along_axis(lv, task[..., None], axis=2)[..., 0]
    excess = (~idle) & (my_cap >= task_level + tables.excess_margin)
    bonus = tables.idle_bonus * idle_weight(model, tables, marg, actions)
    r_ii = np.where(idle, bonus, np.where(excess, tables.excess_penalty, 0.0))
    moved = (prev >= 0) & (model.action_site[np.maximum(prev, 0)] != model.action_site[actions])
    t_rp = np.where(moved, tables.reassign_cost, 0.0)
    return comp + r_ii + t_rp, {"comp": comp, "idle": r_ii, "reassign": t_rp}
