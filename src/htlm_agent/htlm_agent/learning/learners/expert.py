"""The expert-iteration learner (`Settings.learner` `expert`; docs/model.md, The expert-iteration learner): rounds of
the team's own play improved by the lookahead with every agent's own reward and learned into a token policy network
(`learning.expert`), in process and over ROS alike. It is the default learner (`learners.DEFAULT_LEARNER`)."""

from __future__ import annotations

from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from htlm_agent.learning.learners.base import LearnerKind, shared_tokens_policy

if TYPE_CHECKING:
    from htlm_agent.learning.checkpoint import Checkpoint
    from htlm_agent.learning.run import TrainResult
    from htlm_agent.learning.settings import Settings
    from htlm_agent.mind.context import Policy
    from htlm_world.scenario import Scenario


class ExpertLearner(LearnerKind):
    """The expert-iteration learner (module docstring)."""

    name = "expert"
    preset = MappingProxyType(
        {
            "learner": "expert",
            "hidden": (32, 32),
            "rounds": 4,
            "episodes": 8192,
            "envs": 256,
            "imitate": "auction",
            "trainer_lag": 0,
            "batch_size": 1024,
            "value_updates": 0,
        }
    )
    """The token network's layers for its policy, the auction playing the first round, up to 8,192 episodes of its
    own play (4 rounds of 2,048), round 0's value kept for every round's teacher (DAgger; `value_updates` > 0 fits it
    on the team's own play instead), minibatches of 1,024 agent-steps for the policy."""
    network = "tokens"
    imitates = True
    rounds = True
    reads = frozenset(
        {
            "learner",
            "episodes",
            "rounds",
            "envs",
            "imitate",
            "eps_end",
            "value_updates",
            "policy_updates",
            "load_weight",
            "hidden",
            "lr",
            "batch_size",
            "trainer_lag",
            "seed",
            "threads",
            "validate_episodes",
            "eval_episodes",
        }
    )

    def check(self, settings: Settings) -> None:
        """See LearnerKind.check: every round plays its policy whole, the first played by the auction or greedy."""
        if settings.trainer_lag != 0:
            raise ValueError(
                f"settings.trainer_lag: {settings.trainer_lag!r}: the expert-iteration learner's rounds play each "
                "policy whole (0)"
            )
        if settings.imitate == "qmdp":
            raise ValueError(
                "settings.imitate: 'qmdp': the expert-iteration learner's first round is played by 'auction' or "
                "'greedy'"
            )

    def warm_start(self, settings: Settings, episodes_done: int) -> bool:
        """See LearnerKind.warm_start: the first round (`Settings.round_batches`), which the baseline plays."""
        return episodes_done < settings.round_batches * settings.envs

    def warm_baseline(self, settings: Settings) -> str:
        """See LearnerKind.warm_baseline: the auction's unless `imitate` names greedy."""
        return "auction" if settings.imitate == "none" else settings.imitate

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
        """See LearnerKind.train: its rounds (`expert.train_expert_run`)."""
        from htlm_agent.learning.expert import train_expert_run

        return train_expert_run(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)

    def over_ros(self, scenario: Scenario, settings: Settings, seed: int, batch: int, checkpoint: Path | None) -> Any:
        """See LearnerKind.over_ros: its rounds fed from the agents' transitions and the world's true levels
        (`expert_trainer.ExpertTrainer`); a run's rounds are quick to run again, so there is no resuming one."""
        from htlm_agent.learning.expert_trainer import ExpertTrainer

        if checkpoint is not None:
            raise ValueError(f"{checkpoint}: the expert-iteration learner does not resume a run")
        return ExpertTrainer(scenario, settings, batch)

    def transfer_policy(self, ck: Checkpoint, scenario: Scenario) -> Policy | None:
        """See LearnerKind.transfer_policy: its shared token network reads any operation."""
        return shared_tokens_policy(ck, scenario)


EXPERT = ExpertLearner()
