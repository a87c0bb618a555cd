"""Record schemas of the HTLM wire contract: encode to and decode from the JSON text of a std_msgs/String.

Every structured record is one JSON object `{"schema": "htlm/<name>", "v": <version>, ...fields}` (plus `"sig"`
when a team key is set, see `htlm_msgs_py.signing`), so `ros2 topic echo` prints it readably. `decode` accepts a
record only if everything about it is as the schema says: size, JSON syntax, schema name, version, the exact set
of fields, each field's type and range. Ranges that depend on the scenario (agent index, action index, level,
step, vector lengths) are named bounds resolved against `limits` of the running scenario; before a scenario is
known, generous static limits apply. Anything else raises `WireError`, which names the field and the value.

The fields are declared here (Int, Float, ... with their bounds); the checking is msgspec's: for every schema and
set of limits, the declarations become one msgspec Struct type (`Schema.struct`) whose constrained annotations
say all of the above, and one msgspec JSON decoder parses and validates a record text in a single pass. msgspec was
chosen (2026-11) by timing each candidate doing the whole job on the one-transition JSON record of the time: 5.7 µs,
against 12.7 µs with pydantic v2 and 27.4 µs with hand-written checks. Records are encoded by msgspec's JSON encoder
(compact, no spaces).

Arrays that grow with the batch (`Array`: the transitions an agent sends the trainer) travel in binary inside the
record: a JSON object `{"shape": [128, 26], "dtype": "<f4", "data": "<base64>"}` whose header says what the bytes
hold, so `ros2 topic echo` still shows it; msgspec decodes the base64 into bytes, and `decode` checks the byte length
against the shape and every value against its range with numpy, then hands the array over as a read-only numpy
array (`htlm bench` measures encode and decode against the JSON lists they replace).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated, Any, Literal, NamedTuple, Union

import msgspec
import numpy as np
from numpy.typing import NDArray

from .signing import Signer
from .validation import join_path, lookup, parse_error, shown

Bound = int | str
"""An inclusive bound: a number, or the name of a limit resolved against the running scenario."""

EPISODE_MAX = 10**9
SEQ_MAX = 2**53
DEFAULT_MAX_BYTES = 64 * 1024
"""Largest record text accepted by default; larger payloads are rejected before parsing."""

STATIC_LIMITS: dict[str, int] = {
    "agent": 1023,  # largest agent index
    "action": 1023,  # largest index in G-bar
    "task": 1023,  # largest task index
    "level": 1023,  # largest severity level
    "step": 100_000,  # horizon h
    "agents": 1024,  # N
    "tasks": 1024,  # p
    "actions": 1024,  # |G-bar|
    "knowledge": 65_536,  # length of the knowledge state K
    "marginals": 65_536,  # p * L
    "batch": 4096,  # B, episodes per batch
}
"""Limits used before the scenario is known (and for names a Limits mapping leaves out)."""


def limits(
    n_agents: int,
    n_tasks: int,
    n_actions: int,
    levels: int,
    horizon: int,
    batch: int = 4096,
    knowledge: int | None = None,
) -> dict[str, int]:
    """The named bounds of one scenario (N agents, p tasks, |G-bar| actions, L levels, horizon h, the knowledge
    state's length, default p·L + |G-bar|) and of the run's batch (at most B episodes per record)."""
    return {
        "agent": n_agents - 1,
        "action": n_actions - 1,
        "task": n_tasks - 1,
        "level": levels - 1,
        "step": horizon,
        "agents": n_agents,
        "tasks": n_tasks,
        "actions": n_actions,
        "knowledge": n_tasks * levels + n_actions if knowledge is None else knowledge,
        "marginals": n_tasks * levels,
        "batch": batch,
    }


class WireError(ValueError):
    """A received record that does not follow its schema. `reason` is a short code for counters.

    The message (and, for a failed validation, the bad value, looked up in the record text) is built only when
    asked for: a flood of bad records is counted at the cost of the check, not of the explanation."""

    def __init__(self, reason: str, where: str | None, value: Any, path: str | None = None, detail: str = "") -> None:
        """Create the error.

        Args:
            reason: short code for counters (size, json, type, range, ...; see `decode`).
            where: the record's field (None for the whole record).
            value: the bad value.
            path: where inside the field, for the message (e.g. "k[3]"); defaults to `where`.
            detail: what was expected, for the message.
        """
        super().__init__()
        self.reason = reason
        self.where = where
        self._value = value
        self.path = path or where
        self.detail = detail

    @property
    def value(self) -> Any:
        """The bad value."""
        return self._value

    def __str__(self) -> str:
        """ "field 'step': range: 99 (expected `int` <= 29)"."""
        place = f"field {self.path!r}" if self.path else "record"
        return f"{place}: {self.reason}: {shown(self.value)}" + (f" ({self.detail})" if self.detail else "")


class _ValidationError(WireError):
    """A WireError of a record that parsed but failed validation; the bad value is looked up in the record text
    (parsed again) only when asked for."""

    def __init__(self, reason: str, steps: tuple[str | int, ...], path: str, text: str, detail: str) -> None:
        super().__init__(reason, str(steps[0]) if steps else None, None, path or None, detail)
        self._steps, self._text, self._looked_up = steps, text, not text

    @property
    def value(self) -> Any:
        if not self._looked_up:
            self._looked_up = True
            try:
                self._value = lookup(json.loads(self._text), list(self._steps))
            except (LookupError, TypeError, ValueError, RecursionError):
                self._value = None
        return self._value


def record_text(data: bytes) -> str:
    """The text of a serialized std_msgs/String (CDR: a 4-byte encapsulation header, whose second byte is 1 for
    little endian; a uint32 length that counts the closing NUL; the UTF-8 bytes; the NUL).

    Raises:
        WireError: reason "encoding", for a payload that is not a String or text that is not UTF-8.
    """
    if len(data) < 9 or data[0] != 0 or data[1] > 1:
        raise WireError("encoding", None, bytes(data[:16]), None, "not a serialized std_msgs/String")
    n = int.from_bytes(data[4:8], "little" if data[1] == 1 else "big")
    if n < 1 or 8 + n > len(data) or data[7 + n] != 0:
        raise WireError("encoding", None, n, None, f"string length beyond the {len(data)}-byte payload")
    try:
        return data[8 : 7 + n].decode("utf-8")
    except UnicodeDecodeError as e:
        raise WireError("encoding", None, bytes(data[8 + e.start : 8 + e.end]), None, "not UTF-8") from None


def bound(b: Bound, lim: Mapping[str, int] | None) -> int:
    """The number of bound `b` under the limits `lim` (static limits for names it leaves out, or without it)."""
    if isinstance(b, int):
        return b
    if lim is not None and b in lim:
        return lim[b]
    return STATIC_LIMITS[b]


def _int(lo: int, hi: int) -> Any:
    return Annotated[int, msgspec.Meta(ge=lo, le=hi)]


def _number(lo: float, hi: float) -> Any:
    """A JSON number in [lo, hi]: an int stays an int, a float a float (NaN and infinities fail the bounds)."""
    return Union[_int(math.ceil(lo), math.floor(hi)), Annotated[float, msgspec.Meta(ge=lo, le=hi)]]  # noqa: UP007


def _sized(item: Any, length: Bound | None, max_len: Bound, lim: Mapping[str, int] | None) -> Any:
    if length is not None:
        n = bound(length, lim)
        return Annotated[list[item], msgspec.Meta(min_length=n, max_length=n)]
    return Annotated[list[item], msgspec.Meta(max_length=bound(max_len, lim))]


class Field:
    """One field's type and range, declared; `annotation` says it to msgspec."""

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """The msgspec type (with constraints) of this field under the limits `lim`."""
        raise NotImplementedError


@dataclass(frozen=True)
class Int(Field):
    """An integer (not a boolean) in [lo, hi]."""

    lo: Bound
    hi: Bound

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return _int(bound(self.lo, lim), bound(self.hi, lim))


@dataclass(frozen=True)
class Float(Field):
    """A finite number in [lo, hi] (both finite, so NaN and infinities never pass)."""

    lo: float
    hi: float

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return _number(self.lo, self.hi)


@dataclass(frozen=True)
class Bool(Field):
    """true or false."""

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return bool


@dataclass(frozen=True)
class Text(Field):
    """A string of at most max_len characters, matching pattern (the whole string) when given."""

    max_len: int
    pattern: str | None = None

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        whole = None if self.pattern is None else rf"\A(?:{self.pattern})\Z"  # msgspec searches; match all of it
        return Annotated[str, msgspec.Meta(max_length=self.max_len, pattern=whole)]


@dataclass(frozen=True)
class OneOf(Field):
    """One of a fixed set of strings."""

    values: tuple[str, ...]

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return Literal[self.values]


@dataclass(frozen=True)
class IntList(Field):
    """A list of integers in [lo, hi], of exactly `length` (or at most `max_len`) entries, distinct if unique."""

    lo: Bound
    hi: Bound
    length: Bound | None = None
    max_len: Bound = 4096
    unique: bool = False

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation (`unique` is checked by `decode` after msgspec)."""
        return _sized(_int(bound(self.lo, lim), bound(self.hi, lim)), self.length, self.max_len, lim)


@dataclass(frozen=True)
class FloatList(Field):
    """A list of finite numbers in [lo, hi], of exactly `length` (or at most `max_len`) entries."""

    lo: float
    hi: float
    length: Bound | None = None
    max_len: Bound = 65_536

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return _sized(_number(self.lo, self.hi), self.length, self.max_len, lim)


@dataclass(frozen=True)
class BoolList(Field):
    """A list of booleans of exactly `length` entries."""

    length: Bound

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return _sized(bool, self.length, self.length, lim)


@dataclass(frozen=True)
class Rows(Field):
    """A list of 1 to `max_rows` rows (one per episode of a batch), each row a value of `item`."""

    item: Field
    max_rows: Bound = "batch"

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        item = self.item.annotation(lim)
        return Annotated[list[item], msgspec.Meta(min_length=1, max_length=bound(self.max_rows, lim))]  # type: ignore[valid-type]


@dataclass(frozen=True)
class Array(Field):
    """Numbers in binary, one row per episode of a batch: the JSON object `{"shape": [rows, *dims], "dtype": ...,
    "data": "<base64>"}`, the array's bytes in C order (`pack` writes it). Accepted when `dtype` is exactly the
    declared one (numpy's notation with its byte order: "<f4", "<f8", "<i2", "|b1"), `shape` has 1..max_rows rows
    and then exactly `dims`, `data` is valid base64 of exactly prod(shape) x itemsize bytes, and every value is in
    [lo, hi] (finite bounds: NaN and infinities never pass; "|b1" bytes are 0 or 1). Decoded into a read-only numpy
    array of that dtype and shape."""

    dtype: str
    lo: float | str
    hi: float | str
    dims: tuple[Bound, ...] = ()
    max_rows: Bound = "batch"

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation: the header and the bytes (their length is checked by `decode`, against the
        shape)."""
        rows = bound(self.max_rows, lim)
        dims = [bound(d, lim) for d in self.dims]
        shape = tuple.__class_getitem__((_int(1, rows), *[_int(n, n) for n in dims]))
        most = rows * math.prod(dims) * np.dtype(self.dtype).itemsize
        spec = [
            ("shape", shape),
            ("dtype", Literal[self.dtype]),
            ("data", Annotated[bytes, msgspec.Meta(max_length=most)]),
        ]
        return msgspec.defstruct("Array", spec, forbid_unknown_fields=True, module=__name__)

    def value_range(self, lim: Mapping[str, int] | None) -> tuple[float, float]:
        """[lo, hi] of the values under the limits `lim`."""
        lo, hi = (float(bound(b, lim)) if isinstance(b, str) else float(b) for b in (self.lo, self.hi))
        return lo, hi

    def pack(self, value: Any) -> dict[str, Any]:
        """The JSON object of `value` (an array-like, cast to `dtype`); msgspec writes its bytes as base64."""
        a = np.ascontiguousarray(value, dtype=self.dtype)
        return {"shape": a.shape, "dtype": self.dtype, "data": a.data.cast("B")}


@dataclass(frozen=True)
class Object(Field):
    """A JSON object whose content the receiver validates (a scenario, learner settings)."""

    max_items: int = 256

    def annotation(self, lim: Mapping[str, int] | None) -> Any:
        """See Field.annotation."""
        return Annotated[dict[str, Any], msgspec.Meta(max_length=self.max_items)]


@dataclass(frozen=True)
class Schema:
    """A record schema: name, version, fields (all required, no others) and the largest accepted text."""

    name: str
    version: int
    fields: dict[str, Field]
    max_bytes: int = DEFAULT_MAX_BYTES
    doc: str = ""
    _decoders: dict[Any, _Compiled] = field(default_factory=dict, compare=False, repr=False)

    def struct(self, lim: Mapping[str, int] | None = None) -> type[msgspec.Struct]:
        """The msgspec Struct of a record under the limits `lim`: "schema" and "v" (their one value), every field
        with its constraints, then an optional "sig" (checked by the Signer, else ignored); nothing else."""
        spec: list[tuple[str, Any] | tuple[str, Any, Any]] = [
            ("schema", Literal[self.name]),
            ("v", Literal[self.version]),
        ]
        spec += [(key, fld.annotation(lim)) for key, fld in self.fields.items()]
        spec.append(("sig", Any, None))
        title = "".join(part.title() for part in self.name.removeprefix("htlm/").split("_"))
        return msgspec.defstruct(title, spec, forbid_unknown_fields=True, module=__name__)

    @functools.cached_property
    def bound(self) -> bool:
        """Whether a record of this schema is bound to its run: it carries the run id (`run`, filled in by `encode`
        from the signer's run), and a receiver that follows a run rejects a record of another (`other_run`). The
        run announcement itself is judged by `htlm_msgs_py.run_control.RunControl` instead."""
        return "run" in self.fields and self.name != "htlm/scenario"

    @functools.cached_property
    def unique(self) -> tuple[str, ...]:
        """The fields whose entries must be distinct (msgspec has no such constraint)."""
        return tuple(k for k, f in self.fields.items() if isinstance(f, IntList) and f.unique)

    @functools.cached_property
    def arrays(self) -> tuple[tuple[str, Array], ...]:
        """The binary array fields (name, declaration)."""
        return tuple((k, f) for k, f in self.fields.items() if isinstance(f, Array))

    def compiled(self, lim: Mapping[str, int] | None = None) -> _Compiled:
        """The msgspec JSON decoder of `struct(lim)` and the value checks of the binary arrays, made once per schema
        and set of limits."""
        key = None if lim is None else tuple(lim.items())
        out = self._decoders.get(key)
        if out is None:
            if len(self._decoders) >= 64:  # many scenarios in one process (tests): start over
                self._decoders.clear()
            arrays = tuple(_ArrayCheck(k, np.dtype(f.dtype), *f.value_range(lim)) for k, f in self.arrays)
            out = self._decoders[key] = _Compiled(msgspec.json.Decoder(self.struct(lim)), arrays)
        return out


class _ArrayCheck(NamedTuple):
    """What `decode` checks of one binary array after msgspec: its field, dtype and value range."""

    key: str
    dtype: np.dtype[Any]
    lo: float
    hi: float


class _Compiled(NamedTuple):
    """A schema under one set of limits: the msgspec decoder and the checks of its binary arrays."""

    decoder: msgspec.json.Decoder[Any]
    arrays: tuple[_ArrayCheck, ...]


# ----- the records ------------------------------------------------------------------------------------------------

_RUN = Text(64, r"[A-Za-z0-9_.:-]+")
"""A run id: unique per run (`htlm launch` makes one from the run directory's name and a random part)."""
_AGENT = Int(0, "agent")
_EPISODE = Int(0, EPISODE_MAX)
_HEX16 = Text(32, r"[0-9a-f]{16}")
_KNOWLEDGE_ROWS = Array("<f4", -1e6, 1e6, ("knowledge",))
_BATCH_SIZE = Int(1, "batch")


SCENARIO = Schema(
    "htlm/scenario",
    5,
    {
        "run": _RUN,
        "nonce": _HEX16,
        "seq": Int(0, SEQ_MAX),
        "seed": Int(0, 2**63 - 1),
        "mode": OneOf(("train", "evaluate", "deploy")),
        "clock": OneOf(("lockstep", "free")),
        "period": Float(0.0, 3600.0),
        "epoch": Float(0.0, 1e11),
        "operation": OneOf(("simulated", "external")),
        "first_episode": _EPISODE,
        "episodes": Int(0, EPISODE_MAX),
        "batch": Int(1, STATIC_LIMITS["batch"]),
        "trainer_lag": Int(0, 1000),
        "state": OneOf(("running", "stopped")),
        "layout": Text(64, r"[0-9a-f]+"),
        "scenario": Object(),
    },
    max_bytes=256 * 1024,
    doc="The run: its id, the nonce of the world process announcing it (new at every start) and a sequence number "
    "that only grows over the run (also across restarts of the world), the scenario (Scenario.to_dict: its kinds "
    "of task by name with their dynamics, its sites with their tasks, its agents with their capabilities), its layout "
    "hash, master seed, mode, clock and its period, "
    "the epoch (external operation: the wall-clock instant, Unix seconds, of the run's first step, from which every "
    "process keeps the step clock itself; 0 until the world fixed it), "
    "operation (simulated by the world, or external: observations come from the robots), episode range and batch "
    "size B (episodes run at once); `state` turns to stopped when the world ends the run.",
)
STEP = Schema(
    "htlm/step",
    3,
    {
        "run": _RUN,
        "episode": _EPISODE,
        "size": _BATCH_SIZE,
        "step": Int(0, "step"),
        "phase": OneOf(("begin", "step", "end")),
        "acted": IntList(0, "agent", max_len="agents", unique=True),
    },
    doc="The batch of `size` episodes from `episode` on. begin (step 0): reset for the batch and answer with the "
    "actions of step 1 (repeated until every agent answered); step (1..h): step t was applied with the actions of "
    "the agents in `acted`; end (step h): the batch is over.",
)
ACTION = Schema(
    "htlm/action",
    4,
    {
        "run": _RUN,
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "actions": Rows(Int(0, "action")),
        "before": IntList(-1, "action", max_len="step"),
    },
    doc="The agent's assignments for step t in every episode of the batch, indices into G-bar; sent after its "
    "update of step t - 1 (so they also tell the world the agent is ready). `before`: in a deployed team (the "
    "agents' own clock, batch 1), the agent's assignments of steps 1..t-1 of the episode, -1 where it did not act "
    "(an observer that was down rebuilds the steps it missed from them); empty under the lockstep clock.",
)
OBSERVATION = Schema(
    "htlm/observation",
    3,
    {
        "run": _RUN,
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "tasks": Rows(Int(-1, "task")),
        "levels": Rows(Int(-1, "level")),
        "acted": IntList(0, "agent", max_len="agents", unique=True),
    },
    doc="Per episode of the batch, the agent's task and its observed level after the transition (-1 and -1 when "
    "idle or absent); `acted` lists the agents whose actions the world applied this step.",
)
BROADCAST = Schema(
    "htlm/broadcast",
    4,
    {
        "run": _RUN,
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "actions": Rows(Int(0, "action")),
        "levels": Rows(Int(-1, "level")),
        "sent": Float(0.0, 1e11),
    },
    doc="Per episode of the batch, the sender's assignment and its observation after the sender's (simulated) "
    "channel, -1 when idle; `sent`, the sender's wall clock when it sent the record (Unix seconds), from which "
    "its teammates measure how far its clock is from theirs.",
)
READY = Schema(
    "htlm/ready",
    2,
    {"run": _RUN, "agent": _AGENT, "episode": _EPISODE, "step": Int(0, "step")},
    doc="The agent finished its update of the last step t = h of the episode.",
)
TRANSITION = Schema(
    "htlm/transition",
    4,
    {
        "run": _RUN,
        "agent": _AGENT,
        "session": _HEX16,
        "seq": Int(0, SEQ_MAX),
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "k": _KNOWLEDGE_ROWS,
        "a": Array("<i2", 0, "action"),
        "r": Array("<f8", -1e6, 1e6),
        "k2": _KNOWLEDGE_ROWS,
        "mask2": Array("|b1", 0, 1, ("actions",)),
        "done": Bool(),
    },
    max_bytes=16 * 1024 * 1024,
    doc="The agent's transitions of step t in every episode of the batch (K, a, r, K', A-hat(a) as a mask; done "
    "when t = h), one row per episode, in binary; `seq` counts the sender's session's records from 0. K and K' "
    "are float32, the precision of the learner's replay memories (the in-process learner rounds them the same "
    "way); rewards float64, as the learner sums them into n-step returns.",
)
TRANSITION_ACK = Schema(
    "htlm/transition_ack",
    2,
    {"run": _RUN, "agent": _AGENT, "session": _HEX16, "upto": Int(-1, SEQ_MAX)},
    doc="Every transition of this agent session with seq <= upto is on disk (fsynced) in the trainer's store.",
)
WEIGHTS = Schema(
    "htlm/weights",
    3,
    {
        "run": _RUN,
        "agent": _AGENT,
        "version": Int(0, SEQ_MAX),
        "episode": Int(-1, EPISODE_MAX),
        "trained": Int(0, SEQ_MAX),
        "every": Int(1, SEQ_MAX),
        "encoding": OneOf(("base64",)),
        "data": Text(16 * 1024 * 1024),
        "sha256": Text(64, r"[0-9a-f]{64}"),
        "settings": Object(),
    },
    max_bytes=16 * 1024 * 1024 + 64 * 1024,
    doc="The agent's Q-network weights (AgentQ.get_weights bytes, base64) and the learner settings "
    "(for the exploration schedule); `episode` is the last episode the trainer had seen, `trained` the global "
    "step index up to which (excluded) the trainer had done its updates when it took them, `every` the cadence W "
    "(weights are taken whenever trained - g0 is a multiple of W, g0 the run's first step).",
)
TRAINER_PROGRESS = Schema(
    "htlm/trainer_progress",
    2,
    {"run": _RUN, "trained": Int(0, SEQ_MAX), "updates": Int(0, SEQ_MAX), "finished": Bool()},
    doc="The trainer has done the gradient updates of every step whose global index (batch index x h + t - 1) is "
    "below `trained`; the world paces its steps by it. `finished`: the learner needs no more of the run (the "
    "expert-iteration learner's rounds are over): the world ends it after the batch in progress, or before the one "
    "it is beginning. Sent again (a heartbeat) while the trainer works on a round of its own.",
)


class Arrival(StrEnum):
    """Whether an agent's robot has reached the site of its assignment (`BELIEF`'s `arrived`)."""

    YES = "yes"
    """Within the arrival radius of the site."""
    NO = "no"
    """On its way: farther than the radius."""
    UNKNOWN = "unknown"
    """No pose topic, no pose yet, or no assignment yet."""


BELIEF = Schema(
    "htlm/belief",
    4,
    {
        "run": _RUN,
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(0, "step"),
        "marginals": FloatList(-1e-6, 1.000001, length="marginals"),
        "confident": IntList(0, "level", length="tasks"),
        "arrived": OneOf(tuple(a.value for a in Arrival)),
        "distance": Float(-1.0, 1e9),
    },
    doc="Per-task marginals of the agent's belief (p x L, row-major) and the confident level of every task, in one "
    "episode of the batch (`episode`, the agent's belief_episode parameter); whether its robot has reached the site "
    "of its assignment and how far it is, metres (unknown and -1 without a pose topic).",
)
GROUND_TRUTH = Schema(
    "htlm/ground_truth",
    4,
    {
        "run": _RUN,
        "episode": _EPISODE,
        "step": Int(0, "step"),
        "levels": Rows(IntList(0, "level", length="tasks")),
        "actions": Rows(IntList(-1, "action", length="agents")),
        "events": Rows(IntList(0, 1023, max_len=1024)),
    },
    max_bytes=4 * 1024 * 1024,
    doc="Per episode of the batch from `episode` on, the true levels after step t, the joint assignment the world "
    "applied and the scenario's events that happened in step t (indices into the announced scenario's `events`; "
    "monitoring only).",
)
EPISODE_METRICS = Schema(
    "htlm/episode_metrics",
    2,
    {
        "run": _RUN,
        "episode": _EPISODE,
        "severity": OneOf(("simulated", "reported", "unknown")),
        "completion": Int(-1, "step"),
        "failed": Bool(),
        "unused_capability": Float(-1.0, 1e6),
        "unused_fraction": Float(-1.0, 1e6),
        "idle_before": Int(-1, EPISODE_MAX),
        "reassign_before": Int(-1, EPISODE_MAX),
        "absent": IntList(0, "step", length="agents"),
        "seconds": Float(0.0, 1e9),
    },
    doc="Metrics of docs/model.md for one episode; `absent` counts the steps each agent missed (treated as idle). "
    "`severity` says where the true levels came from: the world's simulation, an outside source (external "
    "operation), or nowhere: then completion, failed, unused and the counts before completion are unknown (-1, "
    "false).",
)
SEVERITY = Schema(
    "htlm/severity",
    2,
    {"run": _RUN, "episode": _EPISODE, "step": Int(0, "step"), "levels": Rows(IntList(0, "level", length="tasks"))},
    doc="External operation: the true levels of every task after step t (an outside source, e.g. the simulated "
    "operation of the robot stand-ins, or a human operator's report); the world logs them and computes the metrics.",
)

GOAL = Schema(
    "htlm/goal",
    1,
    {
        "run": _RUN,
        "agent": _AGENT,
        "x": Float(-1e7, 1e7),
        "y": Float(-1e7, 1e7),
        "frame": Text(64, r"[A-Za-z0-9_/]+"),
        "sent": Float(0.0, 1e11),
    },
    doc="The goal the agent's robot drives to (the site of its assignment, metres in `frame`): the signed twin of the "
    "agent's geometry_msgs/PoseStamped goal pose, sent beside it whenever the site changes; `sent`, the agent's wall "
    "clock when it sent it (Unix seconds): a robot takes a goal only if it is newer than the last one it took.",
)

SCHEMAS: dict[str, Schema] = {
    s.name: s
    for s in (
        SCENARIO,
        STEP,
        ACTION,
        OBSERVATION,
        BROADCAST,
        READY,
        TRANSITION,
        TRANSITION_ACK,
        WEIGHTS,
        TRAINER_PROGRESS,
        BELIEF,
        GROUND_TRUTH,
        EPISODE_METRICS,
        SEVERITY,
        GOAL,
    )
}


# ----- encode / decode --------------------------------------------------------------------------------------------

_ENCODER = msgspec.json.Encoder()
_asdict = msgspec.structs.asdict


def encode(schema: Schema, fields: Mapping[str, Any], signer: Signer | None = None) -> str:
    """The record text of `fields` under `schema` (signed when the signer has a key).

    The sender is trusted: values are not validated here (tests check round trips), only JSON-encoded, by msgspec
    (compact, shortest round-trip floats, about 10x faster than the standard library's encoder on the arrays of a
    batch). A NaN or an infinity is written as null, which every receiver rejects; a value JSON cannot hold raises
    ValueError. A record bound to its run (`Schema.bound`) gets the signer's run unless `fields` give one. The
    value of an `Array` field is any array-like, cast to the field's dtype (`Array.pack`: a float64
    array to "<f4" rounds to nearest) and written in binary, NaN and infinities included (receivers reject them).
    """
    body_fields: Mapping[str, Any] = fields
    if schema.bound and "run" not in fields:
        run = signer.run if signer is not None else None
        if run is None:
            raise ValueError(f"{schema.name}: cannot encode: no run (the record is bound to its run)")
        body_fields = {"run": run, **fields}
    try:
        if schema.arrays:
            body_fields = {**body_fields, **{k: f.pack(fields[k]) for k, f in schema.arrays}}
        body = _ENCODER.encode({"schema": schema.name, "v": schema.version, **body_fields}).decode()
    except (TypeError, ValueError, msgspec.EncodeError) as e:
        raise ValueError(f"{schema.name}: cannot encode: {e}") from None
    return signer.sign(body) if signer is not None else body


def _fields(schema: Schema, rec: msgspec.Struct, arrays: tuple[_ArrayCheck, ...]) -> dict[str, Any]:
    out = _asdict(rec)
    del out["schema"], out["v"], out["sig"]
    for key in schema.unique:
        if len(set(out[key])) != len(out[key]):
            raise WireError("range", key, out[key], detail="entries must be distinct")
    for check in arrays:
        out[check.key] = _array(check, out[check.key])
    return out


def _array(check: _ArrayCheck, v: Any) -> NDArray[Any]:
    """The numpy array of a binary array `v` whose header msgspec has validated: its bytes must fill its shape,
    its values lie in [lo, hi] (NaN fails both comparisons; bools are read as their bytes, 0 or 1)."""
    key, dt = check.key, check.dtype
    want = math.prod(v.shape) * dt.itemsize
    if len(v.data) != want:
        raise WireError(
            "length", key, len(v.data), f"{key}.data", f"bytes, expected {want} for shape {list(v.shape)} of {v.dtype}"
        )
    a = np.frombuffer(v.data, dt).reshape(v.shape)
    x = a.view(np.uint8) if dt.kind == "b" else a
    if not (x.min() >= check.lo and x.max() <= check.hi):
        where = np.unravel_index(int(np.argmax(~((x >= check.lo) & (x <= check.hi)))), x.shape)
        path = f"{key}[{', '.join(str(int(i)) for i in where)}]"
        raise WireError("range", key, x[where].item(), path, f"expected values in [{check.lo:g}, {check.hi:g}]")
    return a


def _reason(steps: list[str | int], problem: str, name: str | None) -> str:
    """The counter code of a msgspec validation problem at path `steps`."""
    if not steps:
        return "not_object"
    if name is not None:
        if problem.startswith("Object contains unknown"):
            return "unknown_field"
        return {"schema": "schema", "v": "version"}.get(name, "missing_field")
    if steps[0] == "schema":
        return "schema"
    if steps[0] == "v":
        return "version"
    part = steps[1] if len(steps) > 1 else None  # inside a binary array: "shape", "dtype" or "data"
    if part == "dtype":
        return "type"
    if part == "data" and "base64" in problem:
        return "encoding"
    if part == "shape" and ", got `" not in problem:
        return "length"
    if ", got `" in problem:
        return "type"
    if " of length " in problem:
        return "length"
    return "range"


@functools.lru_cache(maxsize=512)
def _problem(message: str) -> tuple[str, tuple[str | int, ...], str, str, bool]:
    """(reason, path steps, path text, detail, whether the value exists) of a msgspec ValidationError message;
    cached, as a flood of bad records repeats the same few messages."""
    steps, problem, name = parse_error(message)
    detail = problem[:1].lower() + problem[1:]
    has_value = not problem.startswith("Object missing")  # a missing field has no value
    return _reason(steps, problem, name), tuple(steps), join_path(steps), detail, has_value


def _wire_error(message: str, text: str) -> WireError:
    """The WireError of a msgspec ValidationError message about the record `text`."""
    reason, steps, path, detail, has_value = _problem(message)
    return _ValidationError(reason, steps, path, text if has_value else "", detail)


def decode(
    text: Any, schema: Schema, lim: Mapping[str, int] | None = None, signer: Signer | None = None
) -> dict[str, Any]:
    """Parse and validate a received record text; returns its fields (without "schema", "v", "sig").

    Raises:
        WireError: naming the field and the bad value; `.reason` is one of size, signature, json, not_object,
            schema, version, missing_field, unknown_field, type, range, length, encoding (a binary array's data
            that is not base64), other_run (a record bound to another run than the signer's, `Schema.bound`).
            For a binary array, type is a wrong dtype, length a shape beyond the limits or bytes that do not fill
            the shape, range a value out of range (NaN, infinity).
    """
    if type(text) is not str:
        raise WireError("type", None, type(text).__name__)
    if len(text) > schema.max_bytes:
        raise WireError("size", None, f"{len(text)} characters > {schema.max_bytes}")
    if signer is not None and signer.enabled:
        text, problem = signer.verify(text)
        if problem is not None:
            raise WireError("signature", "sig", problem)
    compiled = schema.compiled(lim)
    try:
        rec = compiled.decoder.decode(text)
    except msgspec.ValidationError as e:
        raise _wire_error(str(e), text) from None
    except (msgspec.DecodeError, UnicodeError, RecursionError) as e:
        raise WireError("json", None, str(e)) from None
    if schema.bound and signer is not None and signer.run is not None and rec.run != signer.run:
        raise WireError("other_run", "run", rec.run, detail=f"this node follows run {signer.run}")
    return _fields(schema, rec, compiled.arrays)
