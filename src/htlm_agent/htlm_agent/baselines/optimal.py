"""The centralized, fully observed optimum: value iteration over the joint state of every site with every joint
action (docs/model.md, Reference figures). Joint actions are grouped by the capability vector they produce, since T
depends on the assignment only through it.

The work grows as (tasks + 1)^agents joint actions and levels^tasks states, so `solve` first estimates the size of
the problem from the scenario's sizes alone (`ProblemSize`, `estimate`) and refuses one over `Limits` with
`ProblemTooLarge` before it builds anything.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from htlm_agent.mind.context import Context
from htlm_agent.mind.reward import LOAD_PRICE
from htlm_agent.progress import Progress
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import FloatArray, IntArray

ENUMERATION_RATE = 60_000.0
"""Joint actions per second that `capability_vectors` goes through (measured on the 2-core development machine:
13-18 us per joint action, the default scenario's 3,125 in 0.04-0.06 s)."""

VALUE_ITERATION_RATE = 1.8e9
"""Multiply-adds per second of the value iteration's contractions (measured on the same machine: 1.7-2.4e9 on the
three default teams, 0.1-0.3 s each, and 1.9e9 on 3 sites with 5 agents, 441 capability vectors x 15,625 states,
8 s)."""

MEMORY_FACTOR = 3
"""Arrays of (capability vectors x states) alive at once in a step of the value iteration: a contraction's input
and output and a temporary."""


@dataclass(frozen=True)
class ProblemSize:
    """The sizes of the optimum's problem, all the estimate needs (known from the scenario and the model's small
    tables, before the large ones of the solve are built)."""

    sites: int
    """S."""
    tasks_per_site: int
    """Most tasks at one site (k): a site's joint state has at most L^k values."""
    levels: int
    """L, severity levels of a task."""
    agents: int
    """N."""
    agent_groups: tuple[int, ...]
    """Agents of each distinct capability profile, most first (the heterogeneous team: (1, 1, 1, 1, 1); the
    homogeneous one: (5,)): agents of one profile are interchangeable, which bounds the capability vectors."""
    capability_max: int
    """Cap of a task's joint capability: a capability vector holds p values in 0..capability_max."""
    horizon: int
    """h, steps of the value iteration."""
    total_tasks: int = -1
    """p, when the sites hold different numbers of tasks; -1: S k."""

    @staticmethod
    def of(model: Model) -> ProblemSize:
        """The sizes of a model's scenario."""
        sc = model.scenario
        profiles: dict[tuple[int, ...], int] = {}
        for row in model.agent_caps[:, : sc.n_tasks].tolist():  # capability on every task
            profiles[tuple(row)] = profiles.get(tuple(row), 0) + 1
        return ProblemSize(
            sites=sc.n_sites,
            tasks_per_site=max(len(site.tasks) for site in sc.sites),
            total_tasks=sc.n_tasks,
            levels=sc.levels,
            agents=sc.n_agents,
            agent_groups=tuple(sorted(profiles.values(), reverse=True)),
            capability_max=sc.capability_max,
            horizon=sc.horizon,
        )

    @property
    def tasks(self) -> int:
        """p."""
        return self.sites * self.tasks_per_site if self.total_tasks < 0 else self.total_tasks

    def describe(self) -> str:
        """One line: '2 sites x 2 tasks, 5 levels, 5 agents, horizon 30' (sites of different sizes: '3 sites, 6
        tasks (at most 3 at a site), ...')."""
        tasks = (
            f"{self.sites} sites x {self.tasks_per_site} tasks"
            if self.tasks == self.sites * self.tasks_per_site
            else f"{self.sites} sites, {self.tasks} tasks (at most {self.tasks_per_site} at a site)"
        )
        return f"{tasks}, {self.levels} levels, {self.agents} agents, horizon {self.horizon}"


@dataclass(frozen=True)
class Estimate:
    """What solving a problem costs, from its sizes alone (`estimate`)."""

    states: int
    """Joint states, L^p."""
    joint_actions: int
    """Joint assignments enumerated to find the capability vectors: (p + 1)^N (every idle location, like no task,
    brings no capability: one choice)."""
    capability_vectors: int
    """At most this many distinct capability vectors (the actions of the value iteration): (capability_max + 1)^p
    values, and for every group of n interchangeable agents (n + p choose p) ways to spread them over the p tasks
    and no task. The agents usually produce fewer: the default teams 339, 506 and 116 of at most 1,296, 1,125 and
    126."""
    evaluations: int
    """State-action evaluations (Q-values) over the horizon: h x states x capability vectors."""
    multiply_adds: int
    """Multiply-adds of those evaluations: each contracts every site's L^k next states, S L^k."""
    memory_bytes: int
    """Peak memory of the tables the solve builds (float64 values, int64 policy)."""
    seconds: float
    """Estimated time on the development machine (ENUMERATION_RATE, VALUE_ITERATION_RATE)."""

    def to_dict(self) -> dict[str, int | float]:
        """Plain data (the JSON of `htlm optimal`)."""
        return {
            "states": self.states,
            "joint_actions": self.joint_actions,
            "capability_vectors_max": self.capability_vectors,
            "evaluations": self.evaluations,
            "multiply_adds": self.multiply_adds,
            "memory_bytes": self.memory_bytes,
            "seconds": round(self.seconds, 3),
        }


@dataclass(frozen=True)
class Limits:
    """The largest problem `solve` takes on."""

    seconds: float = 600.0
    """Estimated time: 10 minutes, some 3,000 times the default scenario's (0.1-0.3 s)."""
    memory_bytes: int = 4 * 2**30
    """Estimated memory: 4 GiB, a sixth of the development machine's, which other jobs share."""


DEFAULT_LIMITS = Limits()
"""The limits of `solve`, `htlm optimal` and the optimal baseline unless told otherwise."""


TRAVEL_UNSOLVED = (
    "the optimum is not computed for an operation with travel: its states would need every agent's place and "
    "arrival besides the levels (docs/model.md, Travel)"
)


class ProblemTooLarge(ValueError):
    """A problem whose estimate exceeds the limits; raised before anything is built."""

    def __init__(self, size: ProblemSize, est: Estimate, limits: Limits, reason: str = "") -> None:
        """Keep the numbers and say them (or `reason`, when it is not the size that rules the problem out)."""
        self.size, self.estimate, self.limits = size, est, limits
        if reason:
            super().__init__(reason)
            return
        over = []
        if est.seconds > limits.seconds:
            over.append(f"time {_duration(est.seconds)} > {_duration(limits.seconds)}")
        if est.memory_bytes > limits.memory_bytes:
            over.append(f"memory {_gib(est.memory_bytes)} > {_gib(limits.memory_bytes)}")
        super().__init__(
            f"the optimum of this scenario is too large to compute here: {size.describe()}: "
            f"{_count(est.states)} states x at most {_count(est.capability_vectors)} capability vectors "
            f"(from {_count(est.joint_actions)} joint actions) = {_count(est.evaluations)} state-action evaluations; "
            f"estimated {_duration(est.seconds)} and {_gib(est.memory_bytes)}, over the limits of "
            f"{_duration(limits.seconds)} and {_gib(limits.memory_bytes)} ({'; '.join(over)})"
        )


def estimate(size: ProblemSize) -> Estimate:
    """The states, actions, work, memory and time of solving a problem of these sizes, without building it.

    The capability vectors are bounded from above (their exact number needs the enumeration), so the work, memory
    and time are upper bounds too: the default scenario is estimated at 0.7 s (0.2 s measured); 3 sites with 7
    interchangeable agents at 47 s and 0.63 GiB (39 s and 0.56 GiB peak measured, 1,443 capability vectors of at
    most 1,716).
    """
    p, L, h = size.tasks, size.levels, size.horizon
    states = L**p
    joint = (p + 1) ** size.agents
    caps = min(math.prod(math.comb(n + p, p) for n in size.agent_groups), (size.capability_max + 1) ** p)
    evaluations = h * states * caps
    madds = evaluations * size.sites * L**size.tasks_per_site
    memory = 8 * (
        MEMORY_FACTOR * caps * states  # the expected next values of every capability vector
        + 2 * (h + 1) * states  # values and best
        + size.sites * caps * L ** (2 * size.tasks_per_site)  # every site's transition matrix per capability vector
        + caps * (p + size.agents)  # the capability vectors and their joint actions
    )
    return Estimate(
        states=states,
        joint_actions=joint,
        capability_vectors=caps,
        evaluations=evaluations,
        multiply_adds=madds,
        memory_bytes=memory,
        seconds=_ratio(joint, ENUMERATION_RATE) + _ratio(madds, VALUE_ITERATION_RATE),
    )


def check(model: Model, limits: Limits = DEFAULT_LIMITS) -> Estimate:
    """The estimate of the problem of a model's scenario.

    Raises:
        ProblemTooLarge: when it exceeds `limits` (with the sizes, the estimate and the limits).
    """
    size = ProblemSize.of(model)
    est = estimate(size)
    if model.scenario.travel:
        raise ProblemTooLarge(size, est, limits, TRAVEL_UNSOLVED)
    if est.seconds > limits.seconds or est.memory_bytes > limits.memory_bytes:
        raise ProblemTooLarge(size, est, limits)
    return est


def _ratio(n: int, rate: float) -> float:
    try:
        return n / rate
    except OverflowError:  # more than a float holds: no machine does it
        return float("inf")


def _count(n: int) -> str:
    return f"{n:,}" if n < 10**12 else f"about 10^{len(str(n)) - 1}"


def _duration(seconds: float) -> str:
    if seconds == float("inf") or seconds > 1e9:
        return "over 30 years"
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.0f} h"


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n < 2**70 else f"about 2^{n.bit_length()} bytes"


