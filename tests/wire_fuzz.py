"""Malformed records for every schema of the wire contract: used by the unit tests of decode and by the fuzzing
integration test (tests/ros/test_fuzz.py). Deterministic for a given generator."""

from __future__ import annotations

import base64
import json
import random
from collections.abc import Iterator
from typing import Any

import numpy as np

from htlm_msgs_py import schema as S


def packed(dtype: str, values: Any, shape: list[Any] | None = None) -> dict[str, Any]:
    """A binary array field as it travels (`schema.Array`): its shape, its dtype and its C-order bytes in base64,
    written here independently of the encoder; `shape` overrides the header's shape."""
    a = np.asarray(values, dtype=dtype)
    return {"shape": list(a.shape) if shape is None else shape, "dtype": dtype, "data": _b64(a.tobytes())}


def unpacked(rec: dict[str, Any]) -> dict[str, Any]:
    """The fields of a record as a sender passes them to `schema.encode`: every binary array (a JSON object of
    dtype, shape and data) as the numpy array it holds."""
    return {
        k: np.frombuffer(base64.b64decode(v["data"]), v["dtype"]).reshape(v["shape"])
        if isinstance(v, dict) and v.keys() == {"shape", "dtype", "data"}
        else v
        for k, v in rec.items()
    }


def plain(rec: dict[str, Any]) -> dict[str, Any]:
    """Decoded fields as VALID writes them: every numpy array packed with its own dtype and shape (so comparing
    with VALID also compares dtypes, shapes and every byte)."""
    return {k: packed(v.dtype.str, v) if isinstance(v, np.ndarray) else v for k, v in rec.items()}


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


VALID: dict[str, dict[str, Any]] = {
    "htlm/scenario": {
        "run": "r1",
        "nonce": "0123456789abcdef",
        "seq": 3,
        "seed": 1,
        "mode": "evaluate",
        "clock": "lockstep",
        "period": 0.5,
        "operation": "simulated",
        "first_episode": 0,
        "episodes": 1,
        "batch": 2,
        "trainer_lag": 1,
        "epoch": 0.0,
        "state": "running",
        "layout": "0123abcd",
        "scenario": {"name": "paper"},
    },
    "htlm/step": {"episode": 2, "size": 2, "step": 3, "phase": "step", "acted": [0, 1, 2]},
    "htlm/action": {"agent": 1, "episode": 2, "step": 3, "actions": [2, 5], "before": [4, -1]},
    "htlm/observation": {"agent": 1, "episode": 2, "step": 3, "tasks": [2, -1], "levels": [3, -1], "acted": [0, 1, 2]},
    "htlm/broadcast": {"agent": 1, "episode": 2, "step": 3, "actions": [2, 5], "levels": [3, -1], "sent": 1.5},
    "htlm/ready": {"agent": 1, "episode": 1, "step": 30},
    "htlm/transition": {
        "agent": 1,
        "session": "0123456789abcdef",
        "seq": 0,
        "episode": 2,
        "step": 3,
        "k": packed("<f4", [[0.0] * 26, [0.5] * 26]),
        "a": packed("<i2", [2, 5]),
        "r": packed("<f8", [1.5, -0.25]),
        "k2": packed("<f4", [[0.0] * 26, [0.25] * 26]),
        "mask2": packed("|b1", [[True] * 5 + [False], [False] * 4 + [True] * 2]),
        "done": False,
    },
    "htlm/transition_ack": {"agent": 1, "session": "0123456789abcdef", "upto": 5},
    "htlm/weights": {
        "agent": 1,
        "version": 3,
        "episode": 2,
        "trained": 90,
        "every": 1,
        "encoding": "base64",
        "data": "AAAA",
        "sha256": "0" * 64,
        "settings": {},
    },
    "htlm/trainer_progress": {"run": "r1", "trained": 90, "updates": 12, "finished": False},
    "htlm/belief": {
        "agent": 1,
        "episode": 1,
        "step": 3,
        "marginals": [0.2] * 20,
        "confident": [1, 2, 3, 4],
        "arrived": "yes",
        "distance": 0.25,
    },
    "htlm/ground_truth": {
        "episode": 2,
        "step": 3,
        "levels": [[1, 2, 3, 4], [0, 1, 2, 4]],
        "actions": [[0, 1, 2, 3, 4], [5, -1, 2, 3, 4]],
        "events": [[], [0]],
    },
    "htlm/episode_metrics": {
        "run": "r1",
        "episode": 1,
        "severity": "simulated",
        "completion": 9,
        "failed": False,
        "unused_capability": 0.5,
        "unused_fraction": 0.2,
        "idle_before": 3,
        "reassign_before": 2,
        "absent": [0, 0, 0, 0, 0],
        "seconds": 0.3,
    },
    "htlm/severity": {"episode": 2, "step": 3, "levels": [[1, 2, 3, 4], [0, 1, 2, 4]]},
    "htlm/goal": {"agent": 1, "x": 15.0, "y": -3.5, "frame": "map", "sent": 1.7e9},
}
"""A valid record of every schema for the paper scenario's limits (5 agents, 4 tasks, 6 actions, 5 levels, h 30);
the per-step records are of a batch of B = 2 episodes (2 and 3)."""
VALID = {name: {"run": "r1", **rec} if S.SCHEMAS[name].bound else rec for name, rec in VALID.items()}
"""(Every record but the run announcement carries its run.)"""

