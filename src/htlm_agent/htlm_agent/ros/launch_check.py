"""The input of `htlm launch`, checked once before any process starts: every problem at once.

Without this check, each process refuses its own input when it starts or when the run begins (exit code 2), one
problem at a time: the world its scenario file, the trainer the learner settings, every agent the checkpoint, each
node its parameters. `check_launch` looks at all of it the way those processes will, and returns every problem,
each naming the file or option, the field and the value:

- the scenario file (`htlm_world.scenario.load`; every bad field, see `scenario_problems`);
- the learner settings of `--set` (`htlm_agent.learning.settings.Settings.from_dict`);
- the team key file (`htlm_msgs_py.signing.load_key`);
- the parameters of every process this host starts, exactly as `process_specs` hands them over: unknown names
  (with the known ones), wrong types (`htlm_msgs_py.validation.convert_value`, as `declare_settings` converts
  them) and values the node's validate function refuses (ranges and choices of `htlm_msgs_py.params.problems`);
- the checkpoint the agents would load: `load_checkpoint(path, scenario)` and `learning.learners.agent_policy` for each
  agent started here, as the agent node does (missing, corrupt `meta.json` or `agents.pt`, another layout or team).

ROS-free: it starts no process and writes nothing under the run directory.
"""

from __future__ import annotations

import copy
import dataclasses
import re
import tempfile
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from htlm_agent.experiments.recording import RecordSettings, validate_record_settings
from htlm_agent.learning.settings import Settings
from htlm_agent.ros.launch import COMMANDER_NODE, RECORD_NODE, LaunchConfig, process_specs, ros_env
from htlm_agent.ros.settings import (
    AgentSettings,
    CommanderSettings,
    TrainerSettings,
    validate_agent_settings,
    validate_commander_settings,
    validate_trainer_settings,
)
from htlm_msgs_py.params import problems
from htlm_msgs_py.signing import SigningError, load_key
from htlm_msgs_py.validation import ConversionError, convert_value, lookup, split_path
from htlm_world.ros.robot_settings import (
    OperationSettings,
    RobotSettings,
    validate_operation_settings,
    validate_robot_settings,
)
from htlm_world.ros.settings import WorldSettings, validate_world_settings
from htlm_world.scenario import Scenario, ScenarioError, from_dict, load

AGENT_NODE = "htlm_agent.ros.agent_node"

NODES: dict[str, tuple[type, Callable[[Any], list[str]], str]] = {
    "htlm_world.ros.world_node": (WorldSettings, validate_world_settings, "--world-param"),
    AGENT_NODE: (AgentSettings, validate_agent_settings, "--agent-param"),
    "htlm_agent.ros.trainer_node": (TrainerSettings, validate_trainer_settings, "--trainer-param"),
    "htlm_world.ros.robot_node": (RobotSettings, validate_robot_settings, "--robot-param"),
    "htlm_world.ros.operation_node": (OperationSettings, validate_operation_settings, ""),
    RECORD_NODE: (RecordSettings, validate_record_settings, ""),
    COMMANDER_NODE: (CommanderSettings, validate_commander_settings, ""),
}
"""Per node module: its settings dataclass, its validate function, and the option of `htlm launch` that sets its
parameters (empty: none)."""

_FIELD_PATH = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*|\[\d+\])*")

_MAX_SCENARIO_PROBLEMS = 100


def check_launch(cfg: LaunchConfig) -> list[str]:
    """Every problem of the launch's input, each naming the file or option, the field and the value.

    Args:
        cfg: the launch; `cfg.scenario` is the scenario the launcher loaded from `cfg.scenario_file` (or any
            stand-in when that file does not load: its problems are reported, and the checkpoint is then only
            checked on its own, not against the scenario).

    Returns:
        The problems, one line each, without duplicates; empty when every process can start with its input.
    """
    bad: list[str] = []
    scenario: Scenario | None = cfg.scenario
    if cfg.scenario_file:
        file_bad = scenario_problems(cfg.scenario_file)
        bad += file_bad
        scenario = None if file_bad else scenario
    bad += learner_problems(cfg.learner)
    bad += key_problems(cfg)
    specs = _specs(cfg)
    bad += param_problems(cfg, specs)
    bad += checkpoint_problems(cfg, specs, scenario)
    return list(dict.fromkeys(bad))


def scenario_problems(path: str) -> list[str]:
    """Every problem of a scenario file, each naming the file, the field and the value (empty when it loads).

    `htlm_world.scenario.load` stops at the first problem. To find the others, the field it named is left out of
    the file's data (so its default applies; a required field or list element takes its whole entry with it) and
    the data is checked again, until it loads or a problem names no field. A problem found that way may involve a
    field left out before (e.g. `site_positions` checked against the default `sites`).
    """
    try:
        load(path)
        return []
    except ScenarioError as e:
        found = [str(e)]
    src = str(Path(path))
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError):  # unreadable, not YAML, or a shipped scenario's name: the one problem
        return found
    if not isinstance(data, dict):
        return found
    data = copy.deepcopy(data)
    left_out: set[tuple[str | int, ...]] = set()
    current = found[0]
    for _ in range(_MAX_SCENARIO_PROBLEMS):
        steps = _field_steps(current, src)
        if steps is None or not _leave_out(data, steps, left_out):
            break
        try:
            from_dict(data, src)
            break
        except ScenarioError as e:
            current = str(e)
        again = _field_steps(current, src)
        if again is not None and tuple(_field(again)) in left_out:
            continue  # a required field just left out: leave out more, report nothing new
        if current in found:
            break
        found.append(current)
    return found


def _field_steps(message: str, src: str) -> list[str | int] | None:
    """The field path a scenario problem names ("FILE: agents[1].sensing: ..." -> ["agents", 1, "sensing"]), or None."""
    if not message.startswith(f"{src}: "):
        return None
    path = message[len(src) + 2 :].split(": ", 1)[0].split(" ", 1)[0]
    if not _FIELD_PATH.fullmatch(path):
        return None
    return split_path("." + path)


def _field(steps: list[str | int]) -> list[str | int]:
    """The field of a path: a list element stands for its whole list (the list's length may matter)."""
    while steps and isinstance(steps[-1], int):
        steps = steps[:-1]
    return steps


def _leave_out(data: dict[str, Any], steps: list[str | int], left_out: set[tuple[str | int, ...]]) -> bool:
    """Remove the field at `steps` from the scenario data (its top-level key when that field was already left out
    or is a list element); returns whether anything was removed."""
    steps = _field(steps)
    for candidate in (steps, steps[:1]):
        key = tuple(candidate)
        if not candidate or key in left_out:
            continue
        left_out.add(key)
        try:
            parent = lookup(data, candidate[:-1])
        except (LookupError, TypeError):
            continue
        if isinstance(parent, dict) and candidate[-1] in parent:
            del parent[candidate[-1]]
            return True
    return False


def learner_problems(values: dict[str, Any], src: str = "--set") -> list[str]:
    """Problems of the learner settings given on the command line (every bad key; empty when they are valid)."""
    try:
        Settings.from_dict(Settings.with_preset(values), src)
        return []
    except ValueError as e:
        whole = str(e)
    each = []
    for k, v in values.items():
        try:
            Settings.from_dict(Settings.with_preset({k: v}), src)
        except ValueError as e:
            each.append(str(e))
    return each or [whole]  # no key is bad alone: a problem between keys


def key_problems(cfg: LaunchConfig) -> list[str]:
    """The problem of the team key every process would read (the key file or HTLM_TEAM_KEY), if any."""
    try:
        load_key(ros_env(cfg))
    except SigningError as e:
        return [f"--key-file: {e}" if cfg.key_file else f"environment: {e}"]
    return []


def _specs(cfg: LaunchConfig) -> list[tuple[str, str, dict[str, Any]]]:
    """`process_specs` of the launch, computed under a throwaway run directory of the same name (process_specs
    writes the learner settings file there), so the run directory is not created."""
    with tempfile.TemporaryDirectory(prefix="htlm-launch-check-") as tmp:
        return process_specs(dataclasses.replace(cfg, run_dir=Path(tmp) / cfg.run_dir.resolve().name))


