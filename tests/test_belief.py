"""The belief filter (Eq. 2, docs/model.md) against brute-force Bayes over the 25 states of every site.

The brute force loops over states in plain Python with the reference model of test_model.py, which is re-derived
from the text of docs/model.md, not from the module's tables.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.runtime.team import Team
from htlm_world.model import Model
from htlm_world.scenario import AgentSpec, Scenario, builtin, from_dict
from support.reference_model import L, ref_fire, ref_info, ref_obs, ref_rescue

CMAX = 5


def ref_caps(sc: Scenario, actions: list[int]) -> list[int]:
    """Joint capability on every task: the sum of the assigned agents' capabilities of its type, capped at 5."""
    caps = [0] * sc.n_tasks
    for k, a in enumerate(actions):
        if 0 <= a < sc.n_tasks:
            caps[a] += sc.agents[k].capability("fire" if a % 2 == 0 else "rescue")
    return [min(CMAX, c) for c in caps]


def brute_update(
    sc: Scenario,
    belief: np.ndarray,
    actions: list[int],
    own_obs: int,
    messages: list[int],
    me: int,
    heard: list[bool] | None = None,
) -> tuple[np.ndarray, bool]:
    """Agent `me`'s Bayes update of its (S, L, L) belief for one step, by enumeration; and whether the evidence
    had zero probability (then the prediction is kept)."""
    p = sc.n_tasks
    caps = ref_caps(sc, actions)
    out = np.zeros((sc.n_sites, L, L))
    impossible = False
    for s in range(sc.n_sites):
        cf, cr = caps[2 * s], caps[2 * s + 1]
        pred = [[0.0] * L for _ in range(L)]
        for f in range(L):
            for r in range(L):
                w = float(belief[s, f, r])
                if w == 0.0:
                    continue
                fd, rd = ref_fire(cf, f), ref_rescue(cr, f, r)
                for f2 in range(L):
                    for r2 in range(L):
                        pred[f2][r2] += w * fd[f2] * rd[r2]
        post = [row[:] for row in pred]
        for k, a in enumerate(actions):
            if not 0 <= a < p or a // 2 != s:
                continue
            agent = sc.agents[k]
            if k == me:
                level = own_obs
                like = [ref_obs(agent.sensing, lv)[level] if level >= 0 else 1.0 for lv in range(L)]
            else:
                if heard is not None and not heard[k]:
                    continue
                level = messages[k]
                like = [
                    ref_info(agent.sensing, agent.comm, lv, sc.channel)[level] if level >= 0 else 1.0 for lv in range(L)
                ]
            for f2 in range(L):
                for r2 in range(L):
                    post[f2][r2] *= like[f2] if a % 2 == 0 else like[r2]
        z = sum(sum(row) for row in post)
        if z == 0.0:
            out[s] = pred
            impossible = True
        else:
            out[s] = np.array(post) / z
    return out, impossible


@st.composite
def filter_cases(draw: Any) -> dict[str, Any]:
    """A random team, mode and channel, with random beliefs, joint actions (incl. idle and none), observations
    and messages for a batch of 1-2 episodes."""
    n = draw(st.integers(1, 5))
    cap = st.integers(0, CMAX)
    one = st.integers(1, CMAX)  # the first agent can work on every kind (a scenario needs someone for each)
    agents = tuple(
        AgentSpec(
            name=f"a{i}",
            capabilities={"fire": draw(one if i == 0 else cap), "rescue": draw(one if i == 0 else cap)},
            sensing=draw(cap),
            comm=draw(cap),
        )
        for i in range(n)
    )
    sc = builtin().replace(
        agents=agents,
        team="custom",
        mode=draw(st.sampled_from(["htlm", "ht"])),
        channel=draw(st.booleans()),
    )
    b = draw(st.integers(1, 2))
    # sparse random beliefs (many zero states, so that impossible evidence occurs), from a drawn seed
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    w = rng.choice([0.0, 0.0, 0.0, 1.0, 2.0, 5.0], size=(b, n, sc.n_sites, L * L))
    np.put_along_axis(w, rng.integers(0, L * L, size=(b, n, sc.n_sites, 1)), 1.0, axis=-1)
    belief = (w / w.sum(axis=-1, keepdims=True)).reshape(b, n, sc.n_sites, L, L)
    actions = np.array([[draw(st.integers(-1, sc.n_actions - 1)) for _ in range(n)] for _ in range(b)], dtype=np.int64)
    working = (actions >= 0) & (actions < sc.n_tasks)
    level = st.integers(0, L - 1)
    obs = np.where(working, np.array([[draw(level) for _ in range(n)] for _ in range(b)]), -1).astype(np.int64)
    msgs = np.where(working, np.array([[draw(level) for _ in range(n)] for _ in range(b)]), -1).astype(np.int64)
    heard = np.array([[draw(st.booleans()) for _ in range(n)] for _ in range(b)])
    return {"sc": sc, "belief": belief, "actions": actions, "obs": obs, "msgs": msgs, "heard": heard}


