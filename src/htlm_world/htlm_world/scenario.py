"""Scenario files: every number of the model (docs/model.md), as frozen dataclasses loaded from YAML.

The built-in scenario "paper" with the three teams of docs/model.md is the default. A scenario file only needs the keys
it changes; anything it says is checked (types by `htlm_msgs_py.validation.convert`, ranges by `validate`), and a
bad value stops loading with a message naming the file, the field and the value.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from htlm_msgs_py.validation import ConversionError, convert

TEAMS: dict[str, tuple[tuple[int, int], ...]] = {
    "heterogeneous": ((3, 1), (3, 2), (2, 0), (0, 1), (1, 1)),
    "semi-heterogeneous": ((3, 1), (3, 1), (1, 1), (2, 2), (2, 2)),
    "homogeneous": ((2, 1),) * 5,
}
"""(fire, rescue) capability of agents 1..5 in each team of docs/model.md."""

REASSIGN_COSTS: dict[str, float] = {"none": 0.0, "medium": -1.0, "high": -4.0}
"""Traversing cost tc of the reassignment penalty T_RP, by level name (docs/model.md)."""

TASK_TYPES: tuple[str, str] = ("fire", "rescue")


class ScenarioError(ValueError):
    """A scenario file or dictionary that does not describe a valid scenario."""


@dataclass(frozen=True)
class RewardParams:
    """Parameters of the reward f_R = R_comp + R_II + T_RP (docs/model.md, Eq. 3-5 of the paper)."""

    level_rewards: tuple[float, ...] = (10.0, 5.0, 2.0, 1.0, 0.0)
    """R_l, the completion reward of a task confidently at level l (one per level)."""
    belief_threshold: float = 0.97
    """b_th: a task's confident level is the smallest l with P(level <= l) >= b_th."""
    idle_incentive: float = 1.0
    """Scale of the idle incentive R_II; 0 turns it off."""
    idle_bonus: float = 1.0
    """R_II when the action is an idle location (before scaling), times the belief weight of `idle_belief`."""
    idle_belief: Literal["constant", "site", "mission"] = "site"
    """How R_II(b) depends on the belief: constant (the full bonus whenever idle), site (bonus times the believed
    probability that every task at the idle location's site is done), mission (times that every task is done)."""
    excess_penalty: float = -1.0
    """R_II when working on a task with capability >= confident level + excess_margin (before scaling)."""
    excess_margin: int = 2
    """How far capability must exceed the task's confident level to be penalised as excess."""
    reassign_cost: float = -1.0
    """tc of T_RP, paid when the site of the action differs from the site of the previous assignment."""


@dataclass(frozen=True)
class AgentSpec:
    """One agent: capabilities 0..capability_max and optional own reward parameters (preferences)."""

    name: str
    """Agent name, used in topic names and reports."""
    fire: int
    """Fire-fighting capability."""
    rescue: int
    """Rescue capability."""
    sensing: int = 3
    """Sensing capability s: observation accuracy min(1, 0.5 + 0.1 s)."""
    comm: int = 3
    """Communication capability: a message stays intact with probability comm / capability_max."""
    reward: RewardParams | None = None
    """This agent's own reward parameters; None shares the scenario's."""


