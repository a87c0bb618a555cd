"""The optimizer of the stacked per-agent networks: Adam with a step count per agent, and per-agent gradient
clipping (each agent's row of the stacked parameters is its own network)."""

from __future__ import annotations

import torch


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