@settings(max_examples=120, deadline=None)
@given(case=filter_cases())
def test_team_update_equals_brute_force_bayes(case: dict[str, Any]) -> None:
    sc: Scenario = case["sc"]
    model = Model.build(sc)
    belief, actions, obs, msgs = case["belief"], case["actions"], case["obs"], case["msgs"]
    b, n = actions.shape
    caps = model.joint_capability(actions)
    for e in range(b):
        assert caps[e].tolist() == ref_caps(sc, actions[e].tolist())
    lik = bf.evidence(model, actions, obs, msgs)
    new, bad = bf.update(model, belief, np.broadcast_to(caps[:, None, :], (b, n, sc.n_tasks)), lik)
    assert new.shape == belief.shape and bad.shape == (b, n)
    for e in range(b):
        for i in range(n):
            want, want_bad = brute_update(sc, belief[e, i], actions[e].tolist(), int(obs[e, i]), msgs[e].tolist(), i)
            np.testing.assert_allclose(new[e, i], want, atol=1e-10, err_msg=f"episode {e} agent {i}")
            assert bool(bad[e, i]) == want_bad
    assert (new >= 0.0).all()
    np.testing.assert_allclose(new.sum(axis=(-1, -2)), 1.0, atol=1e-10)


@settings(max_examples=80, deadline=None)
@given(case=filter_cases())
def test_agent_update_with_lost_messages_equals_brute_force(case: dict[str, Any]) -> None:
    sc: Scenario = case["sc"]
    model = Model.build(sc)
    belief, actions, obs, msgs, heard = case["belief"], case["actions"], case["obs"], case["msgs"], case["heard"]
    b, n = actions.shape
    caps = model.joint_capability(actions)
    for i in range(n):
        lik = bf.agent_evidence(model, i, actions, obs[:, i], msgs, heard)
        # what a team too large for the evidence table multiplies out report by report: the same likelihoods
        np.testing.assert_allclose(bf._agent_evidence_product(model, i, actions, obs[:, i], msgs, heard, None), lik)
        new, bad = bf.update(model, belief[:, i], caps, lik)
        assert bad.shape == (b,)
        for e in range(b):
            want, want_bad = brute_update(
                sc, belief[e, i], actions[e].tolist(), int(obs[e, i]), msgs[e].tolist(), i, heard[e].tolist()
            )
            np.testing.assert_allclose(new[e], want, atol=1e-10)
            assert bool(bad[e]) == want_bad
        np.testing.assert_allclose(new.sum(axis=(-1, -2)), 1.0, atol=1e-10)
    # with every message delivered, agent_evidence is the agent's row of evidence
    full = bf.evidence(model, actions, obs, msgs)
    for i in range(n):
        np.testing.assert_allclose(bf.agent_evidence(model, i, actions, obs[:, i], msgs), full[:, i])


