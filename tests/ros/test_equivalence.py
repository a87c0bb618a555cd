"""With the same seed and policies, an evaluation over ROS (7 processes, real DDS) gives exactly the trajectories of
the in-process runtime (team.rollout on Team(scenario, 1, seed, episode=e)), episode by episode."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.runtime.team import Team, rollout

from .conftest import assert_same_as_in_process

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]


@pytest.mark.parametrize(("policy", "seed", "first"), [("greedy", 11, 0), ("random", 5, 40)])
def test_ros_evaluation_equals_in_process(ros_team: Any, policy: str, seed: int, first: int) -> None:
    team = ros_team(policy=policy, seed=seed, episodes=3, first_episode=first)
    team.start()
    assert team.wait("world", 60) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    assert assert_same_as_in_process(team, seed, policy) == 3
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())


def test_ros_evaluation_of_a_checkpoint_equals_in_process(ros_team: Any, tmp_path: Path) -> None:
    """Agents load their own Q-networks (AgentQ) from a checkpoint of the learner, as `htlm evaluate` does."""
    from htlm_agent.learning.checkpoint import load_checkpoint
    from htlm_agent.learning.dqn import Learner
    from htlm_agent.learning.qnet import AgentQ
    from htlm_agent.learning.settings import Settings

    team = ros_team(policy="checkpoint", seed=3, episodes=2, first_episode=7)
    sc = team.cfg.scenario
    learner = Learner(sc, Settings(memory=1000, envs=1), seed=42)
    with np.errstate(all="ignore"):
        ckpt = learner.save(tmp_path / "ckpt")
    team.cfg.checkpoint = str(ckpt)
    team.start()
    assert team.wait("world", 90) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    ck = load_checkpoint(ckpt)
    nets = [AgentQ.from_checkpoint(ck, i) for i in range(sc.n_agents)]

    def reference(e: int) -> Any:
        dp = DecentralizedPolicy(nets, 3, 0.0)  # type: ignore[arg-type]
        dp.begin(e)
        return rollout(Team(sc, 1, 3, episode=e), dp)

    assert assert_same_as_in_process(team, 3, reference) == 2


def test_free_running_clock_equals_in_process(ros_team: Any) -> None:
    """The world steps every 50 ms instead of as soon as everyone answered; agents that keep up give the same run."""
    team = ros_team(policy="greedy", seed=1, episodes=2, world_params={"clock": "free", "period": 0.05})
    team.start()
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    assert assert_same_as_in_process(team, 1, "greedy") == 2
    seconds = [w["metrics"]["seconds"] for w in team.world_episodes()]
    assert seconds[-1] >= 30 * 0.05 * 0.9, seconds  # paced by the clock, not by the agents
