"""Baselines behind the team policy interface (`team.Policy`: act(Context) -> (B, N) actions).

- `RandomPolicy`: every agent draws uniformly from its reduced action space Â(a_o).
- `GreedyPolicy`: a hand-written decentralized heuristic over each agent's own belief.
- the HT Dec-POMDP learner (the paper's predecessor): the same deep Q-learner on the scenario in mode "ht" (no idle
  locations, R_LM = 0), see `train_ht`.
- `OptimalPolicy` (htlm_agent.baselines.optimal): the centralized, fully observed optimum acting on the true state
  (the floor).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.mind.reward import RewardTables, confident_levels
from htlm_agent.runtime.team import Context, Policy
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import IntArray

BASELINES = ("random", "greedy", "ht", "optimal")
"""Names accepted by `make_baseline` and `htlm evaluate --baseline`."""


class RandomPolicy:
    """Every agent picks uniformly from Â(a_o), each with its own generator derived from the seed."""

    def __init__(self, scenario: Scenario, seed: int = 0) -> None:
        """Generators for agents 0..N-1 from SeedSequence([seed, 5, agent])."""
        self.scenario = scenario
        self.rngs = [np.random.default_rng(np.random.SeedSequence([seed, 5, i])) for i in range(scenario.n_agents)]

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
            self.order.append([2 * site + kind for site in sites for kind in (0, 1)])

    def act(self, ctx: Context) -> IntArray:
        """One action per agent from its own row of the Context."""
        sc = self.scenario
        p = sc.n_tasks
        lv = confident_levels(ctx.marginals, self.threshold)  # (B, N, p)
        b, n = ctx.prev.shape
        prev_site = np.where(ctx.prev >= 0, self.model.action_site[np.maximum(ctx.prev, 0)], 0)
        stay = p + prev_site if sc.n_idle else np.where(ctx.prev >= 0, ctx.prev, 0)
        out = stay.astype(np.int64)
        chosen = np.zeros((b, n), dtype=bool)
        for i in range(n):
            for j in self.order[i]:
                if self.model.agent_caps[i, j] == 0:
                    continue
                ok = lv[:, i, j] > 0
                if j % 2 == 1:
                    ok &= lv[:, i, j - 1] <= sc.rescue_block_fire
                take = ok & ~chosen[:, i]
                out[take, i] = j
                chosen[:, i] |= take
        return out


def ht_scenario(scenario: Scenario) -> Scenario:
    """The HT Dec-POMDP version of a scenario: no idle locations, R_LM = 0 (MODEL.md)."""
    return scenario.replace(mode="ht")


def train_ht(scenario: Scenario, settings: Any, out_dir: str | Path, progress: bool = False) -> tuple[Policy, Scenario]:
    """Train the HT Dec-POMDP learner on `scenario` (converted to mode "ht") and return its greedy policy."""
    from htlm_agent.learning.checkpoint import load_checkpoint
    from htlm_agent.learning.dqn import QPolicy, train

    sc = ht_scenario(scenario) if scenario.mode != "ht" else scenario
    res = train(sc, settings, out_dir, progress=progress, evaluate_at_end=False)
    ck = load_checkpoint(res.out_dir / "checkpoint")
    return QPolicy.from_checkpoint(ck), sc


def make_baseline(
    name: str,
    scenario: Scenario,
    seed: int = 0,
    ht_policy: str | Path | None = None,
    ht_out: str | Path | None = None,
    settings: Any = None,
    progress: bool = False,
) -> tuple[Policy, Scenario]:
    """A baseline policy and the scenario it acts in.

    Args:
        name: one of BASELINES.
        scenario: the operation (HTLM mode; "ht" converts it).
        seed: seed of the random baseline and of an HT learner trained here.
        ht_policy: a checkpoint of an HT learner (`htlm train --mode ht`) to use instead of training one.
        ht_out: run directory for an HT learner trained here (required when ht_policy is None and name is "ht").
        settings: learner settings for an HT learner trained here (defaults with the seed).
        progress: show the HT learner's training progress.
    """
    from htlm_agent.baselines.optimal import OptimalPolicy

    if name == "random":
        return RandomPolicy(scenario, seed), scenario
    if name == "greedy":
        return GreedyPolicy(scenario), scenario
    if name == "optimal":
        return OptimalPolicy(scenario), scenario
    if name == "ht":
        from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
        from htlm_agent.learning.dqn import QPolicy, Settings

        if ht_policy is not None:
            ck = load_checkpoint(ht_policy)
            if ck.scenario.mode != "ht":
                raise CheckpointError(
                    f"{ck.path}: not an HT learner (mode {ck.scenario.mode!r}); train one with `htlm train --mode ht`"
                )
            return QPolicy.from_checkpoint(ck), ck.scenario
        if ht_out is None:
            raise ValueError("the ht baseline needs a checkpoint (ht_policy) or a directory to train one in (ht_out)")
        s = settings if settings is not None else Settings(seed=seed)
        return train_ht(scenario, s, ht_out, progress)
    raise ValueError(f"unknown baseline {name!r}; choose one of {list(BASELINES)}")
