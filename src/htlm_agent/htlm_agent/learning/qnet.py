"""Q-networks (docs/model.md, Knowledge state, actions, Q-network): one MLP per agent, stacked for speed.

Every agent has its own network Q(K, ·; θ_i) from its knowledge state (p·L marginals + one-hot a_o) to one Q-value
per element of Ḡ. The N networks of a team are stored as stacked parameters of shape (N, ...) and evaluated as one
batched computation (`torch.baddbmm`): row i of the input only ever meets the parameters of agent i, so the agents
share no parameters; stacking is a layout, not a coupling.

`AgentQ` is one agent's network on its own, for the ROS agent node: it loads from a checkpoint, acts greedily over
the reduced action space Â(a_o), and exchanges its weights with the trainer as compact bytes (`pack_weights`).

Weight bytes format (little endian): magic ``b"HTQW"``, uint16 version (1), uint16 tensor count T, then per tensor
uint8 ndim and ndim × uint32 dims, then the float32 data of every tensor in order (C order). Tensors are, per layer,
the weight (in, out) then the bias (out,).
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from htlm_agent.learning.tokens import TokenQ, flatten, init_token_params, token_shapes, unflatten
from htlm_world.scenario import Scenario

F32 = NDArray[np.float32]

LAYOUT_WARNING = "grad and param do not obey the gradient layout contract"
"""Autograd's note on StackedQ's strided parameter and gradient views (on purpose: it accumulates into them in place;
the note is only about speed). `backward` silences it."""

WEIGHTS_MAGIC = b"HTQW"
WEIGHTS_VERSION = 1


def layer_sizes(scenario: Scenario, hidden: Sequence[int]) -> tuple[int, ...]:
    """Sizes of every layer: knowledge size K, the hidden sizes, |Ḡ|."""
    return (scenario.knowledge_size, *[int(h) for h in hidden], scenario.n_actions)


def param_shapes(sizes: Sequence[int]) -> list[tuple[int, ...]]:
    """Shapes of one agent's parameters in order: per layer the weight (in, out) then the bias (out,)."""
    shapes: list[tuple[int, ...]] = []
    for i in range(len(sizes) - 1):
        shapes += [(sizes[i], sizes[i + 1]), (sizes[i + 1],)]
    return shapes


def init_agent_params(sizes: Sequence[int], seed: int) -> list[torch.Tensor]:
    """Fresh parameters of one agent's MLP, as torch.nn.Linear initialises them (uniform ±1/√fan_in), from a
    torch.Generator seeded with `seed` (derived per agent by the caller)."""
    g = torch.Generator().manual_seed(seed)
    params: list[torch.Tensor] = []
    for i in range(len(sizes) - 1):
        bound = 1.0 / math.sqrt(sizes[i])
        w = (torch.rand((sizes[i], sizes[i + 1]), generator=g, dtype=torch.float32) * 2.0 - 1.0) * bound
        b = (torch.rand((sizes[i + 1],), generator=g, dtype=torch.float32) * 2.0 - 1.0) * bound
        params += [w, b]
    return params


