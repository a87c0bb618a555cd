"""The decentralized deep Q-learner (Algorithm 1): its pieces, independence of the agents, determinism, checkpoints."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from htlm_agent.baselines.heuristics import GreedyPolicy, RandomPolicy
from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.dqn_run import train_batch
from htlm_agent.learning.loop import LaggedNets
from htlm_agent.learning.optim import AgentRows
from htlm_agent.learning.qnet import AgentQ, StackedQ, layer_sizes, masked_argmax, pack_weights, unpack_weights
from htlm_agent.learning.qpolicy import QPolicy
from htlm_agent.learning.replay import Replay
from htlm_agent.learning.run import train
from htlm_agent.learning.settings import Settings
from htlm_agent.learning.targets import NStep, advantage_gap, bellman_targets
from htlm_agent.mind.policies import epsilon_greedy
from htlm_agent.runtime.evaluate import evaluate
from htlm_agent.runtime.team import Team
from htlm_msgs_py.params import field_docs
from htlm_world.scenario import builtin
from support.learning import TINY


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


# ----- settings and schedules ------------------------------------------------------------------------------------


def test_every_settings_field_has_a_docstring() -> None:
    docs = field_docs(Settings)
    import dataclasses

    missing = [f.name for f in dataclasses.fields(Settings) if not docs.get(f.name)]
    assert missing == []


def test_settings_reject_bad_values_naming_the_field() -> None:
    with pytest.raises(ValueError, match=r"settings\.lr"):
        Settings(lr=0.0)
    with pytest.raises(ValueError, match=r"settings\.eps_end"):
        Settings(eps_end=1.5)
    with pytest.raises(ValueError, match=r"settings\.lrr: unknown key \(value 1\)"):
        Settings.from_dict({"lrr": 1})
    with pytest.raises(ValueError, match=r"settings\.batch_size: expected `int`, got str 'x'"):
        Settings.from_dict({"batch_size": "x"})
    assert Settings.from_dict(Settings().to_dict()) == Settings()


def test_epsilon_decays_linearly_then_stays() -> None:
    s = Settings(episodes=1000, eps_start=1.0, eps_end=0.1, eps_fraction=0.5)
    assert s.epsilon(0) == 1.0
    assert s.epsilon(250) == pytest.approx(0.55)
    assert s.epsilon(500) == pytest.approx(0.1)
    assert s.epsilon(10_000) == pytest.approx(0.1)
    eps = [s.epsilon(e) for e in range(0, 1000, 10)]
    assert all(a >= b for a, b in itertools.pairwise(eps))


# ----- masking, targets, n-step ----------------------------------------------------------------------------------


def test_masked_argmax_ignores_masked_actions_and_breaks_ties_low() -> None:
    q = torch.tensor([[1.0, 5.0, 3.0, 3.0], [2.0, 2.0, 2.0, 9.0], [0.0, -1.0, 7.0, 7.0]])
    mask = torch.tensor([[True, False, True, True], [True, True, True, False], [False, True, True, True]])
    assert masked_argmax(q, mask).tolist() == [2, 0, 2]


def test_epsilon_greedy_draws_only_allowed_actions_and_is_greedy_at_zero() -> None:
    n, b, g = 3, 400, 6
    q = torch.randn(n, b, g, generator=torch.Generator().manual_seed(0))
    mask = torch.zeros(n, b, g, dtype=torch.bool)
    mask[..., :4] = True
    mask[..., 5] = True  # idle@site2 allowed, idle@site1 not
    rngs = [np.random.default_rng(i) for i in range(n)]
    best = masked_argmax(q, mask).numpy()  # (N, B)
    m = mask.numpy()
    a = np.stack([epsilon_greedy(best[i], m[i], 1.0, rngs[i]) for i in range(n)], axis=1)
    assert a.shape == (b, n)
    assert not (a == 4).any()
    assert set(np.unique(a)) == {0, 1, 2, 3, 5}
    greedy = np.stack([epsilon_greedy(best[i], m[i], 0.0, rngs[i]) for i in range(n)], axis=1)
    assert (greedy == masked_argmax(q, mask).numpy().T).all()


def test_bellman_target_plain_double_and_terminal() -> None:
    r = torch.tensor([1.0, 1.0, 1.0])
    q_t = torch.tensor([[0.0, 10.0, 4.0], [2.0, 3.0, 4.0], [5.0, 6.0, 7.0]])
    q_o = torch.tensor([[9.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    mask2 = torch.tensor([[True, False, True], [True, True, True], [True, True, True]])
    disc = torch.tensor([0.95, 0.95, 0.0])
    plain = bellman_targets(r, disc, q_t, mask2)
    assert plain.tolist() == pytest.approx([1 + 0.95 * 4.0, 1 + 0.95 * 4.0, 1.0])  # masked 10 is not the max
    double = bellman_targets(r, disc, q_t, mask2, q_o)
    assert double.tolist() == pytest.approx([1 + 0.95 * 0.0, 1 + 0.95 * 2.0, 1.0])  # a' by q_o, valued by q_t


def test_advantage_gap_is_distance_to_the_best_allowed_action() -> None:
    q = torch.tensor([[1.0, 4.0, 9.0], [1.0, 4.0, 9.0]])
    mask = torch.tensor([[True, True, False], [True, True, True]])
    a = torch.tensor([0, 2])
    assert advantage_gap(q, mask, a).tolist() == [3.0, 0.0]


def test_nstep_returns_and_episode_end() -> None:
    g = 0.5
    ns = NStep(3, g)
    out = []
    for t, r in enumerate([1.0, 2.0, 4.0, 8.0]):
        out += ns.push(f"k{t}", t, r, f"k{t + 1}", "m", end=t == 3, terminal=False)
    assert [o[0] for o in out] == ["k0", "k1", "k2", "k3"]
    assert out[0][2] == pytest.approx(1 + 0.5 * 2 + 0.25 * 4) and out[0][3] == "k3" and out[0][5] == 0.125
    assert out[1][2] == pytest.approx(2 + 0.5 * 4 + 0.25 * 8) and out[1][3] == "k4" and out[1][5] == 0.125
    assert out[2][2] == pytest.approx(4 + 0.5 * 8) and out[2][5] == 0.25  # cut by the episode end
    assert out[3][2] == pytest.approx(8) and out[3][5] == 0.5
    term = NStep(1, g).push("k", 0, 3.0, "k2", "m", end=True, terminal=True)
    assert term[0][5] == 0.0


# ----- replay ----------------------------------------------------------------------------------------------------


def test_replay_memories_are_per_agent_ring_buffers_with_seeded_sampling() -> None:
    rep = Replay(2, 4, 3, 2, seeds=[1, 2])
    for i in range(6):  # agent 0 wraps around: keeps 2..5
        rep.add(0, np.full(3, i), 0, float(i), np.zeros(3), np.array([True, False]), 0.9)
    rep.add(1, np.full(3, 100.0), 1, 100.0, np.zeros(3), np.array([True, True]), 0.0)
    assert rep.size.tolist() == [4, 1]
    batch = rep.sample(64, np.array([True, True]))
    assert set(batch.r[0].tolist()) <= {2.0, 3.0, 4.0, 5.0} and len(set(batch.r[0].tolist())) > 1
    assert set(batch.r[1].tolist()) == {100.0}  # an agent samples only its own memory
    assert (batch.mask2[0] == np.array([True, False])).all() and (batch.discount[1] == 0.0).all()
    assert batch.discount[0] == pytest.approx(0.9)
    rep2 = Replay(2, 4, 3, 2, seeds=[1, 2])
    rep2.load_state(
        {
            **rep.state(),
            "rngs": [np.random.default_rng(1).bit_generator.state, np.random.default_rng(2).bit_generator.state],
        }
    )
    again = rep2.sample(64, np.array([True, True]))
    assert (again.r == batch.r).all()


# ----- independence of the agents --------------------------------------------------------------------------------


def test_adam_over_agent_rows_is_one_adam_per_agent() -> None:
    torch.manual_seed(0)
    p0 = torch.randn(3, 7)
    stacked = p0.clone()
    grad = torch.zeros_like(stacked)
    rows = AgentRows(stacked, grad)
    opt = rows.adam(lr=0.01)
    singles = [torch.nn.Parameter(p0[i].clone()) for i in range(3)]
    adams = [torch.optim.Adam([p], lr=0.01) for p in singles]
    active_steps = [[True, True, True], [True, False, True], [False, False, True], [True, True, True]]
    for step, active in enumerate(active_steps):
        g = torch.randn(3, 7, generator=torch.Generator().manual_seed(step))
        grad.copy_(g)  # an agent that does not train keeps its parameters whatever its gradient row holds
        rows.select(np.array(active))
        opt.step()
        for i in range(3):
            if active[i]:
                singles[i].grad = g[i].clone()
                adams[i].step()
    for i in range(3):
        assert torch.allclose(stacked[i], singles[i].detach(), atol=1e-6)
        assert int(opt.state[rows.params[i]]["step"]) == int(adams[i].state[singles[i]]["step"])


def test_an_agent_not_ready_to_train_is_untouched_and_agents_share_nothing() -> None:
    sc = builtin()
    lr = Learner(sc, TINY.replace(learning_starts=10))
    before = lr.net.flat.detach().clone()
    rng = np.random.default_rng(0)
    mask = np.ones(sc.n_actions, dtype=bool)
    for _ in range(12):  # only agent 2 has enough data
        lr.store(2, rng.random(sc.knowledge_size), 1, 5.0, rng.random(sc.knowledge_size), mask, False)
    assert lr.train_step() is not None
    after = lr.net.flat.detach()
    changed = (after != before).any(dim=1).tolist()
    assert changed == [False, False, True, False, False]
    assert lr.updates.tolist() == [0, 0, 1, 0, 0]


def test_the_team_policy_acts_from_each_agents_own_row_only() -> None:
    sc = builtin()
    lr = Learner(sc, TINY)
    team = Team(sc, 8, 0)
    ctx = team.context()
    a = QPolicy(sc, lr.net).act(ctx)
    ctx.knowledge[:, 1:] = np.random.default_rng(0).random(ctx.knowledge[:, 1:].shape)  # change the others' rows
    assert (QPolicy(sc, lr.net).act(ctx)[:, 0] == a[:, 0]).all()


def test_store_rejects_bad_transitions() -> None:
    sc = builtin()
    lr = Learner(sc, TINY)
    k, m = np.zeros(sc.knowledge_size), np.ones(sc.n_actions, dtype=bool)
    with pytest.raises(ValueError, match="agent 7"):
        lr.store(7, k, 0, 0.0, k, m, False)
    with pytest.raises(ValueError, match="shape"):
        lr.store(0, k[:-1], 0, 0.0, k, m, False)
    with pytest.raises(ValueError, match="action 9"):
        lr.store(0, k, 9, 0.0, k, m, False)
    with pytest.raises(ValueError, match="NaN"):
        lr.store(0, k, 0, math.nan, k, m, False)
    with pytest.raises(ValueError, match="mask2"):
        lr.store(0, k, 0, 0.0, k, np.zeros(sc.n_actions, dtype=bool), False)


# ----- the single-agent network and its weights ------------------------------------------------------------------


def test_agent_network_matches_the_stacked_row_and_weights_round_trip() -> None:
    sc = builtin()
    lr = Learner(sc, TINY)
    team = Team(sc, 16, 3)
    ctx = team.context()
    joint = QPolicy(sc, lr.net).act(ctx)
    for i in range(sc.n_agents):
        net = AgentQ(layer_sizes(sc, TINY.hidden))
        net.set_weights(lr.agent_weights(i))
        assert (net.act(ctx.knowledge[:, i], ctx.mask[:, i]) == joint[:, i]).all()
        assert net.get_weights() == lr.agent_weights(i)
        assert net.q_values(ctx.knowledge[:, i]).shape == (16, sc.n_actions)


def test_weight_bytes_are_validated() -> None:
    sc = builtin()
    net = AgentQ(layer_sizes(sc, (8,)))
    data = net.get_weights()
    with pytest.raises(ValueError, match="magic"):
        net.set_weights(b"XXXX" + data[4:])
    with pytest.raises(ValueError, match="size mismatch"):
        net.set_weights(data[:-4])
    with pytest.raises(ValueError, match="shapes"):
        net.set_weights(AgentQ(layer_sizes(sc, (9,))).get_weights())
    bad = [p.copy() for p in unpack_weights(data)]
    bad[0][0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        net.set_weights(pack_weights(bad))
    with pytest.raises(ValueError, match="knowledge must have shape"):
        net.act(np.zeros((2, 3)), np.ones((2, sc.n_actions), dtype=bool))
    with pytest.raises(ValueError, match="no action"):
        net.act(np.zeros((1, sc.knowledge_size)), np.zeros((1, sc.n_actions), dtype=bool))


def test_stacked_networks_evaluate_each_agent_as_on_its_own() -> None:
    sizes = (5, 7, 3)
    stacked = StackedQ.fresh(sizes, [11, 12, 13])
    x = torch.randn(3, 4, 5)
    y = stacked(x)
    for i in range(3):
        alone = AgentQ(sizes, stacked.agent_params(i))
        assert np.allclose(alone.q_values(x[i].numpy()), y[i].detach().numpy(), atol=1e-6)


# ----- training --------------------------------------------------------------------------------------------------


def test_same_seed_same_learning_curve_and_weights(tmp_path: Path) -> None:
    sc = builtin()
    runs = [train(sc, TINY, tmp_path / name, progress=False, tensorboard=False) for name in ("a", "b")]
    curves = [(tmp_path / n / "progress.csv").read_text().splitlines() for n in ("a", "b")]
    strip = [[",".join(x for i, x in enumerate(line.split(",")) if i not in (1, 2)) for line in c] for c in curves]
    assert strip[0] == strip[1]  # identical except wall time and rate
    w = [(tmp_path / n / "checkpoint" / "agents.pt").read_bytes() for n in ("a", "b")]
    ck = [load_checkpoint(tmp_path / n) for n in ("a", "b")]
    assert all(
        np.array_equal(p, q)
        for wa, wb in zip(ck[0].weights, ck[1].weights, strict=True)
        for p, q in zip(wa, wb, strict=True)
    )
    assert len(w[0]) > 0 and runs[0].metrics == runs[1].metrics
    other = train(sc, TINY.replace(seed=1), tmp_path / "c", progress=False, tensorboard=False)
    assert not np.array_equal(load_checkpoint(tmp_path / "c").weights[0][0], ck[0].weights[0][0])
    assert other.episodes == TINY.episodes


def test_resuming_continues_exactly(tmp_path: Path) -> None:
    sc = builtin()
    s = TINY.replace(episodes=48, validate_every=0, select_best=False)
    straight = Learner(sc, s)
    team = Team(sc, s.envs, s.seed)
    for b in range(3):
        train_batch(straight, team, b)
    half = Learner(sc, s)
    for b in range(2):
        train_batch(half, team, b)
    half.save(tmp_path / "ck")
    resumed = Learner.load(tmp_path / "ck")
    assert resumed.episodes_done == 32
    train_batch(resumed, team, 2)
    assert torch.equal(resumed.net.flat, straight.net.flat)
    assert torch.equal(resumed.target.flat, straight.target.flat)


def _rewrite_train_state(ck: Path, change: Any) -> None:
    """Replace the training state of checkpoint `ck` by `change(state)` (its checksum too)."""
    import hashlib

    f = ck / "train_state.pt"
    st = torch.load(f, weights_only=True)
    torch.save(change(st), f)
    meta = json.loads((ck / "meta.json").read_text())
    meta["files"]["train_state.pt"] = hashlib.sha256(f.read_bytes()).hexdigest()
    (ck / "meta.json").write_text(json.dumps(meta))


def _stacked_moments(st: dict[str, Any]) -> dict[str, Any]:
    """The optimizer state as the paper's learner saved it before it used torch.optim: every agent's first and
    second moments stacked (N, P), its step count (N,) float64."""
    adam, flat = st["adam"]["state"], st["target"]
    n = flat.shape[0]
    zeros = torch.zeros(flat.shape[1])
    return {
        **st,
        "adam": {
            "m": torch.stack([adam[i]["exp_avg"] if i in adam else zeros for i in range(n)]),
            "v": torch.stack([adam[i]["exp_avg_sq"] if i in adam else zeros for i in range(n)]),
            "t": torch.tensor([float(adam[i]["step"]) if i in adam else 0.0 for i in range(n)], dtype=torch.float64),
        },
    }


def test_resuming_from_the_optimizer_state_of_earlier_checkpoints_continues_exactly(tmp_path: Path) -> None:
    sc = builtin()
    s = TINY.replace(episodes=48, validate_every=0, select_best=False, learning_starts=100)
    k, mask = np.full(sc.knowledge_size, 0.5), np.ones(sc.n_actions, dtype=bool)
    team = Team(sc, s.envs, s.seed)
    straight, half = Learner(sc, s), Learner(sc, s)
    for lr in (straight, half):  # agent 2 starts training a step before the others: its own step count
        for _ in range(4):
            lr.store(2, k, 1, 0.0, k, mask, False)
    for b in range(3):
        train_batch(straight, team, b)
    for b in range(2):
        train_batch(half, team, b)
    steps = {i: int(st["step"]) for i, st in half.opt.state_dict()["state"].items()}
    assert len(steps) == sc.n_agents and steps[2] > steps[0]
    half.save(tmp_path / "ck")
    _rewrite_train_state(tmp_path / "ck", _stacked_moments)
    resumed = Learner.load(tmp_path / "ck")
    assert {i: int(st["step"]) for i, st in resumed.opt.state_dict()["state"].items()} == steps
    train_batch(resumed, team, 2)
    assert torch.equal(resumed.net.flat, straight.net.flat)


def test_an_optimizer_state_that_does_not_fit_is_refused_naming_the_file(tmp_path: Path) -> None:
    sc = builtin()
    lr = Learner(sc, TINY.replace(learning_starts=1))
    k, mask = np.full(sc.knowledge_size, 0.5), np.ones(sc.n_actions, dtype=bool)
    for i in range(sc.n_agents):
        lr.store(i, k, 1, 0.0, k, mask, False)
    lr.train_step()
    lr.save(tmp_path / "ck")

    def short(st: dict[str, Any]) -> dict[str, Any]:
        moments = _stacked_moments(st)["adam"]
        return {**st, "adam": {**moments, "m": moments["m"][:, :-1]}}

    def none(st: dict[str, Any]) -> dict[str, Any]:
        return {key: v for key, v in st.items() if key != "adam"}

    for change in (short, none):
        d = _copy(tmp_path / "ck", tmp_path / change.__name__)
        _rewrite_train_state(d, change)
        with pytest.raises(CheckpointError, match=rf"{d / 'train_state.pt'}: optimizer state does not fit"):
            Learner.load(d)


def test_under_a_trainer_lag_the_agents_act_with_the_networks_of_k_steps_before() -> None:
    sc = builtin()
    s = TINY.replace(episodes=32, validate_every=0, select_best=False, learning_starts=20, trainer_lag=3)
    learner = Learner(sc, s)
    lagged = LaggedNets(learner, first_step=0)
    team = Team(sc, s.envs, s.seed)
    k, m = team.reset(), team.mask()
    rngs = [np.random.default_rng(i) for i in range(sc.n_agents)]
    seen: list[torch.Tensor] = []  # the online networks at each step, before its action
    for g in range(12):
        seen.append(learner.net.flat.detach().clone())
        net = lagged.at(g)
        assert net is not None
        assert torch.equal(net.flat, seen[max(0, g - 3)]), f"step {g} acts with the networks of {max(0, g - 3)}"
        a = learner.act(k, m, 1.0, rngs, net)
        k2, r, _ = team.step(a)
        learner.store_batch(k, a, r, k2, team.mask(), False)
        learner.train_steps(1)
        k, m = k2, team.mask()
    assert not torch.equal(seen[3], seen[0]), "the networks changed: the test tells the versions apart"
    assert len(lagged.versions) <= 4  # only the versions still needed are kept
    assert LaggedNets(Learner(sc, s.replace(trainer_lag=0)), 0).at(5) is None  # lag 0: the current networks


def test_a_trainer_lag_changes_the_learned_networks_and_a_run_repeats_exactly(tmp_path: Path) -> None:
    sc = builtin()
    s = TINY.replace(episodes=32, validate_every=0, select_best=False, learning_starts=20)
    nets = []
    for lag in (0, 2, 2):
        learner = Learner(sc, s.replace(trainer_lag=lag))
        team, lagged = Team(sc, s.envs, s.seed), LaggedNets(learner, 0)
        for b in range(2):
            train_batch(learner, team, b, lagged)
        nets.append(learner.net.flat.detach().clone())
    assert not torch.equal(nets[0], nets[1])
    assert torch.equal(nets[1], nets[2])


def test_a_short_training_run_beats_the_random_baseline(tmp_path: Path) -> None:
    # The HT mode (no idle locations) of the same learner: the quickest to learn, so the test stays short.
    sc = builtin(mode="ht")
    s = Settings(
        episodes=768,
        envs=64,
        learning_starts=256,
        memory=20_000,
        validate_every=0,
        eval_episodes=200,
        checkpoint_every=0,
    )
    res = train(sc, s, tmp_path / "run", progress=False, tensorboard=False)
    rand = evaluate(RandomPolicy(sc, 0), sc, 200, seed=0)
    learned, base = res.metrics["completion"], rand["completion"]
    assert learned["mean"] + 3 * (learned["se"] + base["se"]) < base["mean"], (learned, base)
    assert learned["failure_rate"] <= base["failure_rate"]


def test_baselines_order() -> None:
    sc = builtin()
    rand = evaluate(RandomPolicy(sc, 0), sc, 100, seed=0)["completion"]["mean"]
    greedy = evaluate(GreedyPolicy(sc), sc, 100, seed=0)["completion"]["mean"]
    assert greedy < rand


# ----- checkpoints -----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("ck") / "checkpoint"
    lr = Learner(builtin(), TINY.replace(seed=5))
    lr.episodes_done = 42
    lr.save(d)
    return d


def test_checkpoint_round_trip(saved: Path) -> None:
    ck = load_checkpoint(saved)
    lr = Learner(builtin(), TINY.replace(seed=5))
    assert ck.scenario == builtin() and ck.settings == TINY.replace(seed=5) and ck.seed == 5
    assert ck.episodes_done == 42 and ck.layout_hash == builtin().layout_hash() and ck.n_agents == 5
    for i in range(5):
        assert ck.agent_weights(i) == lr.agent_weights(i)
        assert AgentQ.from_checkpoint(ck, i).get_weights() == lr.agent_weights(i)
    assert load_checkpoint(saved.parent).path == saved  # a run directory works too
    back = Learner.load(saved)
    assert torch.equal(back.net.flat, lr.net.flat) and back.episodes_done == 42


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_missing_checkpoint_is_named(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=f"{tmp_path / 'nope'}: missing checkpoint"):
        load_checkpoint(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="missing checkpoint"):
        load_checkpoint(tmp_path / "empty")


def test_corrupt_checkpoint_files_are_rejected(saved: Path, tmp_path: Path) -> None:
    d = _copy(saved, tmp_path / "a")
    blob = bytearray((d / "agents.pt").read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    (d / "agents.pt").write_bytes(bytes(blob))
    with pytest.raises(CheckpointError, match=r"agents\.pt: corrupt checkpoint file \(checksum mismatch"):
        load_checkpoint(d)
    d = _copy(saved, tmp_path / "b")
    (d / "meta.json").write_text("{not json")
    with pytest.raises(CheckpointError, match=r"meta\.json: corrupt checkpoint metadata"):
        load_checkpoint(d)
    d = _copy(saved, tmp_path / "c")
    (d / "agents.pt").unlink()
    with pytest.raises(CheckpointError, match=r"agents\.pt: missing checkpoint file"):
        load_checkpoint(d)


def test_layout_and_agent_count_mismatches_are_rejected(saved: Path, tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="layout hash mismatch"):
        load_checkpoint(saved, builtin(mode="ht"))
    four = builtin().replace(agents=builtin().agents[:4])
    with pytest.raises(CheckpointError, match="wrong agent count: the checkpoint holds 5 agents"):
        load_checkpoint(saved, four)
    d = _copy(saved, tmp_path / "d")
    meta = json.loads((d / "meta.json").read_text())
    meta["layout_hash"] = "0123456789abcdef"
    (d / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=r"meta\.json: layout hash mismatch"):
        load_checkpoint(d)
    ck = load_checkpoint(saved)
    save_checkpoint(tmp_path / "e", four, ck.settings, 0, 0, ck.weights[:4])
    meta = json.loads((tmp_path / "e" / "meta.json").read_text())
    meta["n_agents"], meta["scenario"], meta["layout_hash"] = 5, builtin().to_dict(), builtin().layout_hash()
    (tmp_path / "e" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=r"agents\.pt: wrong agent count: 4 networks"):
        load_checkpoint(tmp_path / "e")


def test_dropout_sits_one_teammate_out_of_a_share_of_training_episodes() -> None:
    """Training for resilience: in a share of the episodes one drawn agent idles at its site for the whole episode,
    and its stored transitions are those of idling; with dropout 0 the training draws are untouched."""
    from htlm_agent.learning.dqn_run import dropouts
    from htlm_world import seeds

    mask = dropouts(0.5, 4000, 5, seeds.train_dropout(0, 0))
    assert mask is not None and mask.shape == (4000, 5)
    assert mask.sum(axis=1).max() == 1  # at most one agent per episode
    assert abs(mask.any(axis=1).mean() - 0.5) < 0.05
    assert np.allclose(mask.sum(axis=0) / mask.sum(), 0.2, atol=0.03)  # each agent about equally often
    assert dropouts(0.0, 8, 5, seeds.train_dropout(0, 0)) is None

    sc = builtin()
    s = Settings(envs=16, learning_starts=10_000, dropout=1.0)  # every episode loses one agent
    learner = Learner(sc, s, seed=3)
    team = Team(sc, 16, seed=3)
    train_batch(learner, team, 0)
    dropped = team.dropped
    assert dropped is not None and (dropped.sum(axis=1) == 1).all()
    # the dropped agent's stored decisions are all idling (actions >= p) in its episodes
    for i in range(sc.n_agents):
        rows = np.flatnonzero(dropped[:, i])
        if rows.size == 0:
            continue
        rp = learner.replay
        stored = rp.data[i, : 16 * sc.horizon, rp.cols["a"]].reshape(sc.horizon, 16)  # slots in (step, episode) order
        assert (stored[:, rows] >= sc.n_tasks).all()


def test_the_world_paces_by_the_learners_default_trainer_lag() -> None:
    from htlm_world.protocol import LockstepSettings
    from htlm_world.ros.settings import WorldSettings

    assert WorldSettings().trainer_lag == LockstepSettings().trainer_lag == Settings().trainer_lag