@dataclass(frozen=True)
class OptimalSolution:
    """Finite-horizon value iteration result."""

    scenario: Scenario
    values: FloatArray  # (h+1, L^p) expected completion step with k steps left (capped at h), by state index
    best: IntArray  # (h+1, L^p) index of the best capability vector with k steps left
    cap_vectors: IntArray  # (C, p) distinct capability vectors
    joint_actions: IntArray  # (C, N) a cheapest joint action producing each capability vector

    @property
    def expected_completion(self) -> float:
        """Expected completion step from the initial state (failures count as h)."""
        return float(self.values[self.scenario.horizon, state_index(self.scenario, self.scenario.initial_levels)])


def state_index(sc: Scenario, levels: tuple[int, ...] | IntArray) -> int:
    """Index of a joint state: the levels of the tasks in task order (site by site), base L."""
    idx = 0
    for lv in levels:
        idx = idx * sc.levels + int(lv)
    return idx


def capability_vectors(model: Model, progress: bool = False) -> tuple[IntArray, IntArray]:
    """Distinct capped capability vectors over all joint task assignments, each with a joint action of least
    total committed capability that produces it (idle agents where they add nothing). With `progress`, a progress
    line (rate, ETA) on stderr."""
    sc = model.scenario
    p = sc.n_tasks
    choices = list(range(p)) + [-1]  # -1: contributes nothing (idle)
    best: dict[tuple[int, ...], tuple[float, tuple[int, ...]]] = {}
    total = len(choices) ** sc.n_agents
    bar = Progress(total, unit="joint actions", enabled=progress)
    for n, joint in enumerate(itertools.product(choices, repeat=sc.n_agents)):
        if n % 8192 == 0:
            bar.update(n, phase="capability vectors", found=len(best))
        arr = np.array(joint, dtype=np.int64)
        caps = tuple(int(c) for c in model.joint_capability(arr[None])[0])
        cost = sum(model.agent_caps[i, a] for i, a in enumerate(joint) if a >= 0)
        if caps not in best or cost < best[caps][0]:
            best[caps] = (cost, joint)
    bar.update(total, phase="capability vectors", found=len(best))
    bar.close()
    keys = sorted(best)
    return np.array(keys, dtype=np.int64), np.array([best[k][1] for k in keys], dtype=np.int64)


