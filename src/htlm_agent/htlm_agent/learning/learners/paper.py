"""The paper's learner (`Settings.learner` `paper`): decentralized deep Q-learning, Algorithm 1, with one MLP per
agent from its knowledge state to one Q-value per element of Ḡ, stacked and trained as one batch (`learning.dqn`).
`Settings()` is this learner, which `htlm reproduce`, the benchmarks and the pinned digests use."""

from __future__ import annotations

from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from htlm_agent.learning.learners.base import LearnerKind

if TYPE_CHECKING:
    from htlm_agent.learning.run import TrainResult
    from htlm_agent.learning.settings import Settings
    from htlm_world.scenario import Scenario


class QLearner(LearnerKind):
    """A deep Q-learner of `learning.dqn` (`Learner`): trained batch by batch in process (`learning.dqn_run`) and by
    the trainer node over ROS, step by step, to the same networks."""

    def train(
        self,
        scenario: Scenario,
        settings: Settings,
        out: Path,
        progress: bool,
        resume: bool,
        tensorboard: bool,
        evaluate_at_end: bool,
    ) -> TrainResult:
        """See LearnerKind.train: Algorithm 1 with B parallel episodes (`dqn_run.train_dqn`)."""
        from htlm_agent.learning.dqn_run import train_dqn

        return train_dqn(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)

    def over_ros(self, scenario: Scenario, settings: Settings, seed: int, batch: int, checkpoint: Path | None) -> Any:
        """See LearnerKind.over_ros: the `dqn.Learner` the trainer feeds every agent's transitions, resumed with
        its replay memories and training state from `checkpoint` (CheckpointError where it cannot be)."""
        from htlm_agent.learning.dqn import Learner

        return Learner(scenario, settings, seed) if checkpoint is None else Learner.load(checkpoint, settings)


class PaperLearner(QLearner):
    """The paper's learner (module docstring)."""

    name = "paper"
    preset = MappingProxyType({})
    """None: `Settings`'s own defaults are this learner's."""
    network = "mlp"


PAPER = PaperLearner()
