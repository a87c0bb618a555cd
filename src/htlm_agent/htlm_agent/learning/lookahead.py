"""The auction improved by a one-step lookahead on each agent's own belief (docs/model.md, Baselines).

QMDP needs the centralized optimum, which only the smallest operations allow. This baseline needs none: a value
network learns, from simulated episodes, how many steps the auction run on the true levels takes to finish from a
joint state (`BaseValue`, a regression on the simulator's outcomes through torch autograd and torch.optim), and every
agent, from its own belief alone, improves on the auction with it (`LookaheadPolicy`): the agents in index order
each pick the action that minimizes the expected steps to go, one step ahead, over states drawn from the belief,
with the teammates before it on their improved choices and those after it on the auction's. An agent runs that
sequence in its head and keeps its own choice, as it does the auction (one-agent-at-a-time rollout, Bertsekas 2020).

Trained as a run of `htlm train` it is the lookahead learner (docs/model.md, The lookahead learner;
`learning.learners.lookahead`): its value network is the checkpoint (`value_of`). With the learned value of the team's
own play it is the expert-iteration learner's teacher (`Teacher`).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from htlm_agent.learning.checkpoint import Checkpoint, save_checkpoint
from htlm_agent.learning.run import (
    RunLog,
    TrainResult,
    evaluate_checkpoint,
    fresh_run_dir,
    result_json,
    write_run_files,
)
from htlm_agent.learning.settings import Settings
from htlm_agent.mind import knowledge
from htlm_agent.mind.auction import allocate, team_steps
from htlm_agent.mind.context import Context
from htlm_agent.mind.policies import RowPolicy
from htlm_agent.mind.reward import LOAD_PRICE, RewardTables, confident_levels, reward
from htlm_agent.progress import Progress
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.travel import TravelState, arrival_steps, working_actions
from htlm_world.types import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class ValueSettings:
    """How `BaseValue.fit` learns: the simulated episodes and the regression."""

    rollouts: int = 10_000
    """Episodes of the auction on the true levels, each run for twice the horizon."""
    random_start: float = 0.5
    """Share of those episodes starting from random levels (each task 0 with probability 0.3, else uniform), so
    that the states a belief may hold are covered; the rest start at the scenario's initial levels."""
    perturb_steps: int = 12
    """The others first act for up to this many steps (drawn uniformly) with each agent's choice replaced by a random
    task or nothing with probability 0.3; the states from then on are the auction's alone and are learned from."""
    hidden: tuple[int, ...] = (64, 64)
    """Units of the hidden layers."""
    steps: int = 600
    """Adam updates (on one thread, so that every agent process that fits the value gets the same network)."""
    batch: int = 2048
    """States in a minibatch."""
    lr: float = 1e-3

    @staticmethod
    def of(settings: Settings) -> ValueSettings:
        """The value fit of a run of the lookahead learner: `episodes` simulated episodes, its `hidden` layers,
        `value_updates` Adam updates at `lr` on minibatches of `batch_size` states."""
        return ValueSettings(
            rollouts=settings.episodes,
            hidden=tuple(int(h) for h in settings.hidden),
            steps=settings.value_updates,
            batch=settings.batch_size,
            lr=settings.lr,
        )


TABLE_STATES = 1 << 18
"""A value network over at most this many joint states (L^p) is worked out once for all of them and looked up
(`BaseValue.table`): the lookahead's many draws then cost a gather each, not a forward pass."""


LOOKAHEAD_SAMPLES = 64
"""States each agent draws from its belief for every lookahead (the expected steps to go are their mean; every
candidate action is judged on the same draws and the same transition noise)."""


