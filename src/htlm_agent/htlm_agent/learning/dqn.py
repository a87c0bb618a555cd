"""Decentralized deep Q-learning for load management (Algorithm 1 of the paper).

Every agent has its own Q-network, target network, optimizer state and replay memory; agents never share
parameters, gradients or memories. For speed the N networks are stacked (`qnet.StackedQ`) and trained as one batched
computation: the loss is the sum of the agents' own losses, so every agent's gradient is that of its own loss, and the
optimizer (`StackedAdam`) keeps a step count per agent, exactly as N separate Adam optimizers would.

Two ways to feed the learner:
- in process: `train()` runs B episodes at once in `team.Team` (line 3-10 of Algorithm 1 as array operations);
- from another process (the ROS trainer node): `Learner.store()` one transition at a time, `Learner.train_step()`,
  and `Learner.agent_weights()` to send an agent its new weights.

Random streams (STYLE.md 4), all derived from the run's seed: network initialisation per agent, replay sampling per
agent, exploration per agent and batch, and the world and channels per batch of training episodes. The same seed
gives the same learning curve and the same weights (on CPU, for the same `threads`).

Two departures from textbook DQN, both measured on the heterogeneous team (see `Settings`):
- the horizon is not a terminal state in the target (`horizon_terminal=False`): the knowledge state holds no time, so
  a terminal at h gives one knowledge state targets anywhere between r and r/(1-γ);
- advantage learning (`advantage_learning=0.9`): with the idle incentive, idling now and working next step is worth
  almost as much to one agent as working now (a gap of about 1 in Q-values near 200), so plain Q-learning's greedy
  policy often stalls with every agent idle; widening the gaps keeps the greedy team working.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.learning.qnet import StackedQ, layer_sizes, masked_argmax, masked_max, pack_weights
from htlm_agent.learning.replay import Batch, Replay
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.reward import action_mask
from htlm_agent.runtime.team import Context, Team
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray

# stream tags of SeedSequence([seed, tag, ...]); the simulator uses 0 (world) and 1 (channels) for evaluation
_INIT, _EXPLORE, _REPLAY, _VALIDATE, _TRAIN_WORLD, _TRAIN_CHANNEL = 2, 3, 4, 6, 10, 11


def derive_seed(seed: int, *keys: int) -> int:
    """A 63-bit seed derived from the master seed and stream keys (agent index, batch index, ...)."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(2, np.uint64)[0] >> np.uint64(1))


# ----- pieces of the update -------------------------------------------------------------------------------------


def bellman_targets(
    r: torch.Tensor,
    discount: torch.Tensor,
    q_next_target: torch.Tensor,
    mask2: torch.Tensor,
    q_next_online: torch.Tensor | None = None,
) -> torch.Tensor:
    """y = r + d · max_{a' ∈ Â(K')} Q(K', a'; θ̂) (Eq. 10 of the paper, the Bellman target), with d = γ (one step),
    γ^n (an n-step return r), or 0 (terminal K').

    With `q_next_online` (Double DQN) the maximising a' is chosen by the online network and valued by the target
    network. Shapes: r, discount (..., M); q's and mask2 (..., M, |Ḡ|).
    """
    if q_next_online is None:
        nxt = masked_max(q_next_target, mask2)
    else:
        a2 = masked_argmax(q_next_online, mask2)
        nxt = q_next_target.gather(-1, a2[..., None])[..., 0]
    return r + discount * nxt


