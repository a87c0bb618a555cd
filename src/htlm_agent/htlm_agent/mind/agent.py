"""One agent's side of the lockstep protocol, without ROS: its mind (belief, previous assignment, policy, channel)
and the order in which it accepts the world's and its teammates' messages.

The agent's session (htlm_agent.session.core.AgentSession, which the agent node feeds) calls `AgentMind` and turns
what it returns into records. The mind
keeps the agent's B beliefs of a batch of B episodes and acts for all of them with one batched call of its policy;
it computes exactly what the in-process `Team(scenario, B, seed, b)` computes for that agent's column (same
functions of belief.py and reward.py, same generators from `htlm_world.seeds`), so an evaluation over ROS
reproduces `team.rollout` step for step; `policies.DecentralizedPolicy` runs the same per-agent policies inside
`team.rollout` (the tests' in-process team harness, tests/support/team.py, runs the protocol with a mind per agent
in one process). In train mode the streams are those of `htlm train` (`seeds.train_channel`, `seeds.train_explore`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.mind.policies import AgentPolicy, choose
from htlm_agent.mind.reward import RewardTables, confident_levels, reward
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.simulator import sample_channel
from htlm_world.travel import TravelState, working_actions
from htlm_world.types import BoolArray, FloatArray, IntArray

# ----- the agent's mind -------------------------------------------------------------------------------------------


@dataclass
class Transition:
    """One agent's transitions of one step in the B episodes of a batch (what it sends to the trainer)."""

    episode: int  # first episode of the batch
    step: int
    k: FloatArray  # (B, K) knowledge before acting
    a: IntArray  # (B,)
    r: FloatArray  # (B,)
    k2: FloatArray  # (B, K) knowledge after the update
    mask2: BoolArray  # (B, |G|) Â of the next step
    done: bool
    parts: dict[str, FloatArray]


@dataclass
class Effects:
    """What the session must publish after feeding the mind one message, in this order."""

    broadcast: tuple[int, IntArray, IntArray] | None = None  # (step, actions (B,), levels after the channel (B,))
    transition: Transition | None = None  # a step finished: send the transition
    ready: int | None = None  # publish ready(step): the last step of the batch is finished
    action: tuple[int, IntArray] | None = None  # (step, actions (B,)): our actions for that step
    drop: str | None = None  # the message was dropped by the protocol (counted): past, future, duplicate, length, ...


PolicyGate = Callable[[int, int], "AgentPolicy | None"]
"""(first episode of the batch, step t) -> the policy to act with for step t, or None while it is not there yet
(training: the trainer's weights for that step have not arrived)."""


@dataclass
class _Pending:
    t: int
    k: FloatArray  # (B, K)
    action: IntArray  # (B,)
    acted: bool | None  # None until the world's observation says whether our action was applied
    obs: IntArray | None = None  # (B,)
    observed_at: float | None = None
    acted_set: frozenset[int] | None = None
    heard: dict[int, tuple[IntArray, IntArray]] = field(default_factory=dict)
    drawn: bool = False
    sent: IntArray | None = None  # (B,)
    effective: IntArray | None = None  # (B,) what our action did when it differs from the assignment (not arrived)
    robot: tuple[bool, tuple[float, float] | None] | None = None  # deployed: arrived, and the robot's (x, y)