def solve(sc: Scenario, limits: Limits = DEFAULT_LIMITS, progress: bool = False) -> OptimalSolution:
    """Finite-horizon value iteration for the expected completion step (docs/model.md, Reference figures).

    V_0(s) = 0; V_k(s) = 0 if s is complete, else 1 + min_c sum_s' T_c(s, s') V_{k-1}(s'). V_h(s0) is the
    expected completion step with never-completed episodes counted as h. With a kind's hazard (level 0 not
    absorbing) it is the expected first step with every level 0, a lower bound of the completion step (which then
    also needs every level to stay 0): still the floor (docs/model.md, Reference figures).

    Args:
        sc: the scenario.
        limits: the largest problem to take on (checked on the estimate, before anything is built).
        progress: show progress lines (rate, ETA) on stderr.

    Raises:
        ProblemTooLarge: the estimate exceeds `limits`.
    """
    model = Model.build(sc)  # small tables: T, O, I and the agents' capabilities
    check(model, limits)
    L, S = sc.levels, sc.n_sites
    caps, joints = capability_vectors(model, progress)
    mats = [site_matrices(model, caps, s) for s in range(S)]  # each (C, L^m, L^m), m the site's tasks
    n_states = L**sc.n_tasks
    complete = np.zeros(n_states, dtype=bool)
    complete[0] = True
    values = np.zeros((sc.horizon + 1, n_states))
    best = np.zeros((sc.horizon + 1, n_states), dtype=np.int64)
    bar = Progress(sc.horizon, unit="steps", enabled=progress)
    for k in range(1, sc.horizon + 1):
        q = _expected_next(values[k - 1], mats)
        best[k] = q.argmin(axis=0)
        values[k] = np.where(complete, 0.0, 1.0 + q.min(axis=0))
        bar.update(k, phase="value iteration", capability_vectors=caps.shape[0], states=n_states)
    bar.close()
    return OptimalSolution(sc, values, best, caps, joints)


