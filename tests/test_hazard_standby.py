"""What the project adds to the paper's model (docs/model.md, What the paper fixes and what we add): a kind's hazard
(a finished task reopens) in T, and standing by (an idle agent observes its site's tasks in turn, with the standby
accuracy) in O, the simulator, the world's records and every belief; the paper's scenario is untouched by both."""

from __future__ import annotations

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import GreedyPolicy
from htlm_agent.mind import belief as bf
from htlm_agent.runtime.team import Team
from htlm_agent.session.builtin import builtin_policy
from htlm_msgs_py import schema
from htlm_world.metrics import completion_step
from htlm_world.model import Model, kind_table
from htlm_world.protocol import LockstepProtocol
from htlm_world.scenario import REOPEN_LEVEL, Scenario, ScenarioError, builtin, from_dict, from_record, load
from htlm_world.simulator import sample_world_step
from support.events import MIXED
from support.team import FIELDS, assert_loopback_equals_team, builtin_team, loopback_episode, loopback_run, reference


def _standby() -> Scenario:
    return load("paper-standby")


def test_the_paper_has_neither_and_its_tables_are_unchanged() -> None:
    sc = builtin()
    model = Model.build(sc)
    assert sc.standby_accuracy is None and all(k.hazard == 0.0 for k in sc.kinds)
    assert model.standby_class == -1 and model.obs.shape[0] == 1
    for k in range(sc.n_kinds):
        t = model.kind_tables[k]
        assert (t[:, :, 0, 0] == 1.0).all() and (t[:, :, 0, 1:] == 0.0).all()  # level 0 absorbing
    a = np.array([[0, 4, 5, 3, -1]])
    task, cls = model.observes(a, 3)
    assert task.tolist() == [[0, -1, -1, 3, -1]] and cls.tolist() == [[0, -1, -1, 0, -1]]


def test_hazard_reopens_a_finished_task_and_rows_sum_to_one() -> None:
    sc = _standby()
    model = Model.build(sc)
    fire = kind_table(sc, 0)
    assert np.allclose(fire[:, :, 0, 0], 0.99) and np.allclose(fire[:, :, 0, REOPEN_LEVEL], 0.01)
    assert (kind_table(sc, 1)[:, :, 0, 0] == 1.0).all()  # the rescue keeps level 0 absorbing
    for t in model.kind_tables:
        np.testing.assert_allclose(t.sum(axis=-1), 1.0, atol=1e-12)
        assert (t >= 0.0).all()
    np.testing.assert_allclose(model.transition_pdf.sum(axis=-1), 1.0, atol=1e-12)
    # the rest of the fire's table is the paper's
    paper = kind_table(builtin(), 0)
    assert np.array_equal(fire[:, :, 1:], paper[:, :, 1:])


def test_a_finished_task_is_never_believed_certain_with_a_hazard() -> None:
    """Greedy team, 30 steps: the fires (hazard 0.01) are believed done at most with 1 - something, whatever
    the team observed; the rescues (no hazard) may become certain."""
    sc = _standby()
    team = Team(sc, 32, seed=5)
    pol = GreedyPolicy(sc)
    team.reset()
    fires = [j for j, (_, k) in enumerate(sc.tasks) if k == 0]
    lowest = 1.0
    for _ in range(sc.horizon):
        team.step(team.force_inactive(pol.act(team.context())))
        p0 = team.marg[:, :, fires, 0]
        assert (p0 < 1.0).all()
        lowest = min(lowest, float((1.0 - p0).min()))
    assert lowest > 0.0
    assert (team.sim.levels[:, fires] == 0).any()  # some fire was finished and is still believed uncertain


def test_standby_observes_the_site_tasks_in_turn() -> None:
    sc = _standby()
    model = Model.build(sc)
    p = sc.n_tasks  # idle@site1 = 4, idle@site2 = 5
    a = np.array([[p, p + 1, 0, 3, p]])
    for t in range(1, 5):
        task, cls = model.observes(a, t)
        assert task.tolist() == [[t % 2, 2 + t % 2, 0, 3, t % 2]]
        assert cls.tolist() == [[1, 1, 0, 0, 1]]
    with pytest.raises(ValueError, match="step t"):
        model.observes(a, None)
    ht = Model.build(sc.replace(mode="ht"))  # no idle locations: nobody stands by
    assert ht.standby_class == -1
    assert ht.observes(np.array([[-1, 2]]), 1)[0].tolist() == [[-1, 2]]


