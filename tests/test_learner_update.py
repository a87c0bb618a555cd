"""The hand-written gradient update of the learner (learning/update.py) against autograd on `Learner.loss`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.optim import clip_grad_per_agent
from htlm_agent.learning.qpolicy import greedy_actions
from htlm_agent.learning.settings import Settings
from htlm_world.scenario import builtin


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _filled(settings: Settings, only: int | None = None) -> Learner:
    """A learner whose memories hold random transitions (only agent `only`'s, when given) and whose networks and
    target networks differ."""
    sc = builtin()
    lr = Learner(sc, settings)
    rng = np.random.default_rng(3)
    n, ks = sc.n_agents, sc.knowledge_size
    prev_cols = ks - sc.n_tasks * sc.levels
    for _ in range(40):
        k = rng.random((16, n, ks))
        k2 = rng.random((16, n, ks))
        for arr in (k, k2):  # a valid one-hot previous assignment (or none)
            arr[..., sc.n_tasks * sc.levels :] = 0.0
            prev = rng.integers(-1, prev_cols, (16, n))
            b, i = np.nonzero(prev >= 0)
            arr[b, i, sc.n_tasks * sc.levels + prev[b, i]] = 1.0
        mask2 = lr.model.action_mask(rng.integers(-1, prev_cols, (16, n)))
        a = rng.integers(0, sc.n_tasks, (16, n))
        r = rng.normal(0.0, 30.0, (16, n))
        if only is None:
            lr.store_batch(k, a, r, k2, mask2, False)
        else:
            for j in range(16):
                lr.store(only, k[j, only], int(a[j, only]), float(r[j, only]), k2[j, only], mask2[j, only], False)
    with torch.no_grad():
        lr.net.flat.add_(torch.randn(lr.net.flat.shape, generator=torch.Generator().manual_seed(5)) * 0.05)
    return lr


def _autograd_step(lr: Learner, ready: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-agent losses and the clipped gradient of `Learner.loss` by autograd, on the same minibatch as the next
    `train_step` (the replay generators are copied)."""
    saved = [g.bit_generator.state for g in lr.replay.rngs]
    batch = lr.replay.sample(lr.settings.batch_size, ready)
    for g, st in zip(lr.replay.rngs, saved, strict=True):
        g.bit_generator.state = st
    total, per_agent = lr.loss(batch, torch.from_numpy(ready))
    lr.net.zero_grad_()
    lr.net.backward(total)
    grad = lr.net.grad.clone()
    clip_grad_per_agent(grad, lr.settings.grad_clip)
    return per_agent, grad


@pytest.mark.parametrize(
    "changes",
    [{}, {"double_dqn": False}, {"advantage_learning": 0.0}, {"huber_delta": 0.05}, {"hidden": (16,)}],
)
def test_hand_written_update_is_the_autograd_gradient(changes: dict[str, object]) -> None:
    lr = _filled(Settings(batch_size=64, learning_starts=1, **changes))  # type: ignore[arg-type]
    ready = lr.ready()
    assert ready.all()
    per_agent, grad = _autograd_step(lr, ready)
    loss = lr.train_step()
    assert loss == pytest.approx(float(per_agent.mean()), rel=1e-5)
    assert torch.allclose(lr.net.grad, grad, rtol=1e-4, atol=1e-6)
    assert lr.updates.tolist() == [1] * lr.n_agents


def test_hand_written_update_of_some_agents_only() -> None:
    lr = _filled(Settings(batch_size=32, learning_starts=1), only=2)
    ready = lr.ready()
    assert ready.tolist() == [False, False, True, False, False]
    per_agent, grad = _autograd_step(lr, ready)
    before = lr.net.flat.clone()
    loss = lr.train_step()
    assert loss == pytest.approx(float(per_agent[2]), rel=1e-5)
    assert torch.allclose(lr.net.grad, grad, rtol=1e-4, atol=1e-6)
    assert (lr.net.grad[[0, 1, 3, 4]] == 0).all()
    assert ((lr.net.flat != before).any(dim=1)).tolist() == [False, False, True, False, False]


def test_several_updates_at_once_are_the_updates_one_by_one() -> None:
    s = Settings(batch_size=32, learning_starts=1, target_sync=3)  # a target copy between the updates, too
    one, many = _filled(s), _filled(s)
    losses = [one.train_step() for _ in range(5)]
    assert many.train_steps(5) == losses
    assert torch.equal(one.net.flat, many.net.flat) and torch.equal(one.target.flat, many.target.flat)
    assert torch.equal(one.opt.v, many.opt.v) and one.updates.tolist() == many.updates.tolist() == [5] * 5


def test_acting_greedily_is_the_policy_of_the_networks() -> None:
    lr = _filled(Settings(batch_size=32, learning_starts=1))
    rng = np.random.default_rng(7)
    sc = lr.scenario
    for b in (1, 16, 16, 40):
        k = rng.random((b, sc.n_agents, sc.knowledge_size))
        mask = rng.random((b, sc.n_agents, sc.n_actions)) > 0.5
        mask[..., 0] = True
        if b == 40:  # equal Q-values: ties go to the lowest index
            k[:] = 0.0
        acts = lr.act(k, mask, 0.0, [np.random.default_rng(i) for i in range(sc.n_agents)])
        assert np.array_equal(acts, greedy_actions(lr.net, k, mask))
