"""The gradient update of the stacked learner (`Learner.train_steps`: autograd on `Learner.batch_loss`, per-agent
clipping, torch.optim's Adam over every agent's row) against each agent trained on its own: its own network, its own
loss written out below, its own torch.optim.Adam."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.qnet import StackedQ
from htlm_agent.learning.qpolicy import greedy_actions
from htlm_agent.learning.settings import Settings
from htlm_agent.learning.update import UpdateBatch
from htlm_world.scenario import builtin


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _store_random(lr: Learner, rng: np.random.Generator, steps: int, only: list[int] | None = None) -> None:
    """Random transitions (a valid one-hot previous assignment or none) into every agent's memory, or only into
    those of the agents `only`."""
    sc = lr.scenario
    n, ks = sc.n_agents, sc.knowledge_size
    prev_cols = ks - sc.n_tasks * sc.levels
    for _ in range(steps):
        k = rng.random((16, n, ks))
        k2 = rng.random((16, n, ks))
        for arr in (k, k2):
            arr[..., sc.n_tasks * sc.levels :] = 0.0
            prev = rng.integers(-1, prev_cols, (16, n))
            b, i = np.nonzero(prev >= 0)
            arr[b, i, sc.n_tasks * sc.levels + prev[b, i]] = 1.0
        mask2 = lr.model.action_mask(rng.integers(-1, prev_cols, (16, n)))
        a = rng.integers(0, sc.n_tasks, (16, n))
        r = rng.normal(0.0, 30.0, (16, n))
        if only is None:
            lr.store_batch(k, a, r, k2, mask2, False)
            continue
        for agent in only:
            for j in range(16):
                lr.store(agent, k[j, agent], int(a[j, agent]), float(r[j, agent]), k2[j, agent], mask2[j, agent], False)


def _filled(settings: Settings, only: list[int] | None = None) -> Learner:
    """A learner whose memories hold random transitions (only the agents `only`, when given) and whose networks and
    target networks differ."""
    lr = Learner(builtin(), settings)
    _store_random(lr, np.random.default_rng(3), 40, only)
    with torch.no_grad():
        lr.net.flat.add_(torch.randn(lr.net.flat.shape, generator=torch.Generator().manual_seed(5)) * 0.05)
    return lr


def _one_agent(net: StackedQ, agent: int) -> StackedQ:
    """A copy of one agent's network on its own."""
    params = [torch.from_numpy(p) for p in net.agent_params(agent)]
    return StackedQ(net.sizes, [params])


def _own_loss(lr: Learner, agent: int, b: UpdateBatch, net: StackedQ, target: StackedQ) -> torch.Tensor:
    """Agent `agent`'s loss on its rows of minibatch `b`, written out for one network: the mean Huber TD error of
    Q(K, a) against r + d·Q̂(K', a') with a' the online network's best action in Â(K') (Double DQN; else the target
    network's max over Â(K')), minus α·(max over Â(K) of Q̂(K, ·) − Q̂(K, a)) with advantage learning; Â(K) read
    from K afresh."""
    s = lr.settings
    m = b.m
    k, k2 = b.x[agent, :m][None], b.x[agent, m:][None]
    a = b.a[agent].clone()
    allowed = lr.knowledge_mask(k[0].numpy())
    allowed2 = b.allowed2[agent].clone()
    q = net(k)[0]
    with torch.no_grad():
        qt_k, qt_k2 = target(k)[0], target(k2)[0]
        if s.double_dqn:
            a2 = net(k2)[0].masked_fill(~allowed2, -math.inf).argmax(dim=-1)
            nxt = qt_k2[torch.arange(m), a2]
        else:
            nxt = qt_k2.masked_fill(~allowed2, -math.inf).max(dim=-1).values
        y = b.r[agent] + b.discount[agent] * nxt
        if s.advantage_learning > 0:
            gap = qt_k.masked_fill(~allowed, -math.inf).max(dim=-1).values - qt_k[torch.arange(m), a]
            y = y - s.advantage_learning * gap
    return torch.nn.functional.huber_loss(q[torch.arange(m), a], y, delta=s.huber_delta)


def _next_batches(lr: Learner, count: int) -> list[UpdateBatch]:
    """Copies of the minibatches the learner's next `train_steps(count)` draws (its replay generators are put
    back)."""
    saved = [g.bit_generator.state for g in lr.replay.rngs]
    views = lr.update_batches(lr.ready(), count)
    out = [
        UpdateBatch(
            b.x.clone(), b.a.clone(), b.r.clone(), b.discount.clone(), b.allowed.clone(), b.allowed2.clone(), b.weight
        )
        for b in views
    ]
    for g, st in zip(lr.replay.rngs, saved, strict=True):
        g.bit_generator.state = st
    return out


def _step_count(lr: Learner, agent: int) -> int:
    """Agent `agent`'s step count in the learner's optimizer."""
    assert lr._rows is not None
    return int(lr.opt.state[lr._rows.params[agent]]["step"])


