"""The in-process team harness: a world and every agent of a team in one process, as the ROS nodes run them but
with every message handed over in order, and the in-process `team.rollout` they must equal.

Three depths of the same team, each for the tests of its layer:
- `loopback_episode`: one batch through a `WorldEpisode` and one `AgentMind` per agent, every message delivered at
  once (the minds' side of the protocol, no phases or deadlines);
- `MindNet` (`loopback_run`): the world's `WorldProtocol` with one `AgentMind` per agent, its records queued and
  delivered in order, the clock jumping to the protocol's next deadline when nothing is left to deliver;
- `SessionNet` (`session_team`): the same `WorldProtocol` with one `AgentSession` per agent, every record encoded
  and decoded as on the wire.
`reference` is what they are compared with: batch b of the in-process `Team` under the same per-agent policies.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from htlm_agent.mind.agent import AgentMind, Effects
from htlm_agent.mind.policies import AgentPolicy, DecentralizedPolicy
from htlm_agent.ros.settings import AgentSettings
from htlm_agent.runtime.team import Team, Trajectory, rollout
from htlm_agent.session.builtin import builtin_policy
from htlm_agent.session.core import AgentSession, SessionEffects
from htlm_msgs_py import schema as S
from htlm_msgs_py.schema import limits
from htlm_world.episode import WorldEpisode
from htlm_world.model import Model
from htlm_world.protocol import LockstepSettings, WorldEffects, WorldProtocol, world_protocol
from htlm_world.scenario import Scenario
from htlm_world.types import IntArray

FIELDS = ("levels", "actions", "observations", "messages", "rewards")
"""The fields of a trajectory both runtimes produce."""

SCHEMA = {
    "scenario": S.SCENARIO,
    "step": S.STEP,
    "observation": S.OBSERVATION,
    "action": S.ACTION,
    "broadcast": S.BROADCAST,
    "ready": S.READY,
    "transition": S.TRANSITION,
    "belief": S.BELIEF,
}
"""The schema of each kind of record the world and the sessions publish."""


def builtin_team(sc: Scenario, name: str) -> tuple[list[AgentPolicy], float]:
    """Every agent's built-in policy `name` (greedy, auction, random) and the team's exploration ε.

    Args:
        sc: the scenario.
        name: the built-in policy.

    Returns:
        The per-agent policies and ε.
    """
    out = [builtin_policy(sc, name, i) for i in range(sc.n_agents)]
    return [p for p, _ in out], out[0][1]


def reference(
    sc: Scenario,
    policies: list[AgentPolicy],
    seed: int,
    epsilon: float,
    b: int,
    size: int = 1,
    inactive: tuple[int, ...] = (),
) -> Trajectory:
    """Batch b of `size` episodes of the in-process `Team` under the per-agent `policies`.

    Args:
        sc: the scenario.
        policies: one policy per agent.
        seed: the master seed.
        epsilon: the agents' exploration.
        b: the batch index (the episode's index with size 1).
        size: B, the episodes of the batch.
        inactive: agents forced to idle.

    Returns:
        The batch's trajectory.
    """
    dp = DecentralizedPolicy(policies, seed, epsilon)
    dp.begin(b)
    return rollout(Team(sc, size, seed, episode=b, inactive=inactive), dp)


# ----- a batch through the minds, every message delivered at once -------------------------------------------------


def loopback_episode(
    scenario: Scenario,
    seed: int,
    episode: int,
    policies: list[AgentPolicy],
    epsilon: float = 0.0,
    absent: dict[int, set[int]] | None = None,
    batch: int = 1,
    mode: str = "evaluate",
) -> dict[str, Any]:
    """Run one batch of `batch` episodes from `episode` on (a multiple of `batch`) through the lockstep protocol in
    one process: a WorldEpisode and one AgentMind per agent, every message delivered.

    Args:
        scenario: the scenario.
        seed: the master seed.
        episode: the batch's first episode.
        policies: one policy per agent.
        epsilon: the agents' exploration.
        absent: step -> agents whose actions are lost (the world makes them idle).
        batch: B, the episodes of the batch.
        mode: the run's mode (its random streams).

    Returns:
        levels (h+1, B, p), actions (h, B, N), observations (h, B, N), messages (h, B, N), rewards (h, B, N); with
        batch 1 the B axis is dropped.
    """
    model = Model.build(scenario)
    n, h = scenario.n_agents, scenario.horizon
    b = episode // batch
    world = WorldEpisode(scenario, model, seed, episode, size=batch, b=b, mode=mode)
    minds = [AgentMind(scenario, i, seed, policies[i], model=model, batch=batch, mode=mode) for i in range(n)]
    acts: dict[int, IntArray] = {}
    for i, m in enumerate(minds):
        act = m.begin(episode, epsilon, size=batch).action
        assert act is not None and act[0] == 1
        acts[i] = act[1]
    msgs = np.full((h, batch, n), -1, dtype=np.int64)
    rewards = np.zeros((h, batch, n))
    for t in range(1, h + 1):
        chosen = {i: a for i, a in acts.items() if not (absent and i in absent.get(t, set()))}
        out = world.step(chosen)
        observed, _cls = model.observes(out.actions, t)  # the world's record (`WorldProtocol`)
        tasks = np.where(out.observations >= 0, observed, -1)
        sends = []
        effects: list[list[Effects]] = [[] for _ in range(n)]
        for i, m in enumerate(minds):
            eff = m.observe(episode, t, out.observations[:, i], out.acted, tasks=tasks[:, i])
            if eff.broadcast is not None:
                sends.append((i, eff.broadcast))
                msgs[t - 1, :, i] = eff.broadcast[2]
            effects[i].append(eff)
        for i, m in enumerate(minds):
            for j, (tj, aj, lj) in sends:
                if j != i:
                    effects[i].append(m.hear(j, episode, tj, aj, lj))
        acts = {}
        for i in range(n):
            done = [e for e in effects[i] if e.transition is not None]
            assert len(done) == 1, f"agent {i} did not finish step {t}"
            rewards[t - 1, :, i] = done[0].transition.r  # type: ignore[union-attr]
            if done[0].action is not None:
                acts[i] = done[0].action[1]
    levels = np.stack(world.level_log)
    actions = np.stack(world.action_log)
    observations = np.stack(world.obs_log)
    if batch == 1:
        return {
            "levels": levels[:, 0],
            "actions": actions[:, 0],
            "observations": observations[:, 0],
            "messages": msgs[:, 0],
            "rewards": rewards[:, 0],
        }
    return {"levels": levels, "actions": actions, "observations": observations, "messages": msgs, "rewards": rewards}


def assert_loopback_equals_team(sc: Scenario, name: str, seed: int, b: int, batch: int) -> tuple[Team, Trajectory]:
    """Batch b of `batch` episodes of the built-in policy `name` in both runtimes: equal in every field (FIELDS).

    Returns:
        The Team and its trajectory, for what a test checks beyond equality.
    """
    pols, eps = builtin_team(sc, name)
    dp = DecentralizedPolicy(pols, seed, eps)
    dp.begin(b)
    team = Team(sc, batch, seed, episode=b)
    tr = rollout(team, dp)
    lb = loopback_episode(sc, seed, b * batch, pols, epsilon=eps, batch=batch)
    for f in FIELDS:
        got = lb[f] if batch > 1 else lb[f][:, None]
        assert np.array_equal(getattr(tr, f), got), (f, seed, b)
    return team, tr


# ----- the world's protocol with the agents, records queued and delivered in order ------------------------------


class _Net:
    """A WorldProtocol and the team's agents in one process: what one side publishes is queued and delivered in
    order; when nothing is left to deliver, the clock jumps to the world's next wake-up."""

    drain = True
    """Deliver what is left in the queue once the world is done (its last records: the run stopped)."""

    def __init__(self, world: WorldProtocol) -> None:
        self.world = world
        self.queue: deque[tuple[str, int, Any]] = deque()
        self.now = 0.0
        self.world_log: list[dict[str, Any]] = []

    def deliver(self, kind: str, sender: int, rec: Any) -> None:
        """Hand one queued record to whoever reads it."""
        raise NotImplementedError

    def tick(self, now: float) -> None:
        """The agents' clocks at a wake-up of the world."""

    def run(self, until: Callable[[], bool] | None = None) -> None:
        """Deliver until the world is done (or `until()` holds)."""
        while not self.world.done and not (until is not None and until()):
            if not self.queue:
                self.now = max(self.now, self.world.next_wakeup())
                self.from_world(self.world.tick(self.now))
                self.tick(self.now)
                continue
            self.deliver(*self.queue.popleft())
        while self.drain and self.queue and self.world.done:
            self.deliver(*self.queue.popleft())

    def from_world(self, eff: WorldEffects) -> None:
        """Queue what the world publishes and keep its episode log."""
        raise NotImplementedError


class MindNet(_Net):
    """The world's protocol with one AgentMind per agent, records as Python values (arrays as lists); the actions
    and readies of the `silent` agents are lost."""

    drain = False

    def __init__(
        self, world: WorldProtocol, minds: list[AgentMind], epsilon: float, silent: frozenset[int] = frozenset()
    ) -> None:
        super().__init__(world)
        self.minds = minds
        self.epsilon = epsilon
        self.silent = silent
        self.agent_logs: dict[int, list[dict[str, Any]]] = {i: [] for i in range(len(minds))}

    def from_world(self, eff: WorldEffects) -> None:
        # an agent answers a repeated begin with the same actions again: the world drops the duplicate
        assert set(eff.drops) <= {("action", "duplicate")} and not eff.rejects, (eff.drops, eff.rejects)
        self.queue.extend((kind, -1, fields) for kind, fields in eff.publish)
        self.world_log.extend(eff.episode_log)

    def from_agent(self, i: int, eff: Effects) -> None:
        """Queue what agent i's mind sends."""
        assert eff.drop is None, eff.drop
        m = self.minds[i]
        if eff.broadcast is not None:
            t, a, levels = eff.broadcast
            self.queue.append(("broadcast", i, (i, m.episode, t, a.tolist(), levels.tolist())))
        if eff.action is not None and i not in self.silent:
            rec = {"agent": i, "episode": m.episode, "step": eff.action[0], "actions": eff.action[1].tolist()}
            self.queue.append(("action", i, rec))
        if eff.ready is not None:
            assert m.episode is not None
            self.agent_logs[i].extend({"episode": m.episode + j, **m.episode_log(j)} for j in range(m.size))
            if i not in self.silent:
                self.queue.append(("ready", i, {"agent": i, "episode": m.episode, "step": eff.ready}))

    def deliver(self, kind: str, sender: int, rec: Any) -> None:
        minds, now = self.minds, self.now
        if kind == "step" and rec["phase"] == "begin":
            for i, m in enumerate(minds):
                self.from_agent(i, m.begin(rec["episode"], self.epsilon, size=rec["size"]))
        elif kind == "step" and rec["phase"] == "end":
            for i, m in enumerate(minds):
                self.from_agent(i, m.end(rec["episode"], rec["step"]))
        elif kind == "step":  # step t was applied: the agents learn it from their observations
            assert rec["phase"] == "step" and rec["size"] == self.world.size
        elif kind == "observation":
            i = rec["agent"]
            self.from_agent(i, minds[i].observe(rec["episode"], rec["step"], rec["levels"], rec["acted"], now))
        elif kind == "broadcast":
            j, e, t, a, levels = rec
            for i, m in enumerate(minds):
                if i != j:
                    self.from_agent(i, m.hear(j, e, t, a, levels))
        elif kind == "action":
            self.from_world(self.world.on_action(rec, now))
        elif kind == "ready":
            self.from_world(self.world.on_ready(rec, now))


def loopback_run(
    scenario: Scenario,
    seed: int,
    first: int,
    episodes: int,
    policies: list[AgentPolicy],
    epsilon: float,
    silent: frozenset[int] = frozenset(),
    batch: int = 1,
    protocol: Callable[[Scenario, LockstepSettings, Model], WorldProtocol] = world_protocol,
) -> tuple[list[dict[str, Any]], dict[int, list[dict[str, Any]]]]:
    """Run `episodes` episodes of the world's `protocol` in batches of `batch` with one AgentMind per agent
    (`MindNet`).

    Returns:
        The world's episode log and each agent's episode logs.
    """
    model = Model.build(scenario)
    settings = LockstepSettings(seed=seed, first_episode=first, episodes=episodes, linger=0.0, batch=batch)
    world = protocol(scenario, settings, model)
    minds = [AgentMind(scenario, i, seed, policies[i], model=model, batch=batch) for i in range(scenario.n_agents)]
    net = MindNet(world, minds, epsilon, silent)
    net.from_world(world.start(net.now))
    net.run()
    return net.world_log, net.agent_logs


def assert_logs_equal_rollout(
    world_log: list[dict[str, Any]], agent_logs: dict[int, list[dict[str, Any]]], ref: Callable[[int], Any]
) -> None:
    """The episode logs of a run equal the in-process trajectories: `ref(e)` is the trajectory of the batch holding
    episode e and e's index in it."""
    for w in world_log:
        e = w["metrics"]["episode"]
        tr, j = ref(e)
        assert np.array_equal(tr.levels[:, j], w["levels"]), f"episode {e}: levels"
        assert np.array_equal(tr.actions[:, j], w["actions"]), f"episode {e}: actions"
        assert np.array_equal(tr.observations[:, j], w["observations"]), f"episode {e}: observations"
        for i, logs in agent_logs.items():
            (rec,) = [x for x in logs if x["episode"] == e]
            assert rec["actions"] == tr.actions[:, j, i].tolist(), f"episode {e} agent {i}: actions"
            assert rec["messages"] == tr.messages[:, j, i].tolist(), f"episode {e} agent {i}: broadcasts"
            assert rec["rewards"] == tr.rewards[:, j, i].tolist(), f"episode {e} agent {i}: rewards"


class SessionNet(_Net):
    """The world's protocol with one AgentSession per agent, every record encoded and decoded as on the wire (a
    session's broadcast also comes back to itself, as over DDS). `lost` holds (kind, agent) pairs whose records are
    never delivered."""

    def __init__(self, scenario: Scenario, world: WorldProtocol, sessions: list[AgentSession]) -> None:
        super().__init__(world)
        self.scenario = scenario
        self.sessions = sessions
        self.lim = limits(
            scenario.n_agents, scenario.n_tasks, scenario.n_actions, scenario.levels, scenario.horizon, 64
        )
        self.agent_logs: dict[int, list[dict[str, Any]]] = {i: [] for i in range(len(sessions))}
        self.transitions: list[dict[str, Any]] = []
        self.effects: list[SessionEffects] = []
        self.lost: set[tuple[str, int]] = set()

    def from_world(self, eff: WorldEffects) -> None:
        assert not eff.rejects, eff.rejects
        for kind, fields in eff.publish:
            if kind in ("scenario", "step", "observation"):
                run = {} if kind == "scenario" else {"run": self.world.settings.run_id}  # the world node's signer's
                self.queue.append((kind, -1, S.encode(SCHEMA[kind], {**run, **fields})))
        self.world_log += eff.episode_log

    def from_agent(self, i: int, eff: SessionEffects) -> None:
        """Queue what agent i's session publishes and keep its effects and episode log."""
        self.effects.append(eff)
        self.queue.extend((kind, i, text) for kind, text in eff.publish)
        self.agent_logs[i] += eff.episode_log

    def tick(self, now: float) -> None:
        for i, s in enumerate(self.sessions):
            self.from_agent(i, s.tick(now))

    def deliver(self, kind: str, sender: int, rec: Any) -> None:
        rec = S.decode(rec, SCHEMA[kind], self.lim)
        now, world = self.now, self.world
        if kind == "scenario":
            for i, s in enumerate(self.sessions):
                self.from_agent(i, s.on_scenario(rec, now))
        elif kind == "step":
            for i, s in enumerate(self.sessions):
                self.from_agent(i, s.on_step(rec, now))
        elif kind == "observation":
            i = rec["agent"]
            if ("observation", i) not in self.lost:
                self.from_agent(i, self.sessions[i].on_observation(rec, now))
        elif kind == "broadcast":
            for i, s in enumerate(self.sessions):
                self.from_agent(i, s.on_broadcast(rec, now))
        elif kind == "action" and ("action", sender) not in self.lost:
            self.from_world(world.on_action(rec, now))
        elif kind == "ready" and ("ready", sender) not in self.lost:
            self.from_world(world.on_ready(rec, now))
        elif kind == "transition":
            self.transitions.append(rec)


def session_team(
    scenario: Scenario, seed: int, episodes: int, policy: str, batch: int = 1, first: int = 0, **kw: Any
) -> SessionNet:
    """A `SessionNet` of the built-in `policy` (or the trainer's weights), the world's run announced; `kw` are more
    agent settings.

    Returns:
        The team, ready to `run`.
    """
    settings = LockstepSettings(seed=seed, first_episode=first, episodes=episodes, linger=0.0, batch=batch)
    world = world_protocol(scenario, settings)
    sessions = [
        AgentSession(AgentSettings(**{"agent": a.name, "policy": policy, **kw}).session()) for a in scenario.agents
    ]
    net = SessionNet(scenario, world, sessions)
    net.from_world(world.start(0.0))
    return net
