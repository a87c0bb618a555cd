"""The wire contract as Markdown, from the declarations themselves: the topic table and the record
tables of docs/ros.md (`python -m htlm_msgs_py.docs topics|records`), so the documents never drift from the code."""

from __future__ import annotations

import dataclasses
import sys

from . import qos
from .params import constraint, field_docs
from .schema import (
    SCHEMAS,
    Array,
    Bool,
    BoolList,
    Field,
    Float,
    FloatList,
    Int,
    IntList,
    Object,
    OneOf,
    Rows,
    Schema,
    Text,
)
from .topics import TOPICS


def field_text(f: Field) -> str:
    """One field's type and range, as the record tables show it."""
    if isinstance(f, Int):
        return f"int {f.lo}..{f.hi}"
    if isinstance(f, Float):
        return f"float {f.lo:g}..{f.hi:g}"
    if isinstance(f, Bool):
        return "bool"
    if isinstance(f, Text):
        extra = f", {f.pattern}" if f.pattern else ""
        return f"string (<= {f.max_len} chars{extra})"
    if isinstance(f, OneOf):
        return " \\| ".join(f'"{v}"' for v in f.values)
    if isinstance(f, IntList):
        size = f"list[{f.length}]" if f.length is not None else f"list[<= {f.max_len}]"
        return f"int {f.lo}..{f.hi} {size}" + (", distinct" if f.unique else "")
    if isinstance(f, FloatList):
        size = f"list[{f.length}]" if f.length is not None else f"list[<= {f.max_len}]"
        return f"float {f.lo:g}..{f.hi:g} {size}"
    if isinstance(f, BoolList):
        return f"bool list[{f.length}]"
    if isinstance(f, Rows):
        return f"per episode of the batch (1..{f.max_rows} entries): {field_text(f.item)}"
    if isinstance(f, Array):
        lo, hi = (f"{b:g}" if isinstance(b, float) else str(b) for b in (f.lo, f.hi))
        shape = ", ".join([f"1..{f.max_rows} rows", *map(str, f.dims)])
        dtype = f.dtype.replace("|", "\\|")
        return f'binary "{dtype}" [{shape}]: {lo}..{hi}'
    if isinstance(f, Object):
        return "object"
    return type(f).__name__


def _size(n: int) -> str:
    return f"{n // (1024 * 1024)} MiB" if n >= 1024 * 1024 else f"{n // 1024} KiB"


def schema_markdown(s: Schema) -> str:
    """One record's heading, description and field table."""
    lines = [f"**`{s.name}` v{s.version}** — {s.doc} Largest record: {_size(s.max_bytes)}.", ""]
    lines += ["| field | type and range |", "|---|---|"]
    lines += [f"| `{k}` | {field_text(f)} |" for k, f in s.fields.items()]
    return "\n".join(lines)


def records_markdown() -> str:
    """Every record schema, in the order of SCHEMAS."""
    return "\n\n".join(schema_markdown(s) for s in SCHEMAS.values())


def topics_markdown() -> str:
    """The topic table and the QoS table."""
    lines = ["| topic | type | QoS | schema | publisher | subscribers |", "|---|---|---|---|---|---|"]
    for t in TOPICS:
        schema = f"`{t.schema}` v{SCHEMAS[t.schema].version}" if t.schema else "-"
        lines.append(f"| `{t.name}` | `{t.msg_type}` | {t.qos} | {schema} | {t.publisher} | {t.subscribers} |")
    lines += ["", "| profile | reliability | durability | history |", "|---|---|---|---|"]
    lines += [f"| {q.name} | {q.reliability} | {q.durability} | keep last {q.depth} |" for q in qos.PROFILES.values()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Print the topic table (`topics`) or the record tables (`records`)."""
    what = (argv if argv is not None else sys.argv[1:]) or ["records"]
    print(topics_markdown() if what[0] == "topics" else records_markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())


def params_markdown(cls: type) -> str:
    """The parameter table of a node's settings dataclass (type, default, range or choices, tunable, meaning)."""
    names = {bool: "bool", int: "integer", float: "double", str: "string"}
    docs = field_docs(cls)
    lines = [
        "| parameter | type | default | range or choices | at run time | meaning |",
        "|---|---|---|---|---|---|",
    ]
    for f in dataclasses.fields(cls):
        c = constraint(f)
        rng = ", ".join(c.choices) if c.choices else (c.describe().removeprefix("one of: ") or "-")
        kind = names.get(type(f.default), "string")
        lines.append(
            f"| `{f.name}` | {kind} | `{f.default!r}` | {rng} | {'tunable' if c.tunable else 'read-only'} | "
            f"{docs.get(f.name, '')} |"
        )
    return "\n".join(lines)
