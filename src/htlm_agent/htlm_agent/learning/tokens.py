"""The token Q-network (`learner: tokens`, docs/model.md, The token learner): one network shared across the actions,
scoring each action of Ḡ from that action's own features.

The knowledge state is the paper's, K = {b, a_o} (per-task marginals and the one-hot previous assignment), and so
are the actions. What differs is how K becomes Q-values. The network first turns K into one *token* per element of
Ḡ, a vector of features of that task or idle location seen by this agent (`TokenSpec.features`): the task's belief
(its marginals, its confident level at the agent's b_th, the believed chance that the task it depends on blocks it),
the agent's capability for it and the progress that capability is expected to make (from the kind's drop table),
what the rest of the team could bring (the capability of the teammates, and of those who would win it before this
agent in an auction), the kind's growth and hazard, the travel from a_o (same site or not, and the agent's own
reassignment cost), and for an idle location the believed chance that its site is done and the agent's idle bonus.
Every number comes from the scenario and the agent's own belief: nothing names a kind, a site or a team size.

The tokens go through one small MLP (the same weights for every token), are pooled over the task tokens (mean and
max: a DeepSets context of the whole operation), and a head scores each token from its embedding and the context.
The network is therefore permutation-equivariant over tasks and sites, and the same weights serve any number of
tasks, sites, kinds and agents: a trained team can act on a changed team or operation without retraining.

Parameters are stacked as rows of one flat (R, P) tensor, R = 1 when the agents share one network (their
capabilities and preferences are inputs) or R = N when each agent keeps its own; gradients come from autograd and
the optimizer is torch.optim's. In deployment every agent process holds its own copy and acts on its own belief.
Parameters are stored in (W, b) pairs like the paper's MLP, so checkpoints and the weights records carry them
unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray

from htlm_agent.mind.auction import allocate, own_assignment, team_steps
from htlm_world.model import Model, p_drop_table
from htlm_world.scenario import Scenario
from htlm_world.types import IntArray

F32 = NDArray[np.float32]

GLOBAL_FEATURES = 4
"""Features every token carries about the whole operation (see `TokenSpec.features`)."""


def unflatten(row: torch.Tensor, offsets: Sequence[int], shapes: Sequence[tuple[int, ...]]) -> list[F32]:
    """Copies of the parameters held in one row of a flat parameter tensor, as float32 arrays of `shapes`."""
    flat = row.detach().numpy()
    return [flat[offsets[j] : offsets[j + 1]].reshape(s).astype(np.float32, copy=True) for j, s in enumerate(shapes)]


def flatten(params: Sequence[NDArray[np.float32]], size: int) -> torch.Tensor:
    """Parameters as one row of `size` numbers (the inverse of `unflatten`)."""
    row = np.concatenate([np.asarray(p, dtype=np.float32).reshape(-1) for p in params])
    assert row.shape == (size,), (row.shape, size)
    return torch.from_numpy(row)


TRAVEL_FEATURES = 2
"""Features a token carries with travel (`Scenario.travel`): the steps until the agent could work there, and until
the nearest teammate able to work on it could (see `TokenSpec.features`)."""

REACH_SCALE = 10.0
"""Steps of travel that make a reach feature 1."""


def token_features(levels: int, travel: bool = False) -> int:
    """F, the size of a token for a scenario with `levels` levels: the marginals and the named features below (and
    with travel its `TRAVEL_FEATURES`)."""
    return levels + 20 + GLOBAL_FEATURES + (TRAVEL_FEATURES if travel else 0)


def token_shapes(levels: int, hidden: Sequence[int], travel: bool = False) -> list[tuple[int, ...]]:
    """Shapes of one network's parameters, in (W, b) pairs: the token encoder F -> H1 -> H1, the head
    (3·H1 -> H2 -> 1)."""
    f = token_features(levels, travel)
    h1 = int(hidden[0])
    h2 = int(hidden[1]) if len(hidden) > 1 else h1
    return [(f, h1), (h1,), (h1, h1), (h1,), (3 * h1, h2), (h2,), (h2, 1), (1,)]


def init_token_params(levels: int, hidden: Sequence[int], seed: int, travel: bool = False) -> list[torch.Tensor]:
    """Fresh parameters (uniform ±1/√fan_in, as torch.nn.Linear) from a generator seeded with `seed`."""
    g = torch.Generator().manual_seed(seed)
    out: list[torch.Tensor] = []
    for w_shape, b_shape in zip(*[iter(token_shapes(levels, hidden, travel))] * 2, strict=True):
        bound = 1.0 / math.sqrt(w_shape[0])
        out.append((torch.rand(w_shape, generator=g) * 2.0 - 1.0) * bound)
        out.append((torch.rand(b_shape, generator=g) * 2.0 - 1.0) * bound)
    return out


class TokenSpec:
    """What the tokens of a set of agents need of the scenario, as tensors made once: the tasks' kinds, sites and
    dependencies, the kinds' drop tables, growth and hazard, and each agent's capabilities and reward parameters."""

    def __init__(self, scenario: Scenario, agents: Sequence[int]) -> None:
        """For the agents `agents` (indices into the scenario's team), in that order."""
        sc = scenario
        model = Model.build(sc)
        self.scenario = sc
        self.agents = [int(a) for a in agents]
        p, q, L, cmax = sc.n_tasks, sc.n_idle, sc.levels, sc.capability_max
        self.p, self.q, self.levels = p, q, L
        self.n_actions = sc.n_actions
        idx = np.array(self.agents, dtype=np.int64)
        caps = model.agent_caps[:, :p].astype(np.float64)  # (N_team, p)
        own = caps[idx]  # (A, p)
        n_team = sc.n_agents
        order = np.arange(n_team)
        # capability of the teammates who would win task j before agent i in an auction: larger capability, or
        # equal capability and a lower index (AuctionPolicy's tie-break)
        ahead = (caps[None, :, :] > own[:, None, :]) | (
            (caps[None, :, :] == own[:, None, :]) & (order[None, :, None] < idx[:, None, None])
        )
        ahead &= order[None, :, None] != idx[:, None, None]
        others = caps.sum(axis=0)[None, :] - own
        self.own_cap = torch.tensor(own / cmax, dtype=torch.float32)  # (A, p)
        self.others_cap = torch.tensor(others / cmax, dtype=torch.float32)
        self.ahead_cap = torch.tensor((caps[None] * ahead).sum(axis=1) / cmax, dtype=torch.float32)
        self.team_caps = torch.tensor(caps / cmax, dtype=torch.float32)  # (N_team, p)
        self.ahead_caps = torch.tensor(caps[None] * ahead / cmax, dtype=torch.float32)  # (A, N_team, p)
        self.roster = sc.roster
        self.teammates = sc.teammates
        self.travel = sc.travel
        self.n_team = sc.n_agents
        self.mates_from = p * L + sc.n_actions + (sc.n_agents if sc.roster else 0)
        self.own_total = torch.tensor(own.sum(axis=1) / (cmax * max(1, sc.n_kinds)), dtype=torch.float32)  # (A,)
        rewards = [sc.agent_reward(i) for i in self.agents]
        self.threshold = torch.tensor([r.belief_threshold for r in rewards], dtype=torch.float32)  # (A,)
        self.reassign = torch.tensor([r.reassign_cost / 4.0 for r in rewards], dtype=torch.float32)
        self.idle_bonus = torch.tensor([r.idle_bonus * r.idle_incentive for r in rewards], dtype=torch.float32)
        margin = np.array([r.excess_margin for r in rewards], dtype=np.int64)
        self.excess_from = torch.tensor(own - margin[:, None], dtype=torch.float32)  # penalised when conf <= this
        self.excess_on = torch.tensor(own >= 2, dtype=torch.float32)
        kinds = sc.kinds
        drop = np.zeros((p, cmax + 1, L))  # probability of progress for capability c at level l (any drop)
        for j, (_, k) in enumerate(sc.tasks):
            drop[j] = p_drop_table(sc, kinds[k].p_drop or None)  # (C+1, L)
        # (A, p, L) the chance of progress of each agent alone on each task, by level
        self.own_drop = torch.tensor(drop[np.arange(p)[None, :], own.astype(np.int64)], dtype=torch.float32)
        self.growth = torch.tensor([kinds[k].growth for _, k in sc.tasks], dtype=torch.float32)
        self.hazard = torch.tensor([kinds[k].hazard for _, k in sc.tasks], dtype=torch.float32)
        gate = model.task_gate  # p: none
        self.has_gate = torch.tensor(gate < p, dtype=torch.float32)
        self.gate = torch.tensor(np.where(gate < p, gate, 0), dtype=torch.int64)
        block = model.task_block
        above = np.arange(L)[None, :] > np.minimum(block, L)[:, None]  # (p, L): levels of the gate that block
        self.block_levels = torch.tensor(above, dtype=torch.float32)
        self.task_site = torch.tensor(model.task_site, dtype=torch.int64)
        self.action_site = torch.tensor(model.action_site, dtype=torch.int64)  # (|Ḡ|,)
        site_of = np.zeros((sc.n_sites, p), dtype=np.float32)  # (S, p) 1 where task j is at site s
        site_of[model.task_site, np.arange(p)] = 1.0
        self.site_of = torch.tensor(site_of)
        self.site_count = torch.tensor(site_of.sum(axis=1))
        self.model = model

    def advice(
        self, conf: torch.Tensor, prev_site: torch.Tensor, roster: torch.Tensor | None, drive: IntArray | None = None
    ) -> torch.Tensor:
        """(A, M, |Ḡ|) one-hot of the auction's choice for each agent, run on its own confident levels (A, M, p)
        and roster (A, M, N) (`mind.auction.allocate`; with travel, `drive` (A, M, N, p): the finish-time auction):
        its task, or the idle location at the site of a_o when it gets none."""
        a_n, m, p = conf.shape
        lv = conf.to(torch.int64).numpy().reshape(a_n * m, p)
        present = None if roster is None else roster.numpy().reshape(a_n * m, -1) > 0.5
        who = np.repeat(np.array(self.agents, dtype=np.int64), m)
        if drive is not None:
            pres = None if present is None else present[:, None, :]
            plan = allocate(self.model, lv[:, None, :], pres, drive.reshape(a_n * m, 1, *drive.shape[2:]))[:, 0]
            mine = plan[np.arange(a_n * m), who]
        else:
            mine = own_assignment(self.model, lv, who, present)
        own = torch.from_numpy(mine.reshape(a_n, m))
        site = prev_site.round().to(torch.int64).clamp(0, max(self.q - 1, 0))
        choice = torch.where(own >= 0, own, self.p + site) if self.q else own.clamp(min=0)
        return torch.nn.functional.one_hot(choice, self.n_actions).to(torch.float32)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Tokens (A, M, |Ḡ|, F) of knowledge states (A, M, K), row a of agent `agents[a]`.

        Task token j: marginals (L), P(level 0), confident level, expected level, P(blocked), own capability,
        useful capability min(c, confident level), expected progress with the own capability, the teammates'
        capability (with `Scenario.roster`, of those heard from at the last step), the capability of those ahead in
        an auction, growth, hazard, at the site of a_o, is a_o, reassignment cost of going there, 1 (a task), the
        excess penalty it would earn, 0, and whether the auction run on the agent's own belief (and roster) gives it
        this task (`advice`), then (with `Scenario.teammates`, else zeros) the capability the teammates brought to
        it at the last step and the part of its confident level that capability leaves uncovered. Idle token s:
        zeros for the task-only entries, P(every task of s done) in place of P(level 0), the site's largest confident
        level, its mean expected level, at the site of a_o, is a_o, the reassignment cost, 0 (idle), the idle bonus
        times the chance that s is done, 1, whether the auction leaves the agent idle there, tanh of the number of
        teammates that idled there at the last step, 0. Every token ends with the operation's features: the mean
        P(level 0) over tasks, the share of tasks confidently done, the agent's total capability, whether a_o is an
        idle location.
        """
        p, q, L = self.p, self.q, self.levels
        a_n, m = x.shape[0], x.shape[1]
        marg = x[..., : p * L].reshape(a_n, m, p, L).clamp(min=0.0)
        prev = x[..., p * L : p * L + self.n_actions]  # (A, M, |Ḡ|) one-hot a_o
        lv = torch.arange(L, dtype=torch.float32)
        cdf = marg.cumsum(-1)
        conf = (cdf < (self.threshold[:, None, None, None] - 1e-6)).sum(-1).clamp(max=L - 1).to(torch.float32)
        p0 = marg[..., 0]
        expect = (marg * lv).sum(-1)
        gate_marg = marg[:, :, self.gate]  # (A, M, p, L)
        blocked = (gate_marg * self.block_levels).sum(-1) * self.has_gate
        own = self.own_cap[:, None, :].expand(a_n, m, p)
        useful = torch.minimum(own * self.scenario.capability_max, conf) / (L - 1)
        progress = (marg * self.own_drop[:, None]).sum(-1) * (1.0 - blocked)
        prev_site = (prev * self.action_site.to(torch.float32)).sum(-1)  # (A, M), site of a_o (0 with none)
        has_prev = prev.sum(-1)
        same_task_site = (self.task_site.to(torch.float32)[None, None, :] == prev_site[..., None]).to(torch.float32)
        move = (1.0 - same_task_site) * has_prev[..., None]
        excess = self.excess_on[:, None, :] * (conf <= self.excess_from[:, None, :]).to(torch.float32)
        start = p * L + self.n_actions
        roster = x[..., start : start + self.n_team] if self.roster else None  # (A, M, N) heard at the last step
        if self.teammates:  # where the teammates were at the last step (`knowledge.teammates_of`)
            mates = x[..., self.mates_from : self.mates_from + self.n_actions] * max(1, self.n_team - 1)
        else:
            mates = torch.zeros(a_n, m, self.n_actions)
        mates_cap = mates[..., :p]  # (A, M, p) the teammates' capability on each task, over capability_max
        uncovered = (conf - mates_cap * self.scenario.capability_max).clamp(min=0.0) / (L - 1)
        drive = team_steps(self.scenario, x.detach().numpy()) if self.travel else None  # (A, M, N, p)
        advised = self.advice(conf, prev_site, roster, drive)  # (A, M, |Ḡ|)
        if roster is None:
            others = self.others_cap[:, None, :].expand(a_n, m, p)
            ahead = self.ahead_cap[:, None, :].expand(a_n, m, p)
        else:  # the capability of the teammates still heard from
            others = roster @ self.team_caps - own
            ahead = torch.einsum("amn,anp->amp", roster, self.ahead_caps)
        exp_ = expect / (L - 1)
        tasks = torch.cat(
            [
                marg,
                torch.stack(
                    [
                        p0,
                        conf / (L - 1),
                        exp_,
                        blocked,
                        own,
                        useful,
                        progress,
                        others,
                        ahead,
                        self.growth.expand(a_n, m, p),
                        self.hazard.expand(a_n, m, p) * 10.0,
                        same_task_site,
                        prev[..., :p],
                        move * self.reassign[:, None, None],
                        torch.ones_like(p0),
                        -excess,
                        torch.zeros_like(p0),
                        advised[..., :p],
                        mates_cap,
                        uncovered,
                    ],
                    dim=-1,
                ),
            ],
            dim=-1,
        )
        done_glob = p0.mean(-1)
        conf_done = (conf == 0).to(torch.float32).mean(-1)
        glob = torch.stack(
            [
                done_glob,
                conf_done,
                self.own_total[:, None].expand(a_n, m),
                prev[..., p:].sum(-1),
            ],
            dim=-1,
        )  # (A, M, 4)
        tokens = [tasks]
        if q:
            # P(every task of site s done): a product of marginals as a sum of logs
            site_done = torch.exp(torch.log(p0.clamp(min=1e-12)) @ self.site_of.T)  # (A, M, S)
            site_conf = (conf[..., None, :] * self.site_of).amax(-1) / (L - 1)
            site_exp = (exp_ @ self.site_of.T) / self.site_count
            sites = torch.arange(q, dtype=torch.float32)
            same_idle = (sites[None, None, :] == prev_site[..., None]).to(torch.float32)
            move_idle = (1.0 - same_idle) * has_prev[..., None]
            z = torch.zeros_like(site_done)
            idle = torch.stack(
                [
                    site_done,
                    site_conf,
                    site_exp,
                    z,
                    z,
                    z,
                    z,
                    z,
                    z,
                    z,
                    z,
                    same_idle,
                    prev[..., p:],
                    move_idle * self.reassign[:, None, None],
                    z,
                    site_done * self.idle_bonus[:, None, None],
                    torch.ones_like(z),
                    advised[..., p:],
                    torch.tanh(mates[..., p:]),
                    z,
                ],
                dim=-1,
            )
            tokens.append(torch.cat([torch.zeros(a_n, m, q, L), idle], dim=-1))
        tok = torch.cat(tokens, dim=2)  # (A, M, |Ḡ|, F - 4)
        if drive is not None:
            tok = torch.cat([tok, self.reach(drive, roster)], dim=-1)
        return torch.cat([tok, glob[:, :, None, :].expand(a_n, m, tok.shape[2], GLOBAL_FEATURES)], dim=-1)

    def reach(self, drive: IntArray, roster: torch.Tensor | None) -> torch.Tensor:
        """The travel features (A, M, |Ḡ|, 2) from the steps until every agent could work on every task (A, M, N,
        p): for a task, the steps until the agent could work on it and until the nearest teammate able to (and heard
        from, with the roster) could; for an idle location at site s, the steps until the agent is there, and 0.
        Each over `REACH_SCALE`."""
        p, q = self.p, self.q
        a_n, m, n = drive.shape[:3]
        who = np.array(self.agents, dtype=np.int64)
        own = drive[np.arange(a_n), :, who]  # (A, M, p)
        able = self.model.agent_caps[:, :p] > 0  # (N, p)
        mates = np.broadcast_to(able, (a_n, m, n, p)).copy()
        mates[np.arange(a_n), :, who] = False
        if roster is not None:
            mates &= roster.numpy()[..., None] > 0.5
        far = 4 * self.scenario.horizon
        nearest = np.where(mates, drive, far).min(axis=2)  # (A, M, p)
        task = np.stack([own, nearest], axis=-1).astype(np.float32)
        out = [task]
        if q:  # resting is only at the site of a_o, where the agent is or is heading: its arrival there
            idle = np.zeros((a_n, m, q, 2), dtype=np.float32)
            idle[..., 0] = own.min(axis=-1)[..., None]
            out.append(idle)
        return torch.from_numpy(np.minimum(np.concatenate(out, axis=2), far) / REACH_SCALE)


class TokenQ(torch.nn.Module):
    """The token Q-networks of a set of agents: parameters as the rows of one flat (R, P) tensor (R = 1: shared)."""

    def __init__(
        self,
        scenario: Scenario,
        hidden: Sequence[int],
        agent_params: Sequence[Sequence[torch.Tensor]],
        agents: Sequence[int] | None = None,
        shared: bool = True,
    ) -> None:
        """Networks of the agents `agents` (default: the whole team) from their parameters (one list for R = 1,
        one per agent otherwise; `token_shapes` order)."""
        super().__init__()
        agents = list(range(scenario.n_agents)) if agents is None else [int(a) for a in agents]
        self.spec = TokenSpec(scenario, agents)
        self.n_agents = len(agents)
        self.shared = shared
        self.hidden = tuple(int(h) for h in hidden)
        self.shapes = token_shapes(scenario.levels, hidden, scenario.travel)
        self.sizes = (scenario.knowledge_size, *self.hidden, scenario.n_actions)
        self.offsets = np.cumsum([0] + [int(np.prod(s)) for s in self.shapes]).tolist()
        rows = [torch.cat([torch.as_tensor(t, dtype=torch.float32).reshape(-1) for t in ps]) for ps in agent_params]
        want = 1 if shared else self.n_agents
        if len(rows) != want:
            if shared:
                rows = rows[:1]
            else:
                assert len(rows) == 1, f"{len(rows)} parameter sets for {self.n_agents} agents"
                rows = rows * self.n_agents
        self.flat = torch.nn.Parameter(torch.stack(rows).contiguous())

    @property
    def n_params(self) -> int:
        """P, parameters per network."""
        return int(self.offsets[-1])

    @property
    def grad(self) -> torch.Tensor:
        """The flat gradient (R, P) (zeros before the first backward pass)."""
        if self.flat.grad is None:
            self.flat.grad = torch.zeros_like(self.flat)
        return self.flat.grad

    def _params(self) -> list[torch.Tensor]:
        o, r = self.offsets, self.flat.shape[0]
        return [self.flat[:, o[j] : o[j + 1]].reshape((r, *s)) for j, s in enumerate(self.shapes)]

    @staticmethod
    def _linear(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """x (A, T, in) times the rows' weights (R, in, out) plus bias (R, out): (A, T, out)."""
        if w.shape[0] == 1:
            return torch.addmm(b[0], x.reshape(-1, x.shape[-1]), w[0]).reshape(*x.shape[:-1], w.shape[-1])
        return torch.baddbmm(b[:, None, :], x, w)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Q-values (A, M, |Ḡ|) of knowledge states (A, M, K), row a being agent `agents[a]`'s."""
        return self.score(self.spec.features(x))

    def score(self, tok: torch.Tensor) -> torch.Tensor:
        """Q-values (A, M, |Ḡ|) of tokens (A, M, |Ḡ|, F) made by `spec.features` (so that two networks of the
        same agents, online and target, share one computation of the tokens)."""
        a_n, m, g = tok.shape[0], tok.shape[1], tok.shape[2]
        w1, b1, w2, b2, w3, b3, w4, b4 = self._params()
        h = torch.relu(self._linear(tok.reshape(a_n, m * g, -1), w1, b1))
        h = torch.relu(self._linear(h, w2, b2)).reshape(a_n, m, g, -1)
        task = h[:, :, : self.spec.p]
        ctx = torch.cat([task.mean(dim=2), task.amax(dim=2)], dim=-1)  # (A, M, 2H)
        # the head's first layer on [token, context]: the token's part per token, the context's once per row
        hid = h.shape[-1]
        z_tok = self._linear(h.reshape(a_n, m * g, hid), w3[:, :hid], b3).reshape(a_n, m, g, -1)
        z_ctx = self._linear(ctx, w3[:, hid:], torch.zeros_like(b3))
        z = torch.relu(z_tok + z_ctx[:, :, None, :])
        return self._linear(z.reshape(a_n, m * g, -1), w4, b4).reshape(a_n, m, g)

    def row(self, agent: int) -> int:
        """The parameter row of the network's agent number `agent` (0..A-1)."""
        return 0 if self.shared else agent

    def agent_params(self, agent: int) -> list[F32]:
        """Copies of agent `agent`'s parameters in `token_shapes` order."""
        return unflatten(self.flat[self.row(agent)], self.offsets, self.shapes)

    def set_agent_params(self, agent: int, params: Sequence[NDArray[np.float32]]) -> None:
        """Overwrite agent `agent`'s parameters (for shared networks: the one set)."""
        with torch.no_grad():
            self.flat[self.row(agent)].copy_(flatten(params, self.n_params))
