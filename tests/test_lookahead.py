"""The lookahead baseline: its value network learns the auction's steps to go, and each agent improves on the auction
from its own belief alone."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import AuctionPolicy
from htlm_agent.learning.lookahead import BaseValue, LookaheadPolicy, ValueSettings, base_rollouts
from htlm_agent.mind.auction import allocate
from htlm_agent.runtime.evaluate import evaluate
from htlm_agent.runtime.team import Team
from htlm_world.model import Model
from htlm_world.scenario import Scenario, builtin


def exact_auction_value(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Every joint state of `sc` and the expected steps the auction on the true levels takes from it (capped at
    the horizon), by policy evaluation over the whole state space: the reference the network is checked against."""
    model = Model.build(sc)
    states = np.array(list(itertools.product(range(sc.levels), repeat=sc.n_tasks)))
    plan = allocate(model, states[:, None, :])[:, 0, :]
    rows = model.transition_rows(states, model.joint_capability(plan))  # (S, p, L)
    step = np.ones((len(states), 1))
    for j in range(sc.n_tasks):  # P(s' | s): the tasks move independently given the capabilities
        step = (step[:, :, None] * rows[:, None, j, :]).reshape(len(states), -1)
    value = np.zeros(len(states))
    for _ in range(sc.horizon):
        value = np.minimum(1.0 + step @ value, sc.horizon)
        value[0] = 0.0  # every level 0 (state index 0): complete
    return states, value


@pytest.fixture(scope="module")
def paper_value() -> BaseValue:
    value = BaseValue(builtin(), seed=0)
    value.fit()
    return value


def test_rollout_targets_count_the_steps_to_the_next_completion() -> None:
    """Every target is the steps until every level is 0, at least 1 and at most the horizon, and no complete state
    is kept."""
    sc = builtin()
    x, y = base_rollouts(sc, ValueSettings(rollouts=500), seed=0)
    assert x.shape[1] == sc.n_tasks and len(x) == len(y) > 500
    assert x.any(axis=1).all()
    assert y.min() >= 1 and y.max() <= sc.horizon
    start = (x == np.array(sc.initial_levels)).all(axis=1)
    assert y[start].mean() > y[~start].mean()  # from the start there is the most to do


def test_value_network_matches_the_auctions_exact_value(paper_value: BaseValue) -> None:
    states, exact = exact_auction_value(builtin())
    learned = paper_value(states)
    assert learned[0] == 0.0
    start = states.tolist().index(list(builtin().initial_levels))
    assert abs(learned[start] - exact[start]) < 0.3, (learned[start], exact[start])
    err = np.abs(learned - exact)[1:]
    assert np.median(err) < 0.3 and np.sqrt((err**2).mean()) < 0.6, (np.median(err), np.sqrt((err**2).mean()))


