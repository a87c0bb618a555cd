"""What every learner is (`LearnerKind`): its name, the settings it starts from and the rules they obey, how it
trains in process and over ROS (or why it does not), and the policies its checkpoints act with.

A learner's module holds its object only; its training code lives in the modules of `htlm_agent.learning` and loads
when the learner trains or acts (torch), so that reading settings (`Settings`, which checks them here) loads none of
it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from htlm_agent.learning.checkpoint import Checkpoint
    from htlm_agent.learning.run import TrainResult
    from htlm_agent.learning.settings import Settings
    from htlm_agent.mind.context import Policy
    from htlm_agent.mind.policies import AgentPolicy
    from htlm_world.scenario import Scenario


class LearnerKind(ABC):
    """One learner a run can train (`Settings.learner`), one object of this class each (`learners.LEARNERS`).

    The defaults are those of a learner of Q-networks whose checkpoint holds every agent's own network: the agents
    act greedily on it, in process and in their own processes."""

    name: str
    """The value of `Settings.learner` that names it."""
    preset: Mapping[str, Any]
    """The settings it starts from (`with_preset`): what `htlm train --learner NAME` and `htlm launch train --set
    learner=NAME` start from; those it does not name are `Settings`'s own."""
    network: str
    """The network its checkpoint holds per agent (`Settings.network`): `mlp`, the paper's Q-network; `tokens`, the
    token network (Q-values, or the expert-iteration learner's policy scores); `value`, the lookahead's value
    network of the levels."""
    imitates: bool = False
    """Whether it can start warm on a baseline's choices (`Settings.imitate`)."""
    rounds: bool = False
    """Whether it learns in rounds of the team's whole play: every round plays one policy whole (ε = `eps_end`
    throughout, the first round played by the baseline of `warm_baseline`), and the weights change once a round,
    after the round's learning; over ROS the world waits for it, and the trainer needs the world's true levels."""
    reads: frozenset[str] | None = None
    """The settings it reads, None: every one (a user's change of another picks another default learner,
    `learners.default_learner`)."""
    in_process_only: str | None = None
    """Why it trains in process only (`htlm train`), None when the trainer node trains it over ROS as well."""

    def with_preset(self, changes: Mapping[str, Any]) -> dict[str, Any]:
        """Settings changes as plain data, after this learner's `preset`."""
        return {**self.preset, **changes}

    def check(self, settings: Settings) -> None:
        """Raise ValueError, naming the field and the value, where `settings` break a rule of this learner (those
        of every learner are `Settings`'s own)."""
        return

    def warm_start(self, settings: Settings, episodes_done: int) -> bool:
        """Whether the batch after `episodes_done` training episodes is one of the warm start (`Settings.warm_start`):
        the baseline of `imitate` acts and the networks learn to rank its choices first."""
        return settings.imitate != "none" and episodes_done < settings.imitate_episodes

    def warm_baseline(self, settings: Settings) -> str:
        """The baseline that acts in the warm start (`Settings.warm_baseline`): `imitate`."""
        return settings.imitate

    @abstractmethod
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
        """Train in process into the run directory `out` (`learning.run.train`, whose arguments these are)."""

    def over_ros(self, scenario: Scenario, settings: Settings, seed: int, batch: int, checkpoint: Path | None) -> Any:
        """The learner the trainer node feeds (`trainer.core.TrainerCore`) in a run with master seed `seed` played
        in batches of `batch` episodes: fresh, or resumed from `checkpoint`.

        Raises:
            ValueError: it trains in process only (`in_process_only`), or cannot train this run.
        """
        raise ValueError(f"settings.learner: {self.name!r} {self.in_process_only}")

    def team_policy(self, ck: Checkpoint) -> Policy:
        """The team policy of a checkpoint of this learner, as `htlm evaluate` acts with it: every agent greedy on
        its own Q-network."""
        from htlm_agent.learning.qpolicy import QPolicy

        return QPolicy.from_checkpoint(ck)

    def agent_policy(self, ck: Checkpoint, agent: int) -> AgentPolicy:
        """Agent `agent`'s policy in its own process from a checkpoint of this learner (`team_policy`'s column)."""
        from htlm_agent.learning.qnet import AgentQ

        return AgentQ.from_checkpoint(ck, agent)

    def transfer_policy(self, ck: Checkpoint, scenario: Scenario) -> Policy | None:
        """The team policy of a checkpoint of this learner acting in another operation `scenario` without
        retraining, None where its network cannot (here: the paper's MLPs read the layout they were trained on)."""
        return None


def shared_tokens_policy(ck: Checkpoint, scenario: Scenario) -> Policy | None:
    """The shared token network of a checkpoint acting in `scenario` (`LearnerKind.transfer_policy`): one set of
    weights for every task, site, kind and agent reads any operation; None for networks of their own per agent."""
    from htlm_agent.learning.qnet import build_network
    from htlm_agent.learning.qpolicy import QPolicy

    if not ck.settings.shared:
        return None
    net = build_network(scenario, ck.settings, [ck.weights[0]])
    net.requires_grad_(False)
    return QPolicy(scenario, net)
