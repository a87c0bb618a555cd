"""Speed of the in-process runtime: how many agent-steps a second the simulator alone and the team (simulator, every
agent's belief filter and reward) run at a batch of B episodes. `htlm bench` reports both per scenario, and `htlm
bench scale` the team's beside the ROS 2 runtime's at each team size."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from htlm_agent.baselines.heuristics import RandomPolicy
from htlm_agent.runtime.team import Team
from htlm_world.scenario import Scenario, builtin
from htlm_world.simulator import BatchSim


def rate(step: Any, seconds: float) -> tuple[float, int]:
    """Calls of step() per second over about `seconds` (after one warm-up call)."""
    step()
    n, t0 = 0, time.perf_counter()
    while True:
        step()
        n += 1
        el = time.perf_counter() - t0
        if el >= seconds:
            return n / el, n


def sim_rate(batch: int, seconds: float, sc: Scenario | None = None) -> float:
    """Simulator agent-steps/s at batch B with uniformly random joint actions (the paper's scenario by default)."""
    sc = sc or builtin()
    sim = BatchSim(sc, batch, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    actions = rng.integers(0, sc.n_actions, (64, batch, sc.n_agents))
    i = [0]

    def step() -> None:
        if sim.t >= sc.horizon:
            sim.reset()
        sim.step(actions[i[0] % 64])
        i[0] += 1

    r, _ = rate(step, seconds)
    return r * batch * sc.n_agents


def team_rate(batch: int, seconds: float, sc: Scenario | None = None) -> float:
    """Team agent-steps/s (simulator + belief filters + rewards) at batch B with random actions from Â."""
    sc = sc or builtin()
    team = Team(sc, batch, 0)
    pol = RandomPolicy(sc, 0)

    def step() -> None:
        if team.t >= sc.horizon:
            team.reset()
        team.step(pol.act(team.context()))

    r, _ = rate(step, seconds)
    return r * batch * sc.n_agents
