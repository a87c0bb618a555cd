"""The T, O and I models (htlm_world.model) against docs/model.md, and the simulator's draws against the tables.

The reference model (tests/support/reference_model.py) is re-derived from the text of docs/model.md in plain Python,
independently of the module's tables.

Sampling tolerance: an empirical frequency of n draws with probability p must lie within Z_TOL standard errors
sqrt(p (1 - p) / n) of p; zero-probability outcomes must never occur and certain ones always. With fixed seeds the
tests are deterministic; Z_TOL = 4.5 makes a false alarm over all comparisons of this file (a few hundred) unlikely
(< 0.2 %) for any seed.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from htlm_world.model import Model, p_drop_table
from htlm_world.scenario import builtin, from_dict
from htlm_world.simulator import BatchSim
from support.reference_model import L, ref_fire, ref_info, ref_obs, ref_p_drop, ref_rescue

CMAX = 5  # capability cap
N_DRAWS = 200_000
Z_TOL = 4.5

# ----- tables ------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model() -> Model:
    return Model.build(builtin())


def test_p_drop_by_margin(model: Model) -> None:
    expected = {0: 0.90, -1: 0.60, -2: 0.35, -3: 0.15, -4: 0.05, -5: 0.05}
    table = p_drop_table(model.scenario)
    assert table.shape == (CMAX + 1, L)
    for c in range(CMAX + 1):
        for lv in range(L):
            want = 0.0 if c == 0 or lv == 0 else expected[max(min(c - lv, 0), -5)]
            assert table[c, lv] == pytest.approx(want), (c, lv)
            assert table[c, lv] == pytest.approx(ref_p_drop(c, lv))
    # a few explicit values of docs/model.md
    assert table[3, 4] == pytest.approx(0.60)
    assert table[2, 4] == pytest.approx(0.35)
    assert table[1, 4] == pytest.approx(0.15)
    assert table[5, 1] == pytest.approx(0.90)


def test_a_scenario_is_compiled_once() -> None:
    """Model.build keeps the Model of a scenario: equal scenarios (another object, the same numbers) share it, a
    changed one gets its own, and what it keeps is what `compute` makes."""
    a, b = builtin(), builtin()
    assert a is not b and a == b
    assert Model.build(a) is Model.build(b)
    other = builtin(team="homogeneous")
    assert Model.build(other) is not Model.build(a)
    fresh = Model.compute(a)
    kept = Model.build(a)
    for name in ("transition_cdf", "obs", "info", "task_caps", "keep", "site_task"):
        assert np.array_equal(getattr(fresh, name), getattr(kept, name)), name


def test_p_drop_last_entry_covers_lower_margins() -> None:
    table = p_drop_table(builtin().replace(p_drop=(0.8, 0.3)))
    assert table[1, 4] == pytest.approx(0.3)
    assert table[3, 4] == pytest.approx(0.3)
    assert table[4, 4] == pytest.approx(0.8)


def test_tables_equal_model_md(model: Model) -> None:
    for c in range(CMAX + 1):
        for f in range(L):
            np.testing.assert_allclose(
                model.kind_tables[0][c, 0, f], ref_fire(c, f), atol=1e-12, err_msg=f"fire c={c} f={f}"
            )
            for r in range(L):
                np.testing.assert_allclose(
                    model.kind_tables[1][c, f, r], ref_rescue(c, f, r), atol=1e-12, err_msg=f"rescue c={c} f={f} r={r}"
                )
    for s in range(CMAX + 1):
        for lv in range(L):
            np.testing.assert_allclose(model.obs[0, s, lv], ref_obs(s, lv), atol=1e-12)
            for comm in range(CMAX + 1):
                np.testing.assert_allclose(model.info[0, s, comm, lv], ref_info(s, comm, lv), atol=1e-12)
    assert model.obs[0, 3, 2, 2] == pytest.approx(0.95)
    assert model.obs[0, 3, 0, 1] == pytest.approx(0.05)  # all of the rest to the one neighbour at level 0
    assert model.obs[0, 3, 2, 1] == pytest.approx(0.025)
    np.testing.assert_allclose(model.keep, 0.8)


def test_first_calibration_tables() -> None:
    """The shipped scenario first-calibration keeps the model's first numbers: accuracy 0.8 at sensing 3, tau 0.6."""
    from htlm_world.scenario import load

    m = Model.build(load("first-calibration"))
    for s in range(CMAX + 1):
        for lv in range(L):
            np.testing.assert_allclose(m.obs[0, s, lv], ref_obs(s, lv, 0.5), atol=1e-12)
            for comm in range(CMAX + 1):
                np.testing.assert_allclose(m.info[0, s, comm, lv], ref_info(s, comm, lv, True, 0.5, 0.0), atol=1e-12)
    assert m.obs[0, 3, 2, 2] == pytest.approx(0.8)
    np.testing.assert_allclose(m.keep, 0.6)


