"""Decentralized deep Q-learning for load management (Algorithm 1 of the paper): the learner.

Every agent has its own Q-network, target network, optimizer state and replay memory; agents never share
parameters, gradients or memories. For speed the N networks are stacked (`qnet.StackedQ`) and trained as one batched
computation through autograd: the loss is the sum of the agents' own losses, so every agent's gradient is that of its
own loss, and the optimizer is torch.optim's Adam with every agent's row as its own parameter (`optim.AgentRows`), so
that each agent keeps its own moments and step count, exactly as N separate Adam optimizers would.

Two ways to feed the learner:
- in process: `htlm_agent.learning.run.train()` runs B episodes at once in `team.Team` (line 3-10 of
  Algorithm 1 as array operations);
- from another process (the ROS trainer node): `Learner.store()` one transition at a time, `Learner.train_step()`,
  and `Learner.agent_weights()` to send an agent its new weights.

Random streams (`htlm_world.seeds`), all derived from the run's seed: network initialisation per agent, replay
sampling per agent; exploration comes with the generators the caller passes to `act`. The same seed gives the same
learning curve and the same weights (on CPU, for the same `threads`).

Two departures from textbook DQN, both measured on the heterogeneous team (see `Settings`):
- the horizon is not a terminal state in the target (`horizon_terminal=False`): the knowledge state holds no time, so
  a terminal at h gives one knowledge state targets anywhere between r and r/(1-γ);
- advantage learning (`advantage_learning=0.9`): with the idle incentive, idling now and working next step is worth
  almost as much to one agent as working now (a gap of about 1 in Q-values near 200), so plain Q-learning's greedy
  policy often stalls with every agent idle; widening the gaps keeps the greedy team working.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.learning.checkpoint import TRAIN_STATE, CheckpointError, load_checkpoint, save_checkpoint
from htlm_agent.learning.optim import AgentRows, clip_grad_per_agent
from htlm_agent.learning.qnet import (
    QNetwork,
    StackedQ,
    build_network,
    copy_network,
    init_params,
    layer_sizes,
    pack_weights,
)
from htlm_agent.learning.qpolicy import QPolicy, greedy_actions
from htlm_agent.learning.replay import ExpertMemory, Replay
from htlm_agent.learning.settings import Settings
from htlm_agent.learning.targets import NStep, advantage_gap, bellman_targets
from htlm_agent.learning.tokens import TokenQ
from htlm_agent.learning.update import Minibatches, UpdateBatch, flush_denormals
from htlm_agent.mind.knowledge import AnyFloats, previous
from htlm_agent.mind.policies import team_epsilon_greedy
from htlm_world import seeds
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray

IMITATION_MARGIN = 0.5
"""m of the warm start's large-margin loss, in the learner's scaled Q units (`Settings.reward_scale`): how far
above every other action the baseline's choice must score."""