PAPER_LIMITS = S.limits(5, 4, 6, 5, 30)
"""The paper scenario's limits, with the default bound on the batch (4096 episodes per record)."""


def wrong_type(fld: S.Field, rng: random.Random) -> Any:
    """A value of another JSON type than field `fld` accepts."""
    if isinstance(fld, S.Int):
        return rng.choice(["x", 1.5, True, None, [], {}])
    if isinstance(fld, S.Float):
        return rng.choice(["x", True, None, [1.0], {}])
    if isinstance(fld, (S.Text, S.OneOf)):
        return rng.choice([1, None, [], {}, True])
    if isinstance(fld, S.Bool):
        return rng.choice([1, 0, "true", None, []])
    if isinstance(fld, S.Object):
        return rng.choice([[], "x", 1, None])
    return rng.choice(["x", None, {}, 1, True])  # lists


def out_of_range(fld: S.Field, rng: random.Random, lim: dict[str, int]) -> Any:
    """A value of the right type but outside the range of field `fld` (None if it has no range)."""
    if isinstance(fld, S.Int):
        lo, hi = S.bound(fld.lo, lim), S.bound(fld.hi, lim)
        return rng.choice([lo - 1, lo - 1000, hi + 1, hi + 10**6, 2**70, -(2**70)])
    if isinstance(fld, S.Float):
        return rng.choice([fld.lo - 1.0, fld.hi * 10 + 1.0, 1e300, -1e300])
    if isinstance(fld, S.OneOf):
        return "not-" + fld.values[0]
    if isinstance(fld, S.Text):
        return "x" * (fld.max_len + 1)
    if isinstance(fld, S.IntList):
        return [S.bound(fld.hi, lim) + 1] * max(1, S.bound(fld.length, lim) if fld.length is not None else 1)
    if isinstance(fld, S.FloatList):
        return [fld.hi * 10 + 1.0] * (S.bound(fld.length, lim) if fld.length is not None else 1)
    if isinstance(fld, S.BoolList):
        return [True] * (S.bound(fld.length, lim) + 1)
    if isinstance(fld, S.Rows):  # one episode's value out of range
        inner = out_of_range(fld.item, rng, lim)
        return None if inner is None else [inner]
    if isinstance(fld, S.Array):  # one value of one row out of range: NaN, infinity, beyond a bound, a bool byte of 2
        lo, hi = fld.value_range(lim)
        shape = [1, *(S.bound(d, lim) for d in fld.dims)]
        if fld.dtype == "|b1":
            raw = np.zeros(shape, dtype=np.uint8)
            raw.flat[rng.randrange(raw.size)] = rng.choice([2, 255])
            return {"shape": shape, "dtype": fld.dtype, "data": _b64(raw.tobytes())}
        a = np.full(shape, lo, dtype=fld.dtype)
        floats = np.dtype(fld.dtype).kind == "f"
        a.flat[rng.randrange(a.size)] = rng.choice([lo - 1, hi + 1, *([np.nan, np.inf, -np.inf] if floats else [])])
        return packed(fld.dtype, a)
    return None


def bad_array(fld: S.Array, good: dict[str, Any], rng: random.Random, lim: dict[str, int]) -> Any:
    """A binary array whose header or bytes are wrong: dtype, shape against the limits, byte length, base64."""
    shape, data = good["shape"], base64.b64decode(good["data"])
    rows = S.bound(fld.max_rows, lim)
    other = "<f8" if fld.dtype != "<f8" else "<f4"
    choices = [
        {**good, "dtype": other},  # another dtype (its bytes as long as this dtype's)
        {**good, "dtype": rng.choice(["float32", "f4", "<F4", ">f4", "", 7])},
        {**good, "shape": [rows + 1, *shape[1:]]},  # more rows than the batch
        {**good, "shape": [0, *shape[1:]]},  # no row
        {**good, "shape": shape[:-1] if len(shape) > 1 else [*shape, 1]},  # another rank
        {**good, "shape": [shape[0], *(n + 1 for n in shape[1:])] if len(shape) > 1 else [shape[0] + 1]},
        {**good, "data": _b64(data[: -rng.randrange(1, 3)])},  # bytes short of the shape
        {**good, "data": _b64(data + data[:1])},  # a byte too many
        {**good, "data": _b64(data * (rows + 2))},  # more bytes than any record of the batch holds
        {**good, "data": rng.choice(["!!!!", good["data"][:-1], "A", good["data"] + "=", "@" + good["data"][1:]])},
        {k: v for k, v in good.items() if k != rng.choice(["shape", "dtype", "data"])},  # a missing member
        {**good, "order": "C"},  # an unknown member
    ]
    return rng.choice(choices)