@pytest.mark.parametrize(
    "changes",
    [{}, {"double_dqn": False}, {"advantage_learning": 0.0}, {"huber_delta": 0.05}, {"hidden": (16,)}],
)
def test_each_agents_gradient_is_that_of_its_own_loss_alone(changes: dict[str, object]) -> None:
    lr = _filled(Settings(batch_size=64, learning_starts=1, **changes))  # type: ignore[arg-type]
    assert lr.ready().all()
    (b,) = lr.update_batches(lr.ready(), 1)
    per_agent = lr.batch_loss(b)
    lr.net.zero_grad_()
    StackedQ.backward(per_agent.sum())
    together = lr.net.grad.clone()
    for i in range(lr.n_agents):
        lr.net.zero_grad_()
        StackedQ.backward(lr.batch_loss(b)[i])
        assert torch.equal(lr.net.grad[i], together[i]), f"agent {i}: the others' losses reach its gradient"
        assert (lr.net.grad[np.arange(lr.n_agents) != i] == 0).all(), f"agent {i}'s loss reaches the others"
        own_net, own_target = _one_agent(lr.net, i), _one_agent(lr.target, i)
        own = _own_loss(lr, i, b, own_net, own_target)
        own_net.zero_grad_()
        StackedQ.backward(own)
        assert float(per_agent[i].detach()) == pytest.approx(float(own.detach()), rel=1e-5)
        assert torch.allclose(together[i], own_net.grad[0], rtol=1e-4, atol=1e-6)


def test_an_agent_that_does_not_train_keeps_its_parameters_moments_and_step_count() -> None:
    lr = _filled(Settings(batch_size=32, learning_starts=1))
    lr.train_steps(3)  # every agent has moments and a step count
    lr.settings = lr.settings.replace(learning_starts=int(lr.replay.size.max()) + 10)
    _store_random(lr, np.random.default_rng(4), 1, only=[2])
    ready = lr.ready()
    assert ready.tolist() == [False, False, True, False, False]
    rows = lr._rows
    assert rows is not None

    def state(i: int) -> tuple[torch.Tensor, ...]:
        st = lr.opt.state[rows.params[i]]
        return lr.net.flat[i].clone(), st["exp_avg"].clone(), st["exp_avg_sq"].clone(), st["step"].clone()

    before = [state(i) for i in range(lr.n_agents)]
    assert lr.train_step() is not None
    for i in range(lr.n_agents):
        after = state(i)
        if i == 2:
            assert int(after[3]) == 4 and all(not torch.equal(x, y) for x, y in zip(before[i], after, strict=True))
        else:
            assert all(torch.equal(x, y) for x, y in zip(before[i], after, strict=True)), f"agent {i} changed"
    assert lr.updates.tolist() == [3, 3, 4, 3, 3]


def test_the_learner_trains_every_agent_as_its_own_network_and_adam() -> None:
    """Agents 2 and 4 train alone for a while, then the whole team; each agent's network ends where its own network,
    trained on its own minibatches with its own loss, clipping and torch.optim.Adam, ends (target copies included)."""
    s = Settings(batch_size=16, learning_starts=100, target_sync=3, grad_clip=1.0, hidden=(16, 16))
    lr = Learner(builtin(), s)
    n = lr.n_agents
    nets = [_one_agent(lr.net, i) for i in range(n)]
    targets = [_one_agent(lr.target, i) for i in range(n)]
    adams = [torch.optim.Adam(nets[i].parameters(), lr=s.lr) for i in range(n)]
    updates = [0] * n
    rng = np.random.default_rng(7)
    _store_random(lr, rng, 8, only=[2, 4])
    for phase in range(2):
        ready = lr.ready()
        assert ready.tolist() == ([False, False, True, False, True] if phase == 0 else [True] * n)
        batches = _next_batches(lr, 4)
        lr.train_steps(4)
        for b in batches:
            for i in np.flatnonzero(ready):
                adams[i].zero_grad()
                _own_loss(lr, i, b, nets[i], targets[i]).backward()  # type: ignore[no-untyped-call]
                torch.nn.utils.clip_grad_norm_(nets[i].parameters(), s.grad_clip)
                adams[i].step()
                updates[i] += 1
                if updates[i] % s.target_sync == 0:
                    with torch.no_grad():
                        targets[i].flat.copy_(nets[i].flat)
        _store_random(lr, rng, 8)
    assert lr.updates.tolist() == updates == [4, 4, 8, 4, 8]
    for i in range(n):
        assert torch.allclose(lr.net.flat[i], nets[i].flat[0], rtol=1e-4, atol=1e-5), f"agent {i}"
        assert torch.allclose(lr.target.flat[i], targets[i].flat[0], rtol=1e-4, atol=1e-5), f"agent {i}"
        assert _step_count(lr, i) == updates[i]


def test_several_updates_at_once_are_the_updates_one_by_one() -> None:
    s = Settings(batch_size=32, learning_starts=1, target_sync=3)  # a target copy between the updates, too
    one, many = _filled(s), _filled(s)
    losses = [one.train_step() for _ in range(5)]
    assert many.train_steps(5) == losses
    assert torch.equal(one.net.flat, many.net.flat) and torch.equal(one.target.flat, many.target.flat)
    a, b = one.opt.state_dict()["state"], many.opt.state_dict()["state"]
    assert a.keys() == b.keys() and all(torch.equal(a[k][x], b[k][x]) for k in a for x in a[k])
    assert one.updates.tolist() == many.updates.tolist() == [5] * 5


def test_a_step_of_the_optimizer_writes_the_networks() -> None:
    lr = _filled(Settings(batch_size=32, learning_starts=1))
    rows = lr._rows
    assert rows is not None
    for i, p in enumerate(rows.params):  # the optimizer's parameters are the networks' own rows
        assert p.data_ptr() == lr.net.flat[i].data_ptr() and p.shape == lr.net.flat[i].shape
    before = lr.net.flat.clone()
    lr.train_step()
    assert (lr.net.flat != before).any(dim=1).all()


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
