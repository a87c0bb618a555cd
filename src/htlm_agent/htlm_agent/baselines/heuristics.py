"""Baselines behind the team policy interface (`team.Policy`: act(Context) -> (B, N) actions).

- `RandomPolicy`: every agent draws uniformly from its reduced action space Â(a_o).
- `GreedyPolicy`: a hand-written decentralized heuristic over each agent's own belief.
- `AuctionPolicy`: the market-based allocation used on ROS robots (a sequential single-item auction), run by every
  agent on its own belief (docs/model.md, Baselines).
- the HT Dec-POMDP learner (the paper's predecessor): the same deep Q-learner on the scenario in mode "ht" (no idle
  locations, R_LM = 0), see `htlm_agent.experiments.baselines.train_ht`.
- `QmdpPolicy` (htlm_agent.baselines.optimal): every agent on its own belief with the values of the centralized
  optimum (QMDP), where the optimum can be computed.
- `OptimalPolicy` (htlm_agent.baselines.optimal): the centralized, fully observed optimum acting on the true state
  (the floor).

`htlm_agent.experiments.baselines.make_baseline` builds any of them by name.
"""

from __future__ import annotations

import numpy as np

from htlm_agent.mind import knowledge
from htlm_agent.mind.auction import allocate, own_assignment, team_steps, travel_steps
from htlm_agent.mind.context import Context
from htlm_agent.mind.reward import RewardTables, confident_levels
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, IntArray

BASELINES = ("random", "greedy", "auction", "qmdp", "lookahead", "ht", "optimal")
"""Names accepted by `registry.make_baseline` and `htlm evaluate --baseline` (here, in a module without torch, so
that the command line lists them without loading the learner)."""


class RandomPolicy:
    """Every agent picks uniformly from Â(a_o), each with its own generator derived from the seed."""

    def __init__(self, scenario: Scenario, seed: int = 0) -> None:
        """Generators for agents 0..N-1 from the seed's `seeds.random_policy` streams."""
        self.scenario = scenario
        self.rngs = [seeds.random_policy(seed, i) for i in range(scenario.n_agents)]

    def act(self, ctx: Context) -> IntArray:
        """Uniform draws over each agent's own mask."""
        b, n, g = ctx.mask.shape
        out = np.empty((b, n), dtype=np.int64)
        for i, rng in enumerate(self.rngs):
            u = rng.random((b, g))
            out[:, i] = np.where(ctx.mask[:, i], u, -1.0).argmax(axis=1)
        return out


class GreedyPolicy:
    """A decentralized heuristic over each agent's own belief (no learning, no communication beyond the model's).

    Agent i has a home site (i mod S). From its confident levels (the reward's b_th), it works on the first task,
    in the order home site first, a site's tasks in the order of the scenario's kinds, that is believed unfinished,
    that it has capability for, and that can progress (`Model.blocked`). With travel (docs/model.md, Travel) it
    takes the nearest such task instead: the fewest steps until it could work there, from its place and arrival,
    ties in that order. With nothing to do it idles at its current site (HT mode: it stays on its previous task).
    """

    def __init__(self, scenario: Scenario) -> None:
        """Precompute each agent's task preference order."""
        self.scenario = scenario
        self.model = Model.build(scenario)
        self.threshold = RewardTables.build(scenario).threshold
        s = scenario.n_sites
        self.order = []
        for i in range(scenario.n_agents):
            home = i % s
            sites = [home] + [x for x in range(s) if x != home]
            self.order.append([int(j) for site in sites for j in self.model.site_task[site] if j >= 0])
        # (N, p) each task's place in each agent's order
        self.rank = np.zeros((scenario.n_agents, scenario.n_tasks), dtype=np.int64)
        for i, order in enumerate(self.order):
            self.rank[i, order] = np.arange(len(order))

    def act(self, ctx: Context) -> IntArray:
        """One action per agent from its own row of the Context."""
        return self.act_rows(ctx, np.arange(self.scenario.n_agents))

    def act_rows(self, ctx: Context, who: IntArray) -> IntArray:
        """The actions (B, R) of the agents `who` (R,), each from its own row of the Context."""
        lv = confident_levels(ctx.marginals[:, who], self.threshold[who])  # (B, R, p)
        blk = self.model.blocked(lv)
        b, r = lv.shape[:2]
        out = self.model.rest_action(ctx.prev[:, who])
        if self.scenario.travel:  # the nearest: fewest steps until it could work there, then its order
            sc = self.scenario
            reach = travel_steps(sc, ctx.knowledge[:, who], who)  # (B, R, p)
            key = reach * sc.n_tasks + self.rank[who][None]
            ok = (lv > 0) & ~blk & (self.model.agent_caps[who, : sc.n_tasks] > 0)[None]
            key = np.where(ok, key, np.iinfo(np.int64).max)
            best = key.argmin(axis=-1)
            found = ok.any(axis=-1)
            return np.where(found, best, out).astype(np.int64)
        chosen = np.zeros((b, r), dtype=bool)
        for k, i in enumerate(who.tolist()):
            for j in self.order[i]:
                if self.model.agent_caps[i, j] == 0:
                    continue
                ok = (lv[:, k, j] > 0) & ~blk[:, k, j]
                take = ok & ~chosen[:, k]
                out[take, k] = j
                chosen[:, k] |= take
        return out