def site_matrices(model: Model, caps: IntArray, site: int) -> FloatArray:
    """Every capability vector's transition matrix of one site's joint state: (C, L^m, L^m), entry [c, x, x'] the
    product over the site's tasks, in task order, of T_k[c_j, g, x_j, x'_j] (g the current level of the task it
    depends on, 0 when none)."""
    L = model.scenario.levels
    tasks = [int(j) for j in model.site_task[site] if j >= 0]
    m = len(tasks)
    idx = np.indices((L,) * m).reshape(m, -1)  # every joint state's level of each of the site's tasks
    out = np.ones((caps.shape[0], L**m, L**m))
    for q, j in enumerate(tasks):
        table = model.kind_tables[model.task_kind[j]]  # (C+1, G, L, L)
        gate = int(model.task_gate[j])
        g = idx[tasks.index(gate)] if gate in tasks else np.zeros(L**m, dtype=np.int64)
        c = caps[:, j]
        out *= table[c[:, None, None], g[None, :, None], idx[q][None, :, None], idx[q][None, None, :]]
    return out


def _expected_next(values: FloatArray, mats: list[FloatArray]) -> FloatArray:
    """The expected value of the next state (C, L^p) under every capability vector, from the values (L^p,) and every
    site's matrices (`site_matrices`): each site's axis contracted with its matrix."""
    v = values.reshape(tuple(m.shape[1] for m in mats))
    ev = np.broadcast_to(v, (mats[0].shape[0],) + v.shape)
    for s, mat in enumerate(mats):
        ev = _contract(ev, mat, s + 1)
    return ev.reshape(mats[0].shape[0], -1)


def _contract(ev: FloatArray, mat: FloatArray, axis: int) -> FloatArray:
    """out[c, ..., i, ...] = sum_j mat[c, i, j] ev[c, ..., j, ...] along `axis`."""
    moved = np.moveaxis(ev, axis, -1)  # (C, ..., j)
    out = np.einsum("c...j,cij->c...i", moved, mat)
    return np.moveaxis(out, -1, axis)


