"""The PettingZoo ParallelEnv over the in-process team."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from htlm_agent.runtime.pz_env import HTLMParallelEnv
from htlm_agent.runtime.team import Team
from htlm_world.scenario import builtin


@pytest.mark.parametrize("mode", ["htlm", "ht"])
def test_parallel_api_test(mode: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the API test reports contract slips as warnings
        parallel_api_test(HTLMParallelEnv(builtin(mode=mode)), num_cycles=100)


@pytest.mark.parametrize("mode", ["htlm", "ht"])
def test_parallel_seed_test(mode: str) -> None:
    # parallel_seed_test samples the action space without the mask: actions outside Â are mapped (the default)
    parallel_seed_test(lambda: HTLMParallelEnv(builtin(mode=mode)))


def masked_actions(env: HTLMParallelEnv, obs: dict, rng: np.random.Generator) -> dict[str, int]:
    return {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}


def test_spaces_and_episode_shape() -> None:
    env = HTLMParallelEnv()
    assert env.possible_agents == [f"agent{i}" for i in range(1, 6)]
    obs, infos = env.reset(seed=3)
    assert env.agents == env.possible_agents and set(infos) == set(env.agents)
    rng = np.random.default_rng(0)
    for t in range(1, 31):
        for a in env.agents:
            space = env.observation_space(a)
            assert space.contains(obs[a]), (a, obs[a])
            assert obs[a]["observation"].shape == (26,) and obs[a]["action_mask"].sum() == 5
        obs, rew, term, trunc, info = env.step(masked_actions(env, obs, rng))
        assert set(rew) == set(term) == set(trunc) == set(info) == set(env.possible_agents)
        assert not any(term.values())
        assert all(trunc.values()) == (t == 30) and any(trunc.values()) == (t == 30)
        assert all(isinstance(r, float) for r in rew.values())
    assert env.agents == []
    assert env.state().shape == (4,)
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_same_as_team_with_the_same_seed() -> None:
    """Episode e of master seed s is the in-process team's Team(scenario, 1, s, episode=e)."""
    sc = builtin("semi-heterogeneous")
    env = HTLMParallelEnv(sc)
    env.reset(seed=9)
    obs, _ = env.reset()  # episode 1
    assert env.episode == 1 and env.master_seed == 9
    team = Team(sc, 1, 9, episode=1)
    rng = np.random.default_rng(1)
    for _ in range(sc.horizon):
        know = team.knowledge()[0]
        for i, a in enumerate(env.possible_agents):
            np.testing.assert_allclose(obs[a]["observation"], np.clip(know[i], 0, 1))
            assert obs[a]["action_mask"].tolist() == team.mask()[0, i].astype(int).tolist()
        acts = masked_actions(env, obs, rng)
        obs, rew, _, _, info = env.step(acts)
        _, r, team_info = team.step(np.array([[acts[a] for a in env.possible_agents]]))
        np.testing.assert_array_equal(env.state(), team_info.levels[0])
        assert [rew[a] for a in env.possible_agents] == r[0].tolist()
        assert not any(i["action_mapped"] for i in info.values())


def test_reset_seeds_reproduce_and_differ() -> None:
    def levels(env: HTLMParallelEnv, seed: int | None) -> list[list[int]]:
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(0)
        out = []
        while env.agents:
            obs, *_ = env.step(masked_actions(env, obs, rng))
            out.append(env.state().tolist())
        return out

    env = HTLMParallelEnv()
    first = levels(env, 4)
    second = levels(env, None)  # next episode of seed 4
    assert levels(env, 4) == first and levels(env, None) == second
    assert first != second
    assert levels(HTLMParallelEnv(seed=4), None) == first  # a constructor seed: the first reset() is episode 0
    unseeded = HTLMParallelEnv()
    levels(unseeded, None)
    assert unseeded.master_seed is not None


def test_actions_outside_reduced_space() -> None:
    sc = builtin()
    env = HTLMParallelEnv(sc, invalid_action="raise")
    env.reset(seed=0)
    acts = {a: 4 for a in env.agents}
    acts["agent3"] = 5  # idle@site2 while a_o = idle@site1: not in Â
    with pytest.raises(ValueError, match=r"agent 'agent3': action 5 \(idle@site2\) is not in Â"):
        env.step(acts)
    env = HTLMParallelEnv(sc)  # default: mapped to the idle location at the site of a_o
    env.reset(seed=0)
    _, _, _, _, info = env.step(acts)
    assert info["agent3"]["action_mapped"] and info["agent3"]["executed_action"] == 4
    assert not info["agent1"]["action_mapped"] and info["agent1"]["executed_action"] == 4
    acts = {a: 2 for a in env.agents}  # everyone to fire@site2 ...
    env.step(acts)
    acts = {a: 4 for a in env.agents}  # ... then idle@site1, outside Â(fire@site2): idle@site2
    _, _, _, _, info = env.step(acts)
    assert all(i["executed_action"] == 5 and i["action_mapped"] for i in info.values())


@pytest.mark.parametrize("bad", [6, -1, 2.0, "2", True, None, np.array([1, 2])])
def test_actions_outside_action_space_raise(bad: object) -> None:
    env = HTLMParallelEnv()
    env.reset(seed=0)
    acts: dict[str, object] = {a: 0 for a in env.agents}
    acts["agent2"] = bad
    with pytest.raises(ValueError, match="agent 'agent2'"):
        env.step(acts)


def test_numpy_integer_actions_are_accepted() -> None:
    env = HTLMParallelEnv()
    obs, _ = env.reset(seed=0)
    acts = {a: env.action_space(a).sample(mask=obs[a]["action_mask"]) for a in env.agents}
    assert all(isinstance(v, np.integer) for v in acts.values())
    acts["agent1"] = np.array(1)
    env.step(acts)


def test_missing_or_unknown_agents_raise() -> None:
    env = HTLMParallelEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="agent5"):
        env.step({a: 0 for a in env.agents[:4]})
    with pytest.raises(ValueError, match="agent9"):
        env.step({**{a: 0 for a in env.agents}, "agent9": 0})
    with pytest.raises(ValueError, match="invalid_action"):
        HTLMParallelEnv(invalid_action="ignore")