class StackedQ(torch.nn.Module):
    """The Q-networks of N agents: ReLU MLPs whose parameters are the rows of one flat (N, P) tensor.

    Row i holds agent i's parameters (per layer the weight (in, out) then the bias (out,), C order). The layers,
    W_l (N, in, out) and b_l (N, 1, out), are leaf parameters aliasing `flat`, and autograd accumulates their gradients
    into views of `grad` (N, P), so one gradient clip and one optimizer step (`optim.AgentRows`) treat every agent row
    by row, and a forward pass is one `torch.baddbmm` per layer.
    """

    def __init__(self, sizes: Sequence[int], agent_params: Sequence[Sequence[torch.Tensor]]) -> None:
        """Stack per-agent parameter lists (each in `param_shapes(sizes)` order) into one module.

        Args:
            sizes: layer sizes (K, hidden..., |Ḡ|).
            agent_params: every agent's parameters.
        """
        super().__init__()
        self.sizes = tuple(int(s) for s in sizes)
        self.n_agents = n = len(agent_params)
        self.shapes = param_shapes(self.sizes)
        for k, params in enumerate(agent_params):
            got = [tuple(p.shape) for p in params]
            assert got == self.shapes, f"agent {k}: parameter shapes {got} != {self.shapes}"
        self.offsets = np.cumsum([0] + [int(np.prod(s)) for s in self.shapes]).tolist()
        rows = [
            torch.cat([torch.as_tensor(p, dtype=torch.float32).reshape(-1) for p in params]) for params in agent_params
        ]
        self.flat = torch.stack(rows).contiguous()
        self.grad = torch.zeros_like(self.flat)
        self.weights = torch.nn.ParameterList()
        self.biases = torch.nn.ParameterList()
        o = self.offsets
        for li in range(len(self.sizes) - 1):
            fan_in, fan_out = self.sizes[li], self.sizes[li + 1]
            for j, shape, dst in (
                (2 * li, (n, fan_in, fan_out), self.weights),
                (2 * li + 1, (n, 1, fan_out), self.biases),
            ):
                p = torch.nn.Parameter(self.flat[:, o[j] : o[j + 1]].view(shape))
                p.grad = self.grad[:, o[j] : o[j + 1]].view(shape)
                dst.append(p)
        # the layers as a plain list (ParameterList indexing is slow next to these small products); the parameters
        # are never replaced, only written in place
        self._layers = list(zip(self.weights, self.biases, strict=True))

    def zero_grad_(self) -> None:
        """Clear the flat gradient (gradients accumulate into it in place)."""
        self.grad.zero_()

    _layout_noted = False  # autograd gives its note once per process: after the first backward pass, nothing to hide

    @staticmethod
    def backward(loss: torch.Tensor) -> None:
        """loss.backward() of a loss of stacked networks, the gradient landing in `grad` of the networks involved."""
        if StackedQ._layout_noted:
            loss.backward()  # type: ignore[no-untyped-call]
            return
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=LAYOUT_WARNING)
            loss.backward()  # type: ignore[no-untyped-call]
        StackedQ._layout_noted = True

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Clear the flat gradient; the layer gradients stay views of it whatever `set_to_none` says."""
        self.zero_grad_()

    @property
    def n_params(self) -> int:
        """P, parameters per agent."""
        return int(self.offsets[-1])

    @staticmethod
    def fresh(sizes: Sequence[int], seeds: Sequence[int]) -> StackedQ:
        """New networks, agent i initialised from seeds[i]."""
        return StackedQ(sizes, [init_agent_params(sizes, s) for s in seeds])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Q-values (N, M, |Ḡ|) of inputs (N, M, K): agent i's network on row i."""
        layers = self._layers
        last = len(layers) - 1
        for li, (w, b) in enumerate(layers):
            x = torch.baddbmm(b, x, w)
            if li < last:
                x = x.relu_()  # in place on the product's own output, which its gradient does not read
        return x

    def forward_into(self, x: torch.Tensor, outs: Sequence[torch.Tensor]) -> torch.Tensor:
        """`forward` with every layer's output written into `outs` (one tensor per layer, (N, M, size)); returns the
        last (the same numbers as `forward`, without allocating)."""
        last = len(self._layers) - 1
        for li, (w, b) in enumerate(self._layers):
            x = torch.baddbmm(b, x, w, out=outs[li])
            if li < last:
                x.relu_()
        return x

    def agent_params(self, agent: int) -> list[NDArray[np.float32]]:
        """Copies of one agent's parameters in `param_shapes` order, as float32 arrays."""
        return unflatten(self.flat[agent], self.offsets, self.shapes)

    def set_agent_params(self, agent: int, params: Sequence[NDArray[np.float32]]) -> None:
        """Overwrite one agent's parameters (shapes as `param_shapes`)."""
        with torch.no_grad():
            self.flat[agent].copy_(flatten(params, self.n_params))


