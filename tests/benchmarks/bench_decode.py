"""Decode time of one transition record (the hot path of the trainer node): hand-written checks vs pydantic v2 vs
msgspec, each doing the whole job, and the repository's own `htlm_msgs_py.schema.decode`.

Every variant parses the JSON text, checks the exact field set (schema name, version, no missing or unknown
field), every type (no bool for int, no float for int), the static ranges, the bounds of the running scenario
(agent, action, step, vector lengths) and rejects NaN and infinities, and returns the fields as a dict. Before
timing, each variant is checked to accept the record and to reject a few bad ones.

Run: `.venv/bin/python tests/benchmarks/bench_decode.py [--n 20000] [--repeat 5]` (pydantic is optional: it is
not a dependency of the project, the variant is skipped when it is not installed).

Measured on the 2-core development machine (Python 3.11, msgspec 0.22.0, pydantic 2.14.3), µs per transition
record of 1036 characters: hand-written 27.4, pydantic 12.7, msgspec 5.7; schema.decode on msgspec 7.1 (it also
keeps ints in float fields as ints and checks the distinct entries msgspec has no constraint for). Under load the
numbers double, the ratios stay. msgspec was chosen: about 2x faster than pydantic and 4-5x faster than the
hand-written checks; strict by default where pydantic's strict mode still lets true and 1.0 pass for `Literal[1]`
(the "v" member); no dependencies of its own; one library for the records and the settings files
(`msgspec.convert`). Its errors name the path (`$.k[5]`) but not the value, so the value is looked up at that
path when a record is rejected (the rare path; accepted records pay nothing for it).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

import msgspec

from htlm_msgs_py import schema as S

LIM = S.limits(5, 4, 6, 5, 30)  # the paper scenario: 5 agents, 4 tasks, 6 actions, 5 levels, horizon 30
Decode = Callable[[str], dict[str, Any]]


def realistic_record() -> str:
    """A transition of the paper scenario as an agent sends it: marginals of 4 tasks x 5 levels + one-hot."""
    rng = random.Random(7)

    def knowledge() -> list[float]:
        k: list[float] = []
        for _ in range(4):
            w = [rng.random() for _ in range(5)]
            k += [x / sum(w) for x in w]
        onehot = [0.0] * 6
        onehot[rng.randrange(6)] = 1.0
        return k + onehot

    fields = {
        "agent": 3,
        "session": "9f3a0c17b2d4e6a8",
        "seq": 123_456,
        "episode": 4_321,
        "step": 17,
        "k": knowledge(),
        "a": 2,
        "r": -1.25,
        "k2": knowledge(),
        "mask2": [True, True, False, True, True, True],
        "done": False,
    }
    return S.encode(S.TRANSITION, fields)


# ----- (a) hand-written checks (the validator schema.py had before this benchmark) --------------------------------


def _nan(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


_JSON = json.JSONDecoder(parse_constant=_nan)


class Bad(ValueError):
    """A rejected record (the benchmark does not need the reasons)."""


def _int(v: Any, lo: int, hi: int) -> None:
    if type(v) is not int or not lo <= v <= hi:
        raise Bad(v)


def _floats(v: Any, n: int) -> None:
    if type(v) is not list or len(v) != n:
        raise Bad(v)
    for x in v:
        t = type(x)
        if (t is not float and t is not int) or not -1e6 <= x <= 1e6:
            raise Bad(x)


def handwritten(lim: dict[str, int]) -> Decode:
    """The per-field checks of the old schema.py, specialised to the transition record."""
    names = ("agent", "session", "seq", "episode", "step", "k", "a", "r", "k2", "mask2", "done")

    def decode(text: str) -> dict[str, Any]:
        if len(text) > S.DEFAULT_MAX_BYTES:
            raise Bad("size")
        obj = _JSON.decode(text)
        if type(obj) is not dict or obj.pop("schema", None) != "htlm/transition":
            raise Bad("schema")
        v = obj.pop("v", None)
        if type(v) is not int or v != 1:
            raise Bad("version")
        obj.pop("sig", None)
        for key in names:
            if key not in obj:
                raise Bad(key)
        if len(obj) != len(names):
            raise Bad("unknown")
        _int(obj["agent"], 0, lim["agent"])
        s = obj["session"]
        if type(s) is not str or len(s) != 16 or any(c not in "0123456789abcdef" for c in s):
            raise Bad(s)
        _int(obj["seq"], 0, S.SEQ_MAX)
        _int(obj["episode"], 0, S.EPISODE_MAX)
        _int(obj["step"], 1, lim["step"])
        _floats(obj["k"], lim["knowledge"])
        _int(obj["a"], 0, lim["action"])
        r = obj["r"]
        if (type(r) is not float and type(r) is not int) or not -1e6 <= r <= 1e6:
            raise Bad(r)
        _floats(obj["k2"], lim["knowledge"])
        m = obj["mask2"]
        if type(m) is not list or len(m) != lim["actions"] or any(type(x) is not bool for x in m):
            raise Bad(m)
        if type(obj["done"]) is not bool:
            raise Bad(obj["done"])
        return obj

    return decode


# ----- (b) pydantic v2 ----------------------------------------------------------------------------------------------


def pydantic_decoder(lim: dict[str, int]) -> Decode | None:
    """A strict pydantic model built for the scenario's bounds (built once per scenario, as a node would)."""
    try:
        import pydantic
    except ImportError:
        return None
    from pydantic import ConfigDict, Field, StringConstraints

    def i(lo: int, hi: int) -> Any:
        return Annotated[int, Field(strict=True, ge=lo, le=hi)]

    n = lim["knowledge"]
    vec = Annotated[list[Annotated[float, Field(ge=-1e6, le=1e6)]], Field(min_length=n, max_length=n)]
    model = pydantic.create_model(
        "Transition",
        __config__=ConfigDict(strict=True, extra="forbid", allow_inf_nan=False),
        schema_=(Literal["htlm/transition"], Field(alias="schema")),
        v=(i(1, 1), ...),
        sig=(str | None, None),
        agent=(i(0, lim["agent"]), ...),
        session=(Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{16}$")], ...),
        seq=(i(0, S.SEQ_MAX), ...),
        episode=(i(0, S.EPISODE_MAX), ...),
        step=(i(1, lim["step"]), ...),
        k=(vec, ...),
        a=(i(0, lim["action"]), ...),
        r=(Annotated[float, Field(ge=-1e6, le=1e6)], ...),
        k2=(vec, ...),
        mask2=(Annotated[list[bool], Field(min_length=lim["actions"], max_length=lim["actions"])], ...),
        done=(bool, ...),
    )
    exclude = {"schema_", "v", "sig"}

    def decode(text: str) -> dict[str, Any]:
        if len(text) > S.DEFAULT_MAX_BYTES:
            raise Bad("size")
        out: dict[str, Any] = model.model_validate_json(text).model_dump(exclude=exclude)
        return out

    return decode


# ----- (c) msgspec --------------------------------------------------------------------------------------------------


def msgspec_decoder(lim: dict[str, int]) -> Decode:
    """A msgspec Struct built for the scenario's bounds (built once per scenario, as a node would)."""

    def i(lo: int, hi: int) -> Any:
        return Annotated[int, msgspec.Meta(ge=lo, le=hi)]

    n = lim["knowledge"]
    num = Annotated[float, msgspec.Meta(ge=-1e6, le=1e6)]
    vec = Annotated[list[num], msgspec.Meta(min_length=n, max_length=n)]
    struct = msgspec.defstruct(
        "Transition",
        [
            ("schema", Literal["htlm/transition"]),
            ("v", Literal[1]),
            ("agent", i(0, lim["agent"])),
            ("session", Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{16}$")]),
            ("seq", i(0, S.SEQ_MAX)),
            ("episode", i(0, S.EPISODE_MAX)),
            ("step", i(1, lim["step"])),
            ("k", vec),
            ("a", i(0, lim["action"])),
            ("r", num),
            ("k2", vec),
            ("mask2", Annotated[list[bool], msgspec.Meta(min_length=lim["actions"], max_length=lim["actions"])]),
            ("done", bool),
            ("sig", str | None, None),
        ],
        forbid_unknown_fields=True,
    )
    dec = msgspec.json.Decoder(struct)
    asdict = msgspec.structs.asdict

    def decode(text: str) -> dict[str, Any]:
        if len(text) > S.DEFAULT_MAX_BYTES:
            raise Bad("size")
        out = asdict(dec.decode(text))
        del out["schema"], out["v"], out["sig"]
        return out

    return decode


# ----- (d) the repository's decode ------------------------------------------------------------------------------------


def repository(lim: dict[str, int]) -> Decode:
    """`htlm_msgs_py.schema.decode` as the trainer node calls it."""

    def decode(text: str) -> dict[str, Any]:
        return S.decode(text, S.TRANSITION, lim)

    return decode


# ----- timing -------------------------------------------------------------------------------------------------------


def bad_records(good: str) -> list[str]:
    """Records every variant must reject."""
    rec = json.loads(good)
    out = []
    for key, value in (
        ("agent", 5),
        ("agent", True),
        ("a", 6),
        ("step", 31),
        ("step", 1.0),
        ("session", "XYZ"),
        ("mask2", [1, 1, 0, 1, 1, 1]),
        ("k", rec["k"][:-1]),
        ("r", 2e6),
        ("v", 2),
        ("v", True),
        ("extra", 1),
    ):
        out.append(json.dumps({**rec, key: value}, separators=(",", ":")))
    out.append(good.replace('"r":-1.25', '"r":NaN'))
    out.append(good.replace('"r":-1.25', '"r":1e400'))
    out.append(json.dumps({k: v for k, v in rec.items() if k != "done"}))
    return out


def check(name: str, fn: Decode, good: str, want: dict[str, Any]) -> None:
    """Fail loudly unless `fn` accepts the record (same fields) and rejects every bad one."""
    got = fn(good)
    assert got == want, (name, got)
    for text in bad_records(good):
        try:
            fn(text)
        except ValueError:  # Bad, WireError, json errors, pydantic.ValidationError, msgspec errors
            continue
        raise AssertionError(f"{name} accepted {text}")


def per_record_us(fn: Decode, text: str, n: int, repeat: int) -> float:
    """Median over `repeat` runs of the µs per decode of `text`, over n decodes each."""
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(n):
            fn(text)
        runs.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(runs)


def main() -> None:
    """Check every variant, then print its µs per transition record."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=20_000, help="decodes per timing run")
    ap.add_argument("--repeat", type=int, default=5, help="timing runs (the median is shown)")
    args = ap.parse_args()
    good = realistic_record()
    want = {k: v for k, v in json.loads(good).items() if k not in ("schema", "v")}
    assert all(math.isfinite(x) for x in want["k"])
    variants: list[tuple[str, Decode | None]] = [
        ("hand-written (stdlib json + checks)", handwritten(LIM)),
        (f"pydantic {_version('pydantic')}", pydantic_decoder(LIM)),
        (f"msgspec {msgspec.__version__}", msgspec_decoder(LIM)),
        ("htlm_msgs_py.schema.decode (this tree)", repository(LIM)),
    ]
    print(f"transition record: {len(good)} characters; {args.n} decodes x {args.repeat} runs, median")
    for name, fn in variants:
        if fn is None:
            print(f"{name:42s}  not installed, skipped")
            continue
        check(name, fn, good, want)
        print(f"{name:42s}  {per_record_us(fn, good, args.n, args.repeat):7.2f} µs per record")


def _version(module: str) -> str:
    try:
        return str(__import__(module).__version__)
    except ImportError:
        return "(missing)"


if __name__ == "__main__":
    main()
