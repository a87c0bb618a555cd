"""Scenario files: the built-in teams of docs/model.md, the shipped paper.yaml, and messages for bad files that name the
file, the field and the value."""

from __future__ import annotations

from pathlib import Path

import pytest

from htlm_world.scenario import (
    REASSIGN_COSTS,
    RewardParams,
    ScenarioError,
    builtin,
    from_dict,
    load,
    named_scenarios,
    team_names,
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
    assert [(a.capability("fire"), a.capability("rescue")) for a in sc.agents] == MODEL_MD_TEAMS[team]
    assert sc.capability_table() == [list(c) for c in MODEL_MD_TEAMS[team]]
    assert [a.name for a in sc.agents] == [f"agent{i}" for i in range(1, 6)]
    assert all(a.sensing == 3 and a.comm == 3 and a.reward is None for a in sc.agents)
    assert sc.n_agents == 5 and sc.n_tasks == 4 and sc.n_idle == 2 and sc.n_actions == 6
    assert sc.action_names == ("fire@site1", "rescue@site1", "fire@site2", "rescue@site2", "idle@site1", "idle@site2")
    assert sc.action_sites == (0, 0, 1, 1, 0, 1)
    assert sc.start_assignment == 4  # idle@site1
    assert sc.initial_levels == (4, 4, 4, 4) and sc.levels == 5 and sc.horizon == 30
    assert sc.p_drop == (0.90, 0.60, 0.35, 0.15, 0.05)
    fire, rescue = sc.kinds
    assert (fire.name, fire.growth, fire.depends_on, fire.double_drop) == ("fire", 0.10, "", None)
    assert (rescue.name, rescue.growth, rescue.depends_on, rescue.blocked_above) == ("rescue", 0.0, "fire", 2)
    assert rescue.double_drop is not None
    assert (rescue.double_drop.share, rescue.double_drop.min_level, rescue.double_drop.gate_at_most) == (0.5, 2, 1)
    assert sc.site_positions == ((0.0, 0.0), (50.0, 0.0)) and sc.tasks == ((0, 0), (0, 1), (1, 0), (1, 1))
    assert sc.reward.level_rewards == (10.0, 5.0, 2.0, 1.0, 0.0) and sc.reward.belief_threshold == 0.97
    assert sc.reward.idle_bonus == 1.0 and sc.reward.idle_belief == "site"
    assert sc.sensing_base == 0.65 and sc.sensing_slope == 0.1 and sc.channel_base == 0.2  # accuracy 0.95, tau 0.8
    assert sc.reward.idle_incentive == 1.0 and sc.reward.reassign_cost == -1.0 and sc.gamma == 0.95
    assert sc.knowledge_size == 26
    assert set(team_names()) == set(MODEL_MD_TEAMS)


def test_builtin_settings() -> None:
    for level, tc in (("none", 0.0), ("medium", -1.0), ("high", -4.0)):
        assert builtin(reassign=level).reward.reassign_cost == tc == REASSIGN_COSTS[level]
    assert builtin(idle_incentive=0.0).reward.idle_incentive == 0.0
    ht = builtin(mode="ht")
    assert ht.n_actions == 4 and ht.knowledge_size == 24 and ht.start_assignment == -1
    with pytest.raises(ScenarioError, match="team: 'alien' is not one of the scenario's teams"):
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
KINDS_3 = "kinds:\n  - {name: a}\n  - {name: b, depends_on: c}\n  - {name: c, depends_on: b}\n"

BAD_FILES = [
    # (file text, field path, bad value as it must appear in the message)
    ("horizon: 10\nvelocity: 3\n", "velocity", "unknown key"),
    (AGENTS_2 + "  - {name: b, fire: 1, rescue: 1, velocity: 2}\n", "agents[1].capabilities.velocity", "no kind uses"),
    ("speed: 2\n", "step_seconds", "no step length"),
    ("step_seconds: 5\n", "agents[0].speed", "has no speed"),
    ("step_seconds: 5\nspeed: -1\n", "speed", "must be above 0"),
    ("step_seconds: -5\n", "step_seconds", "must be >= 0"),
    ("step_seconds: 5\nspeed: 1\nmode: ht\n", "step_seconds", "needs idle locations"),
    ("reward: {bonus: 2}\n", "reward.bonus", "unknown key"),
    ("horizon: ten\n", "horizon", "'ten'"),
    ("horizon: 10.5\n", "horizon", "10.5"),
    ("channel: 1\n", "channel", "1"),
    ("mode: xyz\n", "mode", "'xyz'"),
    ("team: alien\n", "team", "'alien'"),
    (AGENTS_2 + "  - {name: b, fire: three, rescue: 1}\n", "agents[1].capabilities.fire", "'three'"),
    (AGENTS_2 + "  - {name: b, fire: 7, rescue: 1}\n", "agents[1].capabilities.fire", "7"),
    (AGENTS_2 + "  - {name: b, fire: 1, rescue: -1}\n", "agents[1].capabilities.rescue", "-1"),
    ("agents:\n  - {name: a, fire: 1, rescue: 1, sensing: 6}\n", "agents[0].sensing", "6"),
    ("agents:\n  - {name: a, fire: 1, rescue: 1, comm: 9}\n", "agents[0].comm", "9"),
    ("fire_growth: 1.5\n", "kinds[0].growth", "1.5"),  # the first file format's key, read into its kind
    ("p_drop: [0.9, 0.6, -0.1]\n", "p_drop[2]", "-0.1"),
    ("rescue_double_share: 2.0\n", "kinds[1].double_drop.share", "2.0"),
    ("reward: {belief_threshold: 1.2}\n", "reward.belief_threshold", "1.2"),
    ("agents: []\n", "agents", "[]"),
    ("initial_levels: [4, 4, 5, 4]\n", "sites[1].tasks.fire", "5"),
    ("initial_levels: [4, 4, 4]\n", "initial_levels", "3 entries, the scenario has 4 tasks"),
    ("sites:\n  - {name: s1, tasks: {fire: 4, smoke: 2}}\n", "sites[0].tasks.smoke", "'smoke' is not a kind"),
    ("sites:\n  - {name: s1, tasks: {}}\n", "sites[0].tasks", "at least one task"),
    ("sites:\n  - {name: s1, tasks: {fire: 4}}\n  - {name: s1, tasks: {fire: 4}}\n", "sites[1].name", "'s1'"),
    ("sites: []\n", "sites", "at least one site"),
    ("kinds: []\n", "kinds", "at least one kind"),
    ("kinds:\n  - {name: fire}\n  - {name: rescue, depends_on: flood}\n", "kinds[1].depends_on", "'flood'"),
    (
        "kinds:\n  - {name: fire, depends_on: rescue}\n  - {name: rescue, depends_on: fire}\n",
        "kinds[0].depends_on",
        "fire -> rescue -> fire",
    ),
    (
        KINDS_3 + "sites:\n  - {name: s, tasks: {a: 1}}\nagents:\n  - {name: x, a: 1}\n",
        "kinds[1].depends_on",
        "b -> c -> b",
    ),
    ("kinds:\n  - {name: fire}\n  - {name: rescue, blocked_above: 2}\n", "kinds[1].blocked_above", "needs depends_on"),
    (
        "kinds:\n  - {name: fire}\n  - {name: rescue, depends_on: fire, blocked_above: 7}\n",
        "kinds[1].blocked_above",
        "7",
    ),
    (
        "kinds:\n  - {name: fire}\n  - {name: rescue, double_drop: {min_level: 1}}\n",
        "kinds[1].double_drop.min_level",
        "1",
    ),
    ("kinds:\n  - {name: fire, growth: 2}\n  - {name: rescue}\n", "kinds[0].growth", "2"),
    (AGENTS_2.replace("rescue: 1", "rescue: 0"), "kinds[1]", "no agent can work on it"),
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


def test_kinds_sites_and_agents_of_any_operation(tmp_path: Path) -> None:
    """Sites may hold different kinds; a kind names the capability it uses; capabilities are a map."""
    f = tmp_path / "depot.yaml"
    f.write_text(
        "name: depot\n"
        "kinds:\n"
        "  - {name: restock, capability: lift, growth: 0.05}\n"
        "  - {name: pick, capability: lift, depends_on: restock, blocked_above: 1}\n"
        "  - {name: inspect, sensing_base: 0.8}\n"
        "sites:\n"
        "  - {name: aisle1, position: [0, 0], tasks: {pick: 3, restock: 2, inspect: 1}}\n"
        "  - {name: dock, position: [30, 10], tasks: {inspect: 4}}\n"
        "agents:\n"
        "  - {name: r1, capabilities: {lift: 3}}\n"
        "  - {name: r2, lift: 1, inspect: 2, sensing: 4}\n"
    )
    sc = load(f)
    assert sc.kind_names == ("restock", "pick", "inspect") and sc.site_names == ("aisle1", "dock")
    assert sc.tasks == ((0, 0), (0, 1), (0, 2), (1, 2))  # site by site, the kinds in the order of `kinds`
    assert sc.initial_levels == (2, 3, 1, 4) and sc.n_tasks == 4 and sc.n_actions == 6
    assert sc.action_names == (
        "restock@aisle1",
        "pick@aisle1",
        "inspect@aisle1",
        "inspect@dock",
        "idle@aisle1",
        "idle@dock",
    )
    assert sc.capability_table() == [[3, 3, 0], [1, 1, 2]]
    assert sc.total_capability(0) == 3 and sc.total_capability(1) == 3  # lift counted once
    assert sc.team == "" and from_dict(sc.to_dict()) == sc


def test_the_first_file_format_still_loads() -> None:
    """Files and checkpoints written before kinds were data: sites by name, initial_levels, site_positions and the
    paper's kind rules as top-level keys."""
    old = {
        "name": "paper",
        "sites": ["site1", "site2"],
        "site_positions": [[0.0, 0.0], [50.0, 0.0]],
        "initial_levels": [4, 4, 4, 4],
        "fire_growth": 0.1,
        "rescue_block_fire": 2,
        "rescue_double_fire": 1,
        "rescue_double_min_level": 2,
        "rescue_double_share": 0.5,
        "team": "heterogeneous",
        "agents": [
            {"name": f"agent{i + 1}", "fire": f, "rescue": r, "sensing": 3, "comm": 3, "reward": None}
            for i, (f, r) in enumerate(MODEL_MD_TEAMS["heterogeneous"])
        ],
    }
    assert from_dict(old) == builtin()
