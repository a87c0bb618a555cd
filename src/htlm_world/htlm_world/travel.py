"""Travel: agents that take steps to drive between sites (docs/model.md, Travel), the one definition used by the
simulator's runtimes, the world node, every agent's mind, the baselines and the learners.

An operation with a step length (`Scenario.step_seconds`) and speeds turns distances into drive steps: agent i
covers `speed_i * step_seconds` metres a step, in a straight line from where it is to the position of its goal's
site. Every agent starts at the site of the initial assignment. Each step, every agent's assignment names a site
(a task's or an idle location's): an agent whose goal changes starts a drive there from where it is (a turn, when it
was still driving); an agent already at its goal's site works on its task (or rests) in that step; any other drives
the step and works on nothing, observes nothing. Arrival is at the end of the step that covers the last metre, so a
drive of d metres takes ceil(d / (speed * step_seconds)) steps. Without a step length nothing moves and nothing
takes a step: the paper's model exactly.

Everything here is a deterministic function of the joint assignments, so a world, an agent's mind and a teammate's
mind that hear the same assignments hold the same state, bit for bit.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray

ARRIVED = 1e-9
"""Metres within which an agent is at its goal's site (float rounding of a drive's last step)."""


@dataclass(frozen=True)
class Travel:
    """What a scenario's travel is, computed once: the sites' positions, every agent's metres per step and the drive
    steps between sites."""

    positions: FloatArray  # (S, 2) the sites' positions, metres
    reach: FloatArray  # (N,) metres each agent covers in a step
    distance: FloatArray  # (S, S) straight-line metres between sites
    steps: IntArray  # (N, S, S) steps agent i drives from site a to site b (0 on the diagonal)
    step_seconds: float
    home: int  # the site every agent starts at (that of the initial assignment)

    @staticmethod
    def of(sc: Scenario) -> Travel:
        """The travel of scenario `sc` (call only when `sc.travel`), computed once per scenario."""
        return _travel_of(sc)

    @staticmethod
    def compute(sc: Scenario) -> Travel:
        """The travel of scenario `sc`, worked out (`of` keeps it)."""
        assert sc.travel, "the scenario has no step length: no travel"
        pos = np.asarray(sc.site_positions, dtype=np.float64).reshape(sc.n_sites, 2)
        dist = np.hypot(pos[:, None, 0] - pos[None, :, 0], pos[:, None, 1] - pos[None, :, 1])
        reach = np.array([sc.agent_speed(i) * sc.step_seconds for i in range(sc.n_agents)])
        model = Model.build(sc)
        start = sc.start_assignment
        return Travel(
            positions=pos,
            reach=reach,
            distance=dist,
            steps=drive_steps(dist[None], reach[:, None, None]),
            step_seconds=sc.step_seconds,
            home=int(model.action_site[start]) if start >= 0 else 0,
        )


@functools.lru_cache(maxsize=16)
def _travel_of(sc: Scenario) -> Travel:
    return Travel.compute(sc)


def drive_steps(metres: FloatArray, reach: FloatArray) -> IntArray:
    """Steps a drive of `metres` takes at `reach` metres a step (broadcast together): ceil(metres / reach), 0 for
    no distance."""
    out: IntArray = np.ceil(np.maximum(metres - ARRIVED, 0.0) / reach).astype(np.int64)
    return out


class TravelState:
    """Where every agent of B episodes is: its position, the site it is at or drives to, and how far it drove."""

    def __init__(self, sc: Scenario, batch: int) -> None:
        """B episodes of scenario `sc` (with travel), every agent at its start site."""
        self.travel = Travel.of(sc)
        self.model = Model.build(sc)
        self.n = sc.n_agents
        self.batch = batch
        self.reset()

    def reset(self) -> None:
        """Every agent at the start site, nothing driven."""
        tr, b, n = self.travel, self.batch, self.n
        self.xy: FloatArray = np.tile(tr.positions[tr.home], (b, n, 1))  # (B, N, 2)
        self.goal: IntArray = np.full((b, n), tr.home, dtype=np.int64)  # (B, N) the site it is at or drives to
        self.left: FloatArray = np.zeros((b, n))  # (B, N) metres to the goal
        self.driven: FloatArray = np.zeros((b, n))  # (B, N) metres driven in the episode
        self.moves: IntArray = np.zeros((b, n), dtype=np.int64)  # (B, N) drives started in the episode

    def eta(self) -> IntArray:
        """(B, N) steps until each agent is at its goal's site (0: it is there)."""
        return drive_steps(self.left, self.travel.reach[None, :])

    def arrives(self, actions: IntArray) -> BoolArray:
        """(B, N) whether each agent would be at its goal's site at the start of a step with the joint assignment
        `actions` (B, N) (what `step` returns, without changing anything)."""
        a = np.asarray(actions, dtype=np.int64)
        site = np.where(a >= 0, self.model.action_site[np.maximum(a, 0)], self.goal)
        delta = self.travel.positions[site] - self.xy
        out: BoolArray = np.hypot(delta[..., 0], delta[..., 1]) <= ARRIVED
        return out

    def place(self, agent: int, actions: IntArray, xy: tuple[float, float] | None) -> None:
        """Put agent `agent` where its robot is (a deployed team): at (x, y), or at the site of its `actions` (B,)
        when its robot is there (None); its goal becomes that site."""
        a = np.asarray(actions, dtype=np.int64)
        site = np.where(a >= 0, self.model.action_site[np.maximum(a, 0)], self.goal[:, agent])
        self.goal[:, agent] = site
        self.xy[:, agent] = self.travel.positions[site] if xy is None else np.asarray(xy, dtype=np.float64)

    def step(self, actions: IntArray) -> BoolArray:
        """Apply one step's joint assignment (B, N) (a negative action keeps the goal): goals change, drives start or
        turn, every agent not at its goal drives for the step. Returns (B, N) whether each agent is at its goal's
        site at the start of the step, i.e. works on its task (or rests) in it."""
        a = np.asarray(actions, dtype=np.int64)
        site = np.where(a >= 0, self.model.action_site[np.maximum(a, 0)], self.goal)
        new = site != self.goal
        self.moves += new
        self.goal = site
        target = self.travel.positions[site]  # (B, N, 2)
        delta = target - self.xy
        self.left = np.hypot(delta[..., 0], delta[..., 1])
        there = self.left <= ARRIVED
        moved = np.minimum(self.left, self.travel.reach[None, :])
        frac = np.where(there, 0.0, moved / np.where(there, 1.0, self.left))
        self.xy = np.where((moved >= self.left)[..., None], target, self.xy + delta * frac[..., None])
        self.left = np.where(there, 0.0, self.left - moved)
        self.left[self.left <= ARRIVED] = 0.0
        self.driven += np.where(there, 0.0, moved)
        return there


def working_actions(actions: IntArray, there: BoolArray) -> IntArray:
    """The joint assignment as the model applies it: an agent on its way works on nothing and observes nothing (-1)."""
    out: IntArray = np.where(there, actions, -1).astype(np.int64)
    return out


def arrival_steps(sc: Scenario, place: IntArray, eta: IntArray) -> IntArray:
    """Steps until each agent could work at every site, as a teammate reckons it from the agent's broadcast place
    and arrival: (..., N) places and etas -> (..., N, S): the eta at its place, the eta plus the drive from there
    elsewhere."""
    tr = Travel.of(sc)
    n = sc.n_agents
    pl = np.asarray(place, dtype=np.int64)
    rows = tr.steps[np.arange(n), pl]  # (..., N, S)
    out: IntArray = (np.asarray(eta, dtype=np.int64)[..., None] + rows).astype(np.int64)
    return out