class AuctionPolicy:
    """A sequential single-item auction (docs/model.md, Baselines), run by every agent on its own belief.

    Agent i runs the whole auction in its head, from its own confident levels l (the reward's b_th; row i of the
    Context) and the capabilities of the whole team (the scenario), and keeps only its own result:

    - a task j is open while l_j > 0, it is not `blocked`, and the capability assigned to it so far does not cover
      l_j: its need n_j = l_j - (sum of the capabilities assigned to j) is > 0 (n_j starts at l_j);
    - every agent k without a task bids on every open task j it has capability for (c_kj > 0) with its useful
      capability min(c_kj, n_j);
    - the highest bid over all (agent, task) pairs wins: k is assigned j and n_j drops by c_kj. Ties go to the larger
      need n_j, then to the larger capability c_kj, then to the lower agent index, then to the lower task index.
      Preferring the larger capability among equal bids makes the winner of a task the same whatever need (up to
      its capability) an agent believes, so teammates whose confident levels differ by a level still agree on who
      takes it;
    - repeated until no agent without a task has a bid; those agents idle at the site of their previous assignment
      (`Model.idle_action`; HT mode: they stay on their previous task, task 0 before any).

    Agents that hold the same belief compute the same allocation, so they never both take what one covers; agents
    whose beliefs differ may. Vectorized over the B episodes and the N auctioneers.
    """

    def __init__(self, scenario: Scenario) -> None:
        """The team's capabilities (N, p) and the confidence thresholds b_th of the agents."""
        self.scenario = scenario
        self.model = Model.build(scenario)
        self.threshold = RewardTables.build(scenario).threshold
        self.caps = self.model.agent_caps[:, : scenario.n_tasks]  # (N, p): c_kj

    def allocate(self, lv: IntArray, present: BoolArray | None = None) -> IntArray:
        """The auction of every auctioneer: (B, M, p) confident levels (auctioneer m's belief) -> (B, M, N) the task
        every agent k gets in auctioneer m's auction, -1 for none; `present` (B, M, N) the teammates each counts on
        (`mind.auction.allocate`)."""
        return allocate(self.model, lv, present)

    def act(self, ctx: Context) -> IntArray:
        """One action per agent: its own assignment in the auction it runs on its own row of the Context."""
        return self.act_rows(ctx, np.arange(self.scenario.n_agents))

    def act_rows(self, ctx: Context, who: IntArray) -> IntArray:
        """The actions (B, R) of the agents `who` (R,): each one's own assignment in the auction it runs on its own
        row of the Context (only the auctions of `who` are run)."""
        sc = self.scenario
        lv = confident_levels(ctx.marginals[:, who], self.threshold[who])  # (B, R, p): row r is agent who[r]'s belief
        b, r, p = lv.shape[0], who.size, sc.n_tasks
        present = knowledge.roster(ctx.knowledge[:, who], sc).reshape(b * r, -1) if sc.roster else None
        if sc.travel:  # bids on the finish time, the drive included: every auctioneer's whole auction
            drive = team_steps(sc, ctx.knowledge[:, who])  # (B, R, N, p)
            pres = None if present is None else present.reshape(b, r, -1)
            plan = allocate(self.model, lv, pres, drive)  # (B, R, N)
            own = plan[:, np.arange(r), who]
            return np.where(own >= 0, own, self.model.rest_action(ctx.prev[:, who])).astype(np.int64)
        # agent who[r]'s result in the auction it runs on its own row (allocate's, without the rounds after it)
        own = own_assignment(self.model, lv.reshape(b * r, p), np.tile(who, b), present).reshape(b, r)
        return np.where(own >= 0, own, self.model.rest_action(ctx.prev[:, who])).astype(np.int64)
