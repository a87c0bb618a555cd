"""The reward f_R = R_comp + R_II + T_RP and the reduced action space Â(a_o) (docs/model.md, Reward)."""

from __future__ import annotations

import numpy as np
import pytest

from htlm_agent.mind.reward import RewardTables, confident_levels, reward
from htlm_world.model import Model
from htlm_world.scenario import AgentSpec, RewardParams, Scenario, builtin

L = 5
IDLE1, IDLE2 = 4, 5  # idle@site1, idle@site2
FIRE1, RESCUE1, FIRE2, RESCUE2 = 0, 1, 2, 3


def rules(*args: object, **kwargs: object) -> Scenario:
    """The built-in scenario with b_th = 0.8 and a constant idle bonus: the numbers the rule tests below state."""
    return builtin(*args, **kwargs).with_reward(belief_threshold=0.8, idle_belief="constant")  # type: ignore[arg-type]


def certain(levels: tuple[int, ...], n: int = 5) -> np.ndarray:
    """(1, n, p, L) marginals certain of the given task levels, the same for every agent."""
    m = np.zeros((1, n, len(levels), L))
    for j, lv in enumerate(levels):
        m[0, :, j, lv] = 1.0
    return m


def run(sc: Scenario, prev: list[int], marg: np.ndarray, actions: list[int]) -> tuple[np.ndarray, dict]:
    model = Model.build(sc)
    r, parts = reward(
        model, RewardTables.build(sc), np.array([prev], dtype=np.int64), marg, np.array([actions], dtype=np.int64)
    )
    return r[0], {k: v[0] for k, v in parts.items()}


def test_confident_level_is_smallest_level_reaching_the_threshold() -> None:
    marg = np.array(
        [
            [
                [0.5, 0.25, 0.1, 0.1, 0.05],  # P(<=1) = 0.75, P(<=2) = 0.85 -> 2
                [0.8, 0.2, 0.0, 0.0, 0.0],  # exactly b_th at 0 -> 0
                [0.0, 0.0, 0.0, 0.0, 1.0],  # -> 4
                [0.1, 0.1, 0.1, 0.1, 0.6],  # P(<=3) = 0.4 -> 4
            ]
        ]
    )[None]
    assert confident_levels(marg, np.array([0.8])).tolist() == [[[2, 0, 4, 4]]]
    assert confident_levels(marg, np.array([0.5])).tolist() == [[[0, 0, 4, 4]]]


def test_r_comp_worked_example() -> None:
    """Half the tasks confidently at level 2, half at 0: R_comp = 0.5 R_0 + 0.5 R_2 = 0.5 * 10 + 0.5 * 2 = 6."""
    task_level_2 = [0.1, 0.2, 0.6, 0.1, 0.0]  # P(<=1) = 0.3, P(<=2) = 0.9
    task_level_0 = [0.85, 0.15, 0.0, 0.0, 0.0]
    marg = np.array([task_level_2, [0, 0, 1.0, 0, 0], task_level_0, [1.0, 0, 0, 0, 0]])
    marg = np.broadcast_to(marg, (1, 5, 4, L)).copy()
    _, parts = run(rules(), [IDLE1] * 5, marg, [IDLE1] * 5)
    np.testing.assert_allclose(parts["comp"], 6.0)


def test_r_comp_extremes() -> None:
    _, parts = run(rules(), [IDLE1] * 5, certain((4, 4, 4, 4)), [IDLE1] * 5)
    np.testing.assert_allclose(parts["comp"], 0.0)
    _, parts = run(rules(), [IDLE1] * 5, certain((0, 0, 0, 0)), [IDLE1] * 5)
    np.testing.assert_allclose(parts["comp"], 10.0)
    _, parts = run(rules(), [IDLE1] * 5, certain((1, 3, 0, 2)), [IDLE1] * 5)
    np.testing.assert_allclose(parts["comp"], (5 + 1 + 10 + 2) / 4)


# heterogeneous team (fire, rescue): agent1 (3,1) agent2 (3,2) agent3 (2,0) agent4 (0,1) agent5 (1,1)
LEVELS = (1, 0, 4, 3)  # confident levels of fire@site1, rescue@site1, fire@site2, rescue@site2
R_II_CASES = [
    # actions of agents 1..5 (all previously at site 1, so no reassignment), expected unscaled R_II
    ([IDLE1, FIRE1, FIRE1, RESCUE1, RESCUE1], [1.0, -1.0, 0.0, 0.0, 0.0]),  # 3 >= 1+2; 2 < 3; 1 < 0+2
    ([FIRE1, RESCUE1, IDLE1, IDLE1, FIRE1], [-1.0, -1.0, 1.0, 1.0, 0.0]),  # 3 >= 3; 2 >= 0+2; 1 < 3
    ([RESCUE1, RESCUE1, RESCUE1, FIRE1, IDLE1], [0.0, -1.0, 0.0, 0.0, 1.0]),  # 1 < 2; 2 >= 2; 0 < 2; 0 < 3
]


