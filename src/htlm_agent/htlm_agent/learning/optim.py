"""The optimizer of stacked per-agent networks: torch.optim.Adam with every agent's row as its own parameter, and
per-agent gradient clipping (each agent's row of the stacked parameters is its own network)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from htlm_world.types import BoolArray


class AgentRows:
    """Every agent's row of stacked parameters (N, P) as its own `torch.nn.Parameter`, for a torch.optim optimizer.

    Parameter i aliases row i of the parameters (a step of the optimizer writes the networks), and its gradient is
    row i of the stacked gradient when agent i trains, None when it does not. torch.optim keeps a state per parameter
    and skips parameters without a gradient, so each agent has its own moments and step count, and an agent that
    does not train on an update keeps its parameters, moments and step count: N separate optimizers, one step.
    """

    def __init__(self, flat: torch.Tensor, grad: torch.Tensor) -> None:
        """Rows of `flat` (N, P); `grad` (N, P) is where their gradient lands."""
        self.params = [torch.nn.Parameter(flat[i], requires_grad=True) for i in range(flat.shape[0])]
        assert all(p.data_ptr() == flat[i].data_ptr() for i, p in enumerate(self.params)), "rows must alias `flat`"
        self._grads = [grad[i] for i in range(grad.shape[0])]

    def select(self, active: BoolArray) -> None:
        """The agents marked in `active` (N,) bool train on the next steps: their parameters see their gradient rows,
        the others none."""
        for p, g, on in zip(self.params, self._grads, active.tolist(), strict=True):
            p.grad = g if on else None

    def adam(self, lr: float) -> torch.optim.Adam:
        """Adam over the rows: the fused CPU implementation (one pass over every agent's row)."""
        return torch.optim.Adam(self.params, lr=lr, fused=True)

    def adam_state(self, moments: dict[str, Any]) -> dict[int, dict[str, torch.Tensor]]:
        """Adam's per-parameter state (`torch.optim.Adam.state_dict()["state"]`) of stacked moments: {"m": (N, P),
        "v": (N, P), "t": (N,)} (first and second moments and every agent's step count); agents with no step yet
        get no state, as torch.optim leaves them. Raises ValueError when the shapes do not fit these rows."""
        m, v, t = (moments.get(key) for key in ("m", "v", "t"))
        n, p = len(self.params), self.params[0].numel()
        for name, x, shape in (("m", m, (n, p)), ("v", v, (n, p)), ("t", t, (n,))):
            if not isinstance(x, torch.Tensor) or tuple(x.shape) != shape:
                got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
                raise ValueError(f"optimizer moments {name!r}: expected shape {shape}, got {got}")
        assert m is not None and v is not None and t is not None
        return {
            i: {
                "step": torch.tensor(float(t[i]), dtype=torch.float32),
                "exp_avg": m[i].detach().to(torch.float32).clone(),
                "exp_avg_sq": v[i].detach().to(torch.float32).clone(),
            }
            for i in range(n)
            if float(t[i]) > 0
        }


def clip_grad_per_agent(g: torch.Tensor, max_norm: float) -> torch.Tensor:
    """Scale each agent's row of the stacked gradient (N, P) to norm <= max_norm in place (0: no clipping); returns
    the norms (N,) before clipping."""
    norm = g.norm(dim=1)
    if max_norm > 0:
        # min(1, max_norm / (norm + 1e-6)) for the N agents in numpy, cheaper than torch on a few numbers; float32
        # operations as torch does them (its `number / tensor` is `tensor.reciprocal() * number`)
        scale = np.minimum(np.float32(1.0) / (norm.numpy() + np.float32(1e-6)) * np.float32(max_norm), np.float32(1.0))
        if (scale < 1.0).any():  # (scaling by 1 changes nothing: skip the pass over the gradient)
            g.mul_(torch.from_numpy(scale)[:, None])
    out: torch.Tensor = norm
    return out
