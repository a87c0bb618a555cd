"""One agent's side of the lockstep protocol, without ROS: its mind (belief, previous assignment, policy, channel)
and the order in which it accepts the world's and its teammates' messages.

The agent node (agent_node.py) only decodes messages, calls `AgentMind` and publishes what it returns. The mind
computes exactly what the in-process `Team` computes for that agent's row (same functions of belief.py and
reward.py on batch 1, same generators from `htlm_world.seeds`), so an evaluation over ROS reproduces `team.rollout`
step for step; `policies.DecentralizedPolicy` runs the same per-agent policies inside `team.rollout`, and
`loopback_episode` runs the protocol in one process (the reference for the ROS equivalence test).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from htlm_agent.mind import belief as bf
from htlm_agent.mind import knowledge
from htlm_agent.mind.policies import AgentPolicy, choose
from htlm_agent.mind.reward import RewardTables, confident_levels, reward
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.protocol import WorldEpisode
from htlm_world.scenario import Scenario
from htlm_world.simulator import sample_channel
from htlm_world.types import BoolArray, FloatArray

# ----- the agent's mind -------------------------------------------------------------------------------------------


@dataclass
class Transition:
    """One transition of one agent (what it sends to the trainer)."""

    episode: int
    step: int
    k: FloatArray  # (K,) knowledge before acting
    a: int
    r: float
    k2: FloatArray  # (K,) knowledge after the update
    mask2: BoolArray  # (|G|,) Â of the next step
    done: bool
    parts: dict[str, float]


@dataclass
class Effects:
    """What the node must publish after feeding the mind one message, in this order."""

    broadcast: tuple[int, int, int] | None = None  # (step, action, level after the channel)
    transition: Transition | None = None  # a step finished: send the transition
    ready: int | None = None  # publish ready(step): the last step of the episode is finished
    action: tuple[int, int] | None = None  # (step, action): our action for that step
    drop: str | None = None  # the message was dropped by the protocol (counted): past, future, duplicate, ...


@dataclass
class _Pending:
    t: int
    k: FloatArray
    action: int
    acted: bool | None  # None until the world's observation says whether our action was applied
    obs: int = -1
    observed_at: float | None = None
    acted_set: frozenset[int] | None = None
    heard: dict[int, tuple[int, int]] = field(default_factory=dict)
    drawn: bool = False
    sent: int = -1


class AgentMind:
    """Belief, previous assignment, policy and simulated channel of one agent, and the protocol's order.

    The lockstep protocol as the agent sees it (docs/architecture.md, data flow of one step): the world's begin of an
    episode resets the mind, which answers with its action for step 1. The world's observation of step t (which
    lists the agents whose action it applied) makes the mind draw its channel and broadcast; once it has heard the
    broadcast of every other agent that acted (or `tick` finds it waited too long), it updates its belief (Eq. 2),
    computes its reward, emits the transition and answers with its action for step t + 1, or with ready after the
    last step. A message of a past or future step is dropped and reported, never applied.
    """

    def __init__(
        self,
        scenario: Scenario,
        agent: int,
        seed: int,
        policy: AgentPolicy,
        model: Model | None = None,
    ) -> None:
        """The mind of agent index `agent` in a run with master seed `seed`."""
        self.scenario = scenario
        self.model = model if model is not None else Model.build(scenario)
        self.tables = RewardTables.build(scenario)
        self.me = agent
        self.seed = seed
        self.policy = policy
        self.n = scenario.n_agents
        self.h = scenario.horizon
        self.episode: int | None = None
        self.epsilon = 0.0
        self.t = 0
        self.pending: _Pending | None = None
        self.early: dict[int, tuple[int, int, int]] = {}
        self.impossible = 0
        self.missed_steps = 0
        self.timeouts = 0
        self.log: dict[str, list[Any]] = {}

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
        """Knowledge state K = {b, a_o} (1, K)."""
        return knowledge.build(self.marg, np.array([self.prev], dtype=np.int64), self.scenario.n_actions)

    def mask(self) -> BoolArray:
        """Â(a_o) (1, |G|)."""
        return self.model.action_mask(np.array([self.prev], dtype=np.int64))

    def idle_action(self) -> int:
        """Idle at the site of the previous assignment: what the world applies when our action is missing."""
        return int(self.model.idle_action(np.asarray(self.prev, dtype=np.int64)))

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
    def begin(self, episode: int, epsilon: float = 0.0, force: bool = False) -> Effects:
        """The world's begin of `episode`: reset and answer with the action of step 1.

        Accepted when fresh, once the previous episode's last step is reached, or with `force` (the node's resync
        after a long silence). A repeated begin of the current episode gets the same answer again.
        """
        out = Effects()
        if self.episode is not None and not force:
            if episode == self.episode:
                p = self.pending
                if self.t == 0 and p is not None and p.t == 1 and p.observed_at is None:
                    out.action = (1, p.action)
                else:
                    out.drop = "duplicate"
                return out
            if episode < self.episode:
                out.drop = "past"
                return out
            if self.current < self.h or episode != self.episode + 1:  # the world never skips an episode
                out.drop = "future"
                return out
        if self.pending is not None and self.episode is not None and episode != self.episode:
            out.transition = self._finish()  # the world moved on before our last step was complete
        sc = self.scenario
        self.episode = episode
        self.epsilon = float(epsilon)
        self.t = 0
        self.pending = None
        self.early = {}
        self.belief = bf.initial_belief(self.model, 1)[:, self.me]  # (1, S, L, L)
        self.marg = bf.marginals(self.belief)  # (1, p, L)
        self.prev = sc.start_assignment
        self.known = np.full(self.n, sc.start_assignment, dtype=np.int64)
        self.chan = seeds.channel(self.seed, self.me, episode)
        self.explore = seeds.explore(self.seed, self.me, episode)
        self.log = {"actions": [], "messages": [], "rewards": [], "acted": []}
        out.action = (1, self._act(1))
        return out

    def _act(self, t: int) -> int:
        k = self.knowledge()
        a = int(choose(self.policy, k, self.mask(), self.epsilon, self.explore)[0])
        self._open(t, k, a, acted=None)
        return a

    def _open(self, t: int, k: FloatArray, a: int, acted: bool | None) -> None:
        self.pending = _Pending(t=t, k=k, action=a, acted=acted)
        for j, (tt, aj, lj) in self.early.items():
            if tt == t:
                self.pending.heard[j] = (aj, lj)
        self.early = {}

    def observe(self, episode: int, t: int, level: int, acted: list[int], now: float = 0.0) -> Effects:
        """The world's observation of step t: draw our channel and broadcast if our action was applied."""
        out = Effects()
        bad = self._where(episode)
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
            p.obs = level
        else:
            if p.acted is None:
                self.missed_steps += 1  # our action came too late
            p.acted = False
            p.action = self.idle_action()
            p.obs = -1
        sent = self._draw(p.obs)
        if p.acted:
            out.broadcast = (t, p.action, sent)
        if self._complete():
            self._step_done(out)
        return out

    def _draw(self, level: int) -> int:
        assert self.pending is not None and not self.pending.drawn
        self.pending.drawn = True
        self.pending.sent = int(sample_channel(self.model, self.me, np.array([level], dtype=np.int64), self.chan)[0])
        return self.pending.sent

    def hear(self, sender: int, episode: int, t: int, action: int, level: int) -> Effects:
        """A teammate's broadcast of step t."""
        out = Effects()
        bad = self._where(episode)
        p = self.pending
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
            out.action = (tr.step + 1, self._act(tr.step + 1))
        else:
            out.ready = tr.step

    # ----- the belief update of one step (Eq. 2), the reward, the transition --------------------------------------
    def _finish(self) -> Transition:
        p = self.pending
        assert p is not None and self.episode is not None
        if not p.drawn:
            self._draw(p.obs if p.acted else -1)
        n, me = self.n, self.me
        action = p.action
        joint = self.known.copy()
        messages = np.full(n, -1, dtype=np.int64)
        heard = np.zeros(n, dtype=bool)
        for j, (aj, lj) in p.heard.items():
            if p.acted_set is not None and j not in p.acted_set:
                continue
            joint[j] = aj
            messages[j] = lj
            heard[j] = True
        joint[me] = action
        lik = bf.agent_evidence(
            self.model, me, joint[None, :], np.array([p.obs], dtype=np.int64), messages[None, :], heard[None, :]
        )
        caps = self.model.joint_capability(joint[None, :])
        self.belief, bad = bf.update(self.model, self.belief, caps, lik)
        self.impossible += int(bad.sum())
        self.marg = bf.marginals(self.belief)
        prev = np.full((1, n), self.prev, dtype=np.int64)
        marg = np.broadcast_to(self.marg[:, None], (1, n, *self.marg.shape[1:]))
        r, parts = reward(self.model, self.tables, prev, marg, joint[None, :])
        if action >= 0:
            self.prev = action
        self.known = np.where(joint >= 0, joint, self.known)
        self.t = p.t
        self.pending = None
        self.log["actions"].append(action)
        self.log["messages"].append(p.sent)
        self.log["rewards"].append(float(r[0, me]))
        self.log["acted"].append(bool(p.acted))
        return Transition(
            episode=self.episode,
            step=p.t,
            k=p.k[0],
            a=action,
            r=float(r[0, me]),
            k2=self.knowledge()[0],
            mask2=self.mask()[0],
            done=p.t >= self.h,
            parts={key: float(v[0, me]) for key, v in parts.items()},
        )

    def belief_summary(self) -> tuple[list[float], list[int]]:
        """Per-task marginals (p*L, row-major) and confident levels (p) of the current belief."""
        conf = confident_levels(self.marg[:, None], self.tables.threshold[self.me : self.me + 1])
        return self.marg[0].ravel().tolist(), [int(x) for x in conf[0, 0]]