@pytest.mark.parametrize(("actions", "expected"), R_II_CASES)
@pytest.mark.parametrize("incentive", [1.0, 0.5, 0.0])
def test_r_ii_idle_bonus_and_excess_penalty(actions: list[int], expected: list[float], incentive: float) -> None:
    sc = rules(idle_incentive=incentive)
    r, parts = run(sc, [IDLE1] * 5, certain(LEVELS), actions)
    np.testing.assert_allclose(parts["idle"], incentive * np.array(expected))
    np.testing.assert_allclose(parts["reassign"], 0.0)
    np.testing.assert_allclose(r, parts["comp"] + parts["idle"] + parts["reassign"])


def test_r_ii_excess_on_far_site_tasks() -> None:
    # fire@site2 and rescue@site2 at levels 4 and 3: no capability exceeds them by 2
    _, parts = run(rules(reassign="none"), [IDLE2] * 5, certain(LEVELS), [FIRE2, RESCUE2, FIRE2, RESCUE2, FIRE2])
    np.testing.assert_allclose(parts["idle"], 0.0)
    _, parts = run(rules(reassign="none"), [IDLE2] * 5, certain((0, 0, 1, 0)), [FIRE2, RESCUE2, FIRE2, RESCUE2, IDLE2])
    np.testing.assert_allclose(parts["idle"], [-1.0, -1.0, 0.0, 0.0, 1.0])  # 3 >= 3; 2 >= 2; 2 < 3; 1 < 2


@pytest.mark.parametrize(("level", "tc"), [("none", 0.0), ("medium", -1.0), ("high", -4.0)])
def test_t_rp_by_level(level: str, tc: float) -> None:
    sc = rules(reassign=level)
    prev = [IDLE1, IDLE1, FIRE1, FIRE2, IDLE2]
    actions = [FIRE2, FIRE1, RESCUE2, IDLE2, RESCUE1]  # moves: site1->2, stays, 1->2, stays, 2->1
    _, parts = run(sc, prev, certain((4, 4, 4, 4)), actions)
    np.testing.assert_allclose(parts["reassign"], tc * np.array([1, 0, 1, 0, 1]))


def test_no_reassignment_penalty_without_a_previous_assignment() -> None:
    _, parts = run(rules(reassign="high"), [-1] * 5, certain((4, 4, 4, 4)), [FIRE2, RESCUE2, FIRE1, RESCUE1, IDLE1])
    np.testing.assert_allclose(parts["reassign"], 0.0)