def advantage_gap(q_target: torch.Tensor, mask: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """max_{b ∈ Â(K)} Q̂(K, b) − Q̂(K, a) >= 0, the term advantage learning subtracts (scaled by α) from the target."""
    return masked_max(q_target, mask) - q_target.gather(-1, a[..., None])[..., 0]


class NStep:
    """Turns a stream of one-step transitions (of one agent, or of arrays of agents and episodes advancing in
    lockstep) into n-step transitions <K_t, a_t, Σ_{j<m} γ^j r_{t+j}, K_{t+m}, Â(K_{t+m}), d> with m = n, or fewer at
    the end of an episode, and d = γ^m, or 0 when the episode ends in a terminal state. Rewards are scaled here."""

    def __init__(self, n: int, gamma: float, scale: float = 1.0) -> None:
        """An empty window of n steps."""
        self.n, self.gamma, self.scale = n, gamma, scale
        self.items: list[tuple[Any, Any, Any]] = []

    def _emit(self, k2: Any, mask2: Any, terminal: bool) -> tuple[Any, ...]:
        k, a, _ = self.items[0]
        ret = sum((self.gamma**j) * r for j, (_, _, r) in enumerate(self.items))
        disc = 0.0 if terminal else self.gamma ** len(self.items)
        self.items.pop(0)
        return k, a, ret * self.scale, k2, mask2, disc

    def push(self, k: Any, a: Any, r: Any, k2: Any, mask2: Any, end: bool, terminal: bool) -> list[tuple[Any, ...]]:
        """Add the step (K, a, r, K', Â(K')); returns the transitions complete now (all pending ones at the end of an
        episode, `end`), each (K, a, return, K', Â(K'), discount)."""
        self.items.append((k, a, r))
        out = []
        if end:
            while self.items:
                out.append(self._emit(k2, mask2, terminal))
        elif len(self.items) == self.n:
            out.append(self._emit(k2, mask2, False))
        return out

    def clear(self) -> None:
        """Forget a partial episode."""
        self.items.clear()


class StackedAdam:
    """Adam over stacked per-agent parameters (N, P) with a step count per agent: identical to one Adam per agent,
    and an agent's parameters and moments change only on updates it takes part in."""

    def __init__(
        self,
        param: torch.Tensor,
        grad: torch.Tensor,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        """Moments start at zero, step counts at zero; `grad` is where the gradient of `param` lands."""
        self.param, self.grad = param, grad
        self.lr, self.betas, self.eps = lr, betas, eps
        self.m = torch.zeros_like(param)
        self.v = torch.zeros_like(param)
        self.t = torch.zeros(param.shape[0], dtype=torch.float64)

    @torch.no_grad()
    def step(self, active: torch.Tensor) -> None:
        """Apply the gradient rows of the agents marked in `active` (N,) bool."""
        b1, b2 = self.betas
        g = self.grad
        self.t += active.to(self.t.dtype)
        t = self.t.clamp(min=1.0)
        c1 = (1.0 - b1**t).to(torch.float32)[:, None]
        c2 = (1.0 - b2**t).to(torch.float32)[:, None]
        if bool(active.all()):
            self.m.mul_(b1).add_(g, alpha=1.0 - b1)
            self.v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
            self.param.sub_(self.lr * (self.m / c1) / ((self.v / c2).sqrt_().add_(self.eps)))
            return
        a = active[:, None]
        self.m.copy_(torch.where(a, b1 * self.m + (1.0 - b1) * g, self.m))
        self.v.copy_(torch.where(a, b2 * self.v + (1.0 - b2) * g * g, self.v))
        upd = self.lr * (self.m / c1) / ((self.v / c2).sqrt() + self.eps)
        self.param.sub_(torch.where(a, upd, torch.zeros_like(upd)))

    def state(self) -> dict[str, torch.Tensor]:
        """Tensors of the optimizer state."""
        return {"m": self.m.clone(), "v": self.v.clone(), "t": self.t.clone()}

    def load_state(self, st: dict[str, torch.Tensor]) -> None:
        """Restore `state()`."""
        self.m.copy_(st["m"])
        self.v.copy_(st["v"])
        self.t.copy_(st["t"])


def clip_grad_per_agent(g: torch.Tensor, max_norm: float) -> torch.Tensor:
    """Scale each agent's row of the stacked gradient (N, P) to norm <= max_norm in place (0: no clipping); returns
    the norms (N,) before clipping."""
    norm = g.norm(dim=1)
    if max_norm > 0:
        g.mul_((max_norm / (norm + 1e-6)).clamp(max=1.0)[:, None])
    out: torch.Tensor = norm
    return out


def epsilon_greedy(
    q: torch.Tensor, mask: torch.Tensor, epsilon: float | FloatArray, rngs: Sequence[np.random.Generator]
) -> IntArray:
    """ε-greedy over Â for every agent: q, mask (N, B, |Ḡ|); ε a number or one per episode (B,); agent i draws from
    rngs[i]. Returns (B, N)."""
    greedy = masked_argmax(q, mask).numpy()  # (N, B)
    m = mask.numpy()
    out = greedy.copy()
    if np.any(np.asarray(epsilon) > 0):
        for i, g in enumerate(rngs):
            u = g.random(m.shape[1:])  # (B, |G|)
            explore = g.random(m.shape[1]) < epsilon
            rand = np.where(m[i], u, -1.0).argmax(axis=-1)
            out[i] = np.where(explore, rand, greedy[i])
    return np.ascontiguousarray(out.T, dtype=np.int64)


# ----- the learner ----------------------------------------------------------------------------------------------


class Learner:
    """The N agents' Q-networks, target networks, optimizer states and replay memories (Algorithm 1)."""

    def __init__(self, scenario: Scenario, settings: Settings, seed: int | None = None) -> None:
        """Fresh networks and empty memories.

        Args:
            scenario: the operation and team (knowledge and action layout).
            settings: learning settings.
            seed: master seed (default: settings.seed).
        """
        self.scenario = scenario
        self.settings = settings
        self.seed = settings.seed if seed is None else int(seed)
        n = scenario.n_agents
        self.sizes = layer_sizes(scenario, settings.hidden)
        self.net = StackedQ.fresh(self.sizes, [derive_seed(self.seed, _INIT, i) for i in range(n)])
        self.target = StackedQ.fresh(self.sizes, [0] * n)
        self.target.flat.copy_(self.net.flat)
        self.target.requires_grad_(False)
        self.opt = StackedAdam(self.net.flat, self.net.grad, settings.lr)
        self.replay = Replay(
            n,
            settings.memory,
            scenario.knowledge_size,
            scenario.n_actions,
            [derive_seed(self.seed, _REPLAY, i) for i in range(n)],
        )
        self.updates = np.zeros(n, dtype=np.int64)
        self.episodes_done = 0
        self.gamma = scenario.gamma
        na = scenario.n_actions
        self._mask_table = torch.from_numpy(action_mask(scenario, np.arange(na)).astype(np.float32))
        self._mask_none = torch.from_numpy(action_mask(scenario, np.array(-1)).astype(np.float32))
        self._nstep = [NStep(settings.n_step, self.gamma, settings.reward_scale) for _ in range(n)]
        self._nstep_batch = NStep(settings.n_step, self.gamma, settings.reward_scale)

    @property
    def n_agents(self) -> int:
        """N."""
        return self.scenario.n_agents

    # ----- acting ----------------------------------------------------------------------------------------------
    def q_values(self, knowledge: FloatArray) -> FloatArray:
        """Q-values (B, N, |Ḡ|) of every agent's own knowledge state (B, N, K)."""
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(knowledge.transpose(1, 0, 2), dtype=np.float32))
            q: FloatArray = self.net(x).numpy().transpose(1, 0, 2).astype(np.float64)
        return q

    def act(
        self,
        knowledge: FloatArray,
        mask: BoolArray,
        epsilon: float | FloatArray,
        rngs: Sequence[np.random.Generator],
    ) -> IntArray:
        """ε-greedy actions (B, N) over Â from knowledge (B, N, K) and masks (B, N, |Ḡ|); ε a number or one per
        episode (B,); agent i explores with rngs[i]."""
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(knowledge.transpose(1, 0, 2), dtype=np.float32))
            q = self.net(x)
            m = torch.from_numpy(np.ascontiguousarray(mask.transpose(1, 0, 2)))
            return epsilon_greedy(q, m, epsilon, rngs)

    # ----- storing ---------------------------------------------------------------------------------------------
    def store(self, agent: int, k: FloatArray, a: int, r: float, k2: FloatArray, mask2: BoolArray, done: bool) -> None:
        """Store one transition <K, a, K', f_R> of one agent (from an agent process), with Â of K' and whether K'
        ends the episode (the horizon: terminal in the target only with settings.horizon_terminal). Invalid input
        raises ValueError naming the bad value."""
        sc = self.scenario
        if not 0 <= agent < sc.n_agents:
            raise ValueError(f"agent {agent!r} is out of range 0..{sc.n_agents - 1}")
        k_arr, k2_arr, m_arr = np.asarray(k), np.asarray(k2), np.asarray(mask2)
        ks = sc.knowledge_size
        if k_arr.shape != (ks,) or k2_arr.shape != (ks,):
            raise ValueError(f"knowledge states must have shape ({ks},), got {k_arr.shape} and {k2_arr.shape}")
        if not (np.isfinite(k_arr).all() and np.isfinite(k2_arr).all() and math.isfinite(float(r))):
            raise ValueError(f"transition of agent {agent} holds NaN or infinity (reward {r!r})")
        if m_arr.shape != (sc.n_actions,) or m_arr.dtype != np.bool_ or not m_arr.any():
            raise ValueError(f"mask2 must be bool of shape ({sc.n_actions},) with an allowed action, got {m_arr!r}")
        if not 0 <= int(a) < sc.n_actions:
            raise ValueError(f"action {a!r} is out of range 0..{sc.n_actions - 1}")
        for t in self._nstep[agent].push(k_arr, int(a), float(r), k2_arr, m_arr, bool(done), self._terminal(done)):
            self.replay.add(agent, *t)

    def _terminal(self, done: bool) -> bool:
        return bool(done) and self.settings.horizon_terminal

    def store_batch(
        self, k: FloatArray, a: IntArray, r: FloatArray, k2: FloatArray, mask2: BoolArray, done: bool
    ) -> None:
        """Store B transitions of every agent (arrays with a leading (B, N)); each goes to its agent's memory.
        `done`: K' is at the horizon (terminal in the target only with settings.horizon_terminal)."""
        for t in self._nstep_batch.push(k, a, r, k2, mask2, bool(done), self._terminal(done)):
            self.replay.add_batch(*t)

    # ----- training --------------------------------------------------------------------------------------------
    def ready(self) -> BoolArray:
        """(N,) agents whose memories hold enough transitions to train."""
        need = max(self.settings.learning_starts, 1)
        return np.asarray(self.replay.size >= need)

    def loss(self, batch: Batch, active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Sum over active agents of each agent's mean Huber TD error, and the per-agent losses (N,)."""
        s = self.settings
        k = torch.from_numpy(batch.k)
        k2 = torch.from_numpy(batch.k2)
        a = torch.from_numpy(batch.a)
        r = torch.from_numpy(batch.r)
        mask2 = torch.from_numpy(batch.mask2) | ~active[:, None, None]  # padding rows of idle learners: any action
        discount = torch.from_numpy(batch.discount)
        m = k.shape[1]
        if s.double_dqn:  # one pass of the online network over K and K'
            q_both = self.net(torch.cat([k, k2], dim=1))
            q, q_o = q_both[:, :m], q_both[:, m:].detach()
        else:
            q, q_o = self.net(k), None
        with torch.no_grad():
            if s.advantage_learning > 0:
                qt_both = self.target(torch.cat([k, k2], dim=1))
                qt_k, qt_k2 = qt_both[:, :m], qt_both[:, m:]
                y = bellman_targets(r, discount, qt_k2, mask2, q_o)
                y = y - s.advantage_learning * advantage_gap(qt_k, self.knowledge_mask(k), a)
            else:
                y = bellman_targets(r, discount, self.target(k2), mask2, q_o)
        q = q.gather(-1, a[..., None])[..., 0]
        per_agent = torch.nn.functional.huber_loss(q, y, reduction="none", delta=s.huber_delta).mean(dim=1)
        per_agent = per_agent * active.to(per_agent.dtype)
        return per_agent.sum(), per_agent.detach()

    def knowledge_mask(self, k: torch.Tensor) -> torch.Tensor:
        """Â(a_o) (..., |Ḡ|) of knowledge states (..., K), from their one-hot previous assignment."""
        onehot = k[..., self.scenario.n_tasks * self.scenario.levels :]
        none = 1.0 - onehot.sum(-1, keepdim=True)
        return (onehot @ self._mask_table + none * self._mask_none) > 0.5

    def train_step(self) -> float | None:
        """One gradient update of every agent whose memory holds enough data (line 10 of Algorithm 1); returns the
        mean loss of those agents, or None when no agent is ready yet."""
        ready = self.ready()
        if not ready.any():
            return None
        active = torch.from_numpy(ready)
        batch = self.replay.sample(self.settings.batch_size, ready)
        total, per_agent = self.loss(batch, active)
        self.net.zero_grad_()
        self.net.backward(total)
        clip_grad_per_agent(self.net.grad, self.settings.grad_clip)
        self.opt.step(active)
        self.updates += ready
        sync = ready & (self.updates % self.settings.target_sync == 0)
        if sync.any():
            self.sync_target(sync)
        return float(per_agent[active].mean())

    def sync_target(self, agents: BoolArray) -> None:
        """Copy the online networks of the marked agents into their target networks."""
        idx = torch.from_numpy(np.flatnonzero(agents))
        with torch.no_grad():
            self.target.flat[idx] = self.net.flat[idx]

    # ----- weights and persistence -----------------------------------------------------------------------------
    def agent_weights(self, agent: int) -> bytes:
        """Agent `agent`'s online network as bytes (the format of `qnet.AgentQ.get_weights`)."""
        if not 0 <= agent < self.n_agents:
            raise ValueError(f"agent {agent!r} is out of range 0..{self.n_agents - 1}")
        return pack_weights(self.net.agent_params(agent))

    def policy(self) -> QPolicy:
        """The greedy decentralized team policy of the current networks."""
        return QPolicy(self.scenario, self.net)

    def save(
        self,
        directory: str | Path,
        replay: bool = True,
        extra: dict[str, Any] | None = None,
        policy_flat: torch.Tensor | None = None,
    ) -> Path:
        """Write a checkpoint directory (see `learning.checkpoint`) with everything needed to continue exactly.

        Args:
            directory: the checkpoint directory.
            replay: also save the replay memories.
            extra: JSON-able additions to the checkpoint's info.
            policy_flat: networks (N, P) to publish as the agents' networks instead of the current ones (a selected
                best); the current ones then go into the training state, from which training resumes.
        """
        from htlm_agent.learning.checkpoint import save_checkpoint

        train_state = {
            "target": self.target.flat.detach().clone(),
            "adam": self.opt.state(),
        }
        weights = [self.net.agent_params(i) for i in range(self.n_agents)]
        if policy_flat is not None:
            train_state["online"] = self.net.flat.detach().clone()
            sel = StackedQ(self.sizes, [[torch.zeros(sh) for sh in self.net.shapes]] * self.n_agents)
            with torch.no_grad():
                sel.flat.copy_(policy_flat)
            weights = [sel.agent_params(i) for i in range(self.n_agents)]
        rs = self.replay.state() if replay else None
        info = {
            "updates": self.updates.tolist(),
            "replay_rngs": rs.pop("rngs") if rs is not None else None,
            **(extra or {}),
        }
        return save_checkpoint(
            directory,
            scenario=self.scenario,
            settings=self.settings,
            seed=self.seed,
            episodes_done=self.episodes_done,
            weights=weights,
            train_state=train_state,
            replay_state=rs,
            info=info,
        )

    @staticmethod
    def load(directory: str | Path, settings: Settings | None = None) -> Learner:
        """A learner from a checkpoint directory, with its target networks, optimizer state and (when saved) replay
        memories; `settings` may replace the saved ones if the network layout is the same (e.g. more episodes)."""
        from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint

        ck = load_checkpoint(directory)
        s = ck.settings if settings is None else settings
        if tuple(s.hidden) != tuple(ck.settings.hidden):
            raise CheckpointError(f"{ck.path}: hidden sizes {list(ck.settings.hidden)} differ from {list(s.hidden)}")
        lr = Learner(ck.scenario, s, ck.seed)
        for i, w in enumerate(ck.weights):
            lr.net.set_agent_params(i, w)
        lr.episodes_done = ck.episodes_done
        ts = ck.train_state()
        if ts is not None:
            with torch.no_grad():
                lr.target.flat.copy_(ts["target"])
                if "online" in ts:
                    lr.net.flat.copy_(ts["online"])
            lr.opt.load_state(ts["adam"])
        else:
            lr.target.flat.copy_(lr.net.flat)
        lr.updates[:] = ck.info.get("updates", [0] * lr.n_agents)
        rs = ck.replay_state()
        if rs is not None and ck.info.get("replay_rngs") is not None and s.memory == ck.settings.memory:
            rs["rngs"] = ck.info["replay_rngs"]
            lr.replay.load_state(rs)
        return lr


class QPolicy:
    """The decentralized team policy of stacked Q-networks: every agent takes the greedy masked argmax of its own
    network over its own knowledge state and Â (its own row of the Context only)."""

    def __init__(self, scenario: Scenario, net: StackedQ) -> None:
        """Wrap networks (not copied: the policy follows later training)."""
        assert net.n_agents == scenario.n_agents and net.sizes[0] == scenario.knowledge_size
        self.scenario = scenario
        self.net = net

    @staticmethod
    def from_checkpoint(ckpt: Any) -> QPolicy:
        """The policy of a loaded checkpoint (`checkpoint.Checkpoint`)."""
        net = StackedQ(
            layer_sizes(ckpt.scenario, ckpt.settings.hidden), [[torch.from_numpy(p) for p in w] for w in ckpt.weights]
        )
        net.requires_grad_(False)
        return QPolicy(ckpt.scenario, net)

    def act(self, ctx: Context) -> IntArray:
        """Greedy actions (B, N)."""
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(ctx.knowledge.transpose(1, 0, 2), dtype=np.float32))
            m = torch.from_numpy(np.ascontiguousarray(ctx.mask.transpose(1, 0, 2)))
            a = masked_argmax(self.net(x), m)  # (N, B)
        return np.ascontiguousarray(a.numpy().T, dtype=np.int64)


