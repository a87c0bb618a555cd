"""The token learner (`Settings.learner` `tokens`; docs/model.md, The token learner): the deep Q-learner of
Algorithm 1 with one network that scores every action from its own features, shared across tasks, sites, kinds and
agents (`learning.tokens`), trained on autograd and torch.optim, with a warm start on a baseline."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from htlm_agent.learning.learners.base import shared_tokens_policy
from htlm_agent.learning.learners.paper import QLearner

if TYPE_CHECKING:
    from htlm_agent.learning.checkpoint import Checkpoint
    from htlm_agent.mind.context import Policy
    from htlm_world.scenario import Scenario


class TokenLearner(QLearner):
    """The token learner (module docstring)."""

    name = "tokens"
    preset = MappingProxyType(
        {
            "learner": "tokens",
            "hidden": (32, 32),
            "updates_per_step": 8,
            "imitate": "auction",
            "imitate_episodes": 2048,
            "eps_start": 0.3,
        }
    )
    """Smaller layers than the paper's MLPs (one network serves every action), a warm start on the auction, and less
    exploration after it."""
    network = "tokens"
    imitates = True

    def with_preset(self, changes: Mapping[str, Any]) -> dict[str, Any]:
        """See LearnerKind.with_preset: a budget of `episodes` below twice the preset's warm start keeps half of it
        for the warm start."""
        base = dict(self.preset)
        if isinstance(changes.get("episodes"), int):
            base["imitate_episodes"] = min(base["imitate_episodes"], max(changes["episodes"], 0) // 2)
        return {**base, **changes}

    def transfer_policy(self, ck: Checkpoint, scenario: Scenario) -> Policy | None:
        """See LearnerKind.transfer_policy: the shared token network reads any operation."""
        return shared_tokens_policy(ck, scenario)


TOKENS = TokenLearner()
