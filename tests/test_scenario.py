"""Scenario files: the built-in teams of docs/model.md, the shipped paper.yaml, and messages for bad files that name the
file, the field and the value."""

from __future__ import annotations

from pathlib import Path

import pytest

from htlm_world.scenario import (
    REASSIGN_COSTS,
    TEAMS,
    RewardParams,
    Scenario,
    ScenarioError,
    builtin,
    from_dict,
    load,
    named_scenarios,
)

PAPER_YAML = Path(__file__).resolve().parent.parent / "src" / "htlm_world" / "htlm_world" / "scenarios" / "paper.yaml"

MODEL_MD_TEAMS = {
    "heterogeneous": [(3, 1), (3, 2), (2, 0), (0, 1), (1, 1)],
    "semi-heterogeneous": [(3, 1), (3, 1), (1, 1), (2, 2), (2, 2)],
    "homogeneous": [(2, 1)] * 5,
}


@pytest.mark.parametrize("team", sorted(MODEL_MD_TEAMS))
def test_builtin_teams(team: str) -> None:
    sc = builtin(team)
    assert sc.team == team
    assert [(a.fire, a.rescue) for a in sc.agents] == MODEL_MD_TEAMS[team]
    assert [a.name for a in sc.agents] == [f"agent{i}" for i in range(1, 6)]
    assert all(a.sensing == 3 and a.comm == 3 and a.reward is None for a in sc.agents)
    assert sc.n_agents == 5 and sc.n_tasks == 4 and sc.n_idle == 2 and sc.n_actions == 6
    assert sc.action_names == ("fire@site1", "rescue@site1", "fire@site2", "rescue@site2", "idle@site1", "idle@site2")
    assert sc.action_sites == (0, 0, 1, 1, 0, 1)
    assert sc.start_assignment == 4  # idle@site1
    assert sc.initial_levels == (4, 4, 4, 4) and sc.levels == 5 and sc.horizon == 30
    assert sc.p_drop == (0.90, 0.60, 0.35, 0.15, 0.05) and sc.fire_growth == 0.10
    assert sc.reward.level_rewards == (10.0, 5.0, 2.0, 1.0, 0.0) and sc.reward.belief_threshold == 0.97
    assert sc.reward.idle_bonus == 1.0 and sc.reward.idle_belief == "site"
    assert sc.sensing_base == 0.65 and sc.sensing_slope == 0.1 and sc.channel_base == 0.2  # accuracy 0.95, tau 0.8
    assert sc.reward.idle_incentive == 1.0 and sc.reward.reassign_cost == -1.0 and sc.gamma == 0.95
    assert sc.knowledge_size == 26
    assert set(TEAMS) == set(MODEL_MD_TEAMS)


def test_builtin_settings() -> None:
    for level, tc in (("none", 0.0), ("medium", -1.0), ("high", -4.0)):
        assert builtin(reassign=level).reward.reassign_cost == tc == REASSIGN_COSTS[level]
    assert builtin(idle_incentive=0.0).reward.idle_incentive == 0.0
    ht = builtin(mode="ht")
    assert ht.n_actions == 4 and ht.knowledge_size == 24 and ht.start_assignment == -1
    with pytest.raises(ScenarioError, match="unknown team 'alien'"):
        builtin("alien")
    with pytest.raises(ScenarioError, match="'extreme'"):
        builtin(reassign="extreme")


def test_first_calibration_is_shipped_by_name() -> None:
    """The model's first numbers stay available as the named scenario first-calibration; only the recalibrated
    open numbers differ from the defaults."""
    first, paper = load("first-calibration"), builtin()
    assert (first.sensing_base, first.channel_base) == (0.5, 0.0)
    assert (first.reward.belief_threshold, first.reward.idle_belief) == (0.8, "constant")
    same = first.replace(name="paper", sensing_base=0.65, channel_base=0.2).with_reward(
        belief_threshold=0.97, idle_belief="site"
    )
    assert same == paper
    assert "first-calibration" in named_scenarios()


def test_shipped_paper_yaml_equals_builtin() -> None:
    assert load(PAPER_YAML) == builtin()
    assert load(PAPER_YAML).layout_hash() == builtin().layout_hash()


