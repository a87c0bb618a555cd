"""Plain data (YAML, JSON, ROS parameters) to frozen dataclasses, checked by msgspec: one converter for every edge.

`convert(data, cls, src)` builds a (frozen) dataclass from nested dicts and lists: nested dataclasses, tuples
(`tuple[int, ...]` and fixed-length), `Literal`, unions (`X | None`), int, float (an int is accepted and made a
float), bool, str. Types are strict: no bool for an int, no float for an int, no string for a number. Keys the
dataclass does not have are refused; fields left out keep the dataclass's defaults. Every problem raises
`ConversionError` naming the source (a file), the field path (like `agents[2].sensing`) and the bad value.

The type checks are msgspec's (`msgspec.convert`, strict): each dataclass is mirrored once by a msgspec Struct
that forbids unknown fields, and the converted Structs are turned into the dataclasses, so the dataclasses' own
defaults and `__post_init__` checks apply. A ValueError raised by a `__post_init__` propagates unchanged.
"""

from __future__ import annotations

import array
import dataclasses
import re
import types
import typing
from functools import cache
from typing import Any, Literal, TypeVar, Union

import msgspec

T = TypeVar("T")

_PATH_STEP = re.compile(r"\.([^.\[\]]+)|\[(\d+)\]")
_AT = re.compile(r" - at `(key` in `)?\$(.*)`$")
_GOT = re.compile(r"^Expected (.*), got `(.*)`$")
_FIELD = re.compile(r"^Object (missing required|contains unknown) field `(.*)`$")