# ----- the in-process training loop -----------------------------------------------------------------------------


@dataclass
class TrainResult:
    """What `train` produced."""

    out_dir: Path
    scenario: Scenario
    settings: Settings
    episodes: int
    wall_time: float
    """Seconds of the whole call, final evaluation included."""
    train_time: float
    """Seconds of training only (no final evaluation, no checkpoint writing)."""
    metrics: dict[str, Any]
    """Final greedy evaluation (`evaluate.evaluate`)."""
    history: list[dict[str, float]] = field(default_factory=list)


LOG_FIELDS = (
    "episodes",
    "wall_s",
    "episodes_per_s",
    "epsilon",
    "updates",
    "loss",
    "reward",
    "completion",
    "failure_rate",
    "unused_fraction",
    "val_completion",
    "val_failure_rate",
    "val_unused_fraction",
)


def _batch_completion(levels_hist: list[IntArray], horizon: int) -> tuple[FloatArray, BoolArray]:
    done = np.stack([(lv == 0).all(axis=1) for lv in levels_hist[1:]])  # (h, B)
    failed: BoolArray = np.asarray(~done.any(axis=0))
    return np.where(failed, horizon, done.argmax(axis=0) + 1).astype(np.float64), failed


def train_batch(learner: Learner, team: Team, batch_index: int) -> dict[str, float]:
    """Algorithm 1, lines 3-10, for B episodes at once: run one batch of episodes ε-greedily, storing every agent's
    transitions in its own memory and training every agent `updates_per_step` times per step."""
    sc, s = learner.scenario, learner.settings
    seed = learner.seed
    n, p, b = sc.n_agents, sc.n_tasks, team.batch
    team.sim.rng = np.random.default_rng(np.random.SeedSequence([seed, _TRAIN_WORLD, batch_index]))
    team.sim.channel_rngs = [
        np.random.default_rng(np.random.SeedSequence([seed, _TRAIN_CHANNEL, i, batch_index])) for i in range(n)
    ]
    rngs = [np.random.default_rng(np.random.SeedSequence([seed, _EXPLORE, i, batch_index])) for i in range(n)]
    eps = s.epsilon(learner.episodes_done)
    eps_env: float | FloatArray = eps
    if s.eps_spread and b > 1:  # from 0 (greedy episodes) to 2ε, mean ε
        eps_env = np.minimum(1.0, eps * 2.0 * np.arange(b) / (b - 1))
    k = team.reset()
    m = team.mask()
    levels = [team.sim.levels.copy()]
    idle = np.zeros((b, n))
    rsum = 0.0
    losses: list[float] = []
    for t in range(sc.horizon):
        a = learner.act(k, m, eps_env, rngs)
        k2, r, info = team.step(a)
        m2 = team.mask()
        learner.store_batch(k, a, r, k2, m2, t == sc.horizon - 1)
        for _ in range(s.updates_per_step):
            loss = learner.train_step()
            if loss is not None:
                losses.append(loss)
        levels.append(info.levels)
        idle += a >= p
        rsum += float(r.mean())
        k, m = k2, m2
    learner.episodes_done += b
    comp, failed = _batch_completion(levels, sc.horizon)
    caps = np.array([ag.fire + ag.rescue for ag in sc.agents], dtype=np.float64)
    unused = (idle * caps).sum(axis=1) / (n * sc.horizon)
    return {
        "epsilon": eps,
        "loss": float(np.mean(losses)) if losses else float("nan"),
        "reward": rsum / sc.horizon,
        "completion": float(comp.mean()),
        "failure_rate": float(failed.mean()),
        "unused_fraction": float(unused.mean() / caps.mean()) if caps.mean() > 0 else 0.0,
    }