class AgentMind:
    """Belief, previous assignment, policy and simulated channel of one agent, and the protocol's order.

    The lockstep protocol as the agent sees it (docs/architecture.md, data flow of one step): the world's begin of a
    batch of B episodes resets the mind, which answers with its actions for step 1. The world's observations of
    step t (which list the agents whose actions it applied) make the mind draw its channel and broadcast; once it
    has heard the broadcast of every other agent that acted (or `tick` finds it waited too long), it updates its B
    beliefs (Eq. 2), computes its rewards, emits the transitions and answers with its actions for step t + 1, or
    with ready after the last step. A message of a past or future step is dropped and reported, never applied; one
    whose arrays do not have the batch's length is dropped as "length".

    With a `gate`, the mind asks it for the policy of each step before acting; while it answers None, the actions
    wait (`deferred`) until the session calls `act_now` (the trainer's weights arrived, or waiting is over).
    """

    def __init__(
        self,
        scenario: Scenario,
        agent: int,
        seed: int,
        policy: AgentPolicy,
        model: Model | None = None,
        batch: int = 1,
        mode: str = "evaluate",
        gate: PolicyGate | None = None,
    ) -> None:
        """The mind of agent index `agent` in a run with master seed `seed`, B = `batch` episodes per batch (the
        stream keys: batch index = first episode // B), in `mode` (train: the training streams)."""
        self.scenario = scenario
        self.model = model if model is not None else Model.build(scenario)
        self.tables = RewardTables.build(scenario)
        self.me = agent
        self.seed = seed
        self.policy = policy
        self.n = scenario.n_agents
        self.h = scenario.horizon
        self.batch = batch
        self.mode = mode
        self.gate = gate
        self.size = 1
        self.deferred: int | None = None
        """The step whose actions wait for the gate's policy (None: none)."""
        self.episode: int | None = None
        self.epsilon: float | FloatArray = 0.0
        self.t = 0
        self.pending: _Pending | None = None
        self.early: dict[int, tuple[int, IntArray, IntArray]] = {}
        self.travel: TravelState | None = None
        """Where the team is (`htlm_world.travel`), from the assignments the agent heard; None without travel."""
        self.impossible = 0
        self.missed_steps = 0
        self.timeouts = 0
        self.log: dict[str, list[Any]] = {}
        self.out = False
        """Out of the team (a person who is not available): every step's action is idle at the site of the previous
        assignment, the model's dropout, until `out` is False again (the return)."""
        self.instead: int | None = None
        """An action chosen from outside for the next step the mind acts for (a person's task taken instead of the
        assignment), used once."""
        self.chosen: IntArray | None = None
        """The policy's own actions of the newest step it acted for, before `out` or `instead` replaced them."""

    # ----- state ----------------------------------------------------------------------------------------------
    @property
    def current(self) -> int:
        """The step in progress (pending), else the last finished one."""
        return self.pending.t if self.pending is not None else self.t

    @property
    def finished(self) -> bool:
        """Whether the current episode's last step is finished (or no episode was begun)."""
        return self.episode is None or (self.pending is None and self.t >= self.h)

    def knowledge(self) -> FloatArray:
        """Knowledge states K = {b, a_o} (B, K)."""
        roster = self.heard if self.scenario.roster else None
        mates = knowledge.teammates_of(self.model, self.known)[:, self.me] if self.scenario.teammates else None
        places = None
        if self.travel is not None:  # the team's places and arrivals, from the assignments it heard
            places = knowledge.places_of(self.travel.goal, self.travel.eta())
        return knowledge.build(self.marg, self.prev, self.scenario.n_actions, roster, mates, places)

    def mask(self) -> BoolArray:
        """Â(a_o) (B, |G|)."""
        return self.model.action_mask(self.prev)

    def idle_action(self) -> IntArray:
        """Idle at the site of the previous assignment (B,): what the world applies when our actions are missing."""
        return np.asarray(self.model.idle_action(self.prev), dtype=np.int64)

    def _where(self, episode: int) -> str | None:
        if self.episode is None:
            return "no_episode"
        if episode < self.episode:
            return "past"
        if episode > self.episode:
            return "future"
        return None

    def _late(self, t: int) -> str:
        return "past" if t <= self.current else "future"

    # ----- messages -------------------------------------------------------------------------------------------
    def begin(self, episode: int, epsilon: float | FloatArray = 0.0, force: bool = False, size: int = 1) -> Effects:
        """The world's begin of the batch of `size` episodes from `episode` on: reset and answer with the actions of
        step 1 (ε one number, or one per episode).

        Accepted when fresh, once the previous batch's last step is reached, or with `force` (the session's resync
        after a long silence). A repeated begin of the current batch gets the same answer again.
        """
        out = Effects()
        if self.episode is not None and not force:
            if episode == self.episode:
                p = self.pending
                if self.t == 0 and p is not None and p.t == 1 and p.observed_at is None:
                    out.action = (1, p.action)
                elif not (self.t == 0 and self.deferred == 1):
                    out.drop = "duplicate"
                return out
            if episode < self.episode:
                out.drop = "past"
                return out
            if self.current < self.h or episode != self.episode + self.size:  # the world never skips a batch
                out.drop = "future"
                return out
        if self.pending is not None and self.episode is not None and episode != self.episode:
            out.transition = self._finish()  # the world moved on before our last step was complete
        sc = self.scenario
        self.episode = episode
        self.size = size
        self.epsilon = epsilon
        self.t = 0
        self.pending = None
        self.deferred = None
        self.early = {}
        self.belief = bf.initial_belief(self.model, size, agents=1)[:, 0]  # (B, S, L, ..., L): its own only
        self.marg = bf.marginals(self.model, self.belief)  # (B, p, L)
        self.prev = np.full(size, sc.start_assignment, dtype=np.int64)
        self.known = np.full((size, self.n), sc.start_assignment, dtype=np.int64)
        self.heard = np.ones((size, self.n), dtype=bool)  # the roster: whose broadcast arrived at the last step
        self.travel = TravelState(sc, size) if sc.travel else None
        b = episode // self.batch
        if self.mode == "train":
            self.chan = seeds.train_channel(self.seed, self.me, b)
            self.explore = seeds.train_explore(self.seed, self.me, b)
        else:
            self.chan = seeds.channel(self.seed, self.me, b)
            self.explore = seeds.explore(self.seed, self.me, b)
        self.log = {"actions": [], "messages": [], "rewards": [], "acted": []}
        self._act(1, out)
        return out

    def _act(self, t: int, out: Effects) -> None:
        """Choose the actions of step t into `out`, or defer them while the gate has no policy for the step."""
        policy = self.policy
        if self.gate is not None:
            assert self.episode is not None
            gated = self.gate(self.episode, t)
            if gated is None:
                self.deferred = t
                return
            policy = gated
        self.deferred = None
        k = self.knowledge()
        a = choose(policy, k, self.mask(), self.epsilon, self.explore)  # drawn whatever overrides it: same streams
        self.chosen = a
        if self.out:
            a = self.idle_action()
        elif self.instead is not None:
            a = np.full(self.size, self.instead, dtype=np.int64)
            self.instead = None
        self._open(t, k, a, acted=None)
        out.action = (t, a)

    def reassign(self, action: int | IntArray) -> Effects:
        """Replace our actions of the step in progress by `action` (one for every episode of the batch, or one per
        episode: a person takes another task, goes out of the team or comes back), answered with the new action
        record of that step; dropped as "applied" once the step's observation came (the step can no longer
        change)."""
        out = Effects()
        p = self.pending
        if p is None or p.observed_at is not None:
            out.drop = "applied"
            return out
        p.action = np.broadcast_to(np.asarray(action, dtype=np.int64), (self.size,)).copy()
        out.action = (p.t, p.action)
        return out

    def act_now(self, force: bool = False) -> Effects:
        """The deferred actions, if the gate now has the policy of their step (or with `force`: act with the
        mind's own `policy`, the newest it has)."""
        out = Effects()
        t = self.deferred
        if t is None:
            return out
        if force:
            gate, self.gate = self.gate, None
            try:
                self._act(t, out)
            finally:
                self.gate = gate
        else:
            self._act(t, out)
        return out

    def skip_to(self, t: int) -> list[Effects]:
        """The steps before t passed without us (a process that joined the agents' clock mid-episode, or fell behind
        it): close the step in progress as it stands (an action never applied counts as idle), every further one as
        missed (idle at the site of the previous assignment, no evidence; teammates keep their last known
        assignment), and act for step t. One Effects per closed step, the last with the actions of step t."""
        outs: list[Effects] = []
        p = self.pending
        if p is not None and p.t < t:
            if p.observed_at is None:  # never applied: we idled
                self.missed_steps += 1
                p.acted = False
                p.action = self.idle_action()
            outs.append(Effects(transition=self._finish()))
        while self.t < t - 1:
            self.missed_steps += 1
            self._open(self.t + 1, self.knowledge(), self.idle_action(), acted=False)
            outs.append(Effects(transition=self._finish()))
        last = Effects()
        if self.pending is None:
            self._act(t, last)
        outs.append(last)
        return outs

    def _open(self, t: int, k: FloatArray, a: IntArray, acted: bool | None) -> None:
        self.pending = _Pending(t=t, k=k, action=a, acted=acted)
        for j, (tt, aj, lj) in self.early.items():
            if tt == t:
                self.pending.heard[j] = (aj, lj)
        self.early = {}

    def observe(
        self,
        episode: int,
        t: int,
        levels: IntArray | list[int],
        acted: list[int],
        now: float = 0.0,
        worked: bool = True,
        tasks: IntArray | list[int] | None = None,
        position: tuple[float, float] | None = None,
    ) -> Effects:
        """The world's observations of step t (B,): draw our channel and broadcast if our actions were applied.

        `tasks` (B,), the world's record of the task we worked on in each episode (-1: none): where it says none
        although we chose a task, an event of the scenario kept us out of that episode and the world made us idle at
        the site of our previous assignment, as it does when our actions are missing.

        `worked` False (an external operation: our robot had not reached the site of its assignment): the assignment
        stands, but it did nothing this step; our belief update and our broadcast count it as idle at that site, so
        neither we nor our teammates predict work that was not done."""
        out = Effects()
        bad = self._where(episode)
        if bad is None and (len(levels) != self.size or (tasks is not None and len(tasks) != self.size)):
            bad = "length"
        p = self.pending
        if bad is None:
            if p is not None and t == p.t:
                if p.observed_at is not None:
                    bad = "duplicate"
            elif (p is not None and t == p.t + 1) or (p is None and t == self.t + 1 and t <= self.h):
                # the world went on without our action for step t: close the step we were in, idle in this one
                if p is not None:
                    out.transition = self._finish()
                self.missed_steps += 1
                self.deferred = None
                self._open(t, self.knowledge(), self.idle_action(), acted=False)
                p = self.pending
            else:
                bad = self._late(t)
        if bad is not None:
            out.drop = bad
            return out
        assert p is not None
        p.observed_at = now
        p.acted_set = frozenset(acted)
        if self.me in p.acted_set:
            p.acted = True
            p.obs = np.asarray(levels, dtype=np.int64)
            if tasks is not None:
                chose_task = (p.action >= 0) & (p.action < self.scenario.n_tasks)
                if self.travel is not None:  # on its way to its task, an agent works on none and is not kept out
                    joint = np.broadcast_to(self.known, (self.size, self.n)).copy()
                    joint[:, self.me] = p.action
                    chose_task &= self.travel.arrives(joint)[:, self.me]
                p.action = np.where(chose_task & (np.asarray(tasks) < 0), self.idle_action(), p.action)
            if not worked:
                p.effective = np.asarray(self.model.idle_action(p.action), dtype=np.int64)
            if self.travel is not None and (not worked or position is not None):
                p.robot = (worked, position)
        else:
            if p.acted is None:
                self.missed_steps += 1  # our action came too late
            p.acted = False
            p.action = self.idle_action()
            p.obs = np.full(self.size, -1, dtype=np.int64)
        sent = self._draw(p.obs)
        if p.acted:
            out.broadcast = (t, p.action if p.effective is None else p.effective, sent)
        if self._complete():
            self._step_done(out)
        return out

    def _draw(self, levels: IntArray) -> IntArray:
        assert self.pending is not None and not self.pending.drawn
        self.pending.drawn = True
        self.pending.sent = sample_channel(self.model, self.me, levels, self.chan)
        return self.pending.sent

    def hear(
        self, sender: int, episode: int, t: int, actions: IntArray | list[int], levels: IntArray | list[int]
    ) -> Effects:
        """A teammate's broadcast of step t: its actions and levels (B,) in every episode of the batch."""
        out = Effects()
        bad = self._where(episode)
        if bad is None and (len(actions) != self.size or len(levels) != self.size):
            bad = "length"
        p = self.pending
        action = np.asarray(actions, dtype=np.int64)
        level = np.asarray(levels, dtype=np.int64)
        if bad is None:
            if sender == self.me:
                bad = "self"
            elif p is not None and t == p.t:
                if sender in p.heard:
                    bad = "duplicate"
                else:
                    p.heard[sender] = (action, level)
                    if self._complete():
                        self._step_done(out)
            elif t == self.current + 1 and t <= self.h:
                if sender in self.early:
                    bad = "duplicate"
                else:  # ahead of our own observation: keep it for that step
                    self.early[sender] = (t, action, level)
            else:
                bad = self._late(t)
        out.drop = bad
        return out

    def tick(self, now: float, timeout: float) -> Effects:
        """Finish the step in progress if we observed it more than `timeout` seconds ago and still miss a
        teammate's broadcast (it died after acting): update with what we heard and go on."""
        out = Effects()
        p = self.pending
        if p is not None and p.observed_at is not None and now - p.observed_at > timeout:
            self.timeouts += 1
            self._step_done(out)
        return out

    def end(self, episode: int, t: int) -> Effects:
        """The world's end of the episode: finish the last step if it is still open."""
        out = Effects()
        where = self._where(episode)
        if where is None and self.pending is not None and self.pending.t == t == self.h:
            out.transition = self._finish()
        elif not (where is None and t == self.h and self.finished):  # the usual case: nothing left to do
            out.drop = where or self._late(t)
        return out

    def _complete(self) -> bool:
        p = self.pending
        if p is None or p.observed_at is None or p.acted_set is None:
            return False
        return all(j in p.heard for j in p.acted_set if j != self.me)

    def _step_done(self, out: Effects) -> None:
        tr = self._finish()
        out.transition = tr
        if tr.step < self.h:
            self._act(tr.step + 1, out)
        else:
            out.ready = tr.step

    # ----- the belief update of one step (Eq. 2), the reward, the transition --------------------------------------
    def _finish(self) -> Transition:
        p = self.pending
        assert p is not None and self.episode is not None
        size = self.size
        if not p.drawn:
            self._draw(p.obs if p.acted and p.obs is not None else np.full(size, -1, dtype=np.int64))
        n, me = self.n, self.me
        action = p.action
        obs = p.obs if p.obs is not None else np.full(size, -1, dtype=np.int64)
        joint = self.known.copy()  # (B, N)
        messages = np.full((size, n), -1, dtype=np.int64)
        heard = np.zeros((size, n), dtype=bool)
        if p.acted_set is not None:  # a teammate whose actions the world did not apply idled at its site
            for j in set(range(n)) - p.acted_set - {me}:
                joint[:, j] = self.model.idle_action(joint[:, j])
        for j, (aj, lj) in p.heard.items():
            if p.acted_set is not None and j not in p.acted_set:
                continue
            joint[:, j] = aj
            messages[:, j] = lj
            heard[:, j] = True
        joint[:, me] = action if p.effective is None else p.effective
        applied = joint
        if self.travel is not None:  # an agent on its way works on nothing and observes nothing
            if p.robot is not None:  # deployed: our robot's place, not the model's guess
                worked, position = p.robot
                self.travel.place(me, joint[:, me], None if worked else position)
            applied = working_actions(joint, self.travel.step(joint))
        lik = bf.agent_evidence(self.model, me, applied, obs, messages, heard, p.t)
        caps = self.model.joint_capability(applied)
        prior = (
            np.broadcast_to(self.marg[:, None], (size, n, *self.marg.shape[1:]))
            if self.tables.difference.any()
            else None
        )
        self.belief, bad = bf.update(self.model, self.belief, caps, lik)
        self.impossible += int(bad.sum())
        self.marg = bf.marginals(self.model, self.belief)
        prev = np.broadcast_to(self.prev[:, None], (size, n))
        marg = np.broadcast_to(self.marg[:, None], (size, n, *self.marg.shape[1:]))
        r, parts = reward(self.model, self.tables, prev, marg, joint, prior)
        self.prev = np.where(action >= 0, action, self.prev)
        self.known = np.where(joint >= 0, joint, self.known)
        self.heard = heard.copy()
        self.heard[:, me] = True
        self.t = p.t
        self.pending = None
        sent = p.sent if p.sent is not None else np.full(size, -1, dtype=np.int64)
        self.log["actions"].append(action)
        self.log["messages"].append(sent)
        self.log["rewards"].append(r[:, me].copy())
        self.log["acted"].append(bool(p.acted))
        return Transition(
            episode=self.episode,
            step=p.t,
            k=p.k,
            a=action,
            r=r[:, me].copy(),
            k2=self.knowledge(),
            mask2=self.mask(),
            done=p.t >= self.h,
            parts={key: v[:, me].copy() for key, v in parts.items()},
        )

    def episode_log(self, i: int) -> dict[str, Any]:
        """Episode i of the batch as the agent lived it: actions, messages, rewards per step and whether acted."""
        return {
            "actions": [int(a[i]) for a in self.log["actions"]],
            "messages": [int(m[i]) for m in self.log["messages"]],
            "rewards": [float(r[i]) for r in self.log["rewards"]],
            "acted": list(self.log["acted"]),
        }

    def history(self, t: int, i: int = 0) -> list[int]:
        """Our assignments of steps 1..t-1 of episode i of the batch, -1 where we did not act (the steps before
        we joined, or closed without our action applied): what an observer that missed them rebuilds them from."""
        lived = [int(a[i]) if acted else -1 for a, acted in zip(self.log["actions"], self.log["acted"], strict=True)]
        lived = lived[: max(t - 1, 0)]
        return [-1] * (t - 1 - len(lived)) + lived

    def belief_summary(self, i: int = 0) -> tuple[list[float], list[int]]:
        """Per-task marginals (p*L, row-major) and confident levels (p) of the current belief in episode i."""
        i = min(max(i, 0), self.size - 1)
        conf = confident_levels(self.marg[i : i + 1, None], self.tables.threshold[self.me : self.me + 1])
        return self.marg[i].ravel().tolist(), [int(x) for x in conf[0, 0]]