@dataclass(frozen=True)
class Scenario:
    """Every number of the HTLM model (docs/model.md). Defaults are the scenario "paper", heterogeneous team."""

    name: str = "paper"
    """Scenario name, written into every report and checkpoint."""
    sites: tuple[str, ...] = ("site1", "site2")
    """Sites; each has a fire task, a rescue task and one idle location."""
    site_positions: tuple[tuple[float, float], ...] = ((0.0, 0.0), (50.0, 0.0))
    """(x, y) in metres of each site in the map frame, for goal poses."""
    levels: int = 5
    """L, number of severity levels 0..L-1."""
    initial_levels: tuple[int, ...] = (4, 4, 4, 4)
    """Level of every task at the start (order fire@site1, rescue@site1, fire@site2, ...)."""
    horizon: int = 30
    """h, steps per episode; episodes always run all h steps."""
    capability_max: int = 5
    """Cap on capabilities and on the joint capability on a task."""
    p_drop: tuple[float, ...] = (0.90, 0.60, 0.35, 0.15, 0.05)
    """p_drop by margin m = c - l: m >= 0, m = -1, -2, -3, m <= -4 (last entry for all lower margins)."""
    fire_growth: float = 0.10
    """Probability that an unattended burning fire grows one level."""
    rescue_block_fire: int = 2
    """Rescue makes no progress while its site's fire is above this level."""
    rescue_double_fire: int = 1
    """Rescue can drop two levels only while its site's fire is at most this level."""
    rescue_double_min_level: int = 2
    """Rescue can drop two levels only from at least this level."""
    rescue_double_share: float = 0.5
    """Share of the drop probability that is a two-level drop when a double drop is possible."""
    sensing_base: float = 0.65
    """Observation accuracy at sensing 0."""
    sensing_slope: float = 0.1
    """Observation accuracy gained per sensing level."""
    channel: bool = True
    """Simulate the communication channel (random replacement of broadcast levels); off for real robots."""
    channel_base: float = 0.2
    """Channel reliability added to comm / capability_max: tau = min(1, channel_base + comm / capability_max)."""
    agents: tuple[AgentSpec, ...] = tuple(
        AgentSpec(name=f"agent{i + 1}", fire=f, rescue=r) for i, (f, r) in enumerate(TEAMS["heterogeneous"])
    )
    """The team."""
    team: str = "heterogeneous"
    """Name of the team (informational when agents are given explicitly)."""
    reward: RewardParams = field(default_factory=RewardParams)
    """Reward parameters shared by every agent without its own."""
    gamma: float = 0.95
    """Discount factor."""
    mode: Literal["htlm", "ht"] = "htlm"
    """"htlm": idle locations and R_LM; "ht": the predecessor HT Dec-POMDP (no idle locations, R_LM = 0)."""
    initial_assignment: int = -1
    """Index in G-bar of every agent's previous assignment before step 1; -1 means the first idle location."""

    # ----- derived layout -------------------------------------------------------------------------------------
    @property
    def n_sites(self) -> int:
        """Number of sites S."""
        return len(self.sites)

    @property
    def n_tasks(self) -> int:
        """p = 2 S: fire and rescue at every site."""
        return 2 * len(self.sites)

    @property
    def n_idle(self) -> int:
        """q: one idle location per site in HTLM mode, none in HT mode."""
        return 0 if self.mode == "ht" else len(self.sites)

    @property
    def n_actions(self) -> int:
        """|G-bar| = p + q."""
        return self.n_tasks + self.n_idle

    @property
    def n_agents(self) -> int:
        """N."""
        return len(self.agents)

    @property
    def action_names(self) -> tuple[str, ...]:
        """Names of G-bar in index order: fire@site1, rescue@site1, ..., idle@site1, ..."""
        tasks = [f"{t}@{s}" for s in self.sites for t in TASK_TYPES]
        return tuple(tasks + [f"idle@{s}" for s in self.sites][: self.n_idle])

    @property
    def action_sites(self) -> tuple[int, ...]:
        """Site index of every element of G-bar."""
        return tuple([j // 2 for j in range(self.n_tasks)] + list(range(self.n_idle)))

    @property
    def start_assignment(self) -> int:
        """Previous assignment before step 1 (idle@site1 by default; -1, none, in HT mode)."""
        if self.mode == "ht":
            return -1
        return self.n_tasks if self.initial_assignment < 0 else self.initial_assignment

    @property
    def knowledge_size(self) -> int:
        """Length of the Q-network input: p*L marginals + one-hot previous assignment over G-bar."""
        return self.n_tasks * self.levels + self.n_actions

    def agent_reward(self, i: int) -> RewardParams:
        """Reward parameters of agent i (its own, else the shared ones)."""
        own = self.agents[i].reward
        return own if own is not None else self.reward

    def replace(self, **changes: Any) -> Scenario:
        """A copy with fields changed, validated."""
        new = dataclasses.replace(self, **changes)
        validate(new, "<replace>")
        return new

    def with_reward(self, **changes: Any) -> Scenario:
        """A copy with the shared reward parameters changed (agents with their own keep theirs)."""
        return self.replace(reward=dataclasses.replace(self.reward, **changes))

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (lists, dicts) that from_dict reads back."""
        plain: dict[str, Any] = _to_plain(dataclasses.asdict(self))
        return plain

    def layout_hash(self) -> str:
        """Hash of the knowledge-state and action layout, to refuse checkpoints of another layout."""
        layout = {
            "mode": self.mode,
            "sites": list(self.sites),
            "levels": self.levels,
            "actions": list(self.action_names),
            "n_agents": self.n_agents,
            "knowledge": ["marginals(p,L)", "onehot(prev,|G|)"],
        }
        return hashlib.sha256(json.dumps(layout, sort_keys=True).encode()).hexdigest()[:16]


def _to_plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_plain(v) for v in x]
    return x


def make_team(team: str, **reward: Any) -> tuple[AgentSpec, ...]:
    """The agents of a built-in team of docs/model.md."""
    if team not in TEAMS:
        raise ScenarioError(f"unknown team {team!r}; choose one of {sorted(TEAMS)}")
    return tuple(AgentSpec(name=f"agent{i + 1}", fire=f, rescue=r) for i, (f, r) in enumerate(TEAMS[team]))


def builtin(
    team: str = "heterogeneous",
    idle_incentive: float = 1.0,
    reassign: str = "medium",
    mode: Literal["htlm", "ht"] = "htlm",
) -> Scenario:
    """The built-in scenario "paper" with a team of docs/model.md and the given load-management settings."""
    if reassign not in REASSIGN_COSTS:
        raise ScenarioError(f"unknown reassignment level {reassign!r}; choose one of {list(REASSIGN_COSTS)}")
    reward = RewardParams(idle_incentive=idle_incentive, reassign_cost=REASSIGN_COSTS[reassign])
    sc = Scenario(agents=make_team(team), team=team, reward=reward, mode=mode)
    validate(sc, "<builtin>")
    return sc


# ----- loading and validation -------------------------------------------------------------------------------------


def from_dict(data: Any, src: str = "<dict>") -> Scenario:
    """Build and validate a scenario from plain data. A `team:` key without `agents:` picks a built-in team.

    Raises:
        ScenarioError: naming src, the field and the bad value.
    """
    if not isinstance(data, dict):
        raise ScenarioError(f"{src}: top level: expected a mapping, got {type(data).__name__} {data!r}")
    data = dict(data)
    if "reassign" in data:  # convenience: a level name instead of reward.reassign_cost
        level = data.pop("reassign")
        if level not in REASSIGN_COSTS:
            raise ScenarioError(f"{src}: reassign: {level!r} is not one of {list(REASSIGN_COSTS)}")
        data.setdefault("reward", {})
        data["reward"] = {**data["reward"], "reassign_cost": REASSIGN_COSTS[level]}
    if "team" in data and "agents" not in data:
        if data["team"] not in TEAMS:
            raise ScenarioError(f"{src}: team: {data['team']!r} is not one of {sorted(TEAMS)}")
        data["agents"] = [dataclasses.asdict(a) for a in make_team(data["team"])]
    try:
        sc = convert(data, Scenario, src)
    except ConversionError as e:
        raise ScenarioError(str(e)) from None
    validate(sc, src)
    return sc


SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
"""The scenario files shipped with the package; `load` also takes their names (`load("first-calibration")`)."""


def named_scenarios() -> list[str]:
    """Names of the shipped scenario files (paper: the defaults written out; first-calibration: the model's first
    numbers, kept for comparison)."""
    return sorted(f.stem for f in SCENARIO_DIR.glob("*.yaml"))


def load(path: str | Path) -> Scenario:
    """Load a scenario YAML file, or a shipped scenario by name (keys a file omits keep the defaults of "paper")."""
    p = Path(path)
    if not p.exists() and p.suffix == "" and p.name in named_scenarios():
        p = SCENARIO_DIR / f"{p.name}.yaml"
    try:
        text = p.read_text()
    except OSError as e:
        hint = f" (or name a shipped scenario: {', '.join(named_scenarios())})" if p.suffix == "" else ""
        raise ScenarioError(f"{p}: cannot read scenario file: {e.strerror}{hint}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ScenarioError(f"{p}: not valid YAML: {e}") from None
    return from_dict({} if data is None else data, str(p))


def _check_prob(src: str, where: str, x: float) -> None:
    if not (0.0 <= x <= 1.0):
        raise ScenarioError(f"{src}: {where}: {x!r} is not a probability in [0, 1]")


def validate(sc: Scenario, src: str) -> None:
    """Check every value of a scenario; raise ScenarioError naming src, the field and the value."""
    cmax = sc.capability_max
    if not sc.sites:
        raise ScenarioError(f"{src}: sites: {list(sc.sites)!r}: at least one site is needed")
    if len(set(sc.sites)) != len(sc.sites):
        raise ScenarioError(f"{src}: sites: {list(sc.sites)!r}: site names must be unique")
    if len(sc.site_positions) != len(sc.sites):
        raise ScenarioError(f"{src}: site_positions: {len(sc.site_positions)} positions for {len(sc.sites)} sites")
    if sc.levels < 2:
        raise ScenarioError(f"{src}: levels: {sc.levels!r} must be at least 2")
    if len(sc.initial_levels) != sc.n_tasks:
        raise ScenarioError(
            f"{src}: initial_levels: {list(sc.initial_levels)!r} has {len(sc.initial_levels)} entries, "
            f"the scenario has {sc.n_tasks} tasks"
        )
    for k, lv in enumerate(sc.initial_levels):
        if not 0 <= lv < sc.levels:
            raise ScenarioError(f"{src}: initial_levels[{k}]: {lv!r} is out of range 0..{sc.levels - 1}")
    if sc.horizon < 1:
        raise ScenarioError(f"{src}: horizon: {sc.horizon!r} must be at least 1")
    if cmax < 1:
        raise ScenarioError(f"{src}: capability_max: {cmax!r} must be at least 1")
    if not sc.p_drop:
        raise ScenarioError(f"{src}: p_drop: needs at least one entry")
    for k, x in enumerate(sc.p_drop):
        _check_prob(src, f"p_drop[{k}]", x)
    for name in ("fire_growth", "rescue_double_share", "sensing_base", "channel_base"):
        _check_prob(src, name, getattr(sc, name))
    if not 0.0 <= sc.sensing_slope <= 1.0:
        raise ScenarioError(f"{src}: sensing_slope: {sc.sensing_slope!r} is not in [0, 1]")
    if not 0.0 <= sc.gamma <= 1.0:
        raise ScenarioError(f"{src}: gamma: {sc.gamma!r} is not in [0, 1]")
    if not sc.agents:
        raise ScenarioError(f"{src}: agents: [] is an agent count of zero; a team needs at least one agent")
    names = [a.name for a in sc.agents]
    if len(set(names)) != len(names):
        raise ScenarioError(f"{src}: agents: names must be unique, got {names!r}")
    for i, a in enumerate(sc.agents):
        if not a.name or not a.name.replace("_", "").isalnum() or not a.name[0].isalpha():
            raise ScenarioError(
                f"{src}: agents[{i}].name: {a.name!r} must start with a letter and hold only letters, digits, _"
            )
        for cap in ("fire", "rescue", "sensing", "comm"):
            v = getattr(a, cap)
            if not 0 <= v <= cmax:
                raise ScenarioError(f"{src}: agents[{i}].{cap}: {v!r} is out of range 0..{cmax}")
        if a.reward is not None:
            _validate_reward(a.reward, sc.levels, src, f"agents[{i}].reward")
    _validate_reward(sc.reward, sc.levels, src, "reward")
    if sc.initial_assignment >= sc.n_actions or sc.initial_assignment < -1:
        raise ScenarioError(
            f"{src}: initial_assignment: {sc.initial_assignment!r} is out of range -1..{sc.n_actions - 1}"
        )


def _validate_reward(r: RewardParams, levels: int, src: str, where: str) -> None:
    if len(r.level_rewards) != levels:
        raise ScenarioError(
            f"{src}: {where}.level_rewards: {list(r.level_rewards)!r} needs one reward per level ({levels})"
        )
    _check_prob(src, f"{where}.belief_threshold", r.belief_threshold)
    if r.belief_threshold == 0.0:
        raise ScenarioError(f"{src}: {where}.belief_threshold: 0.0 must be above 0")
    if r.idle_incentive < 0:
        raise ScenarioError(f"{src}: {where}.idle_incentive: {r.idle_incentive!r} must be >= 0")
    if r.reassign_cost > 0:
        raise ScenarioError(f"{src}: {where}.reassign_cost: {r.reassign_cost!r} must be <= 0 (a cost)")