def test_information_without_channel_is_observation() -> None:
    m = Model.build(builtin().replace(channel=False))
    for comm in range(CMAX + 1):
        np.testing.assert_allclose(m.info[:, :, comm], m.obs, atol=1e-12)
    np.testing.assert_allclose(m.keep, 1.0)


def _assert_distributions(t: np.ndarray) -> None:
    assert (t >= 0.0).all()
    np.testing.assert_allclose(t.sum(axis=-1), 1.0, atol=1e-12)


def test_every_row_is_a_distribution(model: Model) -> None:
    for t in (*model.kind_tables, model.obs, model.info):
        _assert_distributions(t)


@settings(max_examples=60, deadline=None)
@given(
    levels=st.integers(2, 7),
    p_drop=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=6),
    growth=st.floats(0.0, 1.0),
    share=st.floats(0.0, 1.0),
    base=st.floats(0.0, 1.0),
    slope=st.floats(0.0, 1.0),
    channel=st.booleans(),
)
def test_every_row_is_a_distribution_for_any_scenario(
    levels: int, p_drop: list[float], growth: float, share: float, base: float, slope: float, channel: bool
) -> None:
    data = {
        "levels": levels,
        "initial_levels": [levels - 1] * 4,
        "reward": {"level_rewards": [float(levels - k) for k in range(levels)]},
        "p_drop": p_drop,
        "fire_growth": growth,
        "rescue_double_share": share,
        "sensing_base": base,
        "sensing_slope": slope,
        "channel": channel,
    }
    if levels < 3:  # a two-level drop needs three levels
        data["kinds"] = [{"name": "fire"}, {"name": "rescue", "depends_on": "fire", "blocked_above": 1}]
        del data["rescue_double_share"]
    sc = from_dict(data)
    m = Model.build(sc)
    for t in (*m.kind_tables, m.obs, m.info):
        _assert_distributions(t)


# ----- sampling ----------------------------------------------------------------------------------------------------


def assert_frequencies(samples: np.ndarray, probs: list[float] | np.ndarray, what: str) -> None:
    """Empirical frequencies of integer samples against a distribution over 0..len(probs)-1 (see module doc)."""
    samples = np.asarray(samples).ravel()
    n = samples.size
    assert n > 0, what
    assert samples.min() >= 0 and samples.max() < len(probs), what
    freq = np.bincount(samples, minlength=len(probs)) / n
    for k, p in enumerate(probs):
        if p == 0.0:
            assert freq[k] == 0.0, f"{what}: outcome {k} has probability 0 but frequency {freq[k]}"
        elif p == 1.0:
            assert freq[k] == 1.0, f"{what}: outcome {k} is certain but has frequency {freq[k]}"
        else:
            se = np.sqrt(p * (1.0 - p) / n)
            assert abs(freq[k] - p) <= Z_TOL * se, f"{what}: outcome {k}: frequency {freq[k]:.5f} vs p = {p:.5f}"