# ----- the protocol in one process --------------------------------------------------------------------------------


def loopback_episode(
    scenario: Scenario,
    seed: int,
    episode: int,
    policies: list[AgentPolicy],
    epsilon: float = 0.0,
    absent: dict[int, set[int]] | None = None,
    model: Model | None = None,
) -> dict[str, Any]:
    """Run one episode of the lockstep protocol in one process: a WorldEpisode and one AgentMind per agent,
    every message delivered. `absent` maps a step to agents whose action is lost (the world makes them idle).

    Returns levels (h+1, p), actions (h, N), observations (h, N), messages (h, N), rewards (h, N).
    """
    model = model if model is not None else Model.build(scenario)
    n, h = scenario.n_agents, scenario.horizon
    world = WorldEpisode(scenario, model, seed, episode)
    minds = [AgentMind(scenario, i, seed, policies[i], model=model) for i in range(n)]
    acts: dict[int, int] = {}
    for i, m in enumerate(minds):
        act = m.begin(episode, epsilon).action
        assert act is not None and act[0] == 1
        acts[i] = act[1]
    msgs = np.full((h, n), -1, dtype=np.int64)
    rewards = np.zeros((h, n))
    for t in range(1, h + 1):
        chosen = {i: a for i, a in acts.items() if not (absent and i in absent.get(t, set()))}
        out = world.step(chosen)
        sends = []
        effects: list[list[Effects]] = [[] for _ in range(n)]
        for i, m in enumerate(minds):
            eff = m.observe(episode, t, int(out.observations[i]), out.acted)
            if eff.broadcast is not None:
                sends.append((i, eff.broadcast))
                msgs[t - 1, i] = eff.broadcast[2]
            effects[i].append(eff)
        for i, m in enumerate(minds):
            for j, (tj, aj, lj) in sends:
                if j != i:
                    effects[i].append(m.hear(j, episode, tj, aj, lj))
        acts = {}
        for i in range(n):
            done = [e for e in effects[i] if e.transition is not None]
            assert len(done) == 1, f"agent {i} did not finish step {t}"
            rewards[t - 1, i] = done[0].transition.r  # type: ignore[union-attr]
            if done[0].action is not None:
                acts[i] = done[0].action[1]
    traj = world.trajectory()
    return {
        "levels": np.array(traj["levels"]),
        "actions": np.array(traj["actions"]),
        "observations": np.array(traj["observations"]),
        "messages": msgs,
        "rewards": rewards,
    }