def valid(schema: S.Schema) -> dict[str, Any]:
    """A fresh copy of the valid record of `schema`."""
    return json.loads(json.dumps(VALID[schema.name]))


def malformed(
    schema: S.Schema,
    rng: random.Random,
    n: int,
    episodes: tuple[int, int] = (0, 10**6),
    lim: dict[str, int] | None = None,
) -> Iterator[str]:
    """`n` record texts for `schema` that a receiver must reject (or, for the last kinds, drop as past/future):
    garbage, not JSON, not an object, wrong schema or version, missing/extra fields, wrong types, NaN/inf,
    out-of-range values, oversized payloads, and well-formed records of episodes outside [lo, hi)."""
    names = list(schema.fields)
    lo, hi = episodes
    lim = PAPER_LIMITS if lim is None else lim
    ranged = [k for k, f in schema.fields.items() if not isinstance(f, (S.Bool, S.Object))]
    for i in range(n):
        kind = i % 14
        rec = valid(schema)
        if kind == 0:
            yield "".join(chr(rng.randrange(1, 0x2FF)) for _ in range(rng.randrange(1, 200)))
        elif kind == 1:
            yield json.dumps(rec)[: rng.randrange(1, 40)]  # truncated JSON
        elif kind == 2:
            yield json.dumps(rng.choice([[1, 2], 3, "s", None, True, 1.5]))
        elif kind == 3:
            yield json.dumps({"schema": rng.choice(["htlm/nope", "", 7, None]), "v": schema.version, **rec})
        elif kind == 4:
            v = schema.version
            yield json.dumps(
                {"schema": schema.name, "v": rng.choice([0, v + 1, 99, str(v), float(v), True, None]), **rec}
            )
        elif kind == 5:
            rec.pop(rng.choice(names))
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 6:
            rec[f"extra{rng.randrange(9)}"] = 1
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 7:
            f = rng.choice(names)
            rec[f] = wrong_type(schema.fields[f], rng)
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 8:  # NaN and infinities as JSON text
            f = rng.choice(names)
            body = json.dumps({"schema": schema.name, "v": schema.version, **{k: v for k, v in rec.items() if k != f}})
            yield body[:-1] + f',"{f}":{rng.choice(["NaN", "Infinity", "-Infinity", "1e400", "-1e999"])}}}'
        elif kind == 9:  # out-of-range values: levels, agent ids, actions, steps, ...
            f = rng.choice(ranged)
            rec[f] = out_of_range(schema.fields[f], rng, lim)
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 10:  # oversized payload: beyond the schema's limit (70 kB for the 16 MB weights records)
            rec[names[0]] = "x" * (schema.max_bytes + 10 if schema.max_bytes <= 1 << 20 else 70_000)
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 11:  # lists of the wrong length or with bad entries
            lists = [
                k
                for k, fld in schema.fields.items()
                if isinstance(fld, (S.IntList, S.FloatList, S.BoolList, S.Rows, S.Array))
            ]
            if lists:
                k = rng.choice(lists)
                fld = schema.fields[k]
                if isinstance(fld, S.Array):
                    rec[k] = bad_array(fld, rec[k], rng, lim)
                elif isinstance(fld, S.Rows):  # per-episode arrays: no rows, too many, a row of the wrong length
                    row = rec[k][0]
                    if isinstance(row, list):
                        wrong = [row[:-1]] if len(row) > 1 else [row * 2]
                    else:
                        wrong = [row] * (S.bound(fld.max_rows, lim) + 1)
                    rec[k] = rng.choice([[], wrong, [float("nan")], ["a"], [None]])
                else:
                    rec[k] = rng.choice([[1] * 1000, [float("nan")] * 3, ["a"], [None], [[1]]])
            else:
                rec[names[-1]] = [[[]]]
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec}).replace("NaN", "NaN")
        elif kind == 12 and "episode" in rec:  # well-formed, but an episode before the run
            rec["episode"] = rng.randrange(0, max(lo, 1))
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        elif kind == 13 and "episode" in rec:  # well-formed, but an episode after the run
            rec["episode"] = rng.randrange(hi + 5, hi + 1000)
            yield json.dumps({"schema": schema.name, "v": schema.version, **rec})
        else:
            yield "{" * rng.randrange(1, 100_000)  # deep nesting / garbage