def test_the_value_table_gives_every_candidates_value_and_follows_the_network(
    paper_value: BaseValue, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On the paper's operation every joint state's value is looked up in a table worked out once; it gives what
    the network gives (the path of larger operations, forced here), and a new network gets a new table."""
    sc = builtin()
    rng = np.random.default_rng(0)
    none = rng.integers(0, sc.levels, size=(40, 8, sc.n_tasks)) * (rng.random((40, 8, sc.n_tasks)) < 0.6)
    work = np.maximum(none - rng.integers(0, 2, size=none.shape), 0)
    tasks = np.array([0, 2, 3])
    assert paper_value.table() is not None
    looked_up = paper_value.after_step(none, work, tasks, floor=1.0)
    monkeypatch.setattr("htlm_agent.learning.lookahead.TABLE_STATES", 0)
    assert paper_value.table() is None
    forward = paper_value.after_step(none, work, tasks, floor=1.0)
    np.testing.assert_allclose(looked_up, forward, atol=1e-4)
    assert (looked_up[(none == 0).all(axis=-1), 0] == 0).all() and (looked_up >= 0).all()
    monkeypatch.undo()
    other = BaseValue(sc, seed=1).load_params([w * 0.5 for w in paper_value.params()])
    table = other.table()
    assert table is not None and not np.allclose(table, paper_value.table())


def _certain(ctx_marginals: np.ndarray, levels: np.ndarray) -> np.ndarray:
    out = np.zeros_like(ctx_marginals)
    for e, lv in enumerate(levels):
        out[e, :, np.arange(lv.size), lv] = 1.0
    return out


def test_agents_rest_once_every_task_is_believed_done_and_work_a_task_believed_open(paper_value: BaseValue) -> None:
    sc = builtin()
    pol = LookaheadPolicy(sc, paper_value, samples=16)
    team = Team(sc, 3, 3)
    ctx = team.context()
    ctx.marginals = _certain(ctx.marginals, np.array([[0, 0, 0, 0], [3, 0, 0, 0], [0, 0, 4, 0]]))
    a = pol.act(ctx)
    model = Model.build(sc)
    assert (a[0] == model.rest_action(ctx.prev[0])).all()  # complete: nobody works
    for e, task in ((1, 0), (2, 2)):
        workers = np.flatnonzero(a[e] == task)
        assert model.agent_caps[workers, task].sum() >= 3, a[e]  # enough capability on the one open fire
        assert (a[e][a[e] < sc.n_tasks] == task).all(), a[e]  # and nobody on a task believed done


def test_each_agent_acts_on_its_own_row_only(paper_value: BaseValue) -> None:
    """Changing agent 1's belief changes no other agent's choice, and the true levels change nothing."""
    sc = builtin()
    team = Team(sc, 2, 5)
    ctx = team.context()
    before = LookaheadPolicy(sc, paper_value, seed=3).act(ctx)
    ctx.marginals[:, 1] = _certain(ctx.marginals, np.zeros((2, sc.n_tasks), dtype=np.int64))[:, 1]
    ctx.true_levels = np.zeros_like(ctx.true_levels)
    after = LookaheadPolicy(sc, paper_value, seed=3).act(ctx)
    others = np.arange(sc.n_agents) != 1
    assert (after[:, others] == before[:, others]).all()
    assert (after[:, 1] >= sc.n_tasks).all()  # it believes everything done


def test_lookahead_beats_the_auction_on_the_paper_operation(paper_value: BaseValue) -> None:
    """docs/model.md (Baselines, lookahead): on the same episodes, sooner than the auction on its own belief."""
    sc = builtin()
    look = evaluate(LookaheadPolicy(sc, paper_value, samples=32), sc, 100, 0)["completion"]
    auction = evaluate(AuctionPolicy(sc), sc, 100, 0)["completion"]
    assert look["mean"] < auction["mean"] - 0.2, (look, auction)
    assert look["failure_rate"] <= auction["failure_rate"] + 0.02


def test_an_agent_process_works_out_its_own_head_only(paper_value: BaseValue) -> None:
    """`policy:=lookahead` (`builtin_policy`): agent i's process, from its own knowledge state alone, takes an
    action of its reduced action space, and works on the one open task it is needed on."""
    from htlm_agent.learning.lookahead import AgentLookahead
    from htlm_agent.session.builtin import builtin_policy

    sc = builtin()
    team = Team(sc, 4, 7)
    ctx = team.context()
    ctx.marginals = _certain(ctx.marginals, np.array([[4, 4, 4, 4], [0, 0, 3, 0], [0, 0, 0, 0], [1, 2, 3, 4]]))
    k = team.knowledge()
    k[..., : sc.n_tasks * sc.levels] = ctx.marginals.reshape(4, sc.n_agents, -1)
    for i in range(sc.n_agents):
        agent = AgentLookahead(sc, LookaheadPolicy(sc, paper_value, samples=16), i)
        a = agent.act(k[:, i], ctx.mask[:, i])
        assert ctx.mask[np.arange(4), i, a].all(), a
        assert a[2] >= sc.n_tasks  # believed complete: it rests
        assert a[1] in (2, Model.build(sc).rest_action(ctx.prev[1, i]))  # the open fire, or rest
    assert type(builtin_policy(sc, "random", 0)[0]).__name__ == "RowPolicy"


def test_an_agent_draws_the_same_in_any_batch(paper_value: BaseValue) -> None:
    """The draws are a hash of the agent and its own knowledge state: an episode's actions do not depend on the
    episodes batched with it, nor on whether the team or one agent's process asks."""
    from htlm_agent.learning.lookahead import AgentLookahead

    sc = builtin()
    team = Team(sc, 6, 11)
    for _ in range(2):  # beliefs that are not the start's
        team.step(AuctionPolicy(sc).act(team.context()))
    ctx = team.context()
    pol = LookaheadPolicy(sc, paper_value, samples=16)
    whole = pol.act(ctx)
    k, mask = team.knowledge(), ctx.mask
    for i in range(sc.n_agents):
        agent = AgentLookahead(sc, LookaheadPolicy(sc, paper_value, samples=16), i)
        assert (agent.act(k[:, i], mask[:, i]) == whole[:, i]).all()
        assert (agent.act(k[3:5, i], mask[3:5, i]) == whole[3:5, i]).all()


def test_a_run_of_the_lookahead_learner_holds_its_value_network(tmp_path: Path) -> None:
    """`htlm train --learner lookahead`: the checkpoint gives every agent a copy of the value network the same
    settings and seed fit, and the run's evaluation is the team acting with it."""
    from htlm_agent.learning.checkpoint import load_checkpoint
    from htlm_agent.learning.learners import team_policy
    from htlm_agent.learning.lookahead import value_of
    from htlm_agent.learning.run import train
    from htlm_agent.learning.settings import Settings

    sc = builtin()
    settings = Settings.for_learner(
        learner="lookahead", episodes=400, value_updates=40, batch_size=256, eval_episodes=20, seed=3, load_price=0.02
    )
    res = train(sc, settings, tmp_path / "run", progress=False, tensorboard=False)
    ck = load_checkpoint(tmp_path / "run")
    assert ck.settings.learner == "lookahead" and ck.n_agents == sc.n_agents
    assert all(all((a == b).all() for a, b in zip(w, ck.weights[0], strict=True)) for w in ck.weights)
    ref = BaseValue(sc, ValueSettings.of(settings), seed=3)
    ref.fit()
    states = np.random.default_rng(0).integers(0, sc.levels, size=(50, sc.n_tasks))
    np.testing.assert_allclose(value_of(ck)(states), ref(states), rtol=1e-6)
    assert res.metrics["completion"] == evaluate(team_policy(ck), sc, 20, seed=3)["completion"]
    policy = team_policy(ck)
    assert isinstance(policy, LookaheadPolicy) and policy.load[:, 0].max() == 0.0
    assert policy.load[:, 1:].min() == 0.02  # the run's price of a unit of committed capability
    assert (tmp_path / "run" / "eval" / "metrics.json").exists()


def test_the_lookahead_learner_learns_in_process_only(tmp_path: Path) -> None:
    """Over ROS it has nothing to learn from (the agents' transitions): `htlm launch train` says so and where to
    train it instead; a run has nothing to resume."""
    import subprocess
    import sys

    from htlm_agent.learning.checkpoint import CheckpointError
    from htlm_agent.learning.run import train
    from htlm_agent.learning.settings import Settings

    cmd = [sys.executable, "-m", "htlm_agent.cli", "launch", "train", "--set", "learner=lookahead"]
    r = subprocess.run([*cmd, "--run-dir", str(tmp_path / "ros")], capture_output=True, text=True, check=False)
    assert r.returncode != 0
    assert "learner=lookahead learns in process only" in r.stderr and "`htlm train`" in r.stderr
    assert not (tmp_path / "ros").exists()
    settings = Settings.for_learner(learner="lookahead", episodes=100, value_updates=5, batch_size=64)
    train(builtin(), settings, tmp_path / "run", progress=False, tensorboard=False, evaluate_at_end=False)
    with pytest.raises(CheckpointError, match="nothing to resume"):
        train(builtin(), settings, tmp_path / "run", progress=False, tensorboard=False, resume=True)


def test_the_default_learner_is_the_expert_learner_unless_a_q_learner_setting_is_given() -> None:
    """One default for `htlm train` and `htlm launch train`: the expert-iteration learner; the token learner when a
    setting only the Q-learners read is changed; a named learner always."""
    from htlm_agent.learning.settings import Settings

    # the lookahead run learns what the baseline does (the launch report's row `lookahead (learner)` says so)
    assert ValueSettings.of(Settings.for_learner(learner="lookahead")) == ValueSettings()
    assert Settings.for_users({"episodes": 100})["learner"] == "expert"
    assert Settings.for_users({"load_weight": 0.5, "rounds": 2})["learner"] == "expert"
    assert Settings.for_users({"learning_starts": 100})["learner"] == "tokens"
    assert Settings.for_users({"imitate_episodes": 10})["learner"] == "tokens"
    assert Settings.for_users({"learner": "lookahead", "memory": 10})["learner"] == "lookahead"
    assert Settings(**Settings.for_users({})).trainer_lag == 0  # the expert's rounds play each policy whole
