"""The optimizer of the stacked per-agent networks: Adam with a step count per agent, and per-agent gradient
clipping (each agent's row of the stacked parameters is its own network)."""

from __future__ import annotations

import numpy as np
import torch


class StackedAdam:
    """Adam over stacked per-agent parameters (N, P) with a step count per agent: identical to one Adam per agent,
    and an agent's parameters and moments change only on updates it takes part in.

    The update is torch's fused CPU Adam kernel (`torch._fused_adam_`, what `torch.optim.Adam(fused=True)` runs) over
    the agents' rows, each row with its own step count: one pass over parameters, gradients and moments.
    """

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
        n = param.shape[0]
        self._steps = torch.zeros(n, dtype=torch.float32)  # the step counts as the fused kernel reads them
        self._rows = [
            [self.param[i], self.grad[i], self.m[i], self.v[i], self._steps[i]] for i in range(n)
        ]  # every agent's row views
        self._all = tuple(list(x) for x in zip(*self._rows, strict=True))  # the same, by kind

    @torch.no_grad()
    def step(self, active: torch.Tensor) -> None:
        """Apply the gradient rows of the agents marked in `active` (N,) bool."""
        act = active.numpy()
        t = self.t.numpy()  # shares memory with self.t
        t += act
        self._steps.copy_(self.t)
        if act.all():
            params, grads, ms, vs, steps = self._all
        else:
            rows = [r for r, a in zip(self._rows, act.tolist(), strict=True) if a]
            if not rows:
                return
            params, grads, ms, vs, steps = (list(x) for x in zip(*rows, strict=True))
        b1, b2 = self.betas
        torch._fused_adam_(
            params,
            grads,
            ms,
            vs,
            [],
            steps,
            lr=self.lr,
            beta1=b1,
            beta2=b2,
            weight_decay=0.0,
            eps=self.eps,
            amsgrad=False,
            maximize=False,
        )

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
        # min(1, max_norm / (norm + 1e-6)) for the N agents in numpy, cheaper than torch on a few numbers; float32
        # operations as torch does them (its `number / tensor` is `tensor.reciprocal() * number`)
        scale = np.minimum(np.float32(1.0) / (norm.numpy() + np.float32(1e-6)) * np.float32(max_norm), np.float32(1.0))
        if (scale < 1.0).any():  # (scaling by 1 changes nothing: skip the pass over the gradient)
            g.mul_(torch.from_numpy(scale)[:, None])
    out: torch.Tensor = norm
    return out