def param_problems(cfg: LaunchConfig, specs: list[tuple[str, str, dict[str, Any]]]) -> list[str]:
    """Problems of the parameters of every process in `specs` (name, node module, parameters).

    A parameter given with --world-param, --agent-param, --trainer-param or --robot-param is named by that option;
    one the launcher derived from its other options by the process ("world parameter seed").
    """
    given = {
        "--world-param": cfg.world_params,
        "--agent-param": cfg.agent_params,
        "--trainer-param": cfg.trainer_params,
        "--robot-param": cfg.robot_params,
    }
    bad: list[str] = []
    for name, module, params in specs:
        if module not in NODES:  # a process without a settings dataclass: nothing to check here
            continue
        cls, validate, option = NODES[module]
        user = given.get(option, {})

        def source(param: str, name: str = name, option: str = option, user: dict[str, Any] = user) -> str:
            return option if param in user else f"{name} parameter"

        bad += settings_problems(cls, validate, params, source, module.rsplit(".", 1)[-1])
    return bad


def settings_problems(
    cls: type, validate: Callable[[Any], list[str]], params: dict[str, Any], source: Callable[[str], str], node: str
) -> list[str]:
    """Problems of one node's parameters, as the node would refuse them (`htlm_msgs_py.ros.declare_settings`).

    Args:
        cls: the node's settings dataclass.
        validate: its validate function (problems of a settings instance, each "field: value ...").
        params: parameter name -> value, as written to the node's parameters file.
        source: the option or origin of a parameter, for messages (`--world-param`).
        node: the node's name, for messages (`world_node`).
    """
    hints = typing.get_type_hints(cls)
    bad: list[str] = []
    good: dict[str, Any] = {}
    for k, v in params.items():
        if k not in hints:
            bad.append(f"{source(k)}: {k}: unknown parameter of {node} (value {v!r}); known: {', '.join(hints)}")
            continue
        try:
            good[k] = convert_value(v, hints[k], k, source(k))
        except ConversionError as e:
            bad.append(str(e))
    refused = {k for k in params if k not in good}
    settings = cls(**good)
    try:
        found = validate(settings)
    except (ArithmeticError, TypeError, ValueError):  # a validate function that trips over a value out of range
        found = problems(settings)
    for msg in found:
        field = msg.split(":", 1)[0]
        if field not in refused:  # a refused value was replaced by the default: nothing more to say about it
            bad.append(f"{source(field)}: {msg}")
    return bad


def _uses_checkpoint(policy: Any, mode: str) -> bool:
    return policy == "checkpoint" or (policy == "auto" and mode != "train")


def checkpoint_problems(
    cfg: LaunchConfig, specs: list[tuple[str, str, dict[str, Any]]], scenario: Scenario | None
) -> list[str]:
    """The problem of the checkpoint the agents started here would load, if any.

    Loaded as the agent node does (`load_checkpoint(path, scenario)`, then `learning.learners.agent_policy` for
    the index of each agent); with `scenario` None (the scenario file has problems) the checkpoint is only checked on
    its own.
    """
    from htlm_agent.learning.checkpoint import load_checkpoint
    from htlm_agent.learning.learners import agent_policy

    names = [a.name for a in cfg.scenario.agents]
    by_path: dict[str, list[int]] = {}
    for name, module, params in specs:
        path = params.get("checkpoint")
        if module == AGENT_NODE and isinstance(path, str) and path and _uses_checkpoint(params.get("policy"), cfg.mode):
            by_path.setdefault(path, []).extend([names.index(name)] if name in names else [])
    option = "--checkpoint" if cfg.checkpoint else "--agent-param: checkpoint"
    bad = []
    for path, agents in by_path.items():
        try:
            ck = load_checkpoint(path, scenario)
            for i in agents:
                agent_policy(ck, i)
        except ValueError as e:  # CheckpointError, or an agent index outside the checkpoint
            bad.append(f"{option}: {e}")
    return bad