class OptimalPolicy:
    """Acts on the true state with the optimal joint action (the centralized floor, not a decentralized agent)."""

    def __init__(self, sc: Scenario) -> None:
        """Solve the scenario once."""
        self.sol = solve(sc)
        self.sc = sc
        self.model = Model.build(sc)
        self.weights = np.array([sc.levels ** (sc.n_tasks - 1 - j) for j in range(sc.n_tasks)], dtype=np.int64)

    def act(self, ctx: Context) -> IntArray:
        """Joint action for every episode from its true levels; idle agents idle at their current site."""
        sc = self.sc
        k = max(sc.horizon - ctx.t, 1)
        idx = ctx.true_levels @ self.weights
        joint = self.sol.joint_actions[self.sol.best[k, idx]]  # (B, N), -1 where idle
        if sc.n_idle:
            done = (ctx.true_levels == 0).all(axis=1)[:, None]
            joint = np.where((joint < 0) | done, self.model.idle_action(ctx.prev), joint)
        return np.asarray(joint, dtype=np.int64)


def action_values(sol: OptimalSolution, steps_left: int) -> FloatArray:
    """Q of the optimum with `steps_left` steps to go: (C, L^p), entry [c, s] the expected completion step from
    state s when the team applies capability vector c now and acts optimally after (1 + the expected value of the
    next state; 0 for the complete state)."""
    sc = sol.scenario
    model = Model.build(sc)
    mats = [site_matrices(model, sol.cap_vectors, s) for s in range(sc.n_sites)]
    q = 1.0 + _expected_next(sol.values[steps_left - 1], mats)
    q[:, 0] = 0.0  # every task at level 0: complete
    return np.ascontiguousarray(q)


QMDP_LOAD_COST = LOAD_PRICE
"""Steps of expected completion that one unit of committed capability is worth to `QmdpPolicy` (`LOAD_PRICE`)."""


class QmdpPolicy:
    """Every agent on its own belief alone: the capability vector that minimizes the optimum's expected completion
    step averaged over its belief, then its own part of the joint action that makes it (QMDP, Littman, Cassandra and
    Kaelbling 1995; docs/model.md, Baselines). The belief is the product of the agent's task marginals, the values
    those of the centralized optimum with the whole horizon to go (the knowledge state holds no step count); an agent
    whose part brings no capability idles at the site of its previous assignment. Decentralized, but only where the
    optimum can be computed (`solve` refuses larger problems)."""

    def __init__(self, sc: Scenario) -> None:
        """Solve the scenario and keep the optimum's action values (C, L^p)."""
        self.sc = sc
        self.model = Model.build(sc)
        self.sol = solve(sc)
        caps = self.model.agent_caps[:, : sc.n_tasks]
        joint = self.sol.joint_actions  # (C, N), -1 where an agent brings nothing
        n = np.arange(sc.n_agents)
        brought = np.where(joint >= 0, caps[n[None, :], np.maximum(joint, 0)], 0)  # (C, N) each agent's capability
        self.parts = np.where(brought > 0, joint, -1)  # (C, N)
        committed = brought.sum(axis=1)  # (C,)
        self.q_t = (action_values(self.sol, sc.horizon) + QMDP_LOAD_COST * committed[:, None]).T.copy()  # (L^p, C)

    def act(self, ctx: Context) -> IntArray:
        """One action per agent, each from its own row's marginals."""
        return self.act_rows(ctx, np.arange(self.sc.n_agents))

    def act_rows(self, ctx: Context, who: IntArray) -> IntArray:
        """The actions (B, R) of the agents `who` (R,), each from its own row's marginals."""
        sc = self.sc
        marg = ctx.marginals[:, who]  # (B, R, p, L)
        b, r = marg.shape[:2]
        joint = np.ones((b, r, 1))
        for j in range(sc.n_tasks):  # the product belief over every joint state, in `state_index` order
            joint = (joint[..., :, None] * marg[:, :, j, None, :]).reshape(b, r, -1)
        best = (joint @ self.q_t).argmin(axis=2)  # (B, R): each agent's capability vector
        own = self.parts[best, who[None, :]]
        return np.where(own >= 0, own, self.model.rest_action(ctx.prev[:, who])).astype(np.int64)