def test_agents_with_their_own_reward_parameters() -> None:
    own = RewardParams(level_rewards=(20.0, 10.0, 4.0, 2.0, 0.0), idle_incentive=2.0, reassign_cost=-4.0)
    agents = list(rules().agents)
    agents[0] = AgentSpec(name="agent1", capabilities={"fire": 3, "rescue": 1}, reward=own)
    sc = rules().replace(agents=tuple(agents))
    assert sc.agent_reward(0) is own
    assert sc.agent_reward(1) == sc.reward
    tables = RewardTables.build(sc)
    np.testing.assert_allclose(tables.idle_bonus, [2.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(tables.reassign_cost, [-4.0, -1.0, -1.0, -1.0, -1.0])
    marg = certain((0, 0, 2, 2))
    r, parts = run(sc, [IDLE1] * 5, marg, [IDLE1, IDLE1, IDLE1, IDLE1, IDLE1])
    np.testing.assert_allclose(parts["comp"], [12.0, 6.0, 6.0, 6.0, 6.0])
    np.testing.assert_allclose(parts["idle"], [2.0, 1.0, 1.0, 1.0, 1.0])
    r, parts = run(sc, [IDLE1] * 5, marg, [RESCUE2, IDLE1, IDLE1, IDLE1, RESCUE2])
    np.testing.assert_allclose(parts["reassign"], [-4.0, 0.0, 0.0, 0.0, -1.0])
    np.testing.assert_allclose(r, [12.0 - 4.0, 7.0, 7.0, 7.0, 6.0 - 1.0])


def test_ht_mode_has_no_idle_actions_and_no_load_management_reward() -> None:
    sc = rules(mode="ht", reassign="high")
    assert sc.n_actions == 4 and sc.n_idle == 0 and sc.start_assignment == -1
    assert sc.action_names == ("fire@site1", "rescue@site1", "fire@site2", "rescue@site2")
    mask = Model.build(sc).action_mask(np.array([-1, 0, 1, 2, 3], dtype=np.int64))
    assert mask.shape == (5, 4) and mask.all()
    prev = [FIRE1, FIRE1, RESCUE2, FIRE2, RESCUE1]
    actions = [FIRE2, FIRE1, RESCUE1, FIRE2, RESCUE2]  # site moves and capabilities far above the levels
    r, parts = run(sc, prev, certain((0, 0, 0, 0)), actions)
    np.testing.assert_allclose(parts["idle"], 0.0)
    np.testing.assert_allclose(parts["reassign"], 0.0)
    np.testing.assert_allclose(r, 10.0)


@pytest.mark.parametrize(
    ("prev", "idle"),
    [(IDLE1, IDLE1), (FIRE1, IDLE1), (RESCUE1, IDLE1), (FIRE2, IDLE2), (RESCUE2, IDLE2), (IDLE2, IDLE2), (-1, IDLE1)],
)
def test_action_mask_is_tasks_and_idle_at_site_of_previous_assignment(prev: int, idle: int) -> None:
    mask = Model.build(rules()).action_mask(np.array([prev], dtype=np.int64))[0]
    expected = [True, True, True, True, idle == IDLE1, idle == IDLE2]
    assert mask.tolist() == expected
    assert mask.sum() == rules().n_tasks + 1


def test_action_mask_broadcasts_over_batch_and_agents() -> None:
    prev = np.array([[IDLE1, FIRE2], [RESCUE2, IDLE1]], dtype=np.int64)
    mask = Model.build(rules()).action_mask(prev)
    assert mask.shape == (2, 2, 6)
    assert mask[..., 4].tolist() == [[True, False], [False, True]]
    assert mask[..., 5].tolist() == [[False, True], [True, False]]


def test_idle_action_is_the_idle_location_at_the_site_of_the_previous_assignment() -> None:
    prev = np.array([-1, FIRE1, RESCUE1, FIRE2, RESCUE2, IDLE1, IDLE2], dtype=np.int64)
    assert Model.build(rules()).idle_action(prev).tolist() == [IDLE1, IDLE1, IDLE1, IDLE2, IDLE2, IDLE1, IDLE2]
    assert Model.build(rules()).idle_action(prev[None, :2]).shape == (1, 2)
    assert Model.build(rules(mode="ht")).idle_action(prev[:5]).tolist() == [-1] * 5  # HT mode: no idle location


def _uncertain_done(p_done: tuple[float, ...], n: int = 5) -> np.ndarray:
    """(1, n, p, L) marginals with P(level 0) = p_done[j] and the rest at level 1, the same for every agent."""
    m = np.zeros((1, n, len(p_done), L))
    for j, q in enumerate(p_done):
        m[0, :, j, 0] = q
        m[0, :, j, 1] = 1.0 - q
    return m


@pytest.mark.parametrize(
    ("kind", "expected_site1", "expected_site2"),
    [
        ("constant", 1.0, 1.0),
        ("site", 0.9 * 0.5, 1.0 * 0.8),  # tasks 0, 1 at site 1; tasks 2, 3 at site 2
        ("mission", 0.9 * 0.5 * 1.0 * 0.8, 0.9 * 0.5 * 1.0 * 0.8),
    ],
)
def test_idle_bonus_depends_on_the_belief(kind: str, expected_site1: float, expected_site2: float) -> None:
    """R_II(b): the idle bonus times the believed probability that the idle site's tasks (or all tasks) are done."""
    sc = builtin().with_reward(idle_belief=kind, idle_bonus=2.0)
    marg = _uncertain_done((0.9, 0.5, 1.0, 0.8))
    _, parts = run(sc, [IDLE1, IDLE2, IDLE1, IDLE2, FIRE1], marg, [IDLE1, IDLE2, IDLE1, IDLE2, FIRE1])
    np.testing.assert_allclose(parts["idle"][:4], [2 * expected_site1, 2 * expected_site2] * 2)
    assert parts["idle"][4] == 0.0  # working on a task: no bonus (capability 3 vs confident level 1: no excess)


def test_idle_belief_per_agent_preference() -> None:
    """Agents may carry their own R_II(b): one constant, the others from the builtin's shared reward."""
    sc = builtin().with_reward(idle_belief="mission")
    own = RewardParams(idle_belief="constant")
    agents = (AgentSpec(**{**sc.agents[0].__dict__, "reward": own}), *sc.agents[1:])
    sc = sc.replace(agents=agents)
    _, parts = run(sc, [IDLE1] * 5, _uncertain_done((0.5, 0.5, 0.5, 0.5)), [IDLE1] * 5)
    np.testing.assert_allclose(parts["idle"], [1.0] + [0.5**4] * 4)


def test_unknown_idle_belief_is_rejected_naming_the_value(tmp_path) -> None:
    from htlm_world.scenario import ScenarioError, load

    f = tmp_path / "bad.yaml"
    f.write_text("reward: {idle_belief: sometimes}\n")
    with pytest.raises(ScenarioError, match=r"reward\.idle_belief.*sometimes"):
        load(f)
