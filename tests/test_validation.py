"""The generic converter of plain data to frozen dataclasses (htlm_msgs_py.validation): types, paths, values."""

from __future__ import annotations

import array
from dataclasses import dataclass, field
from typing import Literal

import pytest

from htlm_msgs_py.validation import ConversionError, convert, convert_value


@dataclass(frozen=True)
class Inner:
    """A nested dataclass."""

    x: float = 1.0
    """A number."""
    tags: tuple[str, ...] = ()
    """Some strings."""


@dataclass(frozen=True)
class Item:
    """A list entry with a required field."""

    name: str
    """Required."""
    size: int = 3
    """An integer."""
    inner: Inner | None = None
    """Optional nested dataclass."""


@dataclass(frozen=True)
class Outer:
    """The top level."""

    mode: Literal["a", "b"] = "a"
    """A choice."""
    flag: bool = False
    """A boolean."""
    pos: tuple[float, float] = (0.0, 0.0)
    """A fixed-length tuple."""
    items: tuple[Item, ...] = ()
    """Nested dataclasses in a tuple."""
    inner: Inner = field(default_factory=Inner)
    """A nested dataclass with a default factory."""
    count: int = 1
    """Must be positive."""

    def __post_init__(self) -> None:
        """The dataclass's own check."""
        if self.count < 1:
            raise ValueError(f"count: {self.count!r} must be >= 1")


def test_converts_nested_data_and_keeps_defaults() -> None:
    got = convert(
        {"mode": "b", "pos": [1, 2], "items": [{"name": "n", "inner": {"tags": ["t"]}}], "inner": {"x": 4}},
        Outer,
        "f.yaml",
    )
    assert got == Outer(mode="b", pos=(1.0, 2.0), items=(Item(name="n", inner=Inner(tags=("t",))),), inner=Inner(x=4.0))
    assert isinstance(got.pos[0], float) and isinstance(got.inner.x, float)
    assert convert({}, Outer) == Outer()


@pytest.mark.parametrize(
    ("data", "path", "shown"),
    [
        ({"mode": "c"}, "mode", "'c'"),
        ({"flag": 1}, "flag", "1"),
        ({"count": True}, "count", "True"),
        ({"count": 2.0}, "count", "2.0"),
        ({"pos": [1.0]}, "pos", "[1.0]"),
        ({"pos": [1.0, "y"]}, "pos[1]", "'y'"),
        ({"items": [{"name": "a"}, {"name": "b", "size": "big"}]}, "items[1].size", "'big'"),
        ({"items": [{"name": "a", "inner": {"tags": ["t", 5]}}]}, "items[0].inner.tags[1]", "5"),
        ({"items": [{"name": "a", "colour": "red"}]}, "items[0].colour", "'red'"),
        ({"inner": {"y": 2}}, "inner.y", "2"),
        ({"items": [{"size": 2}]}, "items[0].name", "missing"),
        ({"items": "abc"}, "items", "'abc'"),
    ],
)
def test_errors_name_source_path_and_value(data: dict[str, object], path: str, shown: str) -> None:
    with pytest.raises(ConversionError) as err:
        convert(data, Outer, "f.yaml")
    msg = str(err.value)
    assert msg.startswith(f"f.yaml: {path}: "), msg
    assert shown in msg.removeprefix(f"f.yaml: {path}: "), msg
    assert err.value.path == path and err.value.src == "f.yaml"


def test_unknown_keys_are_listed_with_the_known_ones() -> None:
    with pytest.raises(ConversionError, match=r"items\[0\]\.colour: unknown key .*known keys: \['inner', 'name'"):
        convert({"items": [{"name": "a", "colour": "red"}]}, Outer, "f.yaml")


def test_top_level_and_post_init_errors() -> None:
    with pytest.raises(ConversionError, match=r"^f.yaml: top level: expected `object`, got list \[1\]"):
        convert([1], Outer, "f.yaml")
    with pytest.raises(ConversionError, match=r"^f.yaml: top level: keys must be strings"):
        convert({1: 2}, Outer, "f.yaml")
    with pytest.raises(ValueError, match=r"^count: 0 must be >= 1$"):
        convert({"count": 0}, Outer, "f.yaml")


def test_convert_value_for_one_field() -> None:
    assert convert_value([64, 32], tuple[int, ...], "hidden") == (64, 32)
    assert convert_value(array.array("q", [64, 32]), tuple[int, ...], "hidden") == (64, 32)
    assert convert_value(3, float, "lr") == 3.0
    with pytest.raises(ConversionError, match=r"^parameters: hidden\[1\]: expected `int`, got float 3.5$"):
        convert_value([64, 3.5], tuple[int, ...], "hidden", "parameters")
