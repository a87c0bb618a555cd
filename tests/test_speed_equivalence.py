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

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import GreedyPolicy, RandomPolicy
from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.mind.reward import RewardTables, reward
from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import AgentSpec, RewardParams, Scenario, builtin
from htlm_world.simulator import BatchSim

# ----- the reference: the plain implementation --------------------------------------------------------------------


def ref_predict(model: Model, belief: np.ndarray, caps: np.ndarray) -> np.ndarray:
    rescue = model.rescue[caps[..., 1::2]]
    fire = model.fire[caps[..., 0::2]]
    tmp = np.einsum("...fr,...frs->...fs", belief, rescue)
    return np.einsum("...fg,...fs->...gs", fire, tmp)


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
        if k == agent:
            level, table = own, model.obs[model.sensing[k]]
        else:
            level, table = messages[:, k], model.info[model.sensing[k], model.comm[k]]
            if heard is not None:
                works = works & heard[:, k]
        ok = works & (level >= 0)
        if ok.any():
            lik[rows[ok], task[ok]] *= table[:, level[ok]].T
    return lik


def ref_evidence(model: Model, actions: np.ndarray, obs: np.ndarray, msgs: np.ndarray) -> np.ndarray:
    n = actions.shape[1]
    return np.stack([ref_agent_evidence(model, i, actions, obs[:, i], msgs) for i in range(n)], axis=1)