def base_rollouts(sc: Scenario, vs: ValueSettings, seed: int = 0) -> tuple[IntArray, FloatArray]:
    """Joint states (S, p) reached by the auction run on the true levels (every agent knowing them, the whole team
    present) and the steps each took until every level was 0, capped at the horizon; states already complete are
    left out (their value is 0 by definition). With travel the auction bids finish times and its agents drive
    (`htlm_world.travel`), so the steps count the drives, over the places the auction's play takes the team to."""
    rng = seeds.base_rollouts(seed)
    model = Model.build(sc)
    p, levels, n, h = sc.n_tasks, sc.levels, sc.n_agents, sc.horizon
    r = vs.rollouts
    s = np.tile(np.array(sc.initial_levels, dtype=np.int64), (r, 1))
    rand = rng.random(r) < vs.random_start
    rand_levels = rng.integers(0, levels, size=(r, p)) * (rng.random((r, p)) >= 0.3)
    s[rand] = rand_levels[rand]
    prefix = np.where(rand, 0, rng.integers(0, vs.perturb_steps + 1, size=r))
    horizon2 = 2 * h
    states = np.zeros((horizon2, r, p), dtype=np.int64)
    moving = TravelState(sc, r) if sc.travel else None  # with travel: the drives of the auction's choices
    for t in range(horizon2):
        states[t] = s
        drive = None
        if moving is not None:
            drive = arrival_steps(sc, moving.goal, moving.eta())[..., model.task_site][:, None]  # (R, 1, N, p)
        own = allocate(model, s[:, None, :], None, drive)[:, 0, :]  # (R, N): the auction on the true levels
        perturbed = (t < prefix)[:, None] & (rng.random((r, n)) < 0.3)
        a = np.where(perturbed, rng.integers(-1, p, size=(r, n)), own)
        if moving is not None:  # an agent on its way works on nothing
            a = working_actions(a, moving.step(a))
        s = model.sample_transition(s, model.joint_capability(a), rng.random((r, p)))
    complete = (states == 0).all(axis=-1)  # (2h, R)
    next_done = np.full(r, 10**6)
    to_go = np.zeros((horizon2, r), dtype=np.int64)
    for t in range(horizon2 - 1, -1, -1):  # the first step >= t with every level 0
        next_done = np.where(complete[t], t, next_done)
        to_go[t] = next_done - t
    keep = (np.arange(h)[:, None] >= prefix[None, :]) & ~complete[:h]  # (h, R)
    x = states[:h][keep]
    y = np.minimum(to_go[:h][keep], h).astype(np.float64)
    return x, y


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(z: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64's finalizer on every element (wrapping 64-bit arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


class BaseValue:
    """The expected steps the auction on the true levels takes to finish from a joint state: an MLP on the one-hot
    levels of every task, 0 for the complete state."""

    def __init__(self, sc: Scenario, vs: ValueSettings | None = None, seed: int = 0) -> None:
        """A network of `vs.hidden` layers, its weights from the seed; `fit` trains it."""
        self.sc, self.vs, self.seed = sc, vs or ValueSettings(), seed
        torch.manual_seed(seeds.base_value_init(seed))
        sizes = (sc.n_tasks * sc.levels, *self.vs.hidden)
        layers: list[torch.nn.Module] = []
        for i in range(len(sizes) - 1):
            layers += [torch.nn.Linear(sizes[i], sizes[i + 1]), torch.nn.ReLU()]
        self.net = torch.nn.Sequential(*layers, torch.nn.Linear(sizes[-1], 1))
        self._table: FloatArray | None = None

    def params(self) -> list[NDArray[np.float32]]:
        """The parameters in a checkpoint's order (`qnet.network_shapes` of the lookahead learner): per layer the
        weight (in, out), then the bias."""
        out: list[NDArray[np.float32]] = []
        for layer in self.net:
            if isinstance(layer, torch.nn.Linear):
                out += [layer.weight.detach().numpy().T.copy(), layer.bias.detach().numpy().copy()]
        return out

    def load_params(self, params: Sequence[NDArray[np.floating[Any]]]) -> BaseValue:
        """Take the parameters of `params` (the order of `params()`); returns self."""
        linear = [m for m in self.net if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            for i, layer in enumerate(linear):
                layer.weight.copy_(torch.as_tensor(np.asarray(params[2 * i], dtype=np.float32).T))
                layer.bias.copy_(torch.as_tensor(np.asarray(params[2 * i + 1], dtype=np.float32)))
        self._table = None
        return self

    def encode(self, levels: IntArray) -> torch.Tensor:
        """(..., p) levels -> (..., p L) one-hot inputs."""
        x = torch.from_numpy(np.ascontiguousarray(levels, dtype=np.int64))
        return torch.nn.functional.one_hot(x, self.sc.levels).reshape(*x.shape[:-1], -1).to(torch.float32)

    def fit(self, progress: bool = False, on_update: Callable[[int, float], None] | None = None) -> float:
        """Learn from `base_rollouts`: mean squared error, Adam. Returns the last minibatch's root mean squared
        error (steps). `on_update(updates done, minibatch loss)` is called after every update."""
        t0 = time.monotonic()
        x_np, y_np = base_rollouts(self.sc, self.vs, self.seed)
        rmse = self.regress(x_np, y_np, self.vs.steps, seeds.base_value_init(self.seed), on_update)
        if progress:
            print(
                f"lookahead: value of the auction on the true levels learned from {len(y_np):,} states "
                f"(rmse {rmse:.2f} steps, {time.monotonic() - t0:.0f} s)",
                file=sys.stderr,
                flush=True,
            )
        return rmse

    def regress(
        self,
        levels: IntArray,
        to_go: FloatArray,
        updates: int,
        seed: int,
        on_update: Callable[[int, float], None] | None = None,
    ) -> float:
        """`updates` Adam updates (a fresh optimizer, `vs.lr`, minibatches of `vs.batch` drawn with `seed`) of the
        mean squared error between the network on the (S, p) `levels` and the steps `to_go` (S,), on one thread so
        that every process gets the same network; returns the last minibatch's root mean squared error."""
        self._table = None
        x, y = self.encode(levels), torch.from_numpy(np.asarray(to_go, dtype=np.float32))
        gen = torch.Generator().manual_seed(seed)
        opt = torch.optim.Adam(self.net.parameters(), lr=self.vs.lr)
        loss = torch.zeros(())
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            for done in range(1, updates + 1):
                idx = torch.randint(0, len(y), (self.vs.batch,), generator=gen)
                loss = torch.nn.functional.mse_loss(self.net(x[idx])[:, 0], y[idx])
                opt.zero_grad()
                loss.backward()  # type: ignore[no-untyped-call]
                opt.step()
                if on_update is not None:
                    on_update(done, float(loss.detach()))
        finally:
            torch.set_num_threads(threads)
        return float(loss.detach().sqrt())

    def table(self) -> FloatArray | None:
        """The value of every joint state, at index Σ_j level_j · L^j, when there are at most `TABLE_STATES` of them
        (None otherwise); worked out again after the network changes (`regress`, `load_params`)."""
        lv, p = self.sc.levels, self.sc.n_tasks
        if lv**p > TABLE_STATES:
            return None
        if self._table is None:
            index = np.arange(lv**p)
            states = (index[:, None] // lv ** np.arange(p)) % lv  # (L^p, p): the digits of every index
            self._table = self(states)
        return self._table

    def after_step(self, none: IntArray, work: IntArray, tasks: IntArray, floor: float | None = None) -> FloatArray:
        """The values of an agent's candidate next states, from (..., p) next levels without it (`none`) and with it
        on every task (`work`; a task's next level depends on its own capability only): (..., 1 + T), the value of
        `none`, then of `none` with the level of task tasks[c] from `work`; 0 for a complete state, at least `floor`
        for the others when given. The first layer is linear in the one-hot levels, so every candidate's is the none
        state's with one task's term replaced."""
        first = self.net[0]
        assert isinstance(first, torch.nn.Linear)
        lv = self.sc.levels
        shape, p = none.shape[:-1], none.shape[-1]
        none2, work2 = none.reshape(-1, p), work[..., tasks].reshape(-1, tasks.size)
        table = self.table()
        if table is not None:  # every candidate's state is the none state with one task's digit replaced
            power = lv ** np.arange(p)
            key = none2 @ power
            keys = np.concatenate([key[:, None], key[:, None] + (work2 - none2[:, tasks]) * power[tasks]], axis=1)
            got: FloatArray = table[keys]
            if floor is not None:
                np.maximum(got, floor, out=got)
                got[keys == 0] = 0.0
            return got.reshape(*shape, 1 + tasks.size)
        out = np.zeros((none2.shape[0], 1 + tasks.size))
        with torch.no_grad():
            emb = first.weight.T.contiguous()  # (p·L, H): row j·L + l is task j's term at level l
            none_ix = torch.from_numpy(none2 + np.arange(p) * lv)  # rows of emb, one gather (not a 2-index one)
            work_ix = torch.from_numpy(work2 + tasks * lv)
            cand_ix = torch.from_numpy(tasks)
            rest = self.net[1:]
            for i in range(0, none2.shape[0], 4096):
                e_none = torch.nn.functional.embedding(none_ix[i : i + 4096], emb)  # (S, p, H)
                h_none = first.bias + e_none.sum(dim=1)  # (S, H)
                e_work = torch.nn.functional.embedding(work_ix[i : i + 4096], emb)  # (S, T, H)
                h_c = h_none[:, None] - e_none[:, cand_ix] + e_work
                out[i : i + 4096] = rest(torch.cat([h_none[:, None], h_c], dim=1))[..., 0].numpy()
        open_none = (none2 > 0).sum(axis=-1)
        open_c = open_none[:, None] - (none2[:, tasks] > 0) + (work2 > 0)
        is_open = np.concatenate([open_none[:, None], open_c], axis=1) > 0
        if floor is not None:
            np.maximum(out, floor, out=out)
        out[~is_open] = 0.0
        return out.reshape(*shape, 1 + tasks.size)

    def __call__(self, levels: IntArray) -> FloatArray:
        """(..., p) levels -> (...,) expected steps to finish (0 where every level is 0)."""
        shape = levels.shape[:-1]
        flat = levels.reshape(-1, levels.shape[-1])
        out = np.zeros(flat.shape[0])
        open_rows = np.flatnonzero(flat.any(axis=-1))
        with torch.no_grad():
            for i in range(0, open_rows.size, 65536):
                rows = open_rows[i : i + 65536]
                out[rows] = self.net(self.encode(flat[rows]))[:, 0].numpy()
        return out.reshape(shape)


def candidate_tasks(model: Model) -> list[IntArray]:
    """The tasks each agent may take in the lookahead: those it brings capability to (working elsewhere changes
    nothing and costs load), every task for an agent with none (HT mode: it must take one)."""
    caps = model.agent_caps[:, : model.scenario.n_tasks] > 0
    return [np.flatnonzero(c) if c.any() else np.arange(model.scenario.n_tasks) for c in caps]


def own_rewards(sc: Scenario) -> list[str]:
    """The agents of `sc` that carry their own reward fields (`agents[i].reward`)."""
    return [a.name for i, a in enumerate(sc.agents) if sc.has_own_reward(i)]


class LookaheadPolicy:
    """Every agent on its own belief: the auction, improved one agent at a time by a one-step lookahead with the
    learned value of the auction on the true levels (module docstring; docs/model.md, Baselines)."""

    def __init__(
        self,
        sc: Scenario,
        value: BaseValue | None = None,
        samples: int = LOOKAHEAD_SAMPLES,
        seed: int = 0,
        load_price: float = LOAD_PRICE,
        floor: float | None = None,
    ) -> None:
        """`value`: a fitted `BaseValue` (default: one fitted here with `seed`); `load_price`: the steps a unit of
        committed capability is worth (`Settings.load_price`); `floor`: the least value of an open state (the
        `Teacher`'s 1: a mission not finished takes at least one more step)."""
        self.floor = floor
        self.sc, self.model, self.samples = sc, Model.build(sc), samples
        if value is None:
            value = BaseValue(sc, seed=seed)
            value.fit(progress=True)
        self.value = value
        self.threshold = RewardTables.build(sc).threshold
        self.key = np.uint64(seeds.lookahead(seed))
        p = sc.n_tasks
        # candidate 0: no task; candidate 1 + j: task j (N, p + 1, p) the capability each brings to every task
        self.brings = np.zeros((sc.n_agents, p + 1, p), dtype=np.int64)
        self.brings[:, 1 + np.arange(p), np.arange(p)] = self.model.agent_caps[:, :p]
        # mission first, load second: QMDP's price of a unit of committed capability (at least one: working counts)
        self.load = load_price * np.maximum(self.brings.sum(axis=-1), 1) * (np.arange(p + 1) > 0)
        self.candidates = candidate_tasks(self.model)
        self.takes = np.zeros((sc.n_agents, p), dtype=bool)
        """(N, p) the candidate tasks of every agent (`candidates`)."""
        for k, tasks in enumerate(self.candidates):
            self.takes[k, tasks] = True

    def _draws(self, knowledge: FloatArray, who: IntArray) -> tuple[FloatArray, FloatArray]:
        """Two (B, R, M, p) arrays of uniforms for the agents `who` with knowledge states (B, R, K), stratified: each
        task's M of them one in each of M equal strata, in random order (fewer draws for the same accuracy than
        independent ones); the first for the states, the second for the step's noise. They are a hash of the
        seed, the agent and its knowledge state (as float32, the precision of the wire), so an agent draws the
        same whatever the batch, in process and in its own process."""
        m, p = self.samples, self.sc.n_tasks
        bits = np.ascontiguousarray(knowledge, dtype=np.float32).view(np.uint32).astype(np.uint64)
        h = _mix(np.broadcast_to(self.key + who.astype(np.uint64) * _GOLDEN, bits.shape[:-1]))
        for k in range(bits.shape[-1]):
            h = _mix(h ^ bits[..., k])
        z = _mix(h[..., None] + np.arange(1, 4 * p * m + 1, dtype=np.uint64) * _GOLDEN)
        u = (z >> np.uint64(11)).astype(np.float64) * 2.0**-53
        u = u.reshape(*h.shape, 2, 2, p, m)  # (B, R, which, order or jitter, p, M)
        strata = (u[..., 0, :, :].argsort(axis=-1) + u[..., 1, :, :]) / m
        out = np.ascontiguousarray(strata.swapaxes(-1, -2))  # (B, R, which, M, p)
        return out[:, :, 0], out[:, :, 1]

    def act(self, ctx: Context) -> IntArray:
        """One action per agent, each from its own row's marginals and roster."""
        return self.act_rows(ctx, np.arange(self.sc.n_agents))

    def act_rows(
        self, ctx: Context, who: IntArray, own_load: FloatArray | None = None, q_out: FloatArray | None = None
    ) -> IntArray:
        """The actions (B, R) of the agents `who` (R,), each from its own row of the Context: only their heads'
        sequences are worked out (an agent process asks for its own). `own_load` (B, R, |Ḡ|): the steps each head's
        own agent counts for every action of Ḡ besides the load price; `q_out` (B, R, |Ḡ|), filled with inf:
        receives what every action of Ḡ its head judged is worth to each head's own agent (both the `Teacher`'s)."""
        sc, model = self.sc, self.model
        p, n, m = sc.n_tasks, sc.n_agents, self.samples
        marg = ctx.marginals[:, who]  # (B, R, p, L): row r is agent who[r]'s belief
        b, r = marg.shape[0], who.size
        present = knowledge.roster(ctx.knowledge[:, who], sc)  # (B, R, N): row r, the teammates who[r] counts on
        # with travel: the steps until every agent could work on every task, as each head reckons them (B, R, N, p)
        drive = team_steps(sc, ctx.knowledge[:, who]) if sc.travel else None
        conf = confident_levels(marg, self.threshold[who])
        plan = allocate(model, conf, present if sc.roster else None, drive)  # (B, R, N)
        # every auctioneer's draws of the joint state from its belief (product of its marginals), and the noise of
        # the step after it, shared by every candidate
        u, noise = self._draws(ctx.knowledge[:, who], who)
        s = np.minimum((u[..., None] > marg.cumsum(axis=-1)[:, :, None]).sum(axis=-1), sc.levels - 1)  # (B, R, M, p)
        complete = (s == 0).all(axis=-1)  # (B, R, M)
        # a head whose every draw is complete rests: every candidate is worth 0 steps and resting costs no load (in
        # HT mode, where resting is no candidate, every head works the sequence out)
        rest = complete.all(axis=-1) if sc.n_idle > 0 else np.zeros((b, r), dtype=bool)
        plan[rest] = -1
        rest_of = model.rest_action(ctx.prev[:, who])  # (B, R)
        settled = self._settled(rest, rest_of, who, own_load, q_out)
        for k in range(int(who.max()) + 1):  # agent k improves on the plan in the heads of agents k.. (the rest are
            bi, ri = np.nonzero((who >= k)[None, :] & ~rest)  # settled): every (episode, head) pair
            if bi.size == 0:
                continue
            mine = plan[bi, ri]  # (P, N)
            brought = self.brings[np.arange(n), np.where(mine >= 0, mine + 1, 0)]  # (P, N, p)
            if drive is not None:  # a teammate on its way to its task brings nothing in the step
                away = drive[bi, ri][np.arange(bi.size)[:, None], np.arange(n), np.maximum(mine, 0)] > 0  # (P, N)
                brought = np.where((away & (mine >= 0))[..., None], 0, brought)
            others = brought.sum(axis=1) - brought[:, k]  # (P, p)
            # a task's next level depends on its own capability only: every candidate's next state is the one
            # without agent k, with the level of its task taken from the next levels with agent k on every task
            caps = np.stack([others, others + self.model.agent_caps[k, :p]], axis=1)  # (P, 2, p)
            shape = (bi.size, 2, m, p)
            nxt = model.sample_transition(
                np.broadcast_to(s[bi, ri][:, None], shape),
                np.minimum(caps, sc.capability_max)[:, :, None, :],
                np.broadcast_to(noise[bi, ri][:, None], shape),
            )  # (P, 2, M, p)
            tasks = self.candidates[k]
            v = self.value.after_step(nxt[:, 0], nxt[:, 1], tasks, self.floor)  # (P, M, 1 + T)
            if drive is not None:  # a task d steps away: its work, d steps late, and never worse than not going
                d = drive[bi, ri, k][:, tasks][:, None, :]  # (P, 1, T)
                v[..., 1:] = np.where(d > 0, np.minimum(v[..., :1], v[..., 1:] + d), v[..., 1:])
            q = np.full((bi.size, p + 1), np.inf)
            q[:, np.concatenate([[0], 1 + tasks])] = np.where(complete[bi, ri][..., None], 0.0, 1.0 + v).mean(axis=1)
            q += self.load[k]
            mine = who[ri] == k  # the pairs whose head is agent k's own
            if own_load is not None:  # the heads' own agents: their own load terms besides the price
                rows = own_load[bi[mine], ri[mine]]  # (P', |Ḡ|)
                resting = rows[np.arange(rows.shape[0]), rest_of[bi[mine], ri[mine]]]
                q[mine] += np.concatenate([resting[:, None], rows[:, :p]], axis=1)  # the price still breaks ties
            if sc.n_idle == 0:  # HT mode: resting is staying on a task, so only the tasks are candidates
                q[:, 0] = np.inf
            here = present[bi, ri, k]  # whether each head counts on agent k: a silent teammate brings nothing
            q[:, 1:] = np.where(here[:, None], q[:, 1:], np.inf)
            q[:, 0] = np.where(here, q[:, 0], -np.inf)
            plan[bi, ri, k] = q.argmin(axis=-1) - 1
            if q_out is not None:
                bm, rm = bi[mine], ri[mine]
                q_out[bm, rm, :p] = q[mine, 1:]
                if sc.n_idle:
                    q_out[bm, rm, rest_of[bm, rm]] = q[mine, 0]
        own = plan[:, np.arange(r), who]
        own = np.where(settled >= 0, settled, own)
        return np.where(own >= 0, own, rest_of).astype(np.int64)

    def _settled(
        self, rest: BoolArray, rest_of: IntArray, who: IntArray, own_load: FloatArray | None, q_out: FloatArray | None
    ) -> IntArray:
        """The choices (B, R) of the heads whose every draw is complete (`rest`; -1 elsewhere): they rest, every
        candidate worth 0 steps. With `own_load` (the `Teacher`'s) such a head still weighs its own agent's load
        terms, which price what resting leaves unseen: every candidate task is worth its load price and its own load
        terms, and so is resting, and the head takes the least (a task, or -1: rest). `q_out` receives those worths
        (resting's alone, 0 steps, without `own_load`)."""
        out = np.full(rest.shape, -1, dtype=np.int64)
        if not rest.any() or (own_load is None and q_out is None):
            return out
        bi, ri = np.nonzero(rest)
        rests = rest_of[bi, ri]
        if own_load is None:
            assert q_out is not None
            q_out[bi, ri, rests] = 0.0
            return out
        p, each = self.sc.n_tasks, np.arange(bi.size)
        rows = own_load[bi, ri]  # (P, |Ḡ|)
        price = self.load[who[ri]]  # (P, p + 1)
        worth = np.full(rows.shape, np.inf)
        worth[:, :p] = np.where(self.takes[who[ri]], price[:, 1:] + rows[:, :p], np.inf)
        worth[each, rests] = price[:, 0] + rows[each, rests]
        best = worth.argmin(axis=-1)
        out[bi, ri] = np.where(best < p, best, -1)
        if q_out is not None:
            q_out[bi, ri] = worth
        return out


class AgentLookahead(RowPolicy):
    """Agent `agent`'s lookahead in its own process (`policy:=lookahead`): its own head's sequence only, on its own
    knowledge state."""

    policy: LookaheadPolicy


def value_of(ck: Checkpoint) -> BaseValue:
    """The value network of a checkpoint of the lookahead learner (every agent holds the same copy)."""
    return BaseValue(ck.scenario, ValueSettings.of(ck.settings), ck.seed).load_params(ck.weights[0])


def train_lookahead(
    scenario: Scenario,
    settings: Settings,
    out: Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """`learning.run.train` for the lookahead learner (docs/model.md, The lookahead learner): its value network
    learns from `settings.episodes` simulated episodes in one go; the checkpoint gives every agent a copy, and the
    final evaluation acts as the agents do, each improving on the auction from its own belief with it."""
    t_start = time.perf_counter()
    ckpt_dir = fresh_run_dir(out, resume, "lookahead", "it learns in one go, in seconds")
    mine = own_rewards(scenario)
    if mine:  # it weighs load by load_price alone: say so rather than ignore them silently
        print(
            f"warning: the lookahead learner does not read the scenario's reward: the own rewards of {mine} change "
            "nothing it does; `--learner expert` weighs every agent's own R_II and T_RP",
            file=sys.stderr,
            flush=True,
        )
    write_run_files(out, scenario, settings)
    value = BaseValue(scenario, ValueSettings.of(settings), settings.seed)
    bars: list[Progress] = []  # the regression's, from its first update on (after the simulation)

    def show(done: int, loss: float) -> None:
        if not bars:
            bars.append(Progress(settings.value_updates, unit="upd", enabled=progress))
        bars[0].update(done, rmse=f"{math.sqrt(loss):.2f}")

    if progress:
        print(f"lookahead: simulating {settings.episodes:,} episodes of the auction", file=sys.stderr, flush=True)
    try:
        rmse = value.fit(on_update=show)
    finally:
        for bar in bars:
            bar.close()
    train_time = time.perf_counter() - t_start
    row = {
        "episodes": settings.episodes,
        "wall_s": round(train_time, 3),
        "episodes_per_s": settings.episodes / max(train_time, 1e-9),
        "updates": settings.value_updates,
        "loss": rmse**2,
    }
    save_checkpoint(
        ckpt_dir,
        scenario,
        settings,
        settings.seed,
        settings.episodes,
        [value.params()] * scenario.n_agents,
        info={"value_rmse": rmse},
    )
    log = RunLog(out, 0, False, tensorboard)
    metrics: dict[str, Any] = {}
    try:
        log.row(row, settings.episodes)
        log.close_progress()
        if evaluate_at_end and settings.eval_episodes > 0:
            metrics = evaluate_checkpoint(ckpt_dir, out, "htlm-lookahead")
            log.evaluation(metrics, settings.episodes)
    finally:
        log.close()
    wall = result_json(out, settings.episodes, t_start, train_time, None, metrics, progress)
    return TrainResult(out, scenario, settings, settings.episodes, wall, train_time, metrics, [row])


UNSEEN_SHARE = 1.0
"""What leaving a task unseen costs in the `Teacher`'s choice, beyond one step plus the value: this share of the
horizon times the chance that a task the agent's belief holds done (confident level 0), and that it brings capability
to, is open, times the agent's part in looking at it (`Teacher.look_shares`). The value is the auction's on the true
levels, which finishes such a task; but an idle agent observes nothing, a teammate whose belief is the agent's rests
too, and a wrong "done" is then never corrected: the team leaves the task open to the horizon, and a failed episode
counts as the horizon in the completion step, hence the whole horizon. Resting leaves every such task unseen; working
one of them looks at it and leaves the others; working a task believed open leaves none (the agent may look later).
It is weighed too where none of the agent's drawn states has such a task open (`LookaheadPolicy._settled`). A larger
share fails less and holds less capability in reserve (docs/results/market.md, Looking again, where no draw is
open)."""


LOAD_CAP = 0.45
"""The most steps the load-management reward of one choice counts for in the `Teacher`'s choice, either way: two
choices' load terms then differ by less than a step, so a choice sure to finish the mission at the next step is
never beaten by one that leaves it unfinished (mission first)."""


def load_rates(sc: Scenario, weight: float) -> FloatArray:
    """The steps a unit of each agent's load-management reward is worth to the `Teacher` (N,): `weight` over what one
    step of the mission left unfinished costs the team's reward, R_0 − R_4 of the agent's own `level_rewards` for
    each of the N agents (the paper's operation: a unit is worth 1/50 of a step, a medium reassignment 0.02 steps)."""
    tables = RewardTables.build(sc)
    span = (tables.level_rewards[:, 0] - tables.level_rewards[:, -1]) * sc.n_agents
    return np.where(span > 0, weight / np.maximum(span, 1e-12), 0.0)


class Teacher:
    """The lookahead as the teacher of the expert-iteration learner (docs/model.md, The expert-iteration learner).

    Every agent works out in its own head, from its own belief, the lookahead's sequence (`LookaheadPolicy`) with a
    value of the steps the team's current policy takes to finish, and its own choice in it weighs, besides one step
    plus the value, the steps its own load-management reward is worth (R_II + T_RP of the scenario's reward with
    the agent's own fields, `load_rates`, at most `LOAD_CAP` either way), and what it leaves unseen of the tasks it
    believes done (`UNSEEN_SHARE`). Its choice is a function of its own knowledge state, so the policy network it
    teaches can learn it exactly."""

    def __init__(self, sc: Scenario, value: BaseValue, seed: int = 0, load_weight: float = 1.0) -> None:
        """`value`: the steps to go of the policy the team plays; `load_weight`: `Settings.load_weight`."""
        self.look = LookaheadPolicy(sc, value, seed=seed, floor=1.0)
        self.sc, self.model = sc, self.look.model
        self.tables = RewardTables.build(sc)
        self.rates = load_rates(sc, load_weight)
        shared = dataclasses.replace(sc, agents=tuple(dataclasses.replace(a, reward=None) for a in sc.agents))
        self.shared_tables = RewardTables.build(shared)
        self.shared_rates = load_rates(shared, load_weight)
        self.own = np.array([sc.has_own_reward(i) for i in range(sc.n_agents)], dtype=bool)
        """(N,) the agents whose own reward differs from the team's (`improve_shared`)."""

    def load_steps(self, marg: FloatArray, prev: IntArray, shared: bool = False) -> FloatArray:
        """(B, N, |Ḡ|): the steps every action of Ḡ costs every agent in load-management reward (minus R_II + T_RP
        times its rate, within ±`LOAD_CAP`), from its marginals now (B, N, p, L) and a_o (B, N); 0 in HT mode.
        `shared`: with the team's reward in place of every agent's own."""
        tables, rates = (self.shared_tables, self.shared_rates) if shared else (self.tables, self.rates)
        b, n = prev.shape
        out = np.zeros((b, n, self.sc.n_actions))
        if not tables.load_management or not rates.any():
            return out
        prior = marg if tables.difference.any() else None
        for g in range(self.sc.n_actions):
            _, parts = reward(self.model, tables, prev, marg, np.full((b, n), g, dtype=np.int64), prior)
            out[:, :, g] = -(parts["idle"] + parts["reassign"]) * rates[None, :]
        return np.clip(out, -LOAD_CAP, LOAD_CAP)

    def unseen_steps(self, marg: FloatArray, who: IntArray, present: BoolArray) -> FloatArray:
        """(B, R, |Ḡ|): the steps every action of Ḡ costs each of the agents `who` (R,) in what it leaves unseen of
        the tasks it believes done (confident level 0) and brings capability to, from their marginals (B, R, p, L)
        and the teammates each counts on (B, R, N): for each such task, `UNSEEN_SHARE` of the horizon times the
        chance that the task is open, times the agent's part in looking at it (`look_shares`). Resting leaves every
        such task unseen; working one of them looks at it and leaves the others; working a task believed open costs
        nothing (the agent may look later)."""
        p = self.sc.n_tasks
        conf = confident_levels(marg, self.tables.threshold[who])
        mine = (conf == 0) & (self.model.agent_caps[who, :p] > 0)[None]  # (B, R, p)
        miss = np.where(mine, (1.0 - marg[..., 0]) * self.look_shares(who, present), 0.0)  # (B, R, p)
        every = miss.sum(axis=-1, keepdims=True)  # (B, R, 1)
        out = np.empty((*every.shape[:-1], self.sc.n_actions))
        out[..., :p] = np.where(mine, every - miss, 0.0)
        out[..., p:] = every
        cost: FloatArray = UNSEEN_SHARE * self.sc.horizon * np.maximum(out, 0.0)
        return cost

    def look_shares(self, who: IntArray, present: BoolArray) -> FloatArray:
        """(B, R, p): each agent's part in looking again at each task, among the teammates it counts on (B, R, N;
        itself always): the whole of it for the one that brings the most capability to the task (the lowest index
        among equals), its share of their capability for the others. Every capable agent paying the whole made
        larger teams check done work all the time (facility-20: half the capability unused instead of three
        quarters); the one the auction would send paying alone left wrong "done"s to the agent whose own look had
        made them (docs/results/market.md, Looking again at what is believed done, and Looking again, where no draw
        is open)."""
        p, n = self.sc.n_tasks, self.sc.n_agents
        caps = self.model.agent_caps[:, :p].astype(np.float64)  # (N, p)
        counted = present.copy()
        counted[:, np.arange(who.size), who] = True
        brought = counted[..., None] * caps[None, None]  # (B, R, N, p)
        first = (brought + (n - np.arange(n))[None, None, :, None] * 1e-9).argmax(axis=2) == who[None, :, None]
        total = brought.sum(axis=2)  # (B, R, p)
        out: FloatArray = np.where(first, 1.0, caps[who][None] / np.maximum(total, 1e-12))
        return out

    def improve(self, ctx: Context, who: IntArray) -> tuple[IntArray, FloatArray]:
        """The teacher's choices (B, R) of the agents `who` (R,) at the step of `ctx`, each from its own row, and
        what every action of Ḡ is worth to them (B, R, |Ḡ|), in steps (inf: not judged)."""
        return self._improve(ctx, who, self.load_steps(ctx.marginals, ctx.prev)[:, who])

    def improve_shared(self, ctx: Context, who: IntArray) -> tuple[IntArray, FloatArray, FloatArray]:
        """`improve`, and what every action of Ḡ would be worth to the agents `who` had each the team's reward instead
        of its own (B, R, |Ḡ|): their own load terms swapped for the team's (the sequence before an agent's own choice
        does not read its own reward, so nothing else moves)."""
        own = self.load_steps(ctx.marginals, ctx.prev)[:, who]
        a, q = self._improve(ctx, who, own)
        team = self.load_steps(ctx.marginals, ctx.prev, shared=True)[:, who]
        return a, q, q - own + team

    def _improve(self, ctx: Context, who: IntArray, own: FloatArray) -> tuple[IntArray, FloatArray]:
        """`improve` with the agents' own load-management steps `own` (B, R, |Ḡ|)."""
        present = knowledge.roster(ctx.knowledge[:, who], self.sc)
        load = own + self.unseen_steps(ctx.marginals[:, who], who, present)
        q = np.full(load.shape, np.inf)
        return self.look.act_rows(ctx, who, load, q), q