def test_impossible_evidence_keeps_the_prediction_and_is_flagged() -> None:
    agents = list(builtin().agents)
    agents[0] = AgentSpec(name="agent1", capabilities={"fire": 3, "rescue": 1}, sensing=5)  # accuracy 1.0
    sc = builtin().replace(agents=tuple(agents))
    model = Model.build(sc)
    belief = bf.initial_belief(model, 1)  # certain of level 4 everywhere
    actions = np.array([[0, 4, 4, 4, 4]], dtype=np.int64)  # agent1 on fire@site1, the rest idle
    obs = np.array([[0, -1, -1, -1, -1]], dtype=np.int64)  # level 0: impossible from level 4 in one step
    caps = np.broadcast_to(model.joint_capability(actions)[:, None], (1, 5, 4))
    pred = bf.predict(model, belief, caps)
    new, bad = bf.update(model, belief, caps, bf.evidence(model, actions, obs, obs))
    assert bad.tolist() == [[True, False, False, False, False]]
    np.testing.assert_allclose(new[0, 0], pred[0, 0])
    want, want_bad = brute_update(sc, belief[0, 0], actions[0].tolist(), 0, obs[0].tolist(), 0)
    assert want_bad
    np.testing.assert_allclose(new[0, 0], want, atol=1e-12)


def test_team_counts_impossible_evidence() -> None:
    agents = list(builtin().agents)
    agents[0] = AgentSpec(
        name="agent1", capabilities={"fire": 3, "rescue": 1}, sensing=5, comm=5
    )  # exact observations and messages
    sc = builtin().replace(agents=tuple(agents))
    team = Team(sc, 1, seed=3)
    assert team.impossible_count == 0
    # agent1 wrongly believes fire@site1 is out; working on it, it observes the true level 3 or 4
    team.belief[0, 0, 0] = 0.0
    team.belief[0, 0, 0, 0, 4] = 1.0
    _, _, info = team.step(np.array([[0, 4, 4, 4, 4]], dtype=np.int64))
    assert info.impossible.tolist() == [[True, False, False, False, False]]
    assert team.impossible_count == 1
    assert team.belief[0, 0, 0, 0, 4] == pytest.approx(1.0)  # the prediction, kept
    # teammates, whose beliefs hold the truth, weigh agent1's exact message without trouble
    np.testing.assert_allclose(team.belief.sum(axis=(-1, -2)), 1.0)


def test_marginals_and_knowledge_layout() -> None:
    sc = builtin()
    rng = np.random.default_rng(0)
    belief = rng.random((2, 5, 2, L, L))
    belief /= belief.sum(axis=(-1, -2), keepdims=True)
    marg = bf.marginals(Model.build(builtin()), belief)
    assert marg.shape == (2, 5, 4, L)
    np.testing.assert_allclose(marg[:, :, 0], belief[:, :, 0].sum(axis=-1))  # fire@site1
    np.testing.assert_allclose(marg[:, :, 1], belief[:, :, 0].sum(axis=-2))  # rescue@site1
    np.testing.assert_allclose(marg[:, :, 2], belief[:, :, 1].sum(axis=-1))  # fire@site2
    np.testing.assert_allclose(marg[:, :, 3], belief[:, :, 1].sum(axis=-2))  # rescue@site2
    prev = np.array([[4, 0, 5, 3, -1]] * 2, dtype=np.int64)
    k = knowledge.build(marg, prev, sc.n_actions)
    assert k.shape == (2, 5, sc.knowledge_size) and sc.knowledge_size == 26
    np.testing.assert_allclose(k[..., :20], marg.reshape(2, 5, 20))
    assert k[0, 0, 20:].tolist() == [0, 0, 0, 0, 1, 0]
    assert k[0, 4, 20:].tolist() == [0] * 6
    back_marg, back_prev = knowledge.split(k, sc)  # the inverse of build
    np.testing.assert_array_equal(back_marg, marg)
    np.testing.assert_array_equal(back_prev, prev)


def test_initial_belief_is_certain_of_initial_levels() -> None:
    sc = from_dict({"initial_levels": [4, 3, 2, 1]})
    b0 = bf.initial_belief(Model.build(sc), 3)
    assert b0.shape == (3, 5, 2, L, L)
    assert (b0[:, :, 0, 4, 3] == 1.0).all() and (b0[:, :, 1, 2, 1] == 1.0).all()
    np.testing.assert_allclose(b0.sum(axis=(-1, -2)), 1.0)