def shown(value: Any, limit: int = 80) -> str:
    """repr of a value, cut to `limit` characters (for error messages)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class ConversionError(ValueError):
    """Plain data that does not fit a dataclass: names the source, the field path and the bad value."""

    def __init__(self, src: str, path: str, value: Any, problem: str) -> None:
        """Create the error; `path` is "" for the whole data, `value` the bad value (None when it is missing)."""
        self.src = src
        self.path = path
        self.value = value
        self.problem = problem
        super().__init__(f"{src}: {path or 'top level'}: {problem}")


def convert(data: Any, cls: type[T], src: str = "<data>") -> T:
    """The dataclass `cls` built from plain data, every value type-checked.

    Args:
        data: nested dicts and lists (a YAML or JSON document, ROS parameter values).
        cls: a dataclass (frozen or not) whose fields are annotated with the types listed in the module docstring.
        src: where the data comes from, for messages (a file name).

    Raises:
        ConversionError: a value of the wrong type, an unknown key or a missing required field, naming `src`, the
            field path and the value.
    """
    out: T = convert_value(data, cls, "", src)
    return out


def convert_value(value: Any, tp: Any, where: str, src: str = "<data>") -> Any:
    """`value` converted to the annotation `tp` (a dataclass, tuple, Literal, union, scalar type).

    `where` is the field path of `value` itself (e.g. a ROS parameter's name, "" for the top level); errors name
    `src`, `where` plus the path inside `value`, and the bad value. An `array.array` (rclpy's value of an integer
    or double array parameter) is taken as a list.

    Raises:
        ConversionError: see `convert`.
    """
    if isinstance(value, array.array):  # rclpy's integer and double array parameters
        value = value.tolist()
    try:
        raw = msgspec.convert(value, _mirror(tp), strict=True)
    except msgspec.ValidationError as e:
        raise _error(str(e), value, tp, where, src) from None
    return _build(raw)


# ----- dataclasses mirrored by msgspec Structs ---------------------------------------------------------------------

_ORIGIN: dict[type, type] = {}
"""The dataclass of every mirror Struct."""


@cache
def _mirror(tp: Any) -> Any:
    """The msgspec type of annotation `tp`: every dataclass in it replaced by its mirror Struct."""
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _struct(tp)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is None or origin is Literal or not args:
        return tp
    if origin in (Union, types.UnionType):
        return Union[tuple(_mirror(a) for a in args)]  # noqa: UP007 (built from a tuple of types)
    if origin is typing.Annotated:
        return typing.Annotated[(_mirror(args[0]), *tp.__metadata__)]
    return origin[tuple(a if a is Ellipsis else _mirror(a) for a in args)]


def _struct(cls: type) -> type:
    hints = typing.get_type_hints(cls, include_extras=True)
    spec: list[tuple[str, Any] | tuple[str, Any, Any]] = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = _mirror(hints[f.name])
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            spec.append((f.name, tp))
        else:  # left out: the dataclass's default applies
            spec.append((f.name, Union[tp, msgspec.UnsetType], msgspec.UNSET))  # noqa: UP007
    struct = msgspec.defstruct(cls.__name__, spec, forbid_unknown_fields=True, module=__name__)
    _ORIGIN[struct] = cls
    return struct


def _build(x: Any) -> Any:
    """Converted data with every mirror Struct turned into its dataclass."""
    if isinstance(x, msgspec.Struct):
        kwargs = {}
        for name in x.__struct_fields__:
            v = getattr(x, name)
            if v is not msgspec.UNSET:
                kwargs[name] = _build(v)
        return _ORIGIN[type(x)](**kwargs)
    if isinstance(x, tuple):
        return tuple(_build(v) for v in x)
    if isinstance(x, list):
        return [_build(v) for v in x]
    if isinstance(x, dict):
        return {k: _build(v) for k, v in x.items()}
    return x


# ----- error messages ----------------------------------------------------------------------------------------------


def split_path(path: str) -> list[str | int]:
    """The steps of a msgspec path without its "$" (".agents[2].sensing" -> ["agents", 2, "sensing"])."""
    return [name if name else int(index) for name, index in _PATH_STEP.findall(path)]


def join_path(steps: list[str | int]) -> str:
    """A field path for messages (["agents", 2, "sensing"] -> "agents[2].sensing")."""
    out = ""
    for s in steps:
        out += f"[{s}]" if isinstance(s, int) else (f".{s}" if out else s)
    return out


def lookup(data: Any, steps: list[str | int]) -> Any:
    """The value at `steps` inside plain data; raises LookupError or TypeError when there is none."""
    for s in steps:
        data = data[s]
    return data


def parse_error(message: str) -> tuple[list[str | int], str, str | None]:
    """A msgspec ValidationError message as (path steps, problem, name of a missing or unknown field).

    "Expected `int` <= 4 - at `$.agents[2].sensing`" -> (["agents", 2, "sensing"], "Expected `int` <= 4", None);
    "Object contains unknown field `speed` - at `$.agents[1]`" -> (["agents", 1, "speed"], "...", "speed").
    """
    m = _AT.search(message)
    steps = split_path(m.group(2)) if m else []
    problem = message[: m.start()] if m else message
    if m is not None and m.group(1):  # a mapping with a key that is not a string
        problem = f"keys must be strings, {problem[:1].lower()}{problem[1:]}"
    f = _FIELD.match(problem)
    if f is None:
        return steps, problem, None
    return [*steps, f.group(2)], problem, f.group(2)


def describe(problem: str, value: Any) -> str:
    """A msgspec problem with the bad value: "expected `int`, got str 'ten'", "expected `int` <= 4, got 7"."""
    m = _GOT.match(problem)
    if m is not None:
        return f"expected {m.group(1)}, got {'None' if value is None else f'{type(value).__name__} {shown(value)}'}"
    text = problem[:1].lower() + problem[1:]
    return f"{text}: {shown(value)}" if ", got " in text else f"{text}, got {shown(value)}"


def _error(message: str, data: Any, tp: Any, where: str, src: str) -> ConversionError:
    steps, problem, name = parse_error(message)
    path = join_path([*([where] if where else []), *steps])
    if problem.startswith("Object missing required field"):
        return ConversionError(src, path, None, "missing (a required field)")
    try:
        value = lookup(data, steps)
    except (LookupError, TypeError):
        value = None
    if name is not None:
        known = _known_keys(tp, steps[:-1])
        more = f"; known keys: {known}" if known else ""
        return ConversionError(src, path, value, f"unknown key (value {shown(value)}){more}")
    if problem.startswith("Invalid enum value"):
        choices = _literal_choices(tp, steps)
        return ConversionError(src, path, value, f"{shown(value)} is not one of {choices}")
    return ConversionError(src, path, value, describe(problem, value))


def _type_at(tp: Any, steps: list[str | int]) -> Any:
    """The annotation at a path inside `tp` (None when the path leaves the annotated types)."""
    for s in steps:
        tp = _strip_optional(tp)
        if dataclasses.is_dataclass(tp) and isinstance(s, str):
            tp = typing.get_type_hints(tp).get(s)
        elif typing.get_origin(tp) is tuple and isinstance(s, int):
            args = typing.get_args(tp)
            tp = args[0] if len(args) == 2 and args[1] is Ellipsis else (args[s] if s < len(args) else None)
        else:
            return None
    return _strip_optional(tp)


def _strip_optional(tp: Any) -> Any:
    if typing.get_origin(tp) in (Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return inner[0] if len(inner) == 1 else tp
    return tp


def _known_keys(tp: Any, steps: list[str | int]) -> list[str]:
    at = _type_at(tp, steps)
    return sorted(f.name for f in dataclasses.fields(at)) if dataclasses.is_dataclass(at) else []


def _literal_choices(tp: Any, steps: list[str | int]) -> list[Any]:
    at = _type_at(tp, steps)
    return list(typing.get_args(at)) if typing.get_origin(at) is Literal else []
