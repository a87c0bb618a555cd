"""Node parameters as fields of a frozen settings dataclass, without ROS: each field's range, choices and whether it
may change while the node runs.

A node's settings class (htlm_world.ros.settings, htlm_agent.ros.settings) declares each field with `setting(...)`
and a one-line docstring under it; `htlm_msgs_py.ros.declare_settings` turns every field into a ROS parameter whose
descriptor carries that docstring, the type, the range (`floating_point_range` / `integer_range`), the choices (as
`additional_constraints`) and `read_only` unless the field is tunable. `problems` checks the same constraints
without ROS, so the unit tests and the node refuse exactly the same values.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import math
import textwrap
from dataclasses import dataclass
from functools import cache
from typing import Any

SECONDS = (0.001, 3600.0)
"""The range of a duration parameter, seconds."""

INT64_MAX = 2**63 - 1
"""Largest value of a ROS integer parameter."""


@dataclass(frozen=True)
class Constraint:
    """What a parameter accepts besides its type."""

    lo: float | None = None
    """Smallest value (inclusive), None: no bound (numbers only)."""
    hi: float | None = None
    """Largest value (inclusive), None: no bound (numbers only)."""
    choices: tuple[str, ...] = ()
    """The accepted values of a text parameter; empty: any text."""
    tunable: bool = False
    """Whether the node applies a change while it runs (otherwise the parameter is read-only)."""

    def describe(self) -> str:
        """The constraint in words, for `ros2 param describe` and the docs ("" when there is none)."""
        if self.choices:
            return "one of: " + ", ".join(self.choices)
        if self.lo is not None and self.hi is not None:
            return f"in [{_num(self.lo)}, {_num(self.hi)}]"
        if self.lo is not None:
            return f">= {_num(self.lo)}"
        if self.hi is not None:
            return f"<= {_num(self.hi)}"
        return ""


def _num(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def setting(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    choices: tuple[str, ...] = (),
    tunable: bool = False,
) -> Any:
    """A dataclass field with default `default` and its parameter constraint (see `Constraint`)."""
    return dataclasses.field(
        default=default, metadata={"constraint": Constraint(lo=lo, hi=hi, choices=choices, tunable=tunable)}
    )


def constraint(f: dataclasses.Field[Any]) -> Constraint:
    """The constraint of a settings field (none for a field not made with `setting`)."""
    c = f.metadata.get("constraint")
    return c if isinstance(c, Constraint) else Constraint()


def constraints(cls: type) -> dict[str, Constraint]:
    """Every field's constraint of the settings dataclass `cls`, by field name."""
    return {f.name: constraint(f) for f in dataclasses.fields(cls)}


def problems(settings: Any) -> list[str]:
    """Values of a settings instance outside their range or choices, each naming the field and the value."""
    bad: list[str] = []
    for f in dataclasses.fields(settings):
        c = constraint(f)
        v = getattr(settings, f.name)
        if c.choices and v not in c.choices:
            bad.append(f"{f.name}: {v!r} is not one of {', '.join(c.choices)}")
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            if isinstance(v, float) and not math.isfinite(v):
                bad.append(f"{f.name}: {v!r} must be a finite number")
            elif (c.lo is not None and v < c.lo) or (c.hi is not None and v > c.hi):
                bad.append(f"{f.name}: {v!r} must be {c.describe()}")
    return bad


@cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the attribute docstring convention), on one line: the help of
    `htlm train`'s options and the descriptions of node parameters."""
    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = ast.parse(src).body[0]
    assert isinstance(body, ast.ClassDef)
    docs: dict[str, str] = {}
    for a, b in itertools.pairwise(body.body):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs
