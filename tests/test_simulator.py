"""Determinism of the simulator and the in-process team (same seed, same trajectory), and the episode metrics of
docs/model.md and agent importance (Eqs. 6-9) on hand-made arrays."""

from __future__ import annotations

import numpy as np
import pytest

from htlm_agent.mind.context import Context
from htlm_agent.runtime.team import Team, Trajectory, rollout
from htlm_world import seeds
from htlm_world.metrics import completion_step, episode_metrics, importance
from htlm_world.model import Model
from htlm_world.scenario import builtin
from htlm_world.simulator import sample_channel, sample_world_step
from htlm_world.types import IntArray


class RandomPolicy:
    """Uniform over every agent's Â(a_o), from its own seeded generator."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, ctx: Context) -> IntArray:
        scores = self.rng.random(ctx.mask.shape)
        scores[~ctx.mask] = -1.0
        return np.asarray(scores.argmax(axis=-1), dtype=np.int64)


def run(seed: int, policy_seed: int = 0, team: str = "heterogeneous", batch: int = 8, episode: int = 0) -> Trajectory:
    return rollout(Team(builtin(team), batch, seed, episode=episode), RandomPolicy(policy_seed))


def assert_same(a: Trajectory, b: Trajectory) -> None:
    for name in ("levels", "actions", "observations", "messages", "rewards"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("team", ["heterogeneous", "semi-heterogeneous", "homogeneous"])
def test_same_seed_same_trajectory(team: str) -> None:
    a, b = run(11, team=team), run(11, team=team)
    assert a.levels.shape == (31, 8, 4) and a.actions.shape == (30, 8, 5) and a.rewards.shape == (30, 8, 5)
    assert_same(a, b)


def test_different_seeds_different_trajectories() -> None:
    a, b = run(11), run(12)
    assert not np.array_equal(a.levels, b.levels)
    assert not np.array_equal(a.observations, b.observations)
    c = run(11, episode=1)  # another episode index of the same master seed
    assert not np.array_equal(a.levels, c.levels)


def test_world_and_channel_draws_replay_from_the_derived_generators() -> None:
    """The ROS runtime's world and agent processes draw from the same derived generators in the same order."""
    seed, episode = 21, 3
    traj = run(seed, policy_seed=4, batch=4, episode=episode)
    sc = builtin()
    model = Model.build(sc)
    world = seeds.world(seed, episode)
    channels = [seeds.channel(seed, k, episode) for k in range(sc.n_agents)]
    levels = traj.levels[0]
    for t in range(sc.horizon):
        levels, obs, _ = sample_world_step(model, levels, traj.actions[t], world)
        np.testing.assert_array_equal(levels, traj.levels[t + 1])
        np.testing.assert_array_equal(obs, traj.observations[t])
        for k in range(sc.n_agents):
            np.testing.assert_array_equal(sample_channel(model, k, obs[:, k], channels[k]), traj.messages[t][:, k])


def test_rewards_follow_the_trajectory() -> None:
    traj = run(5)
    assert np.isfinite(traj.rewards).all()
    assert ((traj.actions >= 0) & (traj.actions < 6)).all()
    assert ((traj.levels >= 0) & (traj.levels <= 4)).all()
    # idle agents observe nothing and broadcast nothing
    idle = traj.actions >= 4
    assert (traj.observations[idle] == -1).all() and (traj.messages[idle] == -1).all()
    assert (traj.observations[~idle] >= 0).all()


# ----- metrics -----------------------------------------------------------------------------------------------------


def test_completion_step() -> None:
    levels = np.array(
        [
            # h = 4; episodes: completes at 3, never (failure), completes at 1, already complete (1)
            [[4, 4, 4, 4], [4, 4, 4, 4], [1, 0, 0, 0], [0, 0, 0, 0]],
            [[2, 3, 1, 2], [4, 4, 3, 4], [0, 0, 0, 0], [0, 0, 0, 0]],
            [[0, 1, 0, 0], [3, 3, 3, 3], [0, 0, 0, 0], [0, 0, 0, 0]],
            [[0, 0, 0, 0], [2, 2, 2, 2], [0, 0, 0, 0], [0, 0, 0, 0]],
            [[0, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]],
        ]
    )
    comp, failed = completion_step(levels)
    assert comp.tolist() == [3, 4, 1, 1]
    assert failed.tolist() == [False, True, False, False]


def test_unused_capability_and_fraction() -> None:
    sc = builtin()  # total capability per agent 4, 5, 2, 1, 2: mean 2.8
    actions = np.array([[[4, 0, 4, 1, 3]], [[0, 5, 2, 3, 2]]])  # (h=2, B=1, N=5)
    levels = np.array([[[4, 4, 4, 4]], [[3, 4, 4, 4]], [[3, 3, 4, 4]]])
    m = episode_metrics(sc, levels, actions)
    np.testing.assert_allclose(m.agent_unused, [[4 / 2, 5 / 2, 2 / 2, 0.0, 0.0]])
    np.testing.assert_allclose(m.unused_capability, [(4 + 2 + 5) / (5 * 2)])  # 1.1
    np.testing.assert_allclose(m.unused_fraction, [1.1 / 2.8])
    assert m.failed.tolist() == [True] and m.completion.tolist() == [2]


def test_idle_and_reassignment_counts_before_completion() -> None:
    sc = builtin()  # previous assignment before step 1: idle@site1
    actions = np.array(
        [
            [0, 4, 2, 5, 1],
            [4, 4, 3, 5, 0],
            [4, 5, 0, 4, 4],  # after completion in episode 0
            [5, 5, 5, 5, 5],
        ]
    )
    actions = np.stack([actions, actions], axis=1)  # (h=4, B=2, N=5)
    levels = np.array(
        [
            [[4, 4, 4, 4], [4, 4, 4, 4]],
            [[1, 1, 0, 0], [4, 4, 4, 4]],
            [[0, 0, 0, 0], [4, 4, 4, 4]],  # episode 0 completes at step 2; episode 1 never
            [[0, 0, 0, 0], [4, 4, 4, 4]],
            [[0, 0, 0, 0], [4, 4, 4, 4]],
        ]
    )
    m = episode_metrics(sc, levels, actions)
    assert m.completion.tolist() == [2, 4] and m.failed.tolist() == [False, True]
    assert m.agent_idle_before.tolist() == [[1, 2, 0, 2, 0], [3, 4, 1, 4, 2]]
    assert m.idle_before.tolist() == [5, 14]
    assert m.agent_reassign_before.tolist() == [[0, 0, 1, 1, 0], [1, 1, 3, 3, 1]]
    assert m.reassign_before.tolist() == [2, 9]


def test_importance_eqs_6_to_9() -> None:
    sc = builtin()  # C (fire, rescue): (3,1) (3,2) (2,0) (0,1) (1,1)
    actions = np.array(
        [
            [[0, 1, 2, 3, 4], [0, 0, 4, 1, 1]],
            [[2, 4, 0, 5, 3], [5, 1, 0, 3, 2]],
        ]
    )  # (h=2, E=2, N=5)
    imp = importance(sc, actions)
    counts = np.array([[3, 0], [1, 2], [3, 0], [0, 3], [1, 2]])  # decisions of each type over episodes and steps
    caps = np.array([[3, 1], [3, 2], [2, 0], [0, 1], [1, 1]])
    usage = caps * counts / 2  # Eq. 7, E = 2
    np.testing.assert_allclose(imp.capability, caps)
    np.testing.assert_allclose(imp.usage, usage)
    np.testing.assert_allclose(imp.omega, [8 / 15, 7 / 15])  # Eqs. 8-9
    np.testing.assert_allclose(imp.zeta, [2.4, 0.8 + 14 / 15, 1.6, 0.7, 11 / 15])  # Eq. 6