def ref_task_rows(levels: tuple[int, ...], caps: tuple[int, ...]) -> list[list[float]]:
    """Reference next-level distribution of every task (order fire@site1, rescue@site1, fire@site2, ...)."""
    rows = []
    for j, (lv, c) in enumerate(zip(levels, caps, strict=True)):
        rows.append(ref_fire(c, lv) if j % 2 == 0 else ref_rescue(c, levels[j - 1], lv))
    return rows


# (levels, joint capabilities) of both sites; comments: fire@1 | rescue@1 | fire@2 | rescue@2
TRANSITION_CASES = [
    ((4, 4, 4, 4), (0, 0, 0, 0)),  # c=0 at top stays | blocked | same | same
    ((2, 3, 1, 2), (0, 5, 3, 2)),  # growth 0.1 | f=2: single drop 0.9 | 0.9 | f=1, c>=r>=2: double 0.45/0.45
    ((4, 2, 0, 4), (1, 5, 0, 5)),  # margin -3: 0.15 | f=4 blocks c=5 | level 0 stays | double from 4 at f=0
    ((3, 1, 1, 3), (2, 3, 5, 1)),  # margin -1: 0.6 | f=3 blocks | 0.9 | c<r: single, margin -2: 0.35
    ((1, 1, 2, 2), (0, 1, 4, 1)),  # growth 1->2 | r=1: single 0.9 | 0.9 | f=2: single, margin -1: 0.6
    ((4, 1, 2, 4), (5, 1, 2, 0)),  # 0.9 | f=4 blocks | 0.9 | c=0 stays
]


@pytest.mark.parametrize(("levels", "caps"), TRANSITION_CASES)
def test_sample_transition_matches_t(model: Model, levels: tuple[int, ...], caps: tuple[int, ...]) -> None:
    rng = np.random.default_rng(12345)
    lv = np.tile(np.array(levels, dtype=np.int64), (N_DRAWS, 1))
    cp = np.tile(np.array(caps, dtype=np.int64), (N_DRAWS, 1))
    nxt = model.sample_transition(lv, cp, rng.random((N_DRAWS, 4)))
    for j, row in enumerate(ref_task_rows(levels, caps)):
        np.testing.assert_allclose(model.transition_rows(lv[:1], cp[:1])[0, j], row, atol=1e-12)
        assert_frequencies(nxt[:, j], row, f"task {j} levels={levels} caps={caps}")


def test_tasks_are_drawn_independently(model: Model) -> None:
    levels, caps = (2, 3, 1, 2), (0, 5, 3, 2)
    rng = np.random.default_rng(7)
    lv = np.tile(np.array(levels, dtype=np.int64), (N_DRAWS, 1))
    cp = np.tile(np.array(caps, dtype=np.int64), (N_DRAWS, 1))
    nxt = model.sample_transition(lv, cp, rng.random((N_DRAWS, 4)))
    rows = ref_task_rows(levels, caps)
    for a, b in ((0, 1), (2, 3), (1, 3)):
        joint = np.outer(rows[a], rows[b]).ravel()
        assert_frequencies(nxt[:, a] * L + nxt[:, b], joint, f"joint of tasks {a} and {b}")


def test_rescue_blocked_while_fire_above_two(model: Model) -> None:
    rng = np.random.default_rng(99)
    for f in (3, 4):
        for r in range(1, L):
            lv = np.tile(np.array([f, r, f, r], dtype=np.int64), (20_000, 1))
            cp = np.tile(np.array([0, 5, 5, 5], dtype=np.int64), (20_000, 1))
            nxt = model.sample_transition(lv, cp, rng.random(lv.shape))
            assert (nxt[:, 1] == r).all() and (nxt[:, 3] == r).all(), (f, r)
            # the fire may move during the step; the block depends on the fire at the start of the step
            assert (nxt[:, 2] < f).any()


