"""Pieces of the training loop that every trainer shares (`htlm train` in process and the trainer process over ROS):
the ε of a batch's episodes and the selection of the best networks by validation."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.settings import Settings
from htlm_world.types import FloatArray


def episode_epsilons(settings: Settings, episodes_done: int, batch: int) -> tuple[float, float | FloatArray]:
    """ε of the schedule, and the ε of each of the batch's episodes: ε for all, or with `eps_spread` from 0 (greedy
    episodes) to 2ε, mean ε."""
    eps = settings.epsilon(episodes_done)
    if settings.eps_spread and batch > 1:
        return eps, np.minimum(1.0, eps * 2.0 * np.arange(batch) / (batch - 1))
    return eps, eps


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