def write_run_files(out_dir: Path, scenario: Scenario, settings: Settings) -> None:
    """settings.json and scenario.yaml beside the run's results (STYLE.md 2)."""
    import yaml

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "settings.json").write_text(json.dumps(settings.to_dict(), indent=2) + "\n")
    (out_dir / "scenario.yaml").write_text(yaml.safe_dump(scenario.to_dict(), sort_keys=False))


RESUMABLE_CHANGES = (
    "episodes",
    "eval_episodes",
    "validate_every",
    "validate_episodes",
    "checkpoint_every",
    "keep_replay",
    "threads",
)
"""Settings that may differ when a run is resumed; every other field must match the checkpoint's."""


class _Selection:
    """The best networks by validation completion step (lower is better; the later one wins a tie)."""

    def __init__(self, learner: Learner, info: dict[str, Any]) -> None:
        self.learner = learner
        self.score: float = float(info.get("best_score", math.inf))
        self.episode: int = int(info.get("best_episode", -1))
        self.flat: torch.Tensor | None = None

    def offer(self, score: float) -> None:
        if score <= self.score:
            self.score, self.episode = score, self.learner.episodes_done
            self.flat = self.learner.net.flat.detach().clone()

    def info(self) -> dict[str, Any]:
        return {"best_score": None if math.isinf(self.score) else self.score, "best_episode": self.episode}


