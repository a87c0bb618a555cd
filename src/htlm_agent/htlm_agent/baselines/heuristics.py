"""Baselines behind the team policy interface (`team.Policy`: act(Context) -> (B, N) actions).

- `RandomPolicy`: every agent draws uniformly from its reduced action space Â(a_o).
- `GreedyPolicy`: a hand-written decentralized heuristic over each agent's own belief.
- the HT Dec-POMDP learner (the paper's predecessor): the same deep Q-learner on the scenario in mode "ht" (no idle
  locations, R_LM = 0), see `htlm_agent.baselines.registry.train_ht`.
- `OptimalPolicy` (htlm_agent.baselines.optimal): the centralized, fully observed optimum acting on the true state
  (the floor).

`htlm_agent.baselines.registry.make_baseline` builds any of them by name.
"""

from __future__ import annotations

import numpy as np

from htlm_agent.mind.reward import RewardTables, confident_levels
from htlm_agent.runtime.team import Context
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import IntArray

BASELINES = ("random", "greedy", "ht", "optimal")
"""Names accepted by `registry.make_baseline` and `htlm evaluate --baseline` (here, in a module without torch, so
that the command line lists them without loading the learner)."""


class RandomPolicy:
    """Every agent picks uniformly from Â(a_o), each with its own generator derived from the seed."""

    def __init__(self, scenario: Scenario, seed: int = 0) -> None:
        """Generators for agents 0..N-1 from the seed's `seeds.random_policy` streams."""
        self.scenario = scenario
        self.rngs = [seeds.random_policy(seed, i) for i in range(scenario.n_agents)]

    def act(self, ctx: Context) -> IntArray:
        """Uniform draws over each agent's own mask."""
        b, n, g = ctx.mask.shape
        out = np.empty((b, n), dtype=np.int64)
        for i, rng in enumerate(self.rngs):
            u = rng.random((b, g))
            out[:, i] = np.where(ctx.mask[:, i], u, -1.0).argmax(axis=1)
        return out


class GreedyPolicy:
    """A decentralized heuristic over each agent's own belief (no learning, no communication beyond the model's).

    Agent i has a home site (i mod S). From its confident levels (the reward's b_th), it works on the first task,
    in the order home site first, fire before rescue, that is believed unfinished, that it has capability for, and
    that can progress (rescue only while the site's fire is at most rescue_block_fire). With nothing to do it idles at
    its current site (HT mode: it stays on its previous task).
    """

    def __init__(self, scenario: Scenario) -> None:
        """Precompute each agent's task preference order."""
        self.scenario = scenario
        self.model = Model.build(scenario)
        self.threshold = RewardTables.build(scenario).threshold
        s = scenario.n_sites
        self.order = []
        for i in range(scenario.n_agents):
            home = i % s
            sites = [home] + [x for x in range(s) if x != home]
            self.order.append([int(j) for site in sites for j in self.model.site_task[site] if j >= 0])

    def act(self, ctx: Context) -> IntArray:
        """One action per agent from its own row of the Context."""
        sc = self.scenario
        lv = confident_levels(ctx.marginals, self.threshold)  # (B, N, p)
        b, n = ctx.prev.shape
        stay = self.model.idle_action(ctx.prev) if sc.n_idle else np.where(ctx.prev >= 0, ctx.prev, 0)
        out = stay.astype(np.int64)
        chosen = np.zeros((b, n), dtype=bool)
        blocked = self.model.blocked(lv)  # (B, N, p) as each agent believes
        for i in range(n):
            for j in self.order[i]:
                if self.model.agent_caps[i, j] == 0:
                    continue
                ok = (lv[:, i, j] > 0) & ~blocked[:, i, j]
                take = ok & ~chosen[:, i]
                out[take, i] = j
                chosen[:, i] |= take
        return out
