"""What the agent node carries out after feeding its session one record or one look at the clock
(`SessionEffects`), and how the session asks the node about its readers (`Readers`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class SessionEffects:
    """What the node must do after feeding the session one message or one look at the clock, in this order."""

    publish: list[tuple[str, str]] = field(default_factory=list)
    """Records to publish, in order, as (kind, record text signed with the session's signer): kind is action,
    broadcast, ready, transition or belief (on the agent's own belief topic)."""
    goals: list[tuple[float, float]] = field(default_factory=list)
    """Goal poses (x, y) in the map frame to publish: the site of the assignment changed."""
    log: list[tuple[str, str]] = field(default_factory=list)
    """Log lines as (level, text), level info, warning or error."""
    counters: Counter[str] = field(default_factory=Counter)
    """Counters to add to the node's diagnostics (resent, actions_resent, outbox_dropped, stale_weights)."""
    drops: list[tuple[str, str]] = field(default_factory=list)
    """Well-formed records the protocol dropped, as (topic, reason): past, future, duplicate, outside_run, ..."""
    rejects: list[tuple[str, str, str]] = field(default_factory=list)
    """Records refused as invalid for the run, as (topic, reason, detail)."""
    episode_log: list[dict[str, Any]] = field(default_factory=list)
    """Finished episodes for the agent's episode log (<agent>.jsonl): run, episode, actions, messages, rewards."""
    heard_world: bool = False
    """A record of the world was taken (the node's watch of a silent world)."""
    subscribe_weights: bool = False
    """The policy comes from the trainer: subscribe to this agent's weights topic (once)."""
    fatal: str | None = None
    """The agent cannot go on (not in the team, no usable policy): why."""


Readers = Callable[[str], int]
"""kind (action, broadcast, belief) -> how many readers the agent's records of that kind have."""
