"""Scenario files: every number of the model (docs/model.md), as frozen dataclasses loaded from YAML.

The built-in scenario "paper" with the three teams of docs/model.md is the default. A scenario file only needs the keys
it changes; anything it says is checked (types by `htlm_msgs_py.validation.convert`, ranges by `validate`), and a
bad value stops loading with a message naming the file, the field and the value.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path
from typing import Any, Literal

import yaml

from htlm_msgs_py.validation import ConversionError, convert

REOPEN_LEVEL = 1
"""The level a finished task reopens at when its kind's `hazard` strikes (docs/model.md, What the paper fixes and
what we add): the smallest surprise, one level of work."""

REASSIGN_COSTS: dict[str, float] = {"none": 0.0, "medium": -1.0, "high": -4.0}
"""Traversing cost tc of the reassignment penalty T_RP, by level name (docs/model.md)."""

DEFAULT_SCENARIO = "paper"
"""The shipped scenario that files are read over: a key a file leaves out keeps its value there."""


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
    credit: Literal["team", "difference"] = "team"
    """What R_comp credits the agent with: team (the paper: the completion reward of its whole belief) or difference
    (the expected completion reward its own work adds to the step's prediction, against the same step with it idle:
    a difference reward)."""


@dataclass(frozen=True)
class DoubleDrop:
    """Two-level drops of a kind: part of its drop probability takes the task down two levels at once."""

    share: float = 0.5
    """Share of the drop probability that is a two-level drop when one is possible."""
    min_level: int = 2
    """A two-level drop is possible only from at least this level, and only with joint capability >= the level."""
    gate_at_most: int | None = None
    """With `depends_on`: only while the task it depends on (same site) is at most this level; None: any level."""


@dataclass(frozen=True)
class KindSpec:
    """A kind of task and its dynamics (docs/model.md, Transition T): the scenario file's `kinds` entries."""

    name: str
    """Kind name (task names are kind@site)."""
    capability: str = ""
    """The agent capability this kind uses; empty: the kind's own name."""
    growth: float = 0.0
    """Probability that an unfinished task nobody works on grows one level in a step."""
    p_drop: tuple[float, ...] = ()
    """Own drop probabilities by capability margin (as the scenario's `p_drop`); empty: the scenario's."""
    depends_on: str = ""
    """A kind at the same site that this one waits on (no cycles); empty: none. A site without that kind's task
    does not hold this one back."""
    blocked_above: int | None = None
    """With `depends_on`: no progress while the task it depends on is above this level; None: never blocked."""
    double_drop: DoubleDrop | None = None
    """Two-level drops; None: one level at most."""
    sensing_base: float | None = None
    """Own observation accuracy at sensing 0; None: the scenario's `sensing_base`."""
    sensing_slope: float | None = None
    """Own accuracy gained per sensing level; None: the scenario's `sensing_slope`."""
    hazard: float = 0.0
    """Probability per step that a finished task (level 0) of this kind reopens at level `REOPEN_LEVEL` (not in the
    paper: docs/model.md, What the paper fixes and what we add); 0: level 0 is absorbing, as in the paper."""

    @property
    def uses(self) -> str:
        """The capability name agents bring to tasks of this kind."""
        return self.capability or self.name


@dataclass(frozen=True)
class SiteSpec:
    """A site: where it is and the tasks it holds (one per kind at most), each with its start level."""

    name: str
    """Site name (idle locations are idle@site)."""
    tasks: dict[str, int]
    """Start level of every task of the site, by kind name."""
    position: tuple[float, float] = (0.0, 0.0)
    """(x, y) in metres in the map frame, for goal poses and markers."""

    def __hash__(self) -> int:
        return hash((self.name, tuple(sorted(self.tasks.items())), self.position))


@dataclass(frozen=True)
class AgentSpec:
    """One agent: a capability level 0..capability_max per capability name, sensing, communication and optionally
    its own reward parameters (preferences)."""

    name: str
    """Agent name, used in topic names and reports."""
    capabilities: dict[str, int] = field(default_factory=dict)
    """Level of every capability the agent has (capabilities it leaves out are 0)."""
    sensing: int = 3
    """Sensing capability s: observation accuracy min(1, sensing_base + sensing_slope s)."""
    comm: int = 3
    """Communication capability: a message stays intact with probability tau (docs/model.md, Information I)."""
    reward: RewardParams | None = None
    """This agent's own reward parameters; None shares the scenario's."""
    speed: float | None = None
    """Metres per second this agent drives at between sites (docs/model.md, Travel); None: the scenario's `speed`."""

    def __hash__(self) -> int:
        return hash(
            (self.name, tuple(sorted(self.capabilities.items())), self.sensing, self.comm, self.reward, self.speed)
        )

    def capability(self, name: str) -> int:
        """The agent's level of capability `name` (0 when it has none)."""
        return self.capabilities.get(name, 0)


EVENT_KINDS = ("surge", "new_task", "dropout", "return")
"""What can happen to an operation from outside the model (docs/model.md, Events)."""


