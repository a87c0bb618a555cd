"""The paper's learner (`Settings.learner` `paper`): decentralized deep Q-learning, Algorithm 1, with one MLP per
agent from its knowledge state to one Q-value per element of Ḡ, updated by hand (`learning.dqn`, `learning.update`).
`Settings()` is this learner, which `htlm reproduce`, the benchmarks and the pinned digests use."""

from __future__ import annotations

from types import MappingProxyType
from typing import TYPE_CHECKING

from htlm_agent.learning.learners.base import LearnerKind

if TYPE_CHECKING:
    pass


class QLearner(LearnerKind):
    """A deep Q-learner of `learning.dqn` (`Learner`): trained batch by batch in process (`learning.dqn_run`) and by
    the trainer node over ROS, step by step, to the same networks."""


class PaperLearner(QLearner):
    """The paper's learner (module docstring)."""

    name = "paper"
    preset = MappingProxyType({})
    """None: `Settings`'s own defaults are this learner's."""
    network = "mlp"


PAPER = PaperLearner()