def test_standby_keeps_the_random_streams_and_the_workers_observations() -> None:
    """The simulator draws what it drew without standby: the same next levels and, for the workers, the same
    observations; the standing-by agents now see a level of their task (the standby class's O)."""
    sc = _standby()
    plain = sc.replace(standby_accuracy=None)
    m1, m0 = Model.build(sc), Model.build(plain)
    rng = np.random.default_rng(0)
    levels = rng.integers(0, sc.levels, (64, sc.n_tasks))
    actions = rng.integers(0, sc.n_actions, (64, sc.n_agents))
    n1, z1, _ = sample_world_step(m1, levels, actions, np.random.default_rng(9), 3)
    n0, z0, _ = sample_world_step(m0, levels, actions, np.random.default_rng(9), 3)
    assert np.array_equal(n1, n0)
    working = actions < sc.n_tasks
    assert np.array_equal(z1[working], z0[working]) and (z0[~working] == -1).all()
    assert (z1[~working] >= 0).all()
    task, _ = m1.observes(actions, 3)
    assert (np.abs(z1 - np.take_along_axis(n1, task, axis=1)) <= 1).all()  # O moves at most one level


def test_a_standby_observation_is_evidence_with_the_standby_accuracy() -> None:
    """Hand-computed Bayes: agent 0 idles at site 1 at step 1 and reports level 2 of rescue@site1 (task 1 mod 2);
    agent 1 hears it through its channel; nobody works, so the prediction is T with no capability."""
    sc = _standby()
    model = Model.build(sc)
    L, p = sc.levels, sc.n_tasks
    acc, tau = 0.6, model.keep[0]
    actions = np.array([[p, p, p, p, p]])
    obs = np.array([[2, -1, -1, -1, -1]])
    msgs = np.array([[3, -1, -1, -1, -1]])  # the channel changed the level: agent 1 hears 3
    o = np.zeros((L, L))  # O_standby[l, z]
    for lv in range(L):
        nbrs = [x for x in (lv - 1, lv + 1) if 0 <= x < L]
        o[lv, lv] = acc
        for x in nbrs:
            o[lv, x] += (1 - acc) / len(nbrs)
    lik0 = bf.agent_evidence(model, 0, actions, obs[:, 0], msgs, t=1)
    lik1 = bf.agent_evidence(model, 1, actions, obs[:, 1], msgs, t=1)
    np.testing.assert_allclose(lik0[0, 1], o[:, 2])  # its own observation: O of the standby class
    np.testing.assert_allclose(lik1[0, 1], tau * o[:, 3] + (1 - tau) / L)  # a teammate's: I of that class
    for j in (0, 2, 3):
        assert (lik0[0, j] == 1.0).all() and (lik1[0, j] == 1.0).all()
    full = bf.evidence(model, actions, obs, msgs, t=1)
    assert np.array_equal(full[:, 0], lik0) and np.array_equal(full[:, 1], lik1)
    # the update of site 1 by hand: a belief spread over a few (fire, rescue) pairs, predicted with T at c = 0
    rng = np.random.default_rng(1)
    belief = bf.initial_belief(model, 1)[:, 0].copy()
    belief[0, 0] = rng.random((L, L))
    belief[0, 0] /= belief[0, 0].sum()
    fire, rescue = model.kind_tables[0][0, 0], model.kind_tables[1][0]  # (l, l') and (g, l, l')
    pred = np.zeros((L, L))
    for f in range(L):
        for r in range(L):
            for f2 in range(L):
                for r2 in range(L):
                    pred[f2, r2] += belief[0, 0, f, r] * fire[f, f2] * rescue[f, r, r2]
    want = pred * o[:, 2][None, :]
    want /= want.sum()
    caps = model.joint_capability(actions)
    new, bad = bf.update(model, belief, caps, lik0)
    assert not bad.any()
    np.testing.assert_allclose(new[0, 0], want, atol=1e-12)


@pytest.mark.parametrize("name", ["greedy", "random"])
@pytest.mark.parametrize("batch", [1, 6])
def test_loopback_equals_team_with_hazard_and_standby(name: str, batch: int) -> None:
    """The per-agent minds of the ROS runtime (AgentMind through the lockstep protocol) and the batched Team agree
    bit for bit on a scenario with a hazard and standby."""
    sc = _standby()
    for seed, b in [(0, 0), (3, 2)]:
        _, tr = assert_loopback_equals_team(sc, name, seed, b, batch)
        assert (tr.observations[tr.actions >= sc.n_tasks] >= 0).all()  # the idle agents stood by


def test_an_absent_agent_observes_nothing_like_an_inactive_one() -> None:
    sc = _standby()
    pols, _ = builtin_team(sc, "greedy")
    absent = {t: {2} for t in range(1, sc.horizon + 1)}
    lb = loopback_episode(sc, 4, 3, pols, absent=absent)
    tr = reference(sc, pols, 4, 0.0, 3, inactive=(2,))
    for f in FIELDS:
        assert np.array_equal(getattr(tr, f)[:, 0], lb[f]), f
    assert (lb["observations"][:, 2] == -1).all() and (lb["messages"][:, 2] == -1).all()


