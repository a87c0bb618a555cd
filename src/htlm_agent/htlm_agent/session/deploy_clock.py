"""The step clock a deployed agent keeps itself, without ROS (`DeployClock`): once the run announcement carries the
epoch, no world gates the steps; every instant of htlm_world.clock applies our action of its step, and the driver
makes sure the mind has acted for each step before its instant, closes the steps its instants left open, and stops
the run on that clock (docs/ros.md, Connecting your robots)."""

from __future__ import annotations

from typing import Any, Protocol

from htlm_agent.mind.agent import AgentMind, Effects
from htlm_agent.mind.deploy import DeployObservations, Observed
from htlm_agent.session.effects import SessionEffects
from htlm_agent.session.offsets import CLOCK_TOLERANCE
from htlm_world.clock import FUTURE_STEPS, StepClock


class DeployHost(Protocol):
    """What the driver asks of the session whose mind it drives."""

    stopping: bool
    """The run has stopped for this agent."""

    def the_mind(self) -> AgentMind:
        """The agent's mind (made at the first look at the clock)."""
        ...

    def carry(self, topic: str, eff: Effects, out: SessionEffects) -> None:
        """Turn the mind's effects into records."""
        ...

    def observe_deployed(self, ready: list[Observed], now: float, out: SessionEffects) -> None:
        """Feed the mind the steps whose observations are in (or overdue)."""
        ...

    def epsilon(self, episode: int, size: int) -> Any:
        """ε of the batch from `episode` on."""
        ...

    def stop_run(self, now: float, out: SessionEffects, why: str = "stopped by the world") -> None:
        """The run is over for this agent."""
        ...


class DeployClock:
    """Drives an agent's mind by the step clock of a deployed team: `run` at every look at the clock applies the
    instants that passed, `stop_at` finishes the steps in progress when the world announces the stop, `future`
    judges how far ahead a record's step is. A process that joins mid-run (a restart) joins at the next instant;
    the steps it was away count as missed."""

    def __init__(self, clock: StepClock, observations: DeployObservations, wait: float, host: DeployHost) -> None:
        """The driver of `host`'s mind on `clock`; `observations` pairs the steps with the robot's observations,
        waiting `wait` seconds for each."""
        self.clock = clock
        self.observations = observations
        self.wait = wait
        self.host = host
        self.applied = -1
        """The run-wide index of the newest step whose instant this agent has passed on its clock."""
        self.joined_at: tuple[int, int] | None = None
        """(episode, step) at which this process joined the step clock."""
        self.stop_after: int | None = None
        """Once the world announced the run stopped: the run-wide index of the last step we finish before stopping
        (`stop_at`)."""

    def future(self, e: int, t: int, wall: float) -> bool:
        """Whether step t of episode e lies more than FUTURE_STEPS ahead of the clock at wall-clock time `wall`."""
        return self.clock.ahead(e, t, wall) > FUTURE_STEPS

    def stop_at(self, wall: float) -> tuple[int, int] | None:
        """The world announced the run stopped at wall-clock time `wall`: the (episode, step) we finish before
        stopping (None: none). We first finish the steps whose instants
        are at most a quarter period (the clocks' tolerance) ahead of our clock, then stop: the world announces the
        end of the run 0.05 s after the last instant on its clock, which may be ahead of ours, and a busy host may
        read the announcement before its timer has applied that instant; stopping at once would leave the last
        episode unlogged. A stop in mid-run (the world shut down) costs at most the step in progress."""
        c = self.clock
        last = c.last(wall + CLOCK_TOLERANCE * c.period)
        self.stop_after = min(last, c.episodes * c.horizon - 1) if c.episodes else last  # (0 episodes: until stopped)
        return c.step(self.stop_after) if self.stop_after >= 0 else None

    def run(self, now: float, wall: float, out: SessionEffects) -> None:
        """A look at the clock at monotonic time `now`, wall-clock time `wall`: every instant that passed applies our
        action of its step (the robot's observation and the teammates' broadcasts then come in as usual), a step
        still open at the next instant is closed with what arrived, and the next episode begins as soon as the last
        one is done."""
        c, host = self.clock, self.host
        m = host.the_mind()
        target = c.last(wall)
        if self.stop_after is not None:
            target = min(target, self.stop_after)
        if self.joined_at is None:  # our first look at the clock: the action of the first begin counts if in time
            p = m.pending
            mine = c.index(m.episode, p.t) if m.episode is not None and p is not None and p.observed_at is None else -1
            self.applied = mine - 1 if mine >= 0 and target <= mine else max(target, c.index(c.first_episode, 1) - 1)
            self.joined_at = c.step(self.applied + 1)
            if self.applied >= 0:
                e, t = self.joined_at
                out.log.append(("info", f"joined the team's clock at episode {e} step {t}"))
        while self.applied < target:
            i = self.applied + 1
            if not c.in_run(i):
                break
            e, t = c.step(i)
            self._act_for(e, t, now, out)
            self.applied = i
            # the step is applied with our action: the robot's observation, or none after the wait
            host.observe_deployed(self.observations.on_step(e, t, list(range(m.n)), now, self.wait), now, out)
        if self.stop_after is not None:  # stopped by the world: stop once the steps up to stop_after are finished,
            # or at the next instant at the latest (a step still open then is given up: its episode goes unlogged)
            done = c.index(m.episode, m.t) if m.episode is not None else -1
            finished = self.applied >= self.stop_after and done >= self.applied
            if finished or c.last(wall) > self.stop_after:
                host.stop_run(now, out)
            return
        nxt = self.applied + 1
        if not c.in_run(nxt):
            if m.finished and not host.stopping:
                host.stop_run(now, out, "over on our own clock")
            return
        e, t = c.step(nxt)
        if m.episode != e and m.finished:  # the last episode is done (or we just joined): act for the next step now
            self._act_for(e, t, now, out)

    def _act_for(self, e: int, t: int, now: float, out: SessionEffects) -> None:
        """Make sure the mind has its actions of step t of episode e before the step's instant (closing what is
        still open of earlier steps)."""
        host = self.host
        m = host.the_mind()
        if m.episode != e:
            eff = m.begin(e, host.epsilon(e, 1), force=True, size=1)
            if t > 1:  # joining mid-episode: the actions of step 1 are long past
                eff.action = None
            host.carry("clock", eff, out)
            if t == 1:
                return
        p = m.pending
        if p is not None and p.t == t and p.observed_at is None:
            return  # the usual case: acted in time
        if p is not None and p.t == t - 1:  # the previous step is late: close it with what arrived
            out.counters["late_steps"] += 1
            host.observe_deployed(self.observations.due(float("inf")), now, out)
            if m.pending is not None and m.pending.t == t - 1 and m.pending.observed_at is not None:
                host.carry("clock", m.tick(now, -1.0), out)
            p = m.pending
            if p is not None and p.t == t and p.observed_at is None:
                return
        for eff in m.skip_to(t):
            host.carry("clock", eff, out)
