"""The records an agent's mind's effects become, without ROS (`EffectCarrier`): in the order the protocol wants
them, with the goal pose of the assignment and the log of the finished episodes."""

from __future__ import annotations

from htlm_agent.mind.agent import AgentMind, Effects
from htlm_agent.session.arrival import ArrivalTracker
from htlm_agent.session.effects import Readers, SessionEffects
from htlm_agent.session.outbox import ActionResend, Outbox
from htlm_agent.session.records import RecordWriter
from htlm_agent.session.run import JoinedRun
from htlm_agent.session.settings import SessionSettings


class EffectCarrier:
    """Turns the effects of the mind's handling of one record into what the node publishes: the broadcast, the
    action (kept for its resend), the ready, the transition (kept in the outbox until acknowledged), the belief
    summary, the goal pose of the assignment's site, and the log of a finished batch's episodes."""

    def __init__(
        self,
        settings: SessionSettings,
        records: RecordWriter,
        outbox: Outbox,
        action_resend: ActionResend,
        arrival: ArrivalTracker,
        readers: Readers,
        wall_offset: float,
    ) -> None:
        """The carrier of the session's parts it publishes through; `readers` tells how many readers the belief
        records have and `wall_offset` is wall-clock seconds minus the session's `now` (a broadcast's stamp)."""
        self.settings = settings
        self.records = records
        self.outbox = outbox
        self.action_resend = action_resend
        self.arrival = arrival
        self.readers = readers
        self.wall_offset = wall_offset
        self.send_transitions = False
        """Whether the transitions go to the trainer (decided when a run is joined)."""
        self.episodes_done = 0
        """Episodes this process has finished, over all its runs."""

    def carry(
        self,
        topic: str,
        eff: Effects,
        mind: AgentMind | None,
        run: JoinedRun | None,
        now: float,
        deployed: bool,
        out: SessionEffects,
    ) -> None:
        """Turn the mind's effects of a record on `topic` into records, in the order the protocol wants them.

        Args:
            topic: the topic of the record the mind handled (or tick, clock, weights), for the drop counters.
            eff: what the mind's handling of it returned.
            mind: the mind that returned it.
            run: the run joined.
            now: the time of the record or tick being handled, the session's monotonic seconds.
            deployed: whether the agent keeps a deployed team's step clock (its actions carry its history).
            out: the effects to add the records to.
        """
        if eff.drop is not None:
            out.drops.append((topic, eff.drop))
            return
        w = self.records
        assert mind is not None and mind.episode is not None and run is not None
        if eff.broadcast is not None:
            t, a, level = eff.broadcast
            out.publish.append(("broadcast", w.broadcast(mind.episode, t, a, level, now + self.wall_offset)))
        if eff.action is not None:  # before the transition: the world and the team wait for it
            t, a = eff.action
            text = w.action(mind.episode, t, a, mind.history(t) if deployed else [])
            out.publish.append(("action", text))
            self.action_resend.sent(mind.episode, t, text, now)
        if eff.ready is not None:
            out.publish.append(("ready", w.ready(mind.episode, eff.ready)))
        tr = eff.transition
        if tr is not None:
            if self.send_transitions:
                seq = self.outbox.next_seq()
                self.outbox.put(seq, w.transition(tr, seq), now, out)
            every = self.settings.belief_every
            if every and (tr.done or (tr.step % every == 0 and self.readers("belief") > 0)):
                i = min(self.settings.belief_episode, mind.size - 1)
                marginals, confident = mind.belief_summary(i)
                arrived, distance = self.arrival.arrival()
                belief = w.belief(tr.episode + i, tr.step, marginals, confident, arrived, distance)
                out.publish.append(("belief", belief))
            if tr.done:
                self._episode_done(tr.episode, mind, run, out)
        if eff.action is not None:
            action = int(eff.action[1][min(self.settings.belief_episode, len(eff.action[1]) - 1)])
            self.arrival.assign(int(run.model.action_site[action]), out)

    def _episode_done(self, episode: int, mind: AgentMind, run: JoinedRun, out: SessionEffects) -> None:
        """The batch from `episode` on is over: log its episodes (in train mode only the first of each batch)."""
        self.episodes_done += mind.size
        logged = 1 if run.mode == "train" else mind.size
        out.episode_log += [{"run": run.run, "episode": episode + i, **mind.episode_log(i)} for i in range(logged)]
