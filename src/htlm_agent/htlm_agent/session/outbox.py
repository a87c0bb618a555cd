"""What an agent sends again until it is taken, without ROS: its transitions until the trainer acknowledges them
(`Outbox`), and its action of the step in progress until the world applies the step (`ActionResend`)."""

from __future__ import annotations

import secrets
from dataclasses import dataclass

from htlm_agent.session.effects import SessionEffects


@dataclass
class Kept:
    """A transition in the outbox."""

    text: str
    """Its record text (signed), sent again as it is."""
    sent: float
    """When it was last sent."""


class Outbox:
    """The transitions the trainer has not acknowledged, oldest first: each sent again every `resend_period`
    seconds (at most `resend_batch` per pass) until an acknowledgement covers its sequence number; when `limit` of
    them wait, the oldest is dropped for the next.

    The trainer acknowledges per session: `session` is this process's id in its transition records, new at every
    start, so an acknowledgement meant for an earlier process of the agent takes nothing from this one.
    """

    def __init__(self, limit: int, resend_period: float, resend_batch: int) -> None:
        """An empty outbox of a new session id."""
        self.session = secrets.token_hex(8)
        """This process's session id in its transition records (the trainer acknowledges per session)."""
        self.limit = limit
        self.resend_period = resend_period
        self.resend_batch = resend_batch
        self.seq = 0
        """The sequence number of the next transition (so far: how many were sent)."""
        self.acked = 0
        """Transitions acknowledged so far."""
        self.waiting: dict[int, Kept] = {}
        """seq -> the record and when it was last sent: the transitions the trainer has not acknowledged, oldest
        first."""

    def __len__(self) -> int:
        """How many transitions wait for their acknowledgement."""
        return len(self.waiting)

    def next_seq(self) -> int:
        """The sequence number of the transition about to be sent (taken: the next call gives the one after)."""
        self.seq += 1
        return self.seq - 1

    def put(self, seq: int, text: str, now: float, out: SessionEffects) -> None:
        """Transition `seq` (its record `text`) is sent now: publish it and keep it until acknowledged."""
        if len(self.waiting) >= self.limit:
            del self.waiting[next(iter(self.waiting))]
            out.counters["outbox_dropped"] += 1
        self.waiting[seq] = Kept(text, now)
        out.publish.append(("transition", text))

    def ack(self, session: str, upto: int, out: SessionEffects) -> None:
        """The trainer's acknowledgement of the transitions of `session` up to `upto`: they leave the outbox."""
        if session != self.session:
            out.drops.append(("transition_ack", "session"))
            return
        box = self.waiting
        while box:
            first = next(iter(box))
            if first > upto:
                break
            del box[first]
            self.acked += 1

    def resend(self, now: float, out: SessionEffects) -> None:
        """One pass (every `resend_period`): send again, oldest first, at most `resend_batch` of the transitions
        not sent for `resend_period`."""
        if not self.waiting:
            return
        old = now - self.resend_period
        n = 0
        for item in self.waiting.values():
            if item.sent <= old:
                out.publish.append(("transition", item.text))
                item.sent = now
                n += 1
                if n >= self.resend_batch:
                    break
        out.counters["resent"] += n

    def values(self) -> dict[str, str]:
        """The outbox's values for the node's /diagnostics."""
        return {"transitions_sent": str(self.seq), "transitions_acked": str(self.acked), "outbox": str(len(self))}


class ActionResend:
    """Our newest action, sent again every `period` seconds while the world has not applied its step: a record lost
    in a reader's queue (e.g. under a flood of other records) costs a resend instead of the world's deadline."""

    def __init__(self, period: float) -> None:
        """No action sent yet."""
        self.period = period
        self.last: tuple[int, int, str, float] | None = None
        """(episode, step, record text, sent at) of our newest action."""

    def sent(self, episode: int, step: int, text: str, now: float) -> None:
        """Our action of step `step` of the batch from `episode` on went out now."""
        self.last = (episode, step, text, now)

    def due(self, episode: int | None, step: int, now: float, out: SessionEffects) -> None:
        """The world has not applied step `step` of the batch from `episode` on yet: send our action of that step
        again if it went out `period` seconds ago."""
        if self.last is None:
            return
        e, t, text, at = self.last
        if (e, t) == (episode, step) and now - at >= self.period:
            out.publish.append(("action", text))
            self.last = (e, t, text, now)
            out.counters["actions_resent"] += 1