def test_the_world_record_names_the_task_a_standing_by_agent_observed() -> None:
    """LockstepProtocol's observation records: `tasks` is `Model.observes` of the applied actions where a level was
    observed, so an idle agent's record names the task it stood by for."""
    sc = _standby()
    model = Model.build(sc)
    records: dict[tuple[int, int], dict] = {}  # type: ignore[type-arg]

    class Recording(LockstepProtocol):
        def _apply_step(self, now: float, out) -> None:  # type: ignore[no-untyped-def]
            super()._apply_step(now, out)
            for kind, rec in out.publish:
                if kind == "observation":
                    records[(rec["step"], rec["agent"])] = rec

    pols = [builtin_policy(sc, "greedy", i)[0] for i in range(sc.n_agents)]
    world_log, _ = loopback_run(sc, 0, 0, 1, pols, 0.0, protocol=Recording)
    actions = world_log[0]["actions"]
    stood = 0
    for (t, k), rec in records.items():
        task, _ = model.observes(np.array(actions[t - 1]), t)
        want = int(task[k]) if rec["levels"][0] >= 0 else -1
        assert rec["tasks"] == [want], (t, k, rec)
        stood += actions[t - 1][k] >= sc.n_tasks and want >= 0
    assert stood > 0


def test_completion_is_the_first_step_from_which_every_level_stays_zero() -> None:
    z, one = [0, 0], [1, 0]
    levels = np.array([[[4, 4]], [z], [one], [z], [z]]).reshape(5, 1, 2)  # done at 1, reopened at 2, done from 3
    comp, failed = completion_step(levels)
    assert comp.tolist() == [3] and failed.tolist() == [False]
    reopened_last = np.array([[4, 4], z, z, z, one]).reshape(5, 1, 2)
    comp, failed = completion_step(reopened_last)
    assert comp.tolist() == [4] and failed.tolist() == [True]
    absorbing = np.array([[4, 4], one, z, z, z]).reshape(5, 1, 2)  # the paper's case: the first all-zero step
    assert completion_step(absorbing)[0].tolist() == [2]


@pytest.mark.parametrize(
    ("data", "field", "value"),
    [
        ({"standby_accuracy": 1.5}, "standby_accuracy", "1.5"),
        ({"standby_accuracy": "high"}, "standby_accuracy", "high"),
        ({"kinds": [{"name": "fire", "hazard": -0.1}, {"name": "rescue"}]}, "kinds[0].hazard", "-0.1"),
        ({"kinds": [{"name": "fire"}, {"name": "rescue", "hazard": 2}]}, "kinds[1].hazard", "2"),
    ],
)
def test_bad_numbers_are_refused_naming_file_field_and_value(data: dict, field: str, value: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(ScenarioError) as e:
        from_dict(data, "bad.yaml")
    msg = str(e.value)
    assert "bad.yaml" in msg and field in msg and value in msg, msg


def test_the_record_carries_hazard_and_standby() -> None:
    """Scenario.to_dict (checkpoints, run directories, the /htlm/scenario record) carries both numbers: through the
    wire schema and back, the scenario is the same."""
    sc = _standby()
    back = from_dict(sc.to_dict(), "record")
    assert back == sc and back.standby_accuracy == 0.6 and back.kinds[0].hazard == 0.01
    assert sc.layout_hash() == builtin().layout_hash()  # same knowledge state and actions as the paper
    fields = {
        "run": "r1",
        "nonce": "0" * 16,
        "seq": 0,
        "seed": 1,
        "mode": "evaluate",
        "clock": "lockstep",
        "period": 0.0,
        "operation": "simulated",
        "first_episode": 0,
        "episodes": 1,
        "batch": 1,
        "trainer_lag": 0,
        "epoch": 0.0,
        "state": "running",
        "layout": sc.layout_hash(),
        "scenario": sc.to_dict(),
    }
    rec = schema.decode(schema.encode(schema.SCENARIO, fields), schema.SCENARIO)
    assert from_record(rec) == sc


@pytest.mark.parametrize("batch", [1, 6])
def test_both_runtimes_agree_under_events_with_hazard_and_standby(batch: int) -> None:
    """The scenario events (a surge, a dropout and a chance return) on top of the hazard and standby: the lockstep
    minds equal the Team bit for bit, and an agent an event keeps out observes nothing, standing by or not."""
    sc = from_dict({"events": MIXED, "kinds": load("paper-standby").to_dict()["kinds"], "standby_accuracy": 0.6})
    for seed, b in [(0, 0), (5, 3)]:
        _, tr = assert_loopback_equals_team(sc, "greedy", seed, b, batch)
        assert (tr.observations[2:8, :, 1] == -1).all(), "agent2 is out from step 3 to 8: it observes nothing"
        assert (tr.observations[tr.actions >= sc.n_tasks] >= 0).any(), "the others stand by"