def test_defaults_and_partial_files(tmp_path: Path) -> None:
    assert Scenario() == builtin()
    f = tmp_path / "short.yaml"
    f.write_text("horizon: 12\nteam: homogeneous\nreassign: high\nreward: {idle_incentive: 0.5}\n")
    sc = load(f)
    assert sc.horizon == 12 and sc.team == "homogeneous" and sc.agents == builtin("homogeneous").agents
    assert sc.reward.reassign_cost == -4.0 and sc.reward.idle_incentive == 0.5
    assert sc.sites == builtin().sites
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load(empty) == builtin()


def test_round_trip_with_own_reward_parameters() -> None:
    data = builtin("semi-heterogeneous", reassign="high").to_dict()
    data["agents"][2]["reward"] = {"idle_incentive": 0.0, "reassign_cost": -4.0}
    sc = from_dict(data)
    assert sc.agents[2].reward == RewardParams(idle_incentive=0.0, reassign_cost=-4.0)
    assert sc.agent_reward(2) is sc.agents[2].reward and sc.agent_reward(0) == sc.reward
    assert from_dict(sc.to_dict()) == sc


AGENTS_2 = "agents:\n  - {name: a, fire: 1, rescue: 1}\n"

BAD_FILES = [
    # (file text, field path, bad value as it must appear in the message)
    ("horizon: 10\nspeed: 3\n", "speed", "unknown key"),
    (AGENTS_2 + "  - {name: b, fire: 1, rescue: 1, speed: 2}\n", "agents[1].speed", "unknown key"),
    ("reward: {bonus: 2}\n", "reward.bonus", "unknown key"),
    ("horizon: ten\n", "horizon", "'ten'"),
    ("horizon: 10.5\n", "horizon", "10.5"),
    ("channel: 1\n", "channel", "1"),
    ("mode: xyz\n", "mode", "'xyz'"),
    ("team: alien\n", "team", "'alien'"),
    (AGENTS_2 + "  - {name: b, fire: three, rescue: 1}\n", "agents[1].fire", "'three'"),
    (AGENTS_2 + "  - {name: b, fire: 7, rescue: 1}\n", "agents[1].fire", "7"),
    (AGENTS_2 + "  - {name: b, fire: 1, rescue: -1}\n", "agents[1].rescue", "-1"),
    ("agents:\n  - {name: a, fire: 1, rescue: 1, sensing: 6}\n", "agents[0].sensing", "6"),
    ("agents:\n  - {name: a, fire: 1, rescue: 1, comm: 9}\n", "agents[0].comm", "9"),
    ("fire_growth: 1.5\n", "fire_growth", "1.5"),
    ("p_drop: [0.9, 0.6, -0.1]\n", "p_drop[2]", "-0.1"),
    ("rescue_double_share: 2.0\n", "rescue_double_share", "2.0"),
    ("reward: {belief_threshold: 1.2}\n", "reward.belief_threshold", "1.2"),
    ("agents: []\n", "agents", "[]"),
    ("initial_levels: [4, 4, 5, 4]\n", "initial_levels[2]", "5"),
    ("horizon: 0\n", "horizon", "0"),
    (
        "agents:\n  - {name: a, fire: 1, rescue: 1, reward: {reassign_cost: 2.0}}\n",
        "agents[0].reward.reassign_cost",
        "2.0",
    ),
]


@pytest.mark.parametrize(("text", "field", "value"), BAD_FILES)
def test_bad_file_message_names_file_field_and_value(tmp_path: Path, text: str, field: str, value: str) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load(f)
    msg = str(err.value)
    assert str(f) in msg, msg
    assert f"{field}:" in msg, msg
    assert value in msg, msg


def test_bad_yaml(tmp_path: Path) -> None:
    f = tmp_path / "broken.yaml"
    f.write_text("horizon: [1, 2\n")
    with pytest.raises(ScenarioError) as err:
        load(f)
    assert str(f) in str(err.value) and "not valid YAML" in str(err.value)
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ScenarioError, match=r"top level: expected a mapping, got list \[1, 2\]"):
        load(f)


def test_missing_file(tmp_path: Path) -> None:
    f = tmp_path / "nope.yaml"
    with pytest.raises(ScenarioError) as err:
        load(f)
    assert str(f) in str(err.value) and "cannot read" in str(err.value)


def test_replace_validates() -> None:
    with pytest.raises(ScenarioError, match=r"<replace>: horizon: -3"):
        builtin().replace(horizon=-3)