def ref_update(model: Model, belief: np.ndarray, caps: np.ndarray, lik: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = ref_predict(model, belief, caps)
    post = pred * lik[..., 0::2, :, None] * lik[..., 1::2, None, :]
    z = post.sum(axis=(-1, -2))
    bad = z <= 0.0
    post = np.where(bad[..., None, None], pred, post / np.where(bad, 1.0, z)[..., None, None])
    return post, bad.any(axis=-1)


def ref_marginals(belief: np.ndarray) -> np.ndarray:
    out = np.stack([belief.sum(axis=-1), belief.sum(axis=-2)], axis=-2)
    return out.reshape(belief.shape[:-3] + (2 * belief.shape[-3], belief.shape[-1]))


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
    fire_lv = levels[..., 0::2]
    nxt = np.empty_like(levels)
    fcdf = model.fire_cdf[caps[..., 0::2], fire_lv]
    rcdf = model.rescue_cdf[caps[..., 1::2], fire_lv, levels[..., 1::2]]
    nxt[..., 0::2] = (u[..., 0::2, None] >= fcdf).sum(-1)
    nxt[..., 1::2] = (u[..., 1::2, None] >= rcdf).sum(-1)
    return np.minimum(nxt, model.scenario.levels - 1)


def ref_sample_observation(model: Model, true: np.ndarray, sensing: np.ndarray, u: np.ndarray) -> np.ndarray:
    cdf = model.obs_cdf[sensing, true]
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
        true = np.take_along_axis(nxt, np.where(working, actions, 0), axis=1)
        obs = np.where(working, ref_sample_observation(model, true, np.broadcast_to(model.sensing, (b, n)), u_o), -1)
        msgs = np.stack([ref_channel(model, k, obs[:, k], self.chan[k]) for k in range(n)], axis=1)
        self.levels = nxt
        lik = ref_evidence(model, actions, obs, msgs)
        self.belief, bad = ref_update(model, self.belief, np.broadcast_to(caps[:, None, :], (b, n, p)), lik)
        marg = ref_marginals(self.belief)
        r, parts = reward(model, self.tables, self.prev, marg, actions)
        self.prev = np.where(actions >= 0, actions, self.prev)
        k2 = ref_knowledge(marg, self.prev, sc.n_actions)
        return {"k": k2, "r": r, "levels": nxt, "obs": obs, "msgs": msgs, "bad": bad, "belief": self.belief,
                "marg": marg, **{f"part_{key}": v for key, v in parts.items()}}  # fmt: skip


# ----- scenarios ----------------------------------------------------------------------------------------------------


def wide_scenario() -> Scenario:
    """3 sites, 12 levels (the site sums go beyond 128 terms), 3 agents, no channel."""
    L = 12
    agents = tuple(AgentSpec(name=f"a{i}", fire=f, rescue=r, sensing=s, comm=c)
                   for i, (f, r, s, c) in enumerate([(3, 1, 3, 3), (2, 4, 5, 1), (5, 0, 1, 5)]))  # fmt: skip
    return builtin().replace(
        sites=("s1", "s2", "s3"),
        site_positions=((0.0, 0.0), (1.0, 0.0), (2.0, 0.0)),
        levels=L,
        initial_levels=(11, 9, 6, 11, 3, 10),
        agents=agents,
        team="custom",
        channel=False,
        reward=replace(RewardParams(), level_rewards=tuple(float(L - i) for i in range(L))),
    )


def large_team_scenario() -> Scenario:
    """9 agents on 3 levels: the evidence table would be too large, the likelihood is multiplied out."""
    agents = tuple(AgentSpec(name=f"a{i}", fire=i % 4, rescue=(i * 3) % 5, sensing=i % 6, comm=(5 - i) % 6)
                   for i in range(9))  # fmt: skip
    return builtin().replace(
        levels=3,
        initial_levels=(2, 2, 1, 2),
        agents=agents,
        team="custom",
        reward=replace(RewardParams(), level_rewards=(10.0, 4.0, 0.0)),
    )


SCENARIOS = {
    "heterogeneous": builtin(),
    "semi-heterogeneous-ht": builtin("semi-heterogeneous", mode="ht"),
    "homogeneous": builtin("homogeneous", reassign="high"),
    "wide": wide_scenario(),
    "large-team": large_team_scenario(),
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
    w = rng.random(lead + (S, L * L)) ** 3 * (rng.random(lead + (S, L * L)) < 0.5)
    w[..., 0] += 1e-3
    belief = (w / w.sum(axis=-1, keepdims=True)).reshape(lead + (S, L, L))
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
    model = Model.build(sc)
    n, p = sc.n_agents, sc.n_tasks
    for seed in range(3):
        x = random_inputs(sc, (batch, n), seed)
        belief, caps, lik = x["belief"], x["caps"], x["lik"]
        assert np.array_equal(bf.predict(model, belief, caps), ref_predict(model, belief, caps))
        new, bad = bf.update(model, belief, caps, lik)
        want, want_bad = ref_update(model, belief, caps, lik)
        assert np.array_equal(new, want) and np.array_equal(bad, want_bad)
        assert np.array_equal(bf.marginals(belief), ref_marginals(belief))
        # one agent's beliefs (B, S, L, L), as the ROS agents hold them
        new1, bad1 = bf.update(model, belief[:, 0], caps[:, 0], lik[:, 0])
        want1, want_bad1 = ref_update(model, belief[:, 0], caps[:, 0], lik[:, 0])
        assert np.array_equal(new1, want1) and np.array_equal(bad1, want_bad1)
        actions, obs, msgs = x["actions"], x["obs"], x["msgs"]
        assert np.array_equal(bf.evidence(model, actions, obs, msgs), ref_evidence(model, actions, obs, msgs))
        for i in range(n):
            for heard in (None, x["heard"]):
                got = bf.agent_evidence(model, i, actions, obs[:, i], msgs, heard)
                assert np.array_equal(got, ref_agent_evidence(model, i, actions, obs[:, i], msgs, heard))
        assert np.array_equal(
            knowledge.build(bf.marginals(belief), x["prev"], sc.n_actions),
            ref_knowledge(ref_marginals(belief), x["prev"], sc.n_actions),
        )
        assert np.array_equal(model.joint_capability(actions), ref_joint_capability(model, actions))
        jc = model.joint_capability(actions)
        u = x["u"]
        assert np.array_equal(
            model.sample_transition(x["levels"], jc, u[:, :p]), ref_sample_transition(model, x["levels"], jc, u[:, :p])
        )
        true = x["levels"][:, np.arange(n) % p]
        sens = np.broadcast_to(model.sensing, (batch, n))
        assert np.array_equal(
            model.sample_observation(true, sens, u[:, :n]), ref_sample_observation(model, true, sens, u[:, :n])
        )


@pytest.mark.parametrize("name", ["heterogeneous", "wide", "large-team"])
def test_a_row_does_not_depend_on_the_batch(name: str) -> None:
    sc = SCENARIOS[name]
    model = Model.build(sc)
    x = random_inputs(sc, (16, sc.n_agents), 7)
    team_post, team_bad = bf.update(model, x["belief"], x["caps"], x["lik"])
    team_marg = bf.marginals(team_post)
    for e in (0, 5, 15):
        for i in range(sc.n_agents):
            post, bad = bf.update(model, x["belief"][e : e + 1, i], x["caps"][e : e + 1, i], x["lik"][e : e + 1, i])
            assert np.array_equal(post[0], team_post[e, i]) and bool(bad[0]) == bool(team_bad[e, i])
            assert np.array_equal(bf.marginals(post)[0], team_marg[e, i])
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
    team = Team(sc, batch, seed, episode=seed, inactive=inactive)
    ref = RefTeam(sc, batch, seed, seed, inactive)
    pol = RandomPolicy(sc, seed) if policy == "random" else GreedyPolicy(sc)
    k0 = team.reset()
    assert np.array_equal(k0, ref_knowledge(ref_marginals(ref.belief), ref.prev, sc.n_actions))
    for t in range(sc.horizon):
        a = team.force_inactive(pol.act(team.context()))
        k, r, info = team.step(a)
        want = ref.step(a)
        got = {"k": k, "r": r, "levels": info.levels, "obs": info.observations, "msgs": info.messages,
               "bad": info.impossible, "belief": team.belief, "marg": team.marg,
               **{f"part_{key}": v for key, v in info.parts.items()}}  # fmt: skip
        assert set(got) == set(want)
        for key, v in want.items():
            assert np.array_equal(got[key], v), f"{key} differs at step {t}"
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
    model = Model.build(sc)
    rng = np.random.default_rng(0)
    sim = BatchSim(sc, 32, np.random.default_rng(5), [np.random.default_rng(10 + k) for k in range(5)], model)
    ref = RefTeam(sc, 32, 0, 0, ())
    ref.rng, ref.chan = np.random.default_rng(5), [np.random.default_rng(10 + k) for k in range(5)]
    for _ in range(10):
        a = rng.integers(-1, sc.n_actions, (32, 5))
        res = sim.step(a)
        want = ref.step(a)
        for got, key in ((res.levels, "levels"), (res.observations, "obs"), (res.messages, "msgs")):
            assert np.array_equal(got, want[key]) and got.dtype == want[key].dtype, key