def validate(learner: Learner, episodes: int) -> dict[str, Any]:
    """Greedy validation of the current networks on episodes of the run's validation stream."""
    from htlm_agent.experiments.evaluate import evaluate

    return evaluate(learner.policy(), learner.scenario, episodes, seed=derive_seed(learner.seed, _VALIDATE))


def train(
    scenario: Scenario,
    settings: Settings,
    out_dir: str | Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """Train a team in process (Algorithm 1 with B parallel episodes) and evaluate it greedily at the end.

    Writes into out_dir: settings.json, scenario.yaml, progress.csv (one row per batch of episodes), tb/ (TensorBoard),
    checkpoint/ (periodic and final; with select_best its networks are the best validated ones, the latest are in its
    training state), eval/ (final evaluation: metrics.json, CSVs, histogram PNG), result.json.

    Args:
        scenario: operation and team (ignored when resuming: the checkpoint's is used).
        settings: learning settings (when resuming, only the fields in RESUMABLE_CHANGES may differ).
        out_dir: the run directory.
        progress: show a progress line on stderr.
        resume: continue the run in out_dir from its checkpoint.
        tensorboard: also write TensorBoard logs.
        evaluate_at_end: run the final greedy evaluation (settings.eval_episodes episodes, seed settings.seed).
    """
    from htlm_agent.experiments import evaluate as ev
    from htlm_agent.experiments.progress import Progress
    from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint

    t_start = time.perf_counter()
    out = Path(out_dir)
    torch.set_num_threads(settings.threads)
    torch.use_deterministic_algorithms(True)
    ckpt_dir = out / "checkpoint"
    info: dict[str, Any] = {}
    if resume:
        ck = load_checkpoint(ckpt_dir)
        scenario = ck.scenario
        fixed = {k: v for k, v in ck.settings.to_dict().items() if k not in RESUMABLE_CHANGES}
        mine = {k: v for k, v in settings.to_dict().items() if k in fixed}
        if fixed != mine:
            diff = sorted(k for k in fixed if fixed[k] != mine[k])
            raise CheckpointError(
                f"{ck.path}: cannot resume with changed settings {diff}; only {list(RESUMABLE_CHANGES)} may change"
            )
        learner = Learner.load(ckpt_dir, settings)
        info = ck.info
    else:
        if (ckpt_dir / "meta.json").exists():
            raise FileExistsError(f"{out}: already holds a run; resume it or choose another output directory")
        learner = Learner(scenario, settings)
    s = settings
    write_run_files(out, scenario, s)
    team = Team(scenario, s.envs, s.seed)
    selection = _Selection(learner, info)
    if selection.episode >= 0 and resume:
        best = load_checkpoint(ckpt_dir)
        selection.flat = torch.stack([torch.cat([torch.from_numpy(p).reshape(-1) for p in w]) for w in best.weights])
    writer = None
    if tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tb"), purge_step=learner.episodes_done if resume else None)
    log_path = out / "progress.csv"
    rows_before: list[dict[str, str]] = []
    if resume and log_path.exists():  # keep rows up to the checkpoint (drop those of an interrupted tail)
        with log_path.open() as f:
            rows_before = [r for r in csv.DictReader(f) if int(r["episodes"]) <= learner.episodes_done]
    log_file = log_path.open("w", newline="")
    log = csv.DictWriter(log_file, LOG_FIELDS, extrasaction="ignore")
    log.writeheader()
    log.writerows(rows_before)
    decayed_at = s.eps_fraction * s.episodes

    def save() -> None:
        extra = selection.info()
        policy = selection.flat if s.select_best else None
        learner.save(ckpt_dir, replay=s.keep_replay, extra=extra, policy_flat=policy)

    bar = Progress(s.episodes, initial=learner.episodes_done, unit="ep", enabled=progress)
    history: list[dict[str, float]] = []
    train_time = 0.0
    last_ckpt = last_val = learner.episodes_done
    try:
        while learner.episodes_done < s.episodes:
            t0 = time.perf_counter()
            row: dict[str, float] = train_batch(learner, team, learner.episodes_done // s.envs)
            train_time += time.perf_counter() - t0
            row["episodes"] = learner.episodes_done
            row["updates"] = int(learner.updates.max())
            row["wall_s"] = round(time.perf_counter() - t_start, 3)
            row["episodes_per_s"] = bar.rate
            final = learner.episodes_done >= s.episodes
            if (
                s.validate_every
                and s.validate_episodes
                and (learner.episodes_done - last_val >= s.validate_every or final)
            ):
                last_val = learner.episodes_done
                vm = validate(learner, s.validate_episodes)
                row["val_completion"] = vm["completion"]["mean"]
                row["val_failure_rate"] = vm["completion"]["failure_rate"]
                row["val_unused_fraction"] = vm["unused_fraction"]["mean"]
                if learner.episodes_done >= decayed_at:
                    selection.offer(vm["completion"]["mean"])
            history.append(row)
            log.writerow(row)
            log_file.flush()
            if writer is not None:
                for key, val in row.items():
                    if key not in ("episodes", "wall_s") and not math.isnan(val):
                        writer.add_scalar(f"train/{key}", val, learner.episodes_done)
            bar.update(
                learner.episodes_done,
                completion=f"{row['completion']:.2f}",
                unused=f"{row['unused_fraction']:.2f}",
                eps=f"{row['epsilon']:.2f}",
            )
            if s.checkpoint_every and learner.episodes_done - last_ckpt >= s.checkpoint_every and not final:
                last_ckpt = learner.episodes_done
                save()
    finally:
        bar.close()
        log_file.close()
    save()
    metrics: dict[str, Any] = {}
    if evaluate_at_end and s.eval_episodes > 0:
        policy = QPolicy.from_checkpoint(load_checkpoint(ckpt_dir))
        evaluation = ev.evaluate_run(policy, scenario, s.eval_episodes, seed=s.seed, policy_name="htlm-dqn")
        ev.write_reports(evaluation, out / "eval")
        metrics = evaluation.metrics
        if writer is not None:
            writer.add_scalar("eval/completion", metrics["completion"]["mean"], learner.episodes_done)
            writer.add_scalar("eval/failure_rate", metrics["completion"]["failure_rate"], learner.episodes_done)
            writer.add_scalar("eval/unused_fraction", metrics["unused_fraction"]["mean"], learner.episodes_done)
    if writer is not None:
        writer.close()
    wall = time.perf_counter() - t_start
    summary = {
        "episodes": learner.episodes_done,
        "wall_time_s": round(wall, 2),
        "train_time_s": round(train_time, 2),
        "selected_episode": selection.episode if s.select_best else None,
        "metrics": metrics,
    }
    (out / "result.json").write_text(json.dumps(summary, indent=2) + "\n")
    if progress and metrics:
        c = metrics["completion"]
        print(
            f"final greedy evaluation ({metrics['episodes']} episodes): completion {c['mean']:.2f} ± {c['se']:.2f}"
            f", failures {c['failure_rate']:.1%}, unused capability {metrics['unused_fraction']['mean']:.1%}"
            f" ({wall:.0f} s)",
            file=sys.stderr,
        )
    return TrainResult(out, scenario, s, learner.episodes_done, wall, train_time, metrics, history)