@dataclass(frozen=True)
class EventSpec:
    """Something that happens to the operation from outside the model T: a task's level jumps (surge), a dormant
    task starts (new_task), an agent stops acting (dropout) or acts again (return). docs/model.md, Events."""

    event: Literal["surge", "new_task", "dropout", "return"]
    """What happens."""
    site: str = ""
    """surge, new_task: the site of the task."""
    task: str = ""
    """surge, new_task: the kind of the task."""
    level: int = 0
    """surge, new_task: the task's level becomes at least this."""
    agent: str = ""
    """dropout, return: the agent's name."""
    at: int = 1
    """The first step (1..h) in which it can happen."""
    probability: float = 1.0
    """Chance per step, from `at` on, while it has not happened (1: it happens at `at`)."""
    once_done: str = ""
    """Only once every task of this site is at level 0 (the true levels before the step)."""
    name: str = ""
    """Label in logs, records and plots (`label` makes one when empty)."""

    @property
    def label(self) -> str:
        """The name, else what happens and to what, e.g. "surge fire@site1 to 4"."""
        if self.name:
            return self.name
        if self.event in ("surge", "new_task"):
            return f"{self.event} {self.task}@{self.site} to {self.level}"
        return f"{self.event} {self.agent}"


@dataclass(frozen=True)
class Scenario:
    """Every number of the HTLM model (docs/model.md). The kinds, sites and agents come from a scenario file; the
    numbers default to the paper's."""

    name: str = "paper"
    """Scenario name, written into every report and checkpoint."""
    kinds: tuple[KindSpec, ...] = ()
    """The kinds of task, in the order tasks of a site are numbered."""
    sites: tuple[SiteSpec, ...] = ()
    """The sites, each with its tasks and one idle location."""
    levels: int = 5
    """L, number of severity levels 0..L-1 (the same for every kind)."""
    horizon: int = 30
    """h, steps per episode; episodes always run all h steps."""
    capability_max: int = 5
    """Cap on capabilities and on the joint capability on a task."""
    p_drop: tuple[float, ...] = (0.90, 0.60, 0.35, 0.15, 0.05)
    """p_drop by margin m = c - l: m >= 0, m = -1, -2, -3, m <= -4 (last entry for all lower margins)."""
    sensing_base: float = 0.65
    """Observation accuracy at sensing 0."""
    sensing_slope: float = 0.1
    """Observation accuracy gained per sensing level."""
    channel: bool = True
    """Simulate the communication channel (random replacement of broadcast levels); off for real robots."""
    channel_base: float = 0.2
    """Channel reliability added to comm / capability_max: tau = min(1, channel_base + comm / capability_max)."""
    standby_accuracy: float | None = None
    """Accuracy of the observation an agent idling at a site makes of one of the site's tasks, whatever its sensing
    (not in the paper: docs/model.md, What the paper fixes and what we add); None: idle agents observe nothing."""
    roster: bool = False
    """The knowledge state also holds the roster: which teammates the agent heard from at its last step (their
    broadcast arrived), so that a policy can leave out a teammate that has gone silent (not in the paper:
    docs/model.md, Knowledge state)."""
    teammates: bool = False
    """The knowledge state also holds where the teammates were at the last step, by their last known assignments:
    for every task the capability they brought to it, for every idle location how many idled there (not in the
    paper: docs/model.md, Knowledge state)."""
    step_seconds: float = 0.0
    """Length of a step in seconds, with which the agents' speeds turn distances into drive steps (docs/model.md,
    Travel); 0: no travel, an assignment takes effect in the step it is chosen (the paper)."""
    speed: float | None = None
    """Metres per second of every agent without a speed of its own (with `step_seconds`)."""
    agents: tuple[AgentSpec, ...] = ()
    """The team."""
    team: str = ""
    """Name of the team (one of the file's `teams`, or informational when agents are given explicitly)."""
    reward: RewardParams = field(default_factory=RewardParams)
    """Reward parameters shared by every agent without its own."""
    gamma: float = 0.95
    """Discount factor."""
    mode: Literal["htlm", "ht"] = "htlm"
    """"htlm": idle locations and R_LM; "ht": the predecessor HT Dec-POMDP (no idle locations, R_LM = 0)."""
    initial_assignment: int = -1
    """Index in G-bar of every agent's previous assignment before step 1; -1 means the first idle location."""
    events: tuple[EventSpec, ...] = ()
    """What happens in every episode from outside the model (none in the paper's operation)."""
    stress: dict[str, tuple[EventSpec, ...]] = field(default_factory=dict, compare=False)
    """Named sets of events for `htlm stress` (not part of the operation until chosen, nor of its equality)."""

    # ----- derived layout -------------------------------------------------------------------------------------
    @property
    def n_sites(self) -> int:
        """Number of sites S."""
        return len(self.sites)

    @property
    def site_names(self) -> tuple[str, ...]:
        """Names of the sites in index order."""
        return tuple(site.name for site in self.sites)

    @property
    def site_positions(self) -> tuple[tuple[float, float], ...]:
        """(x, y) of every site in the map frame."""
        return tuple(site.position for site in self.sites)

    @property
    def kind_names(self) -> tuple[str, ...]:
        """Names of the kinds in index order."""
        return tuple(k.name for k in self.kinds)

    @property
    def kind_dependencies(self) -> tuple[int, ...]:
        """Index of the kind each kind depends on (`depends_on`), -1 for none."""
        names = self.kind_names
        return tuple(names.index(k.depends_on) if k.depends_on else -1 for k in self.kinds)

    @property
    def n_kinds(self) -> int:
        """K, number of kinds."""
        return len(self.kinds)

    @cached_property
    def tasks(self) -> tuple[tuple[int, int], ...]:
        """(site, kind) of every task in index order: site by site, the kinds of a site in the order of `kinds`
        (computed once: the layout properties below and the hot paths read it every step)."""
        return tuple(
            (s, k) for s, site in enumerate(self.sites) for k, kind in enumerate(self.kinds) if kind.name in site.tasks
        )

    @property
    def n_tasks(self) -> int:
        """p, the number of tasks over all sites."""
        return len(self.tasks)

    @property
    def initial_levels(self) -> tuple[int, ...]:
        """Start level of every task in index order."""
        return tuple(self.sites[s].tasks[self.kinds[k].name] for s, k in self.tasks)

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
        """Names of G-bar in index order: kind@site for every task, then idle@site for every idle location."""
        tasks = [f"{self.kinds[k].name}@{self.sites[s].name}" for s, k in self.tasks]
        return tuple(tasks + [f"idle@{s}" for s in self.site_names][: self.n_idle])

    @property
    def action_sites(self) -> tuple[int, ...]:
        """Site index of every element of G-bar."""
        return tuple([s for s, _ in self.tasks] + list(range(self.n_idle)))

    def total_capability(self, i: int) -> int:
        """Agent i's capability summed over the capabilities the kinds use (each counted once)."""
        return sum(self.agents[i].capability(c) for c in dict.fromkeys(k.uses for k in self.kinds))

    def capability_table(self) -> list[list[int]]:
        """(N, K) every agent's capability on every kind."""
        return [[a.capability(k.uses) for k in self.kinds] for a in self.agents]

    @property
    def start_assignment(self) -> int:
        """Previous assignment before step 1 (idle@site1 by default; -1, none, in HT mode)."""
        if self.mode == "ht":
            return -1
        return self.n_tasks if self.initial_assignment < 0 else self.initial_assignment

    @property
    def travel(self) -> bool:
        """Whether agents take time to drive between sites (`step_seconds` > 0; docs/model.md, Travel)."""
        return self.step_seconds > 0.0

    def without_travel(self) -> Scenario:
        """This operation without step length and speeds: assignments take effect in the step they are chosen."""
        agents = tuple(dataclasses.replace(a, speed=None) for a in self.agents)
        return self.replace(step_seconds=0.0, speed=None, agents=agents)

    def agent_speed(self, i: int) -> float:
        """Agent i's speed in metres per second (its own, else the scenario's; 0 when neither is given)."""
        own = self.agents[i].speed
        if own is not None:
            return own
        return self.speed if self.speed is not None else 0.0

    @property
    def knowledge_size(self) -> int:
        """Length of the Q-network input: p*L marginals + one-hot previous assignment over G-bar (+ the roster of
        N teammates heard from, with `roster`; + the teammates' last assignments over G-bar, with `teammates`; + every
        agent's place and steps to arrival, 2N, with `travel`)."""
        extra = (self.n_agents if self.roster else 0) + (self.n_actions if self.teammates else 0)
        extra += 2 * self.n_agents if self.travel else 0
        return self.n_tasks * self.levels + self.n_actions + extra

    def agent_reward(self, i: int) -> RewardParams:
        """Reward parameters of agent i (its own, else the shared ones)."""
        own = self.agents[i].reward
        return own if own is not None else self.reward

    def has_own_reward(self, i: int) -> bool:
        """Whether agent i's reward differs from the shared one (its own fields set to other values)."""
        return self.agent_reward(i) != self.reward

    def with_events(self, events: tuple[EventSpec, ...] | list[EventSpec], src: str = "events") -> Scenario:
        """A copy whose episodes have `events`, checked against the operation (errors name `src`)."""
        new = dataclasses.replace(self, events=tuple(events))
        validate(new, src)
        return new

    def with_shipped_stress(self) -> Scenario:
        """This scenario, with the stress sets of the shipped file of its name when it has none (a checkpoint written
        before stress sets) and that file's operation is the same."""
        if self.stress or self.name not in named_scenarios():
            return self
        shipped = load(self.name)
        same = (shipped.kinds, shipped.sites, shipped.horizon, shipped.levels) == (
            self.kinds,
            self.sites,
            self.horizon,
            self.levels,
        )
        return dataclasses.replace(self, stress=shipped.stress) if same else self

    def __hash__(self) -> int:
        return hash((self.name, self.kinds, self.sites, self.agents, self.team, self.mode, self.events))

    def replace(self, **changes: Any) -> Scenario:
        """A copy with fields changed, validated."""
        new = dataclasses.replace(self, **changes)
        validate(new, "<replace>")
        return new

    def with_reward(self, **changes: Any) -> Scenario:
        """A copy with the shared reward parameters changed (agents with their own keep theirs)."""
        return self.replace(reward=dataclasses.replace(self.reward, **changes))

    def with_credit(self, credit: Literal["team", "difference"]) -> Scenario:
        """A copy whose every agent's R_comp is credited as `credit` (team or difference, `RewardParams.credit`),
        preferences included."""
        agents = tuple(
            a if a.reward is None else dataclasses.replace(a, reward=dataclasses.replace(a.reward, credit=credit))
            for a in self.agents
        )
        new = self.replace(reward=dataclasses.replace(self.reward, credit=credit), agents=agents)
        validate(new, "credit")
        return new

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (lists, dicts) that from_dict reads back."""
        plain: dict[str, Any] = _to_plain(dataclasses.asdict(self))
        return plain

    def layout_hash(self) -> str:
        """Hash of the knowledge-state and action layout, to refuse checkpoints of another layout."""
        layout = {
            "mode": self.mode,
            "sites": list(self.site_names),
            "levels": self.levels,
            "actions": list(self.action_names),
            "n_agents": self.n_agents,
            "knowledge": ["marginals(p,L)", "onehot(prev,|G|)"]
            + (["roster(N)"] if self.roster else [])
            + (["teammates(|G|)"] if self.teammates else [])
            + (["travel(2N)"] if self.travel else []),
        }
        return hashlib.sha256(json.dumps(layout, sort_keys=True).encode()).hexdigest()[:16]


def _to_plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_plain(v) for v in x]
    return x


def builtin(
    team: str = "heterogeneous",
    idle_incentive: float = 1.0,
    reassign: str = "medium",
    mode: Literal["htlm", "ht"] = "htlm",
) -> Scenario:
    """The shipped scenario "paper" with one of its teams and the given load-management settings."""
    if reassign not in REASSIGN_COSTS:
        raise ScenarioError(f"unknown reassignment level {reassign!r}; choose one of {list(REASSIGN_COSTS)}")
    reward = {"idle_incentive": idle_incentive, "reassign_cost": REASSIGN_COSTS[reassign]}
    return from_dict({"team": team, "reward": reward, "mode": mode}, "<builtin>")


# ----- loading and validation -------------------------------------------------------------------------------------

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
"""The scenario files shipped with the package; `load` also takes their names (`load("warehouse")`)."""

_AGENT_FIELDS = frozenset(f.name for f in dataclasses.fields(AgentSpec))

_OPERATION_KEYS = frozenset({"sites", "levels", "horizon", "agents", "teams"})
"""Keys that make a file's operation its own: it does not take the default file's `events` and `stress` sets."""

_LEGACY_KIND_KEYS: dict[str, tuple[str, tuple[str, ...]]] = {
    "fire_growth": ("fire", ("growth",)),
    "rescue_block_fire": ("rescue", ("blocked_above",)),
    "rescue_double_fire": ("rescue", ("double_drop", "gate_at_most")),
    "rescue_double_min_level": ("rescue", ("double_drop", "min_level")),
    "rescue_double_share": ("rescue", ("double_drop", "share")),
}
"""Keys of the first file format (before kinds were data, still in older checkpoints): the paper's kinds' rules as
top-level numbers, read into the `kinds` entry they belong to."""


@cache
def _file_data(path: Path) -> Any:
    try:
        text = path.read_text()
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read scenario file: {e.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ScenarioError(f"{path}: not valid YAML: {e}") from None


def _base_data() -> dict[str, Any]:
    """The plain data of the default scenario file, which every file is read over (a fresh copy)."""
    data = _file_data(SCENARIO_DIR / f"{DEFAULT_SCENARIO}.yaml")
    assert isinstance(data, dict), "the default scenario file is a mapping"
    return copy.deepcopy(data)


def team_names(path: str | Path | None = None) -> list[str]:
    """Names of the teams a scenario file declares under `teams` (the default scenario's when it has none)."""
    data = _base_data()
    if path is not None:
        own = _file_data(_resolve(path))
        if isinstance(own, dict) and "teams" in own:
            data = own
    teams = data.get("teams") or {}
    return list(teams) if isinstance(teams, dict) else []


def from_dict(data: Any, src: str = "<dict>", team: str | None = None) -> Scenario:
    """Build and validate a scenario from plain data, read over the default scenario file: a top-level key the data
    leaves out keeps its value there. Without `agents`, the team named by `team` (argument, else key) is taken from
    `teams` (the data's, else the default's).

    Raises:
        ScenarioError: naming src, the field path and the bad value.
    """
    if not isinstance(data, dict):
        raise ScenarioError(f"{src}: top level: expected a mapping, got {type(data).__name__} {data!r}")
    own = copy.deepcopy(data)
    if team is not None:
        own["team"] = team
        own.pop("agents", None)
    if "reassign" in own:  # convenience: a level name instead of reward.reassign_cost
        level = own.pop("reassign")
        if level not in REASSIGN_COSTS:
            raise ScenarioError(f"{src}: reassign: {level!r} is not one of {list(REASSIGN_COSTS)}")
        given = own.get("reward")
        reward: dict[str, Any] = given if isinstance(given, dict) else {}
        own["reward"] = {**reward, "reassign_cost": REASSIGN_COSTS[level]}
    merged = {**_base_data(), **own}
    if _OPERATION_KEYS & own.keys():  # events and stress sets belong to the operation they name
        for key in ("events", "stress"):
            merged[key] = own.get(key, [] if key == "events" else {})
    if "agents" in own and "team" not in own:
        merged.pop("team", None)  # a team of the file's own
    _upgrade(merged, src)
    teams = merged.pop("teams", None)
    if "agents" not in merged:
        name = merged.get("team", "")
        if not isinstance(teams, dict) or name not in teams:
            known = sorted(teams) if isinstance(teams, dict) else []
            raise ScenarioError(f"{src}: team: {name!r} is not one of the scenario's teams {known}")
        merged["agents"] = copy.deepcopy(teams[name])
    merged["agents"] = _agent_capabilities(merged["agents"], src)
    try:
        sc = convert(merged, Scenario, src)
    except ConversionError as e:
        raise ScenarioError(str(e)) from None
    validate(sc, src)
    for set_name, events in sc.stress.items():  # checked as read (a copy with fields replaced checks its own use)
        _validate_events(sc, src, f"stress.{set_name}", events)
    return sc


def _agent_capabilities(agents: Any, src: str) -> Any:
    """Agents entries with capability levels written as keys of their own (`{name: a1, lift: 3}`) moved into
    `capabilities`."""
    if not isinstance(agents, list):
        return agents
    out = []
    for i, a in enumerate(agents):
        if isinstance(a, dict):
            a = dict(a)
            given = a.get("capabilities") or {}
            if not isinstance(given, dict):
                raise ScenarioError(f"{src}: agents[{i}].capabilities: {given!r} is not a mapping")
            caps = dict(given)
            for key in [k for k in a if k not in _AGENT_FIELDS]:
                caps[key] = a.pop(key)
            for key, v in caps.items():
                if not isinstance(key, str) or not isinstance(v, int) or isinstance(v, bool):
                    raise ScenarioError(f"{src}: agents[{i}].capabilities.{key}: expected an integer level, got {v!r}")
            a["capabilities"] = caps
        out.append(a)
    return out


def _upgrade(merged: dict[str, Any], src: str) -> None:
    """Read the first file format's keys into today's: `sites` as a list of names (every kind at every site),
    `initial_levels` (start levels in task order), `site_positions`, and the paper's kind rules as top-level keys."""
    kinds = merged.get("kinds")
    if not isinstance(kinds, list) or not all(isinstance(k, dict) and "name" in k for k in kinds):
        return  # convert names the problem
    for key in [k for k in _LEGACY_KIND_KEYS if k in merged]:
        kind_name, path = _LEGACY_KIND_KEYS[key]
        value = merged.pop(key)
        entry = next((k for k in kinds if k["name"] == kind_name), None)
        if entry is None:
            raise ScenarioError(f"{src}: {key}: {value!r} sets a rule of kind {kind_name!r}, which is not a kind here")
        for step in path[:-1]:
            if not isinstance(entry.get(step), dict):
                entry[step] = {}
            entry = entry[step]
        entry[path[-1]] = value
    sites = merged.get("sites")
    positions = merged.pop("site_positions", None)
    levels = merged.pop("initial_levels", None)
    if isinstance(sites, list) and sites and all(isinstance(x, str) for x in sites):
        names = [k["name"] for k in kinds]
        if levels is None:
            raise ScenarioError(f"{src}: initial_levels: needed with sites given by name (start level of every task)")
        merged["sites"] = [{"name": x, "tasks": dict.fromkeys(names, 0)} for x in sites]
        if positions is None:
            positions = [[50.0 * s, 0.0] for s in range(len(sites))]
    sites = merged.get("sites")
    if not isinstance(sites, list) or not all(isinstance(x, dict) for x in sites):
        return
    if positions is not None:
        if not isinstance(positions, list) or len(positions) != len(sites):
            n = len(positions) if isinstance(positions, list) else positions
            raise ScenarioError(f"{src}: site_positions: {n} positions for {len(sites)} sites")
        for site, pos in zip(sites, positions, strict=True):
            site["position"] = pos
    if levels is not None:
        order = [k["name"] for k in kinds]
        slots = [(site, kind) for site in sites for kind in order if kind in (site.get("tasks") or {})]
        if not isinstance(levels, list) or len(levels) != len(slots):
            n = len(levels) if isinstance(levels, list) else 1
            raise ScenarioError(
                f"{src}: initial_levels: {levels!r} has {n} entries, the scenario has {len(slots)} tasks"
            )
        for (site, kind), lv in zip(slots, levels, strict=True):
            site["tasks"][kind] = lv


class ScenarioRecordError(ScenarioError):
    """A /htlm/scenario record whose scenario does not load (`reason` "scenario") or whose layout hash is not the
    scenario's (`reason` "layout")."""

    def __init__(self, reason: str, text: str) -> None:
        """The reason a node counts the rejection under, and the message."""
        super().__init__(text)
        self.reason = reason


def from_record(rec: dict[str, Any]) -> Scenario:
    """The scenario of a decoded /htlm/scenario record (`htlm_msgs_py.schema.SCENARIO`), its layout checked against
    the record's hash: the one definition every node and viewer uses.

    Raises:
        ScenarioRecordError: with the reason to count (scenario, layout) and the problem.
    """
    try:
        sc = from_dict(rec["scenario"], "/htlm/scenario")
    except ScenarioError as e:
        raise ScenarioRecordError("scenario", str(e)) from None
    if sc.layout_hash() != rec["layout"]:
        raise ScenarioRecordError("layout", f"layout {rec['layout']} != {sc.layout_hash()}")
    return sc


def named_scenarios() -> list[str]:
    """Names of the shipped scenario files."""
    return sorted(f.stem for f in SCENARIO_DIR.glob("*.yaml"))


def _resolve(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists() and p.suffix == "" and p.name in named_scenarios():
        p = SCENARIO_DIR / f"{p.name}.yaml"
    if not p.exists():
        hint = f" (or name a shipped scenario: {', '.join(named_scenarios())})" if p.suffix == "" else ""
        raise ScenarioError(f"{p}: cannot read scenario file: No such file or directory{hint}")
    return p


def load(path: str | Path, team: str | None = None) -> Scenario:
    """Load a scenario YAML file, or a shipped scenario by name (keys a file omits keep the values of the default
    scenario file); `team` picks one of the file's `teams`."""
    p = _resolve(path)
    data = _file_data(p)
    return from_dict({} if data is None else data, str(p), team)


def _check_prob(src: str, where: str, x: float) -> None:
    if not (0.0 <= x <= 1.0):
        raise ScenarioError(f"{src}: {where}: {x!r} is not a probability in [0, 1]")


def validate(sc: Scenario, src: str) -> None:
    """Check every value of a scenario; raise ScenarioError naming src, the field and the value."""
    cmax = sc.capability_max
    if sc.levels < 2:
        raise ScenarioError(f"{src}: levels: {sc.levels!r} must be at least 2")
    if sc.horizon < 1:
        raise ScenarioError(f"{src}: horizon: {sc.horizon!r} must be at least 1")
    if cmax < 1:
        raise ScenarioError(f"{src}: capability_max: {cmax!r} must be at least 1")
    _check_drops(src, "p_drop", sc.p_drop)
    for name in ("sensing_base", "channel_base"):
        _check_prob(src, name, getattr(sc, name))
    if not 0.0 <= sc.sensing_slope <= 1.0:
        raise ScenarioError(f"{src}: sensing_slope: {sc.sensing_slope!r} is not in [0, 1]")
    if sc.standby_accuracy is not None:
        _check_prob(src, "standby_accuracy", sc.standby_accuracy)  # HT mode: no idle location, nobody stands by
    if not 0.0 <= sc.gamma <= 1.0:
        raise ScenarioError(f"{src}: gamma: {sc.gamma!r} is not in [0, 1]")
    _validate_kinds(sc, src)
    _validate_sites(sc, src)
    if not sc.agents:
        raise ScenarioError(f"{src}: agents: [] is an agent count of zero; a team needs at least one agent")
    names = [a.name for a in sc.agents]
    if len(set(names)) != len(names):
        raise ScenarioError(f"{src}: agents: names must be unique, got {names!r}")
    uses = {k.uses for k in sc.kinds}
    for i, a in enumerate(sc.agents):
        if not a.name or not a.name.replace("_", "").isalnum() or not a.name[0].isalpha():
            raise ScenarioError(
                f"{src}: agents[{i}].name: {a.name!r} must start with a letter and hold only letters, digits, _"
            )
        for cap, v in a.capabilities.items():
            if cap not in uses:
                raise ScenarioError(
                    f"{src}: agents[{i}].capabilities.{cap}: {v!r}: no kind uses capability {cap!r} "
                    f"(the kinds use {sorted(uses)})"
                )
        for cap, v in [*a.capabilities.items(), ("sensing", a.sensing), ("comm", a.comm)]:
            where = cap if cap in ("sensing", "comm") else f"capabilities.{cap}"
            if not 0 <= v <= cmax:
                raise ScenarioError(f"{src}: agents[{i}].{where}: {v!r} is out of range 0..{cmax}")
        if a.reward is not None:
            _validate_reward(a.reward, sc.levels, src, f"agents[{i}].reward")
    present = {sc.kinds[k].name for _, k in sc.tasks}
    for k, kind in enumerate(sc.kinds):
        if kind.name in present and all(a.capability(kind.uses) == 0 for a in sc.agents):
            raise ScenarioError(
                f"{src}: kinds[{k}]: {kind.name!r}: no agent can work on it (no agent has capability "
                f"{kind.uses!r} above 0), yet sites hold tasks of it"
            )
    _validate_reward(sc.reward, sc.levels, src, "reward")
    _validate_travel(sc, src)
    _validate_events(sc, src, "events", sc.events, placeholder=False)
    if sc.initial_assignment >= sc.n_actions or sc.initial_assignment < -1:
        raise ScenarioError(
            f"{src}: initial_assignment: {sc.initial_assignment!r} is out of range -1..{sc.n_actions - 1}"
        )


def _check_drops(src: str, where: str, p_drop: tuple[float, ...]) -> None:
    if not p_drop:
        raise ScenarioError(f"{src}: {where}: needs at least one entry")
    for k, x in enumerate(p_drop):
        _check_prob(src, f"{where}[{k}]", x)


def _validate_kinds(sc: Scenario, src: str) -> None:
    """Names unique, dependencies on known kinds without cycles, levels in range, probabilities in [0, 1]."""
    if not sc.kinds:
        raise ScenarioError(f"{src}: kinds: []: at least one kind of task is needed")
    names = [k.name for k in sc.kinds]
    top = sc.levels - 1
    for k, kind in enumerate(sc.kinds):
        at = f"kinds[{k}]"
        if not kind.name or "@" in kind.name or kind.name in names[:k]:
            raise ScenarioError(f"{src}: {at}.name: {kind.name!r} must be a unique, non-empty name without '@'")
        _check_prob(src, f"{at}.growth", kind.growth)
        _check_prob(src, f"{at}.hazard", kind.hazard)
        if kind.p_drop:
            _check_drops(src, f"{at}.p_drop", kind.p_drop)
        for name in ("sensing_base", "sensing_slope"):
            value = getattr(kind, name)
            if value is not None:
                _check_prob(src, f"{at}.{name}", value)
        if kind.depends_on and kind.depends_on not in names:
            raise ScenarioError(f"{src}: {at}.depends_on: {kind.depends_on!r} is not a kind (kinds: {names})")
        if kind.depends_on == kind.name:
            raise ScenarioError(f"{src}: {at}.depends_on: {kind.depends_on!r}: a kind cannot depend on itself")
        if kind.blocked_above is not None:
            if not kind.depends_on:
                raise ScenarioError(f"{src}: {at}.blocked_above: {kind.blocked_above!r} needs depends_on")
            if not 0 <= kind.blocked_above <= top:
                raise ScenarioError(f"{src}: {at}.blocked_above: {kind.blocked_above!r} is out of range 0..{top}")
        dd = kind.double_drop
        if dd is not None:
            _check_prob(src, f"{at}.double_drop.share", dd.share)
            if not 2 <= dd.min_level <= top:
                raise ScenarioError(
                    f"{src}: {at}.double_drop.min_level: {dd.min_level!r} is out of range 2..{top} "
                    "(two levels down from it must stay >= 0)"
                )
            if dd.gate_at_most is not None:
                if not kind.depends_on:
                    raise ScenarioError(f"{src}: {at}.double_drop.gate_at_most: {dd.gate_at_most!r} needs depends_on")
                if not 0 <= dd.gate_at_most <= top:
                    raise ScenarioError(
                        f"{src}: {at}.double_drop.gate_at_most: {dd.gate_at_most!r} is out of range 0..{top}"
                    )
    for k, kind in enumerate(sc.kinds):  # follow every chain of depends_on: a cycle comes back to a kind seen
        seen = [kind.name]
        nxt = kind.depends_on
        while nxt:
            if nxt in seen:
                chain = " -> ".join([*seen, nxt])
                raise ScenarioError(f"{src}: kinds[{k}].depends_on: {kind.depends_on!r} closes a cycle: {chain}")
            seen.append(nxt)
            nxt = sc.kinds[names.index(nxt)].depends_on


def _validate_sites(sc: Scenario, src: str) -> None:
    """At least one site, unique names, tasks of known kinds with start levels in range."""
    if not sc.sites:
        raise ScenarioError(f"{src}: sites: []: at least one site is needed")
    names = list(sc.site_names)
    kinds = list(sc.kind_names)
    for s, site in enumerate(sc.sites):
        if not site.name or "@" in site.name or site.name in names[:s]:
            raise ScenarioError(f"{src}: sites[{s}].name: {site.name!r} must be a unique, non-empty name without '@'")
        if not site.tasks:
            raise ScenarioError(f"{src}: sites[{s}].tasks: {{}}: a site needs at least one task")
        for kind, lv in site.tasks.items():
            if kind not in kinds:
                raise ScenarioError(f"{src}: sites[{s}].tasks.{kind}: {lv!r}: {kind!r} is not a kind (kinds: {kinds})")
            if not 0 <= lv < sc.levels:
                raise ScenarioError(f"{src}: sites[{s}].tasks.{kind}: {lv!r} is out of range 0..{sc.levels - 1}")


def _validate_travel(sc: Scenario, src: str) -> None:
    """Speeds and the step length: positive where given; with a step length every agent has a speed, and speeds are
    refused without one (they would change nothing); no travel in HT mode (its agents have no idle location)."""
    if sc.step_seconds < 0:
        raise ScenarioError(f"{src}: step_seconds: {sc.step_seconds!r} must be >= 0 (0: no travel)")
    if sc.speed is not None and sc.speed <= 0:
        raise ScenarioError(f"{src}: speed: {sc.speed!r} must be above 0 (metres per second)")
    for i, a in enumerate(sc.agents):
        if a.speed is not None and a.speed <= 0:
            raise ScenarioError(f"{src}: agents[{i}].speed: {a.speed!r} must be above 0 (metres per second)")
    given = sc.speed is not None or any(a.speed is not None for a in sc.agents)
    if not sc.travel:
        if given:
            raise ScenarioError(
                f"{src}: step_seconds: {sc.step_seconds!r}: speeds are given but no step length; set step_seconds "
                "(the seconds of one step) for drives to take steps"
            )
        return
    if sc.mode == "ht":
        raise ScenarioError(f"{src}: step_seconds: {sc.step_seconds!r}: travel needs idle locations (mode: htlm)")
    for i, a in enumerate(sc.agents):
        if sc.agent_speed(i) <= 0:
            raise ScenarioError(
                f"{src}: agents[{i}].speed: {a.name} has no speed and the scenario no `speed` for it, yet "
                f"step_seconds is {sc.step_seconds!r}"
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


def _validate_events(
    sc: Scenario, src: str, where: str, events: tuple[EventSpec, ...], placeholder: bool = True
) -> None:
    """Events name sites, kinds and agents of the operation, a new task is dormant (start level 0) until it starts,
    steps are in 1..h and levels and probabilities in range. With `placeholder`, an agent named `most_important` is
    left to `htlm stress`, which names the agent when it runs."""
    sites = {site.name: site for site in sc.sites}
    agents = [a.name for a in sc.agents]
    top = sc.levels - 1
    for i, ev in enumerate(events):
        at = f"{where}[{i}]"
        if ev.event in ("surge", "new_task"):
            if ev.site not in sites:
                raise ScenarioError(f"{src}: {at}.site: {ev.site!r} is not a site (sites: {list(sites)})")
            tasks = sites[ev.site].tasks
            if ev.task not in tasks:
                raise ScenarioError(
                    f"{src}: {at}.task: {ev.task!r} is not a task of site {ev.site!r} (its tasks: {list(tasks)}); "
                    "a task that appears later is listed at its site with start level 0"
                )
            if ev.event == "new_task" and tasks[ev.task] != 0:
                raise ScenarioError(
                    f"{src}: {at}: new_task {ev.task}@{ev.site}: the task starts at level {tasks[ev.task]}; a new "
                    "task is dormant until it appears: give it start level 0 at its site"
                )
            if not 1 <= ev.level <= top:
                raise ScenarioError(f"{src}: {at}.level: {ev.level!r} is out of range 1..{top}")
        elif ev.agent == "most_important" and not placeholder:
            raise ScenarioError(
                f"{src}: {at}.agent: 'most_important' is allowed only in a stress set (htlm stress names the agent)"
            )
        elif ev.agent not in agents and ev.agent != "most_important":
            raise ScenarioError(f"{src}: {at}.agent: {ev.agent!r} is not an agent of the team {agents}")
        if not 1 <= ev.at <= sc.horizon:
            raise ScenarioError(f"{src}: {at}.at: {ev.at!r} is out of range 1..{sc.horizon} (the steps)")
        _check_prob(src, f"{at}.probability", ev.probability)
        if ev.probability == 0.0:
            raise ScenarioError(f"{src}: {at}.probability: 0.0: the event could never happen")
        if ev.once_done and ev.once_done not in sites:
            raise ScenarioError(f"{src}: {at}.once_done: {ev.once_done!r} is not a site (sites: {list(sites)})")


RANDOM_EVENTS = "random"
"""The name (`--events random`) of the events every scenario can draw by chance (`random_events`), unless it has a
stress set or there is a file of that name."""

RANDOM_EVENTS_PER_EPISODE = 0.5
"""How many random events (`random_events`) an episode holds on average: half relapses after completion, a quarter
surges of an open task, a quarter dropouts."""


def random_events(sc: Scenario, per_episode: float = RANDOM_EVENTS_PER_EPISODE) -> tuple[EventSpec, ...]:
    """Events that happen by chance, made from the operation alone, for training that prepares for the unexpected
    (docs/model.md, Events): every task can come back to level L − 2 once its site is done (a relapse, or a new
    task where the team believes the work is over), can surge to level L − 1 from step 3 on, and every agent can
    drop out from step 2 on. The chances per step are set so that an episode holds `per_episode` events on average
    (half relapses, a quarter surges, a quarter dropouts; a relapse's window is taken as half the horizon)."""
    h, top = sc.horizon, sc.levels - 1
    n_tasks = max(1, sc.n_tasks)
    relapse = min(1.0, per_episode / 2 / (n_tasks * max(1, h // 2)))
    surge = min(1.0, per_episode / 4 / (n_tasks * max(1, h - 2)))
    drop = min(1.0, per_episode / 4 / (max(1, sc.n_agents) * max(1, h - 1)))
    out: list[EventSpec] = []
    for s, k in sc.tasks:
        site, kind = sc.sites[s].name, sc.kinds[k].name
        out.append(
            EventSpec(
                "surge",
                site=site,
                task=kind,
                level=max(1, top - 1),
                at=1,
                probability=relapse,
                once_done=site,
                name=f"{kind}@{site} comes back",
            )
        )
        out.append(
            EventSpec(
                "surge", site=site, task=kind, level=top, at=min(3, h), probability=surge, name=f"{kind}@{site} surges"
            )
        )
    out += [
        EventSpec("dropout", agent=a.name, at=min(2, h), probability=drop, name=f"{a.name} drops out")
        for a in sc.agents
    ]
    return tuple(out)


def read_events(path: str | Path, sc: Scenario) -> tuple[EventSpec, ...]:
    """The events of an events file (`events:` a list, or the list itself), or of the scenario's stress set named
    `path`, or (`RANDOM_EVENTS`) those that happen by chance (`random_events`), checked against the operation `sc`.

    Raises:
        ScenarioError: naming the file, the field and the bad value.
    """
    name = str(path)
    if name in sc.stress:
        _validate_events(sc, f"scenario {sc.name!r}", f"stress.{name}", sc.stress[name])
        return sc.stress[name]
    p = Path(path)
    if name == RANDOM_EVENTS and not p.exists():
        return random_events(sc)
    if not p.exists():
        sets = f" (or name a stress set of the scenario: {', '.join(sc.stress)})" if sc.stress else ""
        raise ScenarioError(f"{p}: cannot read events file: No such file or directory{sets}")
    data = _file_data(p)
    if isinstance(data, dict) and set(data) == {"events"}:
        data = data["events"]
    if not isinstance(data, list):
        raise ScenarioError(f"{p}: top level: expected a list of events or a mapping with `events:`, got {data!r}")
    try:
        with_events = convert({**sc.to_dict(), "events": data}, Scenario, str(p))
    except ConversionError as e:
        raise ScenarioError(str(e)) from None
    _validate_events(sc, str(p), "events", with_events.events)
    return with_events.events
