"""Every baseline by name (`heuristics.BASELINES`): the random, greedy and auction heuristics, the HT Dec-POMDP learner
(the paper's predecessor: the same deep Q-learner on the scenario in mode "ht", no idle locations, R_LM = 0) and the
centralized optimum."""

from __future__ import annotations

from pathlib import Path

from htlm_agent.baselines.heuristics import BASELINES, AuctionPolicy, GreedyPolicy, RandomPolicy
from htlm_agent.baselines.optimal import OptimalPolicy, QmdpPolicy
from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
from htlm_agent.learning.learners import team_policy
from htlm_agent.learning.lookahead import LookaheadPolicy
from htlm_agent.learning.run import train
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.context import Policy
from htlm_world.scenario import Scenario


def ht_scenario(scenario: Scenario) -> Scenario:
    """The HT Dec-POMDP version of a scenario: no idle locations, R_LM = 0 (docs/model.md)."""
    return scenario.replace(mode="ht")


def train_ht(
    scenario: Scenario, settings: Settings, out_dir: str | Path, progress: bool = False
) -> tuple[Policy, Scenario]:
    """Train the HT Dec-POMDP learner on `scenario` (converted to mode "ht") and return its greedy policy."""
    sc = ht_scenario(scenario) if scenario.mode != "ht" else scenario
    res = train(sc, settings, out_dir, progress=progress, evaluate_at_end=False)
    ck = load_checkpoint(res.out_dir / "checkpoint")
    return team_policy(ck), sc


def make_baseline(
    name: str,
    scenario: Scenario,
    seed: int = 0,
    ht_policy: str | Path | None = None,
    ht_out: str | Path | None = None,
    settings: Settings | None = None,
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
    if name == "random":
        return RandomPolicy(scenario, seed), scenario
    if name == "greedy":
        return GreedyPolicy(scenario), scenario
    if name == "auction":
        return AuctionPolicy(scenario), scenario
    if name == "qmdp":
        return QmdpPolicy(scenario), scenario
    if name == "lookahead":
        return LookaheadPolicy(scenario, seed=seed), scenario
    if name == "optimal":
        return OptimalPolicy(scenario), scenario
    if name == "ht":
        if ht_policy is not None:
            ck = load_checkpoint(ht_policy)
            if ck.scenario.mode != "ht":
                raise CheckpointError(
                    f"{ck.path}: not an HT learner (mode {ck.scenario.mode!r}); train one with `htlm train --mode ht`"
                )
            return team_policy(ck), ck.scenario
        if ht_out is None:
            raise ValueError("the ht baseline needs a checkpoint (ht_policy) or a directory to train one in (ht_out)")
        s = settings if settings is not None else Settings(seed=seed)
        return train_ht(scenario, s, ht_out, progress)
    raise ValueError(f"unknown baseline {name!r}; choose one of {list(BASELINES)}")