def masked_argmax(q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Greedy action over the allowed actions only (Â(a_o)); ties go to the lowest index.

    Args:
        q: (..., |Ḡ|) Q-values.
        mask: (..., |Ḡ|) bool, at least one True per row.
    """
    # torch.argmax returns the first of several maximal values (documented for CPU tensors, where all of this runs)
    return torch.where(mask, q, -math.inf).argmax(dim=-1)


def masked_max(q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """max over the allowed actions: (..., |Ḡ|) -> (...)."""
    return torch.where(mask, q, -math.inf).amax(dim=-1)


# ----- compact weight bytes ---------------------------------------------------------------------------------------


def pack_weights(params: Sequence[NDArray[Any]]) -> bytes:
    """One agent's parameters as bytes (format in the module docstring)."""
    head = bytearray(WEIGHTS_MAGIC + struct.pack("<HH", WEIGHTS_VERSION, len(params)))
    body = bytearray()
    for p in params:
        a = np.ascontiguousarray(p, dtype="<f4")
        head += struct.pack("<B", a.ndim) + struct.pack(f"<{a.ndim}I", *a.shape)
        body += a.tobytes()
    return bytes(head + body)


def unpack_weights(data: bytes, expected: Sequence[tuple[int, ...]] | None = None) -> list[NDArray[np.float32]]:
    """Parameters from `pack_weights` bytes.

    Args:
        data: the bytes.
        expected: shapes the parameters must have (checked when given).

    Raises:
        ValueError: the bytes are not weights of this format, are truncated, or have other shapes than expected.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f"weights must be bytes, got {type(data).__name__}")
    buf = bytes(data)
    if len(buf) < 8 or buf[:4] != WEIGHTS_MAGIC:
        raise ValueError(f"not HTLM Q-network weights: expected magic {WEIGHTS_MAGIC!r}, got {buf[:4]!r}")
    version, count = struct.unpack_from("<HH", buf, 4)
    if version != WEIGHTS_VERSION:
        raise ValueError(f"unsupported weights format version {version} (this build reads {WEIGHTS_VERSION})")
    off = 8
    shapes: list[tuple[int, ...]] = []
    try:
        for _ in range(count):
            (ndim,) = struct.unpack_from("<B", buf, off)
            off += 1
            shapes.append(tuple(int(d) for d in struct.unpack_from(f"<{ndim}I", buf, off)))
            off += 4 * ndim
    except struct.error:
        raise ValueError(f"weights header truncated: {len(buf)} bytes for {count} tensors") from None
    if expected is not None and [tuple(s) for s in expected] != shapes:
        raise ValueError(f"weights have shapes {shapes}, this network needs {[tuple(s) for s in expected]}")
    need = off + 4 * sum(int(np.prod(s)) for s in shapes)
    if len(buf) != need:
        raise ValueError(f"weights size mismatch: {len(buf)} bytes, the header describes {need}")
    out: list[NDArray[np.float32]] = []
    for s in shapes:
        n = int(np.prod(s))
        out.append(np.frombuffer(buf, dtype="<f4", count=n, offset=off).astype(np.float32).reshape(s))
        off += 4 * n
    if not all(np.isfinite(a).all() for a in out):
        raise ValueError("weights contain NaN or infinity")
    return out


# ----- the network of a learner's settings ------------------------------------------------------------------------

QNetwork = StackedQ | TokenQ
"""The Q-networks of a set of agents, whichever the learner (`Settings.learner`)."""


def network_shapes(scenario: Scenario, settings: Any) -> list[tuple[int, ...]]:
    """Shapes of one agent's parameters for the learner of `settings` (a `learning.settings.Settings`)."""
    if settings.network == "tokens":
        return token_shapes(scenario.levels, settings.hidden, scenario.travel)
    if settings.network == "value":  # the value network: one-hot levels of every task -> steps to go
        return param_shapes((scenario.n_tasks * scenario.levels, *[int(h) for h in settings.hidden], 1))
    return param_shapes(layer_sizes(scenario, settings.hidden))


def init_params(scenario: Scenario, settings: Any, seed: int) -> list[torch.Tensor]:
    """Fresh parameters of one agent's network for the learner of `settings`."""
    if settings.network == "tokens":
        return init_token_params(scenario.levels, settings.hidden, seed, scenario.travel)
    return init_agent_params(layer_sizes(scenario, settings.hidden), seed)


def build_network(
    scenario: Scenario, settings: Any, params: Sequence[Sequence[Any]], agents: Sequence[int] | None = None
) -> QNetwork:
    """The networks of the agents `agents` (default: the whole team) with the given parameters, one list per agent
    (`network_shapes` order), for the learner of `settings`."""
    tparams = [[torch.as_tensor(np.asarray(t, dtype=np.float32)) for t in ps] for ps in params]
    if settings.network == "tokens":
        return TokenQ(scenario, settings.hidden, tparams, agents, shared=settings.shared)
    return StackedQ(layer_sizes(scenario, settings.hidden), tparams)


def copy_network(net: QNetwork) -> QNetwork:
    """A network of the same layout, agents and parameters (its own storage)."""
    out: QNetwork
    if isinstance(net, TokenQ):
        out = TokenQ(net.spec.scenario, net.hidden, [[torch.zeros(s) for s in net.shapes]], net.spec.agents, net.shared)
    else:
        out = StackedQ(net.sizes, [[torch.zeros(sh) for sh in net.shapes]] * net.n_agents)
    with torch.no_grad():
        out.flat.copy_(net.flat)
    return out


# ----- one agent's network ----------------------------------------------------------------------------------------


class AgentQ:
    """One agent's Q-network on its own (for the ROS agent node): greedy masked argmax, weights as bytes."""

    def __init__(
        self,
        sizes: Sequence[int],
        params: Sequence[NDArray[np.float32]] | None = None,
        seed: int = 0,
        net: QNetwork | None = None,
    ):
        """A network of layer sizes `sizes` (K, hidden..., |Ḡ|) with the given parameters, or fresh ones; or the
        one-agent network `net` (any learner's, `for_agent`)."""
        self.sizes = tuple(int(s) for s in sizes)
        if net is not None:
            self.shapes = list(net.shapes)
            self.net: QNetwork = net
            self.net.requires_grad_(False)
            return
        self.shapes = param_shapes(self.sizes)
        if params is None:
            tparams = init_agent_params(self.sizes, seed)
        else:
            got = [tuple(np.shape(p)) for p in params]
            if got != self.shapes:
                raise ValueError(f"parameters have shapes {got}, this network needs {self.shapes}")
            tparams = [torch.from_numpy(np.asarray(p, dtype=np.float32)) for p in params]
        self.net = StackedQ(self.sizes, [tparams])
        self.net.requires_grad_(False)

    @staticmethod
    def for_agent(
        scenario: Scenario, settings: Any, agent: int, params: Sequence[NDArray[np.float32]] | None = None
    ) -> AgentQ:
        """Agent `agent`'s network of the learner of `settings` (a `Settings`), with the given parameters or fresh
        ones (raises ValueError when they do not fit)."""
        if params is None:
            params = [t.numpy() for t in init_params(scenario, settings, 0)]
        got, want = [tuple(np.shape(p)) for p in params], network_shapes(scenario, settings)
        if got != want:
            raise ValueError(f"parameters have shapes {got}, this network needs {want}")
        net = build_network(scenario, settings, [params], [agent])
        return AgentQ((scenario.knowledge_size, scenario.n_actions), net=net)

    @staticmethod
    def from_checkpoint(ckpt: Any, agent_index: int) -> AgentQ:
        """Agent `agent_index`'s network from a loaded checkpoint (`htlm_agent.learning.checkpoint.Checkpoint`)."""
        n = len(ckpt.weights)
        if not 0 <= agent_index < n:
            raise ValueError(f"agent index {agent_index!r} is out of range 0..{n - 1} of checkpoint {ckpt.path}")
        return AgentQ.for_agent(ckpt.scenario, ckpt.settings, agent_index, ckpt.weights[agent_index])

    @property
    def knowledge_size(self) -> int:
        """K, the input size."""
        return self.sizes[0]

    @property
    def n_actions(self) -> int:
        """|Ḡ|, the output size."""
        return self.sizes[-1]

    def _input(self, knowledge: NDArray[Any]) -> torch.Tensor:
        k = np.asarray(knowledge)
        if k.ndim != 2 or k.shape[1] != self.knowledge_size:
            raise ValueError(f"knowledge must have shape (B, {self.knowledge_size}), got {k.shape}")
        if not np.isfinite(k).all():
            raise ValueError("knowledge contains NaN or infinity")
        return torch.from_numpy(np.ascontiguousarray(k, dtype=np.float32))[None]

    def q_values(self, knowledge: NDArray[Any]) -> F32:
        """Q-values (B, |Ḡ|) of knowledge states (B, K)."""
        with torch.no_grad():
            q: F32 = self.net(self._input(knowledge))[0].numpy().copy()
        return q

    def act(self, knowledge: NDArray[Any], mask: NDArray[np.bool_]) -> NDArray[np.int64]:
        """Greedy action (B,) over Â: masked argmax of the Q-values, ties to the lowest index."""
        x = self._input(knowledge)
        m = np.asarray(mask)
        if m.shape != (x.shape[1], self.n_actions) or m.dtype != np.bool_:
            raise ValueError(f"mask must be bool of shape ({x.shape[1]}, {self.n_actions}), got {m.dtype} {m.shape}")
        if not m.any(axis=1).all():
            raise ValueError("mask allows no action in some row")
        with torch.no_grad():
            q = self.net(x)[0]
            return masked_argmax(q, torch.from_numpy(m)).numpy().astype(np.int64)

    def get_weights(self) -> bytes:
        """The parameters as compact bytes (module docstring)."""
        return pack_weights(self.net.agent_params(0))

    def set_weights(self, data: bytes) -> None:
        """Replace the parameters by bytes from `get_weights` / `Learner.agent_weights`; ValueError if they do not fit
        this network."""
        self.net.set_agent_params(0, unpack_weights(data, self.shapes))
