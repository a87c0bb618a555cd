"""The fast team step computes the very numbers of the plain formulas, bit for bit (np.array_equal, not allclose).

The reference below is the straightforward implementation the fast code replaced (belief filter with einsum and
numpy sums, evidence multiplied out report by report, inverse-CDF sampling by comparing whole cumulative rows, joint
capabilities by np.add.at). Every test compares the fast path with it on the same inputs: the functions of
`belief`, `knowledge` and `Model` on random inputs (zero-probability evidence included), and whole `Team` rollouts of
every kind (teams, HT mode, batch 1 and 64, random and greedy policies, an inactive agent, unusual scenarios: 3 and
12 levels, a team too large for the evidence table). A row's result must not depend on the batch either: the ROS
agents compute their own row at batch 1 (`AgentMind`) and must equal the in-process Team.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import GreedyPolicy, RandomPolicy
from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.mind.policies import epsilon_greedy, team_epsilon_greedy
from htlm_agent.mind.reward import RewardTables, reward
from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario, builtin, from_dict
from htlm_world.simulator import BatchSim


def assert_same(got: np.ndarray, want: np.ndarray, exact: bool) -> bool:
    """Bit for bit when `exact`, else equal to round-off."""
    if exact:
        assert np.array_equal(got, want)
    else:
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    return True


# ----- the reference: the plain implementation --------------------------------------------------------------------


def _slots(model: Model, caps: np.ndarray, fill: int) -> list[np.ndarray]:
    """Every kind's per-site values (..., S) of per-task values (..., p); `fill` where a site has no such task."""
    ext = np.concatenate([caps, np.full(caps.shape[:-1] + (1,), fill, dtype=caps.dtype)], axis=-1)
    task = np.where(model.site_task >= 0, model.site_task, model.scenario.n_tasks)  # (S, K)
    return [ext[..., task[:, k]] for k in range(model.scenario.n_kinds)]


def _factor_order(sc: Scenario) -> list[int]:
    """Kinds that depend on another first (they read the level of the one they depend on before it changes)."""
    names = list(sc.kind_names)

    def depth(k: int) -> int:
        dep = sc.kinds[k].depends_on
        return 0 if not dep else 1 + depth(names.index(dep))

    return sorted(range(sc.n_kinds), key=lambda k: (-depth(k), -k))


def ref_predict(model: Model, belief: np.ndarray, caps: np.ndarray) -> np.ndarray:
    """T applied kind by kind with einsum over a site's joint (..., S, L, ..., L)."""
    sc = model.scenario
    K, L = sc.n_kinds, sc.levels
    names = list(sc.kind_names)
    slot_caps = _slots(model, caps, sc.capability_max + 1)
    letters = "abcdefgh"[:K]
    for k in _factor_order(sc):
        table = model.kind_tables[k]
        full = np.concatenate([table, np.broadcast_to(np.eye(L), (1,) + table.shape[1:])])  # row C+1: no task
        t = full[slot_caps[k]]  # (..., S, G, L, L)
        dep = sc.kinds[k].depends_on
        out = letters.replace(letters[k], "z")
        if dep:
            g = letters[names.index(dep)]
            belief = np.einsum(f"...{letters},...{g}{letters[k]}z->...{out}", belief, t)
        else:
            belief = np.einsum(f"...{letters},...{letters[k]}z->...{out}", belief, t[..., 0, :, :])
    return belief


def ref_agent_evidence(
    model: Model, agent: int, actions: np.ndarray, own: np.ndarray, messages: np.ndarray, heard: Any = None
) -> np.ndarray:
    sc = model.scenario
    b, n = actions.shape
    p = sc.n_tasks
    lik = np.ones((b, p, sc.levels))
    rows = np.arange(b)
    for k in range(n):
        works = (actions[:, k] >= 0) & (actions[:, k] < p)
        task = np.where(works, actions[:, k], 0)
        cls = model.task_class[task]
        if k == agent:
            level, table = own, model.obs[cls, model.sensing[k]]  # (B, L, L)
        else:
            level, table = messages[:, k], model.info[cls, model.sensing[k], model.comm[k]]
            if heard is not None:
                works = works & heard[:, k]
        ok = works & (level >= 0)
        if ok.any():
            lik[rows[ok], task[ok]] *= table[rows[ok], :, level[ok]]
    return lik


