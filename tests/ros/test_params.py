"""Node parameters over real DDS: every parameter of the world, trainer and agent nodes is declared with its type,
description, range and read-only flag as the settings dataclasses say (what `ros2 param describe` shows), and a
running node refuses a bad value or a change of a read-only parameter with a reason that names it."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

import pytest

from htlm_agent.ros.settings import AgentSettings, TrainerSettings
from htlm_msgs_py.params import constraints
from htlm_world.ros.settings import WorldSettings
from support.ros import read_json

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

TYPES = {bool: 1, int: 2, float: 3, str: 4}
"""rcl_interfaces/ParameterType of each field type."""


def _expected(cls: type, name: str) -> dict[str, Any]:
    c = constraints(cls)[name]
    tp = typing.get_type_hints(cls)[name]
    ranged = c.lo is not None and tp in (int, float)
    return {
        "type": TYPES[tp],
        "read_only": not c.tunable,
        "additional_constraints": c.describe(),
        "floating_point_range": [[float(c.lo), float(c.hi), 0.0]] if ranged and tp is float else [],
        "integer_range": [[int(c.lo), int(c.hi), 0]] if ranged and tp is int else [],  # type: ignore[arg-type]
    }


def test_parameters_carry_their_types_ranges_and_read_only_flags(ros_team: Any) -> None:
    team = ros_team(episodes=1)
    team.start("world", "trainer", "agent1")  # the world waits for the missing agents meanwhile
    out = team.tmp / "describe.json"
    nodes = {"/htlm_world": WorldSettings, "/htlm_trainer": TrainerSettings, "/htlm_agent1": AgentSettings}
    helper = team.helper("describe", "--out", str(out), "--nodes", ",".join(nodes))
    assert helper.wait(timeout=60) == 0, (team.tmp / "helper-0.log").read_text()
    described = read_json(out)
    for node, cls in nodes.items():
        params = described[node]
        for f in dataclasses.fields(cls):
            d = params[f.name]
            assert d["description"], f"{node} {f.name}: no description"
            got = {
                k: d[k]
                for k in ("type", "read_only", "additional_constraints", "floating_point_range", "integer_range")
            }
            assert got == _expected(cls, f.name), f"{node} {f.name}"
    world = described["/htlm_world"]
    assert (
        world["act_deadline"]["floating_point_range"] == [[0.001, 3600.0, 0.0]]
        and not world["act_deadline"]["read_only"]
    )
    assert world["seed"]["integer_range"] == [[0, 2**63 - 1, 0]] and world["seed"]["read_only"]
    assert world["mode"]["additional_constraints"] == "one of: train, evaluate, deploy"
    assert described["/htlm_agent1"]["epsilon"]["floating_point_range"] == [[-1.0, 1.0, 0.0]]
    assert not described["/htlm_trainer"]["round_deadline"]["read_only"]
    assert described["/htlm_world"]["batch"]["integer_range"] == [[1, 4096, 0]] and world["batch"]["read_only"]

    def setparam(name: str, value: str) -> dict[str, Any]:
        res = team.tmp / f"set-{name}-{value}.json"
        p = team.helper("setparam", "--out", str(res), "--name", name, "--value", value)
        assert p.wait(timeout=40) == 0
        return read_json(res)  # type: ignore[no-any-return]

    bad = setparam("act_deadline", "-1.0")
    assert not bad["successful"] and "-1.0" in bad["reasons"][0], bad
    frozen = setparam("seed", "5")
    assert not frozen["successful"] and "read-only" in frozen["reasons"][0], frozen
    assert setparam("act_deadline", "3")["successful"]  # an integer for a float parameter is taken as 3.0
    assert team.procs["world"].popen.poll() is None, "the world died"
