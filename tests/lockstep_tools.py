"""The comparison the lockstep tests share: a batch of episodes of built-in per-agent policies run by the in-process
Team and through the lockstep protocol in one process (WorldEpisode and one AgentMind per agent, as the ROS nodes
run them), field by field."""

from __future__ import annotations

import numpy as np

from htlm_agent.baselines.heuristics import builtin_policy
from htlm_agent.mind.agent import loopback_episode
from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.runtime.team import Team, Trajectory, rollout
from htlm_world.model import Model
from htlm_world.scenario import Scenario

FIELDS = ("levels", "actions", "observations", "messages", "rewards")


def assert_loopback_equals_team(sc: Scenario, name: str, seed: int, b: int, batch: int) -> tuple[Team, Trajectory]:
    """Batch b of `batch` episodes of the built-in policy `name` in both runtimes: equal in every field (FIELDS).
    Returns the Team and its trajectory, for what a test checks beyond equality."""
    model = Model.build(sc)
    out = [builtin_policy(sc, name, i) for i in range(sc.n_agents)]
    pols, eps = [p for p, _ in out], out[0][1]
    dp = DecentralizedPolicy(pols, seed, eps)
    dp.begin(b)
    team = Team(sc, batch, seed, episode=b)
    tr = rollout(team, dp)
    lb = loopback_episode(sc, seed, b * batch, pols, epsilon=eps, model=model, batch=batch)
    for f in FIELDS:
        got = lb[f] if batch > 1 else lb[f][:, None]
        assert np.array_equal(getattr(tr, f), got), (f, seed, b)
    return team, tr
