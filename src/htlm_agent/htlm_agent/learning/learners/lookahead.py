"""The lookahead learner (`Settings.learner` `lookahead`; docs/model.md, The lookahead learner): a value network of
the auction on the true levels, fitted on simulated episodes, with which every agent improves on the auction from its
own belief (`learning.lookahead`). It learns from the true levels of simulated episodes, so in process only."""

from __future__ import annotations

from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

from htlm_agent.learning.learners.base import LearnerKind

if TYPE_CHECKING:
    from htlm_agent.learning.checkpoint import Checkpoint
    from htlm_agent.learning.lookahead import LookaheadPolicy
    from htlm_agent.learning.run import TrainResult
    from htlm_agent.learning.settings import Settings
    from htlm_agent.mind.context import Policy
    from htlm_agent.mind.policies import AgentPolicy
    from htlm_world.scenario import Scenario


class LookaheadLearner(LearnerKind):
    """The lookahead learner (module docstring)."""

    name = "lookahead"
    preset = MappingProxyType({"learner": "lookahead", "episodes": 10_000, "batch_size": 2048})
    """10,000 simulated episodes and minibatches of 2,048 states for its value network."""
    network = "value"
    in_process_only = (
        "learns in process only (from the true levels of simulated episodes, which a trainer node does not receive): "
        "train it with `htlm train`, then run the team with `htlm launch evaluate --checkpoint RUN`"
    )

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
        """See LearnerKind.train: the value network fitted in one go (`lookahead.train_lookahead`)."""
        from htlm_agent.learning.lookahead import train_lookahead

        return train_lookahead(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)

    def team_policy(self, ck: Checkpoint) -> Policy:
        """See LearnerKind.team_policy: the lookahead with the checkpoint's value network."""
        return _lookahead(ck, ck.scenario)

    def agent_policy(self, ck: Checkpoint, agent: int) -> AgentPolicy:
        """See LearnerKind.agent_policy: the agent's own head of the lookahead."""
        from htlm_agent.learning.lookahead import AgentLookahead

        return AgentLookahead(ck.scenario, _lookahead(ck, ck.scenario), agent)

    def transfer_policy(self, ck: Checkpoint, scenario: Scenario) -> Policy | None:
        """See LearnerKind.transfer_policy: the value network reads every task's level, so it acts in an operation
        of as many tasks."""
        return _lookahead(ck, scenario) if scenario.n_tasks == ck.scenario.n_tasks else None


def _lookahead(ck: Checkpoint, scenario: Scenario) -> LookaheadPolicy:
    """The lookahead in `scenario` with the value network of `ck`."""
    from htlm_agent.learning.lookahead import LookaheadPolicy, value_of

    return LookaheadPolicy(scenario, value_of(ck), seed=ck.seed, load_price=ck.settings.load_price)


LOOKAHEAD = LookaheadLearner()
