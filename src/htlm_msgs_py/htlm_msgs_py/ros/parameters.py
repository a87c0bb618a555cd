"""Node parameters from a settings dataclass: one statically typed, described ROS parameter per field, checked
before anything is declared and on every later change (docs/ros.md, Node parameters)."""

from __future__ import annotations

import dataclasses
import sys
import typing
from collections.abc import Callable
from typing import Any, TypeVar

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..params import INT64_MAX, Constraint, constraints, field_docs
from ..validation import ConversionError, convert, convert_value

T = TypeVar("T")


class SettingsError(ValueError):
    """A node parameter with a bad value (names the parameter and the value)."""


_PARAMETER_TYPES = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}
"""The ROS parameter type of each field type a settings dataclass may use."""


def parameter_descriptor(name: str, tp: type, doc: str, c: Constraint) -> ParameterDescriptor:
    """The descriptor of the parameter of a settings field: its type, description, range, choices, read-only."""
    d = ParameterDescriptor(
        name=name,
        type=_PARAMETER_TYPES[tp],
        description=doc,
        additional_constraints=c.describe(),
        read_only=not c.tunable,
    )
    if tp is float and (c.lo is not None or c.hi is not None):
        lo = -sys.float_info.max if c.lo is None else float(c.lo)
        hi = sys.float_info.max if c.hi is None else float(c.hi)
        d.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    elif tp is int and (c.lo is not None or c.hi is not None):
        lo_i = -INT64_MAX - 1 if c.lo is None else int(c.lo)
        hi_i = INT64_MAX if c.hi is None else int(c.hi)
        d.integer_range = [IntegerRange(from_value=lo_i, to_value=hi_i, step=0)]
    return d


def declare_settings(
    node: Node, cls: type[T], validate: Callable[[T], None], on_change: Callable[[T], None] | None = None
) -> T:
    """Declare one parameter per field of the frozen settings dataclass `cls` and return the settings.

    Every parameter is statically typed and gets a descriptor (`parameter_descriptor`) with the field's docstring,
    its range (`floating_point_range` / `integer_range`) and choices from the field's `htlm_msgs_py.params`
    constraint, and `read_only` unless the field is tunable, so `ros2 param describe` shows them. The values
    (defaults, or given with `--ros-args -p name:=value` or a parameters file; an integer is taken for a float) are
    converted with `htlm_msgs_py.validation.convert` and checked with `validate(settings)` before anything is
    declared; both raise SettingsError naming the parameter and the value. Later changes of tunable parameters go
    through rclpy's type and range checks and then the same `validate`; a refusal is a
    SetParametersResult(successful=False, reason=...) naming the parameter and the value, and an accepted change
    calls `on_change(new settings)`.
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)  # type: ignore[arg-type]
    cons = constraints(cls)
    # rclpy keeps the values given on the command line and in parameter files here until they are declared
    overrides: dict[str, Any] = getattr(node, "_parameter_overrides", {})
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name in overrides:
            values[f.name] = overrides[f.name].value
        else:
            values[f.name] = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[operator]
    try:
        settings = convert(values, cls, "parameters")
    except ConversionError as e:
        raise SettingsError(str(e)) from None
    validate(settings)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        desc = parameter_descriptor(f.name, hints[f.name], docs.get(f.name, ""), cons[f.name])
        node.declare_parameter(f.name, getattr(settings, f.name), desc, ignore_override=True)
    floats = {name for name, tp in hints.items() if tp is float}
    state = {"settings": settings}

    def widen(params: list[Parameter]) -> list[Parameter]:
        """An integer given for a float parameter (`ros2 param set /node period 1`) is taken as that float."""
        return [
            Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
            if p.name in floats and p.type_ == Parameter.Type.INTEGER
            else p
            for p in params
        ]

    def on_set(params: list[Parameter]) -> SetParametersResult:
        try:
            changes = {
                p.name: convert_value(p.value, hints[p.name], p.name, "parameters") for p in params if p.name in hints
            }
            new = dataclasses.replace(state["settings"], **changes)  # type: ignore[type-var]
            validate(new)
        except (ConversionError, SettingsError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        state["settings"] = new
        if on_change is not None:
            on_change(new)
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(widen)
    node.add_on_set_parameters_callback(on_set)
    return settings