def test_rescue_double_drop_frequency(model: Model) -> None:
    rng = np.random.default_rng(2024)
    n = 50_000
    for f in range(L):
        for r in range(1, L):
            for c in range(1, CMAX + 1):
                lv = np.tile(np.array([f, r, f, r], dtype=np.int64), (n, 1))
                cp = np.tile(np.array([0, c, 0, c], dtype=np.int64), (n, 1))
                nxt = model.sample_transition(lv, cp, rng.random(lv.shape))[:, 1]
                double = float((nxt == r - 2).mean())
                if f <= 1 and c >= r >= 2:
                    p = 0.5 * ref_p_drop(c, r)
                    assert abs(double - p) <= Z_TOL * np.sqrt(p * (1 - p) / n), (f, r, c, double)
                else:
                    assert double == 0.0, (f, r, c, double)


# the heterogeneous team: agent1 (3,1) agent2 (3,2) agent3 (2,0) agent4 (0,1) agent5 (1,1)
SIM_CASES = [
    # levels, actions of agents 1..5, expected joint capabilities
    ((4, 4, 1, 3), (0, 1, 2, 3, 3), (3, 2, 2, 2)),
    ((0, 2, 2, 4), (1, 1, 2, 3, 3), (0, 3, 2, 2)),
    ((3, 4, 4, 4), (1, 1, 1, 1, 1), (0, 5, 0, 0)),  # all on rescue@site1 (capability 5), fire 3 blocks it
    ((1, 3, 4, 2), (0, 4, 2, 1, 5), (3, 1, 2, 0)),  # idle agents bring nothing
]


@pytest.mark.parametrize(("levels", "actions", "caps"), SIM_CASES)
def test_batch_sim_step_matches_t_and_o(
    levels: tuple[int, ...], actions: tuple[int, ...], caps: tuple[int, ...]
) -> None:
    sc = builtin()
    sim = BatchSim(sc, N_DRAWS, np.random.default_rng(31337))
    sim.levels = np.tile(np.array(levels, dtype=np.int64), (N_DRAWS, 1))
    acts = np.tile(np.array(actions, dtype=np.int64), (N_DRAWS, 1))
    res = sim.step(acts)
    assert (res.caps == np.array(caps)).all()
    for j, row in enumerate(ref_task_rows(levels, caps)):
        assert_frequencies(res.levels[:, j], row, f"BatchSim task {j} levels={levels} caps={caps}")
    if levels[0] > 2:
        assert (res.levels[:, 1] == levels[1]).all()
    for k, a in enumerate(actions):
        if a >= sc.n_tasks:
            assert (res.observations[:, k] == -1).all() and (res.messages[:, k] == -1).all()
            continue
        true = res.levels[:, a]
        for lv in np.unique(true):
            sel = true == lv
            if sel.sum() < 1000:
                continue
            assert_frequencies(res.observations[sel, k], ref_obs(3, int(lv)), f"agent {k} observes level {lv}")
        z = res.observations[:, k]
        for zv in np.unique(z):  # the channel: keep with tau = 0.8, else a uniform level
            sel = z == zv
            if sel.sum() < 1000:
                continue
            want = [0.8 * (m == zv) + 0.2 / L for m in range(L)]
            assert_frequencies(res.messages[sel, k], want, f"agent {k} channel on {zv}")


def test_sample_observation_matches_o(model: Model) -> None:
    rng = np.random.default_rng(5)
    n = 40_000
    for s in range(CMAX + 1):
        for lv in range(L):
            true = np.full(n, lv, dtype=np.int64)
            z = model.sample_observation(
                np.zeros(n, dtype=np.int64), true, np.full(n, s, dtype=np.int64), rng.random(n)
            )
            assert_frequencies(z, ref_obs(s, lv), f"sensing {s} level {lv}")


@pytest.mark.parametrize(("base", "comm", "tau"), [(0.0, 3, 0.6), (0.2, 3, 0.8), (0.2, 0, 0.2), (0.5, 4, 1.0)])
def test_channel_reliability_tau(base: float, comm: int, tau: float) -> None:
    """tau = min(1, channel_base + comm / capability_max); the information table I mixes O with uniform by it."""
    sc = builtin().replace(channel_base=base)
    sc = sc.replace(agents=tuple(a.__class__(**{**a.__dict__, "comm": comm}) for a in sc.agents))
    model = Model.build(sc)
    np.testing.assert_allclose(model.keep, tau)