def ref_evidence(model: Model, actions: np.ndarray, obs: np.ndarray, msgs: np.ndarray) -> np.ndarray:
    n = actions.shape[1]
    return np.stack([ref_agent_evidence(model, i, actions, obs[:, i], msgs) for i in range(n)], axis=1)


def ref_update(model: Model, belief: np.ndarray, caps: np.ndarray, lik: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = model.scenario.n_kinds
    pred = ref_predict(model, belief, caps)
    ones = np.ones(lik.shape[:-2] + (1, lik.shape[-1]))
    post = pred
    for k, lk in enumerate(_slots(model, np.concatenate([lik, ones], axis=-2).swapaxes(-1, -2), 0)):
        shape = lk.swapaxes(-1, -2).shape[:-1] + tuple(lk.shape[-2] if j == k else 1 for j in range(K))
        post = post * lk.swapaxes(-1, -2).reshape(shape)
    axes = tuple(range(-K, 0))
    z = post.sum(axis=axes)
    bad = z <= 0.0
    post = np.where(bad[(...,) + (None,) * K], pred, post / np.where(bad, 1.0, z)[(...,) + (None,) * K])
    return post, bad.any(axis=-1)


def ref_marginals(model: Model, belief: np.ndarray) -> np.ndarray:
    K = model.scenario.n_kinds
    slots = [belief.sum(axis=tuple(j - K for j in range(K) if j != k)) for k in range(K)]  # each (..., S, L)
    stacked = np.stack(slots, axis=-3)  # (..., K, S, L)
    return stacked[..., model.task_kind, model.task_site, :]


def ref_knowledge(marg: np.ndarray, prev: np.ndarray, n_actions: int) -> np.ndarray:
    flat = marg.reshape(marg.shape[:-2] + (-1,))
    return np.concatenate([flat, (prev[..., None] == np.arange(n_actions)).astype(np.float64)], axis=-1)


def ref_joint_capability(model: Model, actions: np.ndarray) -> np.ndarray:
    sc = model.scenario
    n = actions.shape[-1]
    flat = actions.reshape(-1, n)
    out = np.zeros((flat.shape[0], sc.n_actions), dtype=np.int64)
    rows = np.arange(flat.shape[0])
    for i in range(n):
        a = flat[:, i]
        valid = a >= 0
        np.add.at(out, (rows[valid], a[valid]), model.agent_caps[i, a[valid]])
    return np.minimum(out[:, : sc.n_tasks], sc.capability_max).reshape(actions.shape[:-1] + (sc.n_tasks,))


def ref_sample_transition(model: Model, levels: np.ndarray, caps: np.ndarray, u: np.ndarray) -> np.ndarray:
    nxt = np.empty_like(levels)
    gate_levels = np.concatenate([levels, np.zeros(levels.shape[:-1] + (1,), dtype=levels.dtype)], axis=-1)
    for j in range(model.scenario.n_tasks):
        table = model.kind_tables[model.task_kind[j]]
        cdf = np.cumsum(table, axis=-1)
        cdf[cdf >= 1.0 - 1e-9] = np.inf
        g = gate_levels[..., model.task_gate[j]] if table.shape[1] > 1 else 0
        nxt[..., j] = (u[..., j, None] >= cdf[caps[..., j], g, levels[..., j]]).sum(-1)
    return np.minimum(nxt, model.scenario.levels - 1)


def ref_sample_observation(
    model: Model, task: np.ndarray, true: np.ndarray, sensing: np.ndarray, u: np.ndarray
) -> np.ndarray:
    cdf = model.obs_cdf[model.task_class[task], sensing, true]
    return np.minimum((u[..., None] >= cdf).sum(-1), model.scenario.levels - 1)


def ref_channel(model: Model, agent: int, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    L = model.scenario.levels
    u = rng.random((obs.shape[0], 2))
    random_level = np.minimum((u[:, 1] * L).astype(np.int64), L - 1)
    sent = np.where(u[:, 0] < model.keep[agent], obs, random_level)
    return np.where(obs >= 0, sent, -1)


class RefTeam:
    """The in-process team step of the reference implementation (same seeds and draws as `Team`)."""

    def __init__(self, sc: Scenario, batch: int, seed: int, episode: int, inactive: tuple[int, ...]) -> None:
        self.sc, self.batch, self.inactive = sc, batch, inactive
        self.model = Model.build(sc)
        self.tables = RewardTables.build(sc)
        self.rng = seeds.world(seed, episode)
        self.chan = [seeds.channel(seed, k, episode) for k in range(sc.n_agents)]
        self.levels = np.tile(np.array(sc.initial_levels, dtype=np.int64), (batch, 1))
        self.belief = bf.initial_belief(self.model, batch)
        self.prev = np.full((batch, sc.n_agents), sc.start_assignment, dtype=np.int64)

    def step(self, actions: np.ndarray) -> dict[str, np.ndarray]:
        sc, model, b, n, p = self.sc, self.model, self.batch, self.sc.n_agents, self.sc.n_tasks
        actions = actions.copy()
        for k in self.inactive:
            actions[:, k] = model.idle_action(self.prev[:, k])
        caps = ref_joint_capability(model, actions)
        nxt = ref_sample_transition(model, self.levels, caps, self.rng.random((b, p)))
        u_o = self.rng.random((b, n))
        working = (actions >= 0) & (actions < p)
        task = np.where(working, actions, 0)
        true = np.take_along_axis(nxt, task, axis=1)
        sens = np.broadcast_to(model.sensing, (b, n))
        obs = np.where(working, ref_sample_observation(model, task, true, sens, u_o), -1)
        msgs = np.stack([ref_channel(model, k, obs[:, k], self.chan[k]) for k in range(n)], axis=1)
        self.levels = nxt
        lik = ref_evidence(model, actions, obs, msgs)
        self.belief, bad = ref_update(model, self.belief, np.broadcast_to(caps[:, None, :], (b, n, p)), lik)
        marg = ref_marginals(model, self.belief)
        r, parts = reward(model, self.tables, self.prev, marg, actions)
        self.prev = np.where(actions >= 0, actions, self.prev)
        k2 = ref_knowledge(marg, self.prev, sc.n_actions)
        return {"k": k2, "r": r, "levels": nxt, "obs": obs, "msgs": msgs, "bad": bad, "belief": self.belief,
                "marg": marg, **{f"part_{key}": v for key, v in parts.items()}}  # fmt: skip


# ----- scenarios ----------------------------------------------------------------------------------------------------


def wide_scenario() -> Scenario:
    """3 sites, 12 levels (the site sums go beyond 128 terms), 3 agents, no channel."""
    L = 12
    agents = [{"name": f"a{i}", "fire": f, "rescue": r, "sensing": se, "comm": c}
              for i, (f, r, se, c) in enumerate([(3, 1, 3, 3), (2, 4, 5, 1), (5, 0, 1, 5)])]  # fmt: skip
    return from_dict(
        {
            "sites": ["s1", "s2", "s3"],
            "site_positions": [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]],
            "levels": L,
            "initial_levels": [11, 9, 6, 11, 3, 10],
            "agents": agents,
            "team": "custom",
            "channel": False,
            "reward": {"level_rewards": [float(L - i) for i in range(L)]},
        }
    )


def large_team_scenario() -> Scenario:
    """9 agents on 3 levels: the evidence table would be too large, the likelihood is multiplied out."""
    agents = [{"name": f"a{i}", "fire": i % 4, "rescue": (i * 3) % 5, "sensing": i % 6, "comm": (5 - i) % 6}
              for i in range(9)]  # fmt: skip
    return from_dict(
        {
            "levels": 3,
            "initial_levels": [2, 2, 1, 2],
            "agents": agents,
            "team": "custom",
            "reward": {"level_rewards": [10.0, 4.0, 0.0]},
        }
    )


def three_kinds_scenario() -> Scenario:
    """Three kinds in a chain of dependencies (c waits on b, b on a), a kind with two-level drops and its own
    accuracy, sites holding different kinds (one site a single kind)."""
    return from_dict(
        {
            "name": "three",
            "kinds": [
                {"name": "a", "growth": 0.2},
                {"name": "b", "depends_on": "a", "blocked_above": 1, "sensing_base": 0.5},
                {"name": "c", "depends_on": "b", "blocked_above": 2,
                 "double_drop": {"share": 0.4, "min_level": 2, "gate_at_most": 0}},
            ],
            "sites": [
                {"name": "s1", "tasks": {"a": 3, "b": 4, "c": 4}},
                {"name": "s2", "tasks": {"c": 3}},
                {"name": "s3", "tasks": {"b": 2, "a": 1}},
            ],
            "agents": [{"name": f"x{i}", "a": i % 3, "b": (i + 1) % 3, "c": (i * 2) % 4, "sensing": i % 4}
                       for i in range(4)],
        }
    )  # fmt: skip


def packed_scenario() -> Scenario:
    """Four kinds, at most two tasks at a site: a site's belief holds a slot per task it has, not per kind. b waits
    on a where both are (s1), and on nothing where a is absent (s3)."""
    return from_dict(
        {
            "name": "packed",
            "kinds": [
                {"name": "a", "growth": 0.2},
                {"name": "b", "depends_on": "a", "blocked_above": 1},
                {"name": "c", "sensing_base": 0.5},
                {"name": "d", "double_drop": {"share": 0.4, "min_level": 2}},
            ],
            "sites": [
                {"name": "s1", "tasks": {"a": 3, "b": 4}},
                {"name": "s2", "tasks": {"c": 3, "d": 2}},
                {"name": "s3", "tasks": {"c": 1, "b": 2}},
                {"name": "s4", "tasks": {"d": 4}},
            ],
            "agents": [{"name": f"x{i}", "a": i % 3, "b": (i + 1) % 3, "c": (i * 2) % 4, "d": i % 2, "sensing": i % 4}
                       for i in range(4)],
        }
    )  # fmt: skip


def test_a_site_of_fewer_tasks_than_kinds_keeps_the_marginals_of_a_slot_per_kind() -> None:
    """The packed layout (a slot per task of the site) gives the marginals of the plain filter over one slot per
    kind, step after step, to round-off (its sums add fewer exact zeros in another order)."""
    sc = packed_scenario()
    model = Model.build(sc)
    tables = bf.filter_tables(model)
    assert tables.slots == 2 < sc.n_kinds
    b, n, p, L = 16, sc.n_agents, sc.n_tasks, sc.levels
    packed = bf.initial_belief(model, b)  # (B, N, S, L, L)
    full = np.zeros((b, n, sc.n_sites) + (L,) * sc.n_kinds)
    for s in range(sc.n_sites):
        at = tuple(sc.initial_levels[j] if j >= 0 else 0 for j in model.site_task[s])
        full[(slice(None), slice(None), s, *at)] = 1.0
    np.testing.assert_array_equal(bf.marginals(model, packed), ref_marginals(model, full))
    rng = np.random.default_rng(0)
    for _ in range(8):
        caps = rng.integers(0, sc.capability_max + 1, (b, n, p))
        lik = rng.random((b, n, p, L)) * (rng.random((b, n, p, L)) < 0.8)
        packed, bad = bf.update(model, packed, caps, lik)
        full, want_bad = ref_update(model, full, caps, lik)
        np.testing.assert_array_equal(bad, want_bad)
        np.testing.assert_allclose(bf.marginals(model, packed), ref_marginals(model, full), rtol=1e-12, atol=1e-15)
    assert np.asarray(bad).any(), "some evidence should have been impossible"


SCENARIOS = {
    "heterogeneous": builtin(),
    "semi-heterogeneous-ht": builtin("semi-heterogeneous", mode="ht"),
    "homogeneous": builtin("homogeneous", reassign="high"),
    "wide": wide_scenario(),
    "large-team": large_team_scenario(),
    "three-kinds": three_kinds_scenario(),
}


def test_the_unusual_scenarios_take_the_other_paths() -> None:
    large = bf.filter_tables(Model.build(SCENARIOS["large-team"]))
    assert large.evidence is None, "the large team should not get an evidence table"
    default = bf.filter_tables(Model.build(SCENARIOS["heterogeneous"]))
    assert default.evidence is not None, "the default team should get an evidence table"
    assert SCENARIOS["wide"].levels ** 2 > 128


# ----- functions on random inputs -----------------------------------------------------------------------------------


def random_inputs(sc: Scenario, lead: tuple[int, ...], seed: int) -> dict[str, np.ndarray]:
    """Sparse random beliefs (so that impossible evidence happens), capabilities, likelihoods with zeros, actions,
    observations, messages and delivery masks."""
    rng = np.random.default_rng(seed)
    L, S, p, n = sc.levels, sc.n_sites, sc.n_tasks, sc.n_agents
    K = sc.n_kinds
    w = rng.random(lead + (S, L**K)) ** 3 * (rng.random(lead + (S, L**K)) < 0.5)
    w[..., 0] += 1e-3
    belief = (w / w.sum(axis=-1, keepdims=True)).reshape(lead + (S,) + (L,) * K)
    lik = rng.random(lead + (p, L)) * (rng.random(lead + (p, L)) < 0.7)
    b = int(np.prod(lead[:1])) if lead else 1
    actions = rng.integers(-1, sc.n_actions, (b, n))
    working = (actions >= 0) & (actions < p)
    obs = np.where(working, rng.integers(0, L, (b, n)), -1)
    msgs = np.where(working, rng.integers(0, L, (b, n)), -1)
    return {
        "belief": belief,
        "caps": rng.integers(0, sc.capability_max + 1, lead + (p,)),
        "lik": lik,
        "actions": actions,
        "obs": obs,
        "msgs": msgs,
        "heard": rng.random((b, n)) < 0.6,
        "prev": rng.integers(-1, sc.n_actions, (b, n)),
        "levels": rng.integers(0, L, (b, p)),
        "u": rng.random((b, max(p, n))),
    }


@pytest.mark.parametrize("name", list(SCENARIOS))
@pytest.mark.parametrize("batch", [1, 3, 64])
def test_filter_functions_equal_the_reference(name: str, batch: int) -> None:
    sc = SCENARIOS[name]
    exact = sc.n_kinds == 2  # beyond two kinds the reference's numpy sums may add in another order
    model = Model.build(sc)
    n, p = sc.n_agents, sc.n_tasks
    for seed in range(3):
        x = random_inputs(sc, (batch, n), seed)
        belief, caps, lik = x["belief"], x["caps"], x["lik"]
        assert_same(bf.predict(model, belief, caps), ref_predict(model, belief, caps), exact)
        new, bad = bf.update(model, belief, caps, lik)
        want, want_bad = ref_update(model, belief, caps, lik)
        assert_same(new, want, exact) and np.array_equal(bad, want_bad)
        assert_same(bf.marginals(model, belief), ref_marginals(model, belief), exact)
        # one agent's beliefs (B, S, L, L), as the ROS agents hold them
        new1, bad1 = bf.update(model, belief[:, 0], caps[:, 0], lik[:, 0])
        want1, want_bad1 = ref_update(model, belief[:, 0], caps[:, 0], lik[:, 0])
        assert_same(new1, want1, exact) and np.array_equal(bad1, want_bad1)
        actions, obs, msgs = x["actions"], x["obs"], x["msgs"]
        assert np.array_equal(bf.evidence(model, actions, obs, msgs), ref_evidence(model, actions, obs, msgs))
        for i in range(n):
            for heard in (None, x["heard"]):
                got = bf.agent_evidence(model, i, actions, obs[:, i], msgs, heard)
                assert np.array_equal(got, ref_agent_evidence(model, i, actions, obs[:, i], msgs, heard))
        assert_same(
            knowledge.build(bf.marginals(model, belief), x["prev"], sc.n_actions),
            ref_knowledge(ref_marginals(model, belief), x["prev"], sc.n_actions),
            exact,
        )
        assert np.array_equal(model.joint_capability(actions), ref_joint_capability(model, actions))
        jc = model.joint_capability(actions)
        u = x["u"]
        assert np.array_equal(
            model.sample_transition(x["levels"], jc, u[:, :p]), ref_sample_transition(model, x["levels"], jc, u[:, :p])
        )
        task = np.broadcast_to(np.arange(n) % p, (batch, n))
        true = x["levels"][:, np.arange(n) % p]
        sens = np.broadcast_to(model.sensing, (batch, n))
        assert np.array_equal(
            model.sample_observation(task, true, sens, u[:, :n]),
            ref_sample_observation(model, task, true, sens, u[:, :n]),
        )


@pytest.mark.parametrize("name", ["heterogeneous", "wide", "large-team", "three-kinds"])
def test_a_row_does_not_depend_on_the_batch(name: str) -> None:
    sc = SCENARIOS[name]
    model = Model.build(sc)
    x = random_inputs(sc, (16, sc.n_agents), 7)
    team_post, team_bad = bf.update(model, x["belief"], x["caps"], x["lik"])
    team_marg = bf.marginals(model, team_post)
    for e in (0, 5, 15):
        for i in range(sc.n_agents):
            post, bad = bf.update(model, x["belief"][e : e + 1, i], x["caps"][e : e + 1, i], x["lik"][e : e + 1, i])
            assert np.array_equal(post[0], team_post[e, i]) and bool(bad[0]) == bool(team_bad[e, i])
            assert np.array_equal(bf.marginals(model, post)[0], team_marg[e, i])
    lik = bf.evidence(model, x["actions"], x["obs"], x["msgs"])
    for e in (0, 9):
        row = bf.evidence(model, x["actions"][e : e + 1], x["obs"][e : e + 1], x["msgs"][e : e + 1])
        assert np.array_equal(row[0], lik[e])


def test_out_of_range_reported_levels_still_raise() -> None:
    sc = builtin()
    model = Model.build(sc)
    actions = np.array([[0, 1, 2, 3, 4]], dtype=np.int64)
    obs = np.array([[1, 2, 3, 9, -1]], dtype=np.int64)  # agent 4 reports level 9 of 0..4
    with pytest.raises(IndexError):
        bf.evidence(model, actions, obs, obs)
    with pytest.raises(IndexError):
        bf.agent_evidence(model, 0, actions, obs[:, 0], obs)
    idle = np.array([[0, 1, 2, 4, 4]], dtype=np.int64)  # ... unless that agent did not work
    assert np.array_equal(bf.evidence(model, idle, obs, obs), ref_evidence(model, idle, obs, obs))


# ----- whole rollouts -----------------------------------------------------------------------------------------------


def assert_rollouts_equal(sc: Scenario, batch: int, seed: int, policy: str, inactive: tuple[int, ...] = ()) -> None:
    exact = sc.n_kinds == 2
    team = Team(sc, batch, seed, episode=seed, inactive=inactive)
    ref = RefTeam(sc, batch, seed, seed, inactive)
    pol = RandomPolicy(sc, seed) if policy == "random" else GreedyPolicy(sc)
    k0 = team.reset()
    assert_same(k0, ref_knowledge(ref_marginals(ref.model, ref.belief), ref.prev, sc.n_actions), exact)
    for t in range(sc.horizon):
        a = team.force_inactive(pol.act(team.context()))
        k, r, info = team.step(a)
        want = ref.step(a)
        got = {"k": k, "r": r, "levels": info.levels, "obs": info.observations, "msgs": info.messages,
               "bad": info.impossible, "belief": team.belief, "marg": team.marg,
               **{f"part_{key}": v for key, v in info.parts.items()}}  # fmt: skip
        assert set(got) == set(want)
        for key, v in want.items():
            assert_same(got[key], v, exact or key in ("levels", "obs", "msgs")), f"{key} differs at step {t}"
            assert got[key].shape == v.shape and got[key].dtype == v.dtype, key
        assert np.array_equal(team.knowledge(), k) and np.array_equal(team.context().knowledge, k)


@pytest.mark.parametrize("name", list(SCENARIOS))
@pytest.mark.parametrize("batch", [1, 64])
def test_team_rollouts_equal_the_reference(name: str, batch: int) -> None:
    sc = SCENARIOS[name]
    for seed, policy in ((0, "random"), (1, "greedy")):
        assert_rollouts_equal(sc, batch, seed, policy)


def test_team_rollout_with_an_inactive_agent_equals_the_reference() -> None:
    assert_rollouts_equal(builtin(), 8, 2, "greedy", inactive=(1,))
    assert_rollouts_equal(builtin(mode="ht"), 8, 3, "random", inactive=(0, 3))


def test_batch_sim_draws_equal_the_reference() -> None:
    sc = builtin()
    rng = np.random.default_rng(0)
    sim = BatchSim(sc, 32, np.random.default_rng(5), [np.random.default_rng(10 + k) for k in range(5)])
    ref = RefTeam(sc, 32, 0, 0, ())
    ref.rng, ref.chan = np.random.default_rng(5), [np.random.default_rng(10 + k) for k in range(5)]
    for _ in range(10):
        a = rng.integers(-1, sc.n_actions, (32, 5))
        res = sim.step(a)
        want = ref.step(a)
        for got, key in ((res.levels, "levels"), (res.observations, "obs"), (res.messages, "msgs")):
            assert np.array_equal(got, want[key]) and got.dtype == want[key].dtype, key


def ref_epsilon_greedy(greedy: np.ndarray, mask: np.ndarray, epsilon: Any, rng: np.random.Generator) -> np.ndarray:
    """One agent's ε-greedy as first written: two uniforms per row, the ⌊u · |Â|⌋-th allowed action."""
    u = rng.random((greedy.shape[0], 2))
    allowed = mask.sum(axis=1)
    nth = np.minimum((u[:, 1] * allowed).astype(np.int64), allowed - 1)
    uniform = np.array([np.flatnonzero(row)[k] for row, k in zip(mask, nth, strict=True)], dtype=np.int64)
    return np.where(u[:, 0] < epsilon, uniform, greedy).astype(np.int64)


@pytest.mark.parametrize("epsilon", [0.0, 0.3, 1.0, "per-row"])
def test_team_exploration_equals_every_agent_on_its_own(epsilon: Any) -> None:
    """The learner draws the team's ε-greedy actions in one call; each agent's actions and generator must be those of
    the agent deciding alone (as the ROS agents do), and of the plain rule."""
    sc = builtin()
    model = Model.build(sc)
    rng = np.random.default_rng(4)
    b, n = 200, sc.n_agents
    prev = rng.integers(-1, sc.n_actions, (b, n))
    mask = model.action_mask(prev)
    greedy = np.argmax(mask * rng.random(mask.shape), axis=-1)  # some allowed action
    eps = rng.random(b) if epsilon == "per-row" else epsilon
    team = team_epsilon_greedy(greedy, mask, eps, [np.random.default_rng(10 + i) for i in range(n)])
    for i in range(n):
        alone, ref = np.random.default_rng(10 + i), np.random.default_rng(10 + i)
        got = epsilon_greedy(greedy[:, i], mask[:, i], eps, alone)
        want = ref_epsilon_greedy(greedy[:, i], mask[:, i], eps, ref)
        assert np.array_equal(team[:, i], want) and np.array_equal(got, want)
        assert alone.random() == ref.random()  # the generators stayed in step
    if epsilon == 0.0:
        assert np.array_equal(team, greedy)
    if epsilon == 1.0:
        assert not np.array_equal(team, greedy)


@pytest.mark.parametrize("name", ["heterogeneous", "semi-heterogeneous-ht", "three-kinds"])
def test_action_masks_from_the_table_equal_the_rule(name: str) -> None:
    """`Model.action_mask` reads a table of every a_o; it must give the rule's mask for any shape and value."""
    sc = SCENARIOS[name]
    model = Model.build(sc)
    prev = np.random.default_rng(1).integers(-2, sc.n_actions, (7, 3, sc.n_agents))
    want = np.zeros(prev.shape + (sc.n_actions,), dtype=bool)
    want[..., : sc.n_tasks] = True
    if sc.n_idle:  # the idle location at the site of a_o, site 1 without a_o
        site = np.where(prev >= 0, np.asarray(sc.action_sites)[np.maximum(prev, 0)], 0)
        np.put_along_axis(want, (sc.n_tasks + site)[..., None], True, axis=-1)
    assert (prev == -2).any() and (prev == -1).any()
    assert np.array_equal(model.action_mask(prev), want)  # with -2 among them: worked out by the rule
    assert np.array_equal(model.action_mask(np.maximum(prev, -1)), want)  # read from the table
    assert np.array_equal(model.action_mask(np.int64(-1)), want[prev == -1][0])  # one a_o


def test_pairwise_sums_row_by_row_equal_numpys_sums() -> None:
    """The marginals of a middle slot (three kinds and more) are summed row by row, without stacking the rows (a copy
    of every belief); the sums must be numpy's, as `pairwise_sum` of the stacked rows is."""
    rng = np.random.default_rng(0)
    for n in [*range(1, 40), 127, 128, 129, 255, 256, 300]:
        x = rng.random((n, 3, 4)) * 10.0 ** rng.integers(-8, 8, (n, 1, 1))
        want = np.ascontiguousarray(np.moveaxis(x, 0, -1)).sum(axis=-1)
        assert np.array_equal(bf.pairwise_sum(x), want), n
        assert np.array_equal(bf.pairwise_sum_rows(list(x)), want), n
