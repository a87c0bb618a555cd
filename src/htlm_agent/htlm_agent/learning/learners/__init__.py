"""The learners a run can train, by name (`Settings.learner`): one module each under this package, one object each
(`base.LearnerKind`) that holds everything a learner decides — its preset and the rules of its settings, its training
in process and over ROS (or why it trains in process only), and the policies of its checkpoints — so that nothing
else asks which learner it is.

    paper      the paper's deep Q-learner, one MLP per agent (`Settings()`)
    tokens     the deep Q-learner with the shared token network
    lookahead  a value network of the auction, with which every agent improves on it (in process only)
    expert     expert iteration: the team's play improved by the lookahead, learned into a token policy network
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from htlm_agent.learning.learners.base import LearnerKind
from htlm_agent.learning.learners.expert import EXPERT
from htlm_agent.learning.learners.lookahead import LOOKAHEAD
from htlm_agent.learning.learners.paper import PAPER
from htlm_agent.learning.learners.tokens import TOKENS

if TYPE_CHECKING:
    from htlm_agent.learning.checkpoint import Checkpoint
    from htlm_agent.learning.settings import Settings
    from htlm_agent.mind.context import Policy
    from htlm_agent.mind.policies import AgentPolicy

LEARNERS: dict[str, LearnerKind] = {k.name: k for k in (PAPER, TOKENS, LOOKAHEAD, EXPERT)}
"""Every learner by name (`learner`), in the order the command line lists them."""

DEFAULT_LEARNER = EXPERT.name
"""The learner `htlm train` and `htlm launch train` (and so `make run` and `ros2 launch`) train unless told otherwise
(`--learner`, `--set learner=...`; `default_learner`): the expert-iteration learner, which learns from the team's
own play in process and over ROS alike, reads every agent's own reward, and acts in one forward pass
(docs/results/market.md)."""

DEFAULT_Q_LEARNER = TOKENS.name
"""The learner a user's settings changes train when they name none and change a setting the default learner does
not read (a Q-learner's, such as learning_starts): the token learner."""


def learner(name: str) -> LearnerKind:
    """The learner called `name` (a value of `Settings.learner`).

    Raises:
        ValueError: no learner has that name; the message names the value and the choices.
    """
    try:
        return LEARNERS[name]
    except (KeyError, TypeError):
        raise ValueError(f"settings.learner: {name!r} is not one of {', '.join(LEARNERS)}") from None


def default_learner(changes: Mapping[str, Any]) -> str:
    """The learner a user's settings changes train when they name none (`Settings.for_users`): `DEFAULT_LEARNER`,
    or `DEFAULT_Q_LEARNER` when they change a setting the default learner does not read (`LearnerKind.reads`)."""
    reads = learner(DEFAULT_LEARNER).reads
    return DEFAULT_LEARNER if reads is None or set(changes) <= reads else DEFAULT_Q_LEARNER


def check(settings: Settings) -> None:
    """Raise ValueError, naming the field and the value, where `settings` break a rule of their learner: a warm start
    only for a learner that imitates (`LearnerKind.imitates`), then the learner's own (`LearnerKind.check`)."""
    kind = learner(settings.learner)
    if settings.imitate != "none" and not kind.imitates:
        names = " or ".join(repr(k.name) for k in LEARNERS.values() if k.imitates)
        raise ValueError(f"settings.imitate: {settings.imitate!r} needs learner {names}, not {settings.learner!r}")
    kind.check(settings)


def team_policy(ck: Checkpoint) -> Policy:
    """The team policy of a checkpoint of any learner (`LearnerKind.team_policy`)."""
    return learner(ck.settings.learner).team_policy(ck)


def agent_policy(ck: Checkpoint, agent: int) -> AgentPolicy:
    """Agent `agent`'s policy in its own process from a checkpoint of any learner (`LearnerKind.agent_policy`)."""
    return learner(ck.settings.learner).agent_policy(ck, agent)
