"""Pieces of the deep Q-learners' training loop that every trainer shares (`htlm train` in process and the trainer
over ROS): the ε of a batch's episodes, which networks act at a step under a trainer lag, the warm start's baseline
and its update, validation and the selection of the best networks by it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy
from htlm_agent.baselines.optimal import ProblemTooLarge, QmdpPolicy
from htlm_agent.learning import learners
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.qnet import QNetwork, copy_network
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.context import Policy
from htlm_agent.mind.policies import knowledge_context
from htlm_agent.runtime.evaluate import evaluate
from htlm_world import seeds
from htlm_world.scenario import Scenario
from htlm_world.types import FloatArray


def episode_epsilons(settings: Settings, episodes_done: int, batch: int) -> tuple[float, float | FloatArray]:
    """ε of the schedule, and the ε of each of the batch's episodes: ε for all, or with `eps_spread` from 0 (greedy
    episodes) to 2ε, mean ε; eps_end for all in the warm start (`Settings.warm_start`), around the baseline's
    choices; eps_end for all throughout for a learner in rounds (`LearnerKind.rounds`), which plays its policy around
    ε = eps_end."""
    if settings.warm_start(episodes_done) or learners.learner(settings.learner).rounds:
        return settings.eps_end, settings.eps_end
    eps = settings.epsilon(episodes_done)
    if settings.eps_spread and batch > 1:
        return eps, np.minimum(1.0, eps * 2.0 * np.arange(batch) / (batch - 1))
    return eps, eps


def acting_weights(g: int, first: int, lag: int, every: int = 1) -> tuple[int, int]:
    """Which networks act at global step g (index b·h + t − 1 of step t of batch b) of a run whose first step is
    `first`, under a trainer lag and a weights cadence: (T, R), T = max(first, g − lag) and R the cadence's last
    version at or below T, first + ⌊(T − first) / every⌋ · every. A network's version is the number of steps whose
    updates it has had (`trained`); the agents act at g with version R, so the trainer's updates of steps T..g − 1
    overlap the agents' work of those steps. With lag 0 and every 1 it is the version g: the updates of every step
    before g, Algorithm 1 as written."""
    target = max(first, g - lag)
    return target, first + (target - first) // every * every


class LaggedNets:
    """The networks that act under a trainer lag in process (`htlm train`), as the agents' processes act over ROS:
    at global step g, the learner's networks as they were after the updates of the steps before R (`acting_weights`,
    every version kept until it is no longer needed)."""

    def __init__(self, learner: Learner, first_step: int) -> None:
        """For a run (or a resumed part of one) whose first step is `first_step`."""
        self.learner = learner
        self.first = first_step
        self.lag = learner.settings.trainer_lag
        self.versions: dict[int, torch.Tensor] = {}
        self.net: QNetwork | None = None

    def at(self, g: int) -> QNetwork | None:
        """The networks to act with at global step g, None for the learner's current ones (lag 0). Called once per
        step, in order, after the updates of the steps before g."""
        if self.lag == 0:
            return None
        online = self.learner.net
        self.versions[g] = online.flat.detach().clone()
        _, version = acting_weights(g, self.first, self.lag)
        for v in [v for v in self.versions if v < version]:
            del self.versions[v]
        if self.net is None:
            self.net = copy_network(online)
        with torch.no_grad():
            self.net.flat.copy_(self.versions[version])
        return self.net


# ----- the warm start ---------------------------------------------------------------------------------------------


def imitate_step(learner: Learner, expert: Policy, k: FloatArray) -> float:
    """The warm start's update of one step for the whole team, in process and in the trainer over ROS alike: the
    networks learn to rank first the expert's choices made from every agent's own knowledge state (B, N, K) and its
    Â(a_o) (`Learner.imitate`), the knowledge as the trainer receives it (float32, the precision of the wire and of
    the replay memories); with `Settings.imitate_updates` > 1, also on minibatches of the expert choices stored so
    far. Returns the last update's loss."""
    k32 = np.asarray(k, dtype=np.float32).astype(np.float64)  # the values of float32, as the trainer has them
    m = learner.knowledge_mask(k32).numpy()
    a = np.asarray(expert.act(knowledge_context(learner.scenario, k32, m)), dtype=np.int64)
    loss = learner.imitate(k32, m, a)
    s = learner.settings
    if s.imitate_updates > 1:  # more updates on every expert choice of the warm start so far
        memory = learner.expert_memory()
        memory.add(k32, m, a)
        for _ in range(s.imitate_updates - 1):
            loss = learner.imitate(*memory.sample(s.batch_size))
    return loss


def warm_start_expert(scenario: Scenario, settings: Settings) -> Policy | None:
    """The baseline the warm start imitates (`Settings.imitate`), None without a warm start."""
    if settings.imitate == "none" or settings.imitate_episodes == 0:
        return None
    if settings.imitate == "qmdp":
        try:
            return QmdpPolicy(scenario)
        except ProblemTooLarge as e:
            raise ValueError(f"settings.imitate: 'qmdp' needs the centralized optimum, and {e}") from None
    return AuctionPolicy(scenario) if settings.imitate == "auction" else GreedyPolicy(scenario)


# ----- validation and selection -----------------------------------------------------------------------------------


def validate(learner: Learner, episodes: int) -> dict[str, Any]:
    """Greedy validation of the current networks on episodes of the run's validation stream."""
    return evaluate(learner.policy(), learner.scenario, episodes, seed=seeds.validation(learner.seed))


class Selection:
    """The best networks by validation completion step (lower is better; the later one wins a tie)."""

    def __init__(self, learner: Learner, info: dict[str, Any]) -> None:
        """Start from the best recorded in a checkpoint's `info` (none for a fresh run)."""
        self.learner = learner
        best = info.get("best_score")
        self.score: float = math.inf if best is None else float(best)  # None: no validation counted yet
        self.episode: int = int(info.get("best_episode", -1))
        self.flat: torch.Tensor | None = None

    def restore(self, ckpt_dir: Path) -> None:
        """Take the selected networks of a resumed run from its checkpoint (they are its published networks)."""
        if self.episode >= 0:
            best = load_checkpoint(ckpt_dir)
            self.flat = torch.stack([torch.cat([torch.from_numpy(p).reshape(-1) for p in w]) for w in best.weights])

    def offer(self, score: float) -> None:
        """Keep the current networks if `score` is at least as good as the best so far."""
        if score <= self.score:
            self.score, self.episode = score, self.learner.episodes_done
            self.flat = self.learner.net.flat.detach().clone()

    def info(self) -> dict[str, Any]:
        """What a checkpoint records of the selection."""
        return {"best_score": None if math.isinf(self.score) else self.score, "best_episode": self.episode}