class Learner:
    """The N agents' Q-networks, target networks, optimizer states and replay memories (Algorithm 1)."""

    def __init__(
        self, scenario: Scenario, settings: Settings, seed: int | None = None, model: Model | None = None
    ) -> None:
        """Fresh networks and empty memories.

        Args:
            scenario: the operation and team (knowledge and action layout).
            settings: learning settings.
            seed: master seed (default: settings.seed).
            model: the scenario compiled (`Model.build`), when the caller has it already.
        """
        self.scenario = scenario
        self.settings = settings
        self.seed = settings.seed if seed is None else int(seed)
        n = scenario.n_agents
        self.sizes = layer_sizes(scenario, settings.hidden)
        count = 1 if settings.network == "tokens" and settings.shared else n
        init = [init_params(scenario, settings, seeds.network_init(self.seed, i)) for i in range(count)]
        self.net: QNetwork = build_network(scenario, settings, init)
        self.target: QNetwork = copy_network(self.net)
        self.target.requires_grad_(False)
        self.net.grad.zero_()
        self._rows: AgentRows | None = None
        """The paper's networks: every agent's row of parameters on its own, for its own optimizer state."""
        self.opt: torch.optim.Adam
        if isinstance(self.net, StackedQ):
            self._rows = AgentRows(self.net.flat, self.net.grad)
            self.opt = self._rows.adam(settings.lr)
        else:
            self.opt = torch.optim.Adam([self.net.flat], lr=settings.lr)
        assert model is None or model.scenario == scenario, "a model of another scenario"
        self.model = model if model is not None else Model.build(scenario)
        self._mask_by_bits = self._masks_by_bits()
        self.replay = Replay(
            n,
            settings.memory,
            scenario.knowledge_size,
            scenario.n_actions,
            [seeds.replay(self.seed, i) for i in range(n)],
            knowledge_mask=self._knowledge_mask,
        )
        self.updates = np.zeros(n, dtype=np.int64)
        self.episodes_done = 0
        self._experts: ExpertMemory | None = None
        self.gamma = scenario.gamma
        self._nstep = [NStep(settings.n_step, self.gamma, settings.reward_scale) for _ in range(n)]
        self._nstep_batch = NStep(settings.n_step, self.gamma, settings.reward_scale)
        self._minibatches: dict[int, Minibatches] = {}  # storage of `update_batches`, by number of minibatches
        self._act_buffers: dict[int, tuple[torch.Tensor, torch.Tensor, list[torch.Tensor], torch.Tensor]] = {}
        self._outs: dict[int, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
        """Every layer's output of the online networks on K' and of the target networks on K and K', by M."""

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
        net: QNetwork | None = None,
    ) -> IntArray:
        """ε-greedy actions (B, N) over Â from knowledge (B, N, K) and masks (B, N, |Ḡ|); ε a number or one per
        episode (B,); agent i explores with rngs[i] (`policies.team_epsilon_greedy`, as the agents' processes do).
        `net`: the networks to act with (default: the online ones; `loop.LaggedNets` gives older ones under a trainer
        lag)."""
        acting = self.net if net is None else net
        with flush_denormals():
            if isinstance(acting, StackedQ):
                greedy = self._greedy(knowledge, mask, acting)
            else:
                greedy = greedy_actions(acting, knowledge, mask)
        return team_epsilon_greedy(greedy, mask, epsilon, rngs)

    def _greedy(self, knowledge: FloatArray, mask: BoolArray, net: StackedQ) -> IntArray:
        """`qpolicy.greedy_actions` of `net` (the same numbers) in buffers made once per batch size."""
        b = knowledge.shape[0]
        bufs = self._act_buffers.get(b)
        if bufs is None:
            n, sizes = self.n_agents, self.net.sizes
            bufs = self._act_buffers[b] = (
                torch.zeros(n, b, sizes[0]),
                torch.zeros(n, b, sizes[-1], dtype=torch.bool),
                [torch.zeros(n, b, f) for f in sizes[1:]],
                torch.zeros(n, b, dtype=torch.int64),
            )
        x, blocked, outs, a = bufs
        np.copyto(x.numpy(), knowledge.transpose(1, 0, 2), casting="same_kind")
        np.logical_not(mask.transpose(1, 0, 2), out=blocked.numpy())
        with torch.no_grad():
            q = net.forward_into(x, outs).masked_fill_(blocked, -math.inf)
            torch.argmax(q, dim=-1, out=a)  # the first of equal maxima, as qnet.masked_argmax
        out: IntArray = a.numpy().T
        return out

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

    def knowledge_mask(self, k: AnyFloats) -> torch.Tensor:
        """Â(a_o) (..., |Ḡ|) of knowledge states (..., K), from the previous assignment they hold."""
        return torch.from_numpy(self._knowledge_mask(k))

    def _knowledge_mask(self, k: AnyFloats) -> BoolArray:
        """Â(previous(k)) as arrays, by a table of the one-hot part's bits (what `previous` reads: the first entry
        above 0.5, none: -1) when it has at most 16 entries."""
        sc = self.scenario
        if self._mask_by_bits is None:
            out: BoolArray = self.model.action_mask(previous(k, sc))
            return out
        start = sc.n_tasks * sc.levels
        bits = np.packbits(np.asarray(k)[..., start : start + sc.n_actions] > 0.5, axis=-1, bitorder="little")
        code = bits[..., 0].astype(np.int64)
        if bits.shape[-1] > 1:
            code |= bits[..., 1].astype(np.int64) << 8
        out = self._mask_by_bits[code]
        return out

    def _masks_by_bits(self) -> BoolArray | None:
        """Â(a_o) for every pattern of the one-hot part of K taken as bits (bit j: entry j > 0.5), a_o the lowest set
        bit (-1 for none), as `previous` decodes it; None when the part has more than 16 entries."""
        sc = self.scenario
        width = sc.n_actions
        if width > 16:
            return None
        codes = np.arange(2**width)
        lowest = np.array([(c & -c).bit_length() - 1 for c in codes.tolist()], dtype=np.int64)  # -1 for 0
        out: BoolArray = self.model.action_mask(lowest)
        return out

    def update_batches(self, ready: BoolArray, count: int = 1) -> list[UpdateBatch]:
        """`count` minibatches of every agent marked in `ready` (others: padding) from its own memory, drawn one
        after the other as `count` calls of `Replay.sample_records` would, as the tensors of `batch_loss` (with
        Â of K and K' from the memories' `allowed`)."""
        s, sc = self.settings, self.scenario
        n, m, ks = sc.n_agents, s.batch_size, sc.knowledge_size
        replay = self.replay
        mb = self._minibatches.get(count)
        if mb is None:
            mb = self._minibatches[count] = Minibatches(count, n, m, ks, sc.n_actions, replay.width)
        slots = replay.slots(replay.sample_indices(m, ready, count)).reshape(-1)  # agent-major, then draw
        rec = np.take(replay.data.reshape(-1, replay.width), slots, axis=0, out=mb.records)
        rec4 = rec.reshape(n, count, m, replay.width).swapaxes(0, 1)  # (count, N, M, D)
        c = replay.cols
        mb.x[:, :, :m] = rec4[..., c["k"]]
        mb.x[:, :, m:] = rec4[..., c["k2"]]
        mb.a[...] = rec4[..., c["a"].start]
        mb.r[...] = rec4[..., c["r"].start]
        mb.discount[...] = rec4[..., c["discount"].start]
        assert replay.allowed is not None
        np.take(replay.allowed.reshape(-1, 2, sc.n_actions), slots, axis=0, out=mb.allowed)
        if not ready.all():  # padding rows of idle learners: any action
            mb.allowed.reshape(n, count * m, 2, -1)[~ready, :, 1] = True
        mb.weight[:, 0, 0] = np.where(ready, np.float32(1.0 / m), np.float32(0.0))
        return mb.batches

    def train_step(self) -> float | None:
        """One gradient update of every agent whose memory holds enough data (line 10 of Algorithm 1); returns the
        mean loss of those agents, or None when no agent is ready yet."""
        losses = self.train_steps(1)
        return losses[0] if losses else None

    def train_steps(self, count: int) -> list[float]:
        """`count` calls of `train_step` (the memories do not change in between, so the minibatches are drawn and
        gathered together); returns the losses, none while no agent is ready."""
        ready = self.ready()
        if not ready.any():
            return []
        with flush_denormals():
            return self._train(ready, count)

    def _train(self, ready: BoolArray, count: int) -> list[float]:
        """`count` updates of the agents marked in `ready`: the gradient of the sum of their `batch_loss`es through
        autograd, clipped per agent, one step of Adam."""
        s = self.settings
        net = self.net
        if self._rows is not None:
            self._rows.select(ready)
        all_ready = bool(ready.all())
        losses = []
        for batch in self.update_batches(ready, count):
            per_agent = self.batch_loss(batch)
            net.grad.zero_()
            if isinstance(net, StackedQ):
                net.backward(per_agent.sum())
            else:
                per_agent.sum().backward()  # type: ignore[no-untyped-call]
            clip_grad_per_agent(net.grad, s.grad_clip)
            self.opt.step()
            self.updates += ready
            sync = ready & (self.updates % s.target_sync == 0)
            if sync.any():
                self.sync_target(sync)
            done = per_agent.detach()
            losses.append(float(done.mean() if all_ready else done[torch.from_numpy(ready)].mean()))
        return losses

    def expert_memory(self) -> ExpertMemory:
        """The warm start's memory of expert choices (`Settings.imitate_updates`), made at its first use: as many
        team steps as `memory` holds transitions. A resumed run starts it anew."""
        if self._experts is None:
            sc = self.scenario
            self._experts = ExpertMemory(
                self.settings.memory, sc.n_agents, sc.knowledge_size, sc.n_actions, seeds.imitation(self.seed)
            )
        return self._experts

    def imitate(self, knowledge: FloatArray, mask: BoolArray, expert: IntArray) -> float:
        """One supervised update of the token networks towards a baseline's actions (the warm start,
        `Settings.imitate`): the large-margin loss of DQfD (Hester et al. 2018), max_a [Q(K, a) + m·(a ≠ a_E)] −
        Q(K, a_E) over Â, m = `IMITATION_MARGIN`, on every agent's knowledge (B, N, K), masks (B, N, |Ḡ|) and
        the baseline's actions (B, N) from the agent's own belief. Returns the loss."""
        net = self.net
        assert isinstance(net, TokenQ)
        x = torch.from_numpy(np.ascontiguousarray(knowledge.transpose(1, 0, 2), dtype=np.float32))
        allowed = torch.from_numpy(np.ascontiguousarray(mask.transpose(1, 0, 2)))
        a = torch.from_numpy(np.ascontiguousarray(expert.T, dtype=np.int64))[..., None]
        with flush_denormals():
            q = net(x)
            margin = torch.full_like(q, IMITATION_MARGIN).scatter_(-1, a, 0.0)
            best = (q + margin).masked_fill(~allowed, -math.inf).amax(dim=-1, keepdim=True)
            loss = (best - q.gather(-1, a)).mean()
            net.grad.zero_()
            loss.backward()
            clip_grad_per_agent(net.grad, self.settings.grad_clip)
            self.opt.step()
        return float(loss.detach())

    def batch_loss(self, b: UpdateBatch) -> torch.Tensor:
        """Every agent's loss (N,) on a minibatch of `update_batches`, through autograd: its mean Huber TD error
        (Double DQN and advantage learning as `Settings` says), 0 for the agents that do not train. Agents share
        nothing, so the gradient of the sum is every agent's own gradient."""
        s = self.settings
        m = b.m
        q_k, q_o, qt = self._q_values(b)
        q_a = q_k.gather(-1, b.a_col)  # (N, M, 1)
        with torch.no_grad():
            y = bellman_targets(b.r, b.discount, qt[:, m:], b.allowed2, q_o)
            if s.advantage_learning > 0:
                y.sub_(advantage_gap(qt[:, :m], b.allowed, b.a), alpha=s.advantage_learning)
        hub = torch.nn.functional.huber_loss(q_a, y[..., None], reduction="none", delta=s.huber_delta)
        return (hub * b.weight).sum(dim=(1, 2))

    def _q_values(self, b: UpdateBatch) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Q-values of the online networks on K (N, M, |Ḡ|, with a gradient) and on K' (N, M, |Ḡ|, without; for
        Double DQN only, else None), and of the target networks on K and K' (N, 2M, |Ḡ|, without)."""
        m, double = b.m, self.settings.double_dqn
        if isinstance(self.net, TokenQ):
            assert isinstance(self.target, TokenQ)
            tok = self.net.spec.features(b.x)  # K then K' of every agent, the tokens of both networks
            q_all = self.net.score(tok)
            with torch.no_grad():
                qt = self.target.score(tok)
            return q_all[:, :m], q_all[:, m:].detach() if double else None, qt
        assert isinstance(self.target, StackedQ)
        outs = self._outs.get(m)
        if outs is None:
            n, sizes = self.n_agents, self.net.sizes
            outs = self._outs[m] = (
                [torch.zeros(n, m, f) for f in sizes[1:]],
                [torch.zeros(n, 2 * m, f) for f in sizes[1:]],
            )
        q_k = self.net(b.x[:, :m])  # the gradient flows from K only: the backward pass is over M rows, not 2M
        with torch.no_grad():
            q_o = self.net.forward_into(b.x[:, m:], outs[0]) if double else None
            qt = self.target.forward_into(b.x, outs[1])
        return q_k, q_o, qt

    def sync_target(self, agents: BoolArray) -> None:
        """Copy the online networks of the marked agents into their target networks."""
        if isinstance(self.net, TokenQ) and self.net.shared:
            agents = np.ones(1, dtype=bool)
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
        train_state = {"target": self.target.flat.detach().clone(), "adam": self.opt.state_dict()}
        weights = [self.net.agent_params(i) for i in range(self.n_agents)]
        if policy_flat is not None:
            train_state["online"] = self.net.flat.detach().clone()
            sel = copy_network(self.net)
            with torch.no_grad():
                sel.flat.copy_(policy_flat[: sel.flat.shape[0]])
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
            lr._load_optimizer(ts.get("adam"), ck.path / TRAIN_STATE)
        else:
            lr.target.flat.copy_(lr.net.flat)
        lr.updates[:] = ck.info.get("updates", [0] * lr.n_agents)
        rs = ck.replay_state()
        if rs is not None and ck.info.get("replay_rngs") is not None and s.memory == ck.settings.memory:
            rs["rngs"] = ck.info["replay_rngs"]
            lr.replay.load_state(rs)
        return lr

    def _load_optimizer(self, saved: Any, path: Path) -> None:
        """Restore the optimizer state saved in the checkpoint file `path`: a torch.optim state dict, or (from the
        paper's learner before it used torch.optim) stacked moments {"m", "v", "t"}, converted. The step size and
        other hyperparameters stay those of the settings. Raises CheckpointError naming the file when the state does
        not fit the networks."""
        params = [p for group in self.opt.param_groups for p in group["params"]]
        try:
            if not isinstance(saved, dict):
                raise ValueError(f"expected a dict, got {type(saved).__name__}")
            if self._rows is not None and set(saved) == {"m", "v", "t"}:
                state: dict[Any, Any] = self._rows.adam_state(saved)
            elif isinstance(saved.get("state"), dict):
                state = saved["state"]
            else:
                raise ValueError(f"neither a torch.optim state dict nor stacked moments (keys {sorted(saved)})")
            for key, st in state.items():
                if not (isinstance(key, int) and 0 <= key < len(params)):
                    raise ValueError(f"state of parameter {key!r}, the optimizer has {len(params)}")
                for name, want in (("step", ()), ("exp_avg", params[key].shape), ("exp_avg_sq", params[key].shape)):
                    got = st.get(name) if isinstance(st, dict) else None
                    if not isinstance(got, torch.Tensor) or got.shape != want:
                        shape = tuple(got.shape) if isinstance(got, torch.Tensor) else None
                        raise ValueError(f"parameter {key}: {name} of shape {shape}, the network needs {tuple(want)}")
            self.opt.load_state_dict({"state": state, "param_groups": self.opt.state_dict()["param_groups"]})
        except (ValueError, KeyError, TypeError) as e:
            raise CheckpointError(f"{path}: optimizer state does not fit the networks: {e}") from None
