"""Record schemas of the HTLM wire contract: encode to and decode from the JSON text of a std_msgs/String.

Every structured record is one JSON object `{"schema": "htlm/<name>", "v": <version>, ...fields}` (plus `"sig"`
when a team key is set, see `htlm_msgs_py.signing`), so `ros2 topic echo` prints it readably. `decode` accepts a
record only if everything about it is as the schema says: size, JSON syntax, schema name, version, the exact set
of fields, each field's type and range. Ranges that depend on the scenario (agent index, action index, level,
step, vector lengths) are named bounds resolved against `Limits` of the running scenario; before a scenario is
known, generous static limits apply. Anything else raises `WireError`, which names the field and the value.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .signing import Signer

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
}
"""Limits used before the scenario is known (and for names a Limits mapping leaves out)."""


def limits(n_agents: int, n_tasks: int, n_actions: int, levels: int, horizon: int) -> dict[str, int]:
    """The named bounds of one scenario (N agents, p tasks, |G-bar| actions, L levels, horizon h)."""
    return {
        "agent": n_agents - 1,
        "action": n_actions - 1,
        "task": n_tasks - 1,
        "level": levels - 1,
        "step": horizon,
        "agents": n_agents,
        "tasks": n_tasks,
        "actions": n_actions,
        "knowledge": n_tasks * levels + n_actions,
        "marginals": n_tasks * levels,
    }


class WireError(ValueError):
    """A received record that does not follow its schema. `reason` is a short code for counters."""

    def __init__(self, reason: str, where: str | None, value: Any) -> None:
        """Create the error; `where` names the field (None for the whole record), `value` is the bad value."""
        self.reason = reason
        self.where = where
        self.value = value
        shown = repr(value)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        place = f"field {where!r}" if where else "record"
        super().__init__(f"{place}: {reason}: {shown}")


def _bound(b: Bound, lim: Mapping[str, int] | None) -> int:
    if isinstance(b, int):
        return b
    if lim is not None and b in lim:
        return lim[b]
    return STATIC_LIMITS[b]


class Field:
    """One field's type and range."""

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """Raise WireError unless v is a valid value of this field."""
        raise NotImplementedError

    def describe(self) -> str:
        """Human-readable type, for the README."""
        raise NotImplementedError


@dataclass(frozen=True)
class Int(Field):
    """An integer (not a boolean) in [lo, hi]."""

    lo: Bound
    hi: Bound

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        if type(v) is not int:
            raise WireError("type", name, v)
        if not _bound(self.lo, lim) <= v <= _bound(self.hi, lim):
            raise WireError("range", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return f"int {self.lo}..{self.hi}"


@dataclass(frozen=True)
class Float(Field):
    """A finite number in [lo, hi] (both finite, so NaN and infinities never pass)."""

    lo: float
    hi: float

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        t = type(v)
        if t is not float and t is not int:
            raise WireError("type", name, v)
        if not self.lo <= v <= self.hi:
            raise WireError("range", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return f"float {self.lo:g}..{self.hi:g}"


@dataclass(frozen=True)
class Bool(Field):
    """true or false."""

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        if type(v) is not bool:
            raise WireError("type", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return "bool"


@dataclass(frozen=True)
class Text(Field):
    """A string of at most max_len characters, matching pattern when given."""

    max_len: int
    pattern: str | None = None
    _re: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        """Compile the pattern once."""
        if self.pattern is not None:
            object.__setattr__(self, "_re", re.compile(self.pattern))

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        if type(v) is not str:
            raise WireError("type", name, v)
        if len(v) > self.max_len:
            raise WireError("length", name, v)
        if self._re is not None and self._re.fullmatch(v) is None:
            raise WireError("range", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return f"string (<= {self.max_len} chars{', ' + self.pattern if self.pattern else ''})"


@dataclass(frozen=True)
class OneOf(Field):
    """One of a fixed set of strings."""

    values: tuple[str, ...]

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        if type(v) is not str:
            raise WireError("type", name, v)
        if v not in self.values:
            raise WireError("range", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return " | ".join(f'"{v}"' for v in self.values)


def _check_len(name: str, v: Any, length: Bound | None, max_len: Bound, lim: Mapping[str, int] | None) -> None:
    if type(v) is not list:
        raise WireError("type", name, v)
    n = len(v)
    if length is not None:
        if n != _bound(length, lim):
            raise WireError("length", name, v)
    elif n > _bound(max_len, lim):
        raise WireError("length", name, v)


@dataclass(frozen=True)
class IntList(Field):
    """A list of integers in [lo, hi], of exactly `length` (or at most `max_len`) entries, distinct if unique."""

    lo: Bound
    hi: Bound
    length: Bound | None = None
    max_len: Bound = 4096
    unique: bool = False

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        _check_len(name, v, self.length, self.max_len, lim)
        lo, hi = _bound(self.lo, lim), _bound(self.hi, lim)
        for x in v:
            if type(x) is not int:
                raise WireError("type", name, x)
            if not lo <= x <= hi:
                raise WireError("range", name, x)
        if self.unique and len(set(v)) != len(v):
            raise WireError("range", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        n = f"[{self.length}]" if self.length is not None else f"[<= {self.max_len}]"
        return f"int {self.lo}..{self.hi} list{n}{' (distinct)' if self.unique else ''}"


@dataclass(frozen=True)
class FloatList(Field):
    """A list of finite numbers in [lo, hi], of exactly `length` (or at most `max_len`) entries."""

    lo: float
    hi: float
    length: Bound | None = None
    max_len: Bound = 65_536

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        _check_len(name, v, self.length, self.max_len, lim)
        lo, hi = self.lo, self.hi
        for x in v:
            t = type(x)
            if t is not float and t is not int:
                raise WireError("type", name, x)
            if not lo <= x <= hi:
                raise WireError("range", name, x)

    def describe(self) -> str:
        """See Field.describe."""
        n = f"[{self.length}]" if self.length is not None else f"[<= {self.max_len}]"
        return f"float {self.lo:g}..{self.hi:g} list{n}"


@dataclass(frozen=True)
class BoolList(Field):
    """A list of booleans of exactly `length` entries."""

    length: Bound

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        _check_len(name, v, self.length, self.length, lim)
        for x in v:
            if type(x) is not bool:
                raise WireError("type", name, x)

    def describe(self) -> str:
        """See Field.describe."""
        return f"bool list[{self.length}]"


@dataclass(frozen=True)
class Object(Field):
    """A JSON object whose content the receiver validates (a scenario, learner settings)."""

    max_items: int = 256

    def check(self, name: str, v: Any, lim: Mapping[str, int] | None) -> None:
        """See Field.check."""
        if type(v) is not dict:
            raise WireError("type", name, v)
        if len(v) > self.max_items:
            raise WireError("length", name, v)

    def describe(self) -> str:
        """See Field.describe."""
        return "object"


@dataclass(frozen=True)
class Schema:
    """A record schema: name, version, fields (all required, no others) and the largest accepted text."""

    name: str
    version: int
    fields: dict[str, Field]
    max_bytes: int = DEFAULT_MAX_BYTES
    doc: str = ""


# ----- the records ------------------------------------------------------------------------------------------------

_AGENT = Int(0, "agent")
_EPISODE = Int(0, EPISODE_MAX)
_HEX16 = Text(32, r"[0-9a-f]{16}")
_KNOWLEDGE = FloatList(-1e6, 1e6, length="knowledge")

SCENARIO = Schema(
    "htlm/scenario",
    1,
    {
        "run": Text(64, r"[A-Za-z0-9_.:-]+"),
        "seed": Int(0, 2**63 - 1),
        "mode": OneOf(("train", "evaluate", "deploy")),
        "clock": OneOf(("lockstep", "free")),
        "first_episode": _EPISODE,
        "episodes": Int(0, EPISODE_MAX),
        "state": OneOf(("running", "stopped")),
        "layout": Text(64, r"[0-9a-f]+"),
        "scenario": Object(),
    },
    max_bytes=256 * 1024,
    doc="The run: the scenario (Scenario.to_dict), its layout hash, master seed, mode and episode range; "
    "`state` turns to stopped when the world ends the run.",
)
STEP = Schema(
    "htlm/step",
    1,
    {"episode": _EPISODE, "step": Int(0, "step"), "phase": OneOf(("begin", "end"))},
    doc="begin (step 0): reset for the episode and answer with the action of step 1 (repeated until every agent "
    "answered); end (step h): the episode is over.",
)
ACTION = Schema(
    "htlm/action",
    1,
    {"agent": _AGENT, "episode": _EPISODE, "step": Int(1, "step"), "action": Int(0, "action")},
    doc="The agent's assignment for step t, an index into G-bar; sent after its update of step t - 1 (so it also "
    "tells the world the agent is ready).",
)
OBSERVATION = Schema(
    "htlm/observation",
    1,
    {
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "task": Int(-1, "task"),
        "level": Int(-1, "level"),
        "acted": IntList(0, "agent", max_len="agents", unique=True),
    },
    doc="Observed level of the agent's task after the transition (-1 and task -1 when idle or absent); `acted` "
    "lists the agents whose action the world applied this step.",
)
BROADCAST = Schema(
    "htlm/broadcast",
    1,
    {
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "action": Int(0, "action"),
        "level": Int(-1, "level"),
    },
    doc="The sender's assignment and its observation after the sender's (simulated) channel, -1 when idle.",
)
READY = Schema(
    "htlm/ready",
    1,
    {"agent": _AGENT, "episode": _EPISODE, "step": Int(0, "step")},
    doc="The agent finished its update of the last step t = h of the episode.",
)
TRANSITION = Schema(
    "htlm/transition",
    1,
    {
        "agent": _AGENT,
        "session": _HEX16,
        "seq": Int(0, SEQ_MAX),
        "episode": _EPISODE,
        "step": Int(1, "step"),
        "k": _KNOWLEDGE,
        "a": Int(0, "action"),
        "r": Float(-1e6, 1e6),
        "k2": _KNOWLEDGE,
        "mask2": BoolList("actions"),
        "done": Bool(),
    },
    doc="One transition (K, a, r, K', A-hat(a) as a mask, done); `seq` counts the sender's session from 0.",
)
TRANSITION_ACK = Schema(
    "htlm/transition_ack",
    1,
    {"agent": _AGENT, "session": _HEX16, "upto": Int(-1, SEQ_MAX)},
    doc="Every transition of this agent session with seq <= upto is on disk (fsynced) in the trainer's store.",
)
WEIGHTS = Schema(
    "htlm/weights",
    1,
    {
        "agent": _AGENT,
        "version": Int(0, SEQ_MAX),
        "episode": Int(-1, EPISODE_MAX),
        "encoding": OneOf(("base64",)),
        "data": Text(16 * 1024 * 1024),
        "sha256": Text(64, r"[0-9a-f]{64}"),
        "settings": Object(),
    },
    max_bytes=16 * 1024 * 1024 + 64 * 1024,
    doc="The agent's Q-network weights (AgentQ.get_weights bytes, base64) and the learner settings "
    "(for the exploration schedule); `episode` is the last episode the trainer had seen.",
)
BELIEF = Schema(
    "htlm/belief",
    1,
    {
        "agent": _AGENT,
        "episode": _EPISODE,
        "step": Int(0, "step"),
        "marginals": FloatList(-1e-6, 1.000001, length="marginals"),
        "confident": IntList(0, "level", length="tasks"),
    },
    doc="Per-task marginals of the agent's belief (p x L, row-major) and the confident level of every task.",
)
GROUND_TRUTH = Schema(
    "htlm/ground_truth",
    1,
    {
        "episode": _EPISODE,
        "step": Int(0, "step"),
        "levels": IntList(0, "level", length="tasks"),
        "actions": IntList(-1, "action", length="agents"),
    },
    doc="True levels after step t and the joint assignment the world applied (monitoring only).",
)
EPISODE_METRICS = Schema(
    "htlm/episode_metrics",
    1,
    {
        "episode": _EPISODE,
        "completion": Int(0, "step"),
        "failed": Bool(),
        "unused_capability": Float(0.0, 1e6),
        "unused_fraction": Float(0.0, 1e6),
        "idle_before": Int(0, EPISODE_MAX),
        "reassign_before": Int(0, EPISODE_MAX),
        "absent": IntList(0, "step", length="agents"),
        "seconds": Float(0.0, 1e9),
    },
    doc="Metrics of MODEL.md for one episode; `absent` counts the steps each agent missed (treated as idle).",
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
        BELIEF,
        GROUND_TRUTH,
        EPISODE_METRICS,
    )
}


# ----- encode / decode --------------------------------------------------------------------------------------------

_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


def encode(schema: Schema, fields: Mapping[str, Any], signer: Signer | None = None) -> str:
    """The record text of `fields` under `schema` (signed when the signer has a key).

    The sender is trusted: values are not validated here (tests check round trips), only JSON-encoded; NaN or an
    infinity raises ValueError.
    """
    body = _ENCODER.encode({"schema": schema.name, "v": schema.version, **fields})
    return signer.sign(body) if signer is not None else body


def check(schema: Schema, obj: Any, lim: Mapping[str, int] | None = None) -> dict[str, Any]:
    """Validate a parsed record against its schema; returns it without "schema", "v" and "sig"."""
    if type(obj) is not dict:
        raise WireError("not_object", None, obj)
    name = obj.pop("schema", None)
    if name != schema.name:
        raise WireError("schema", "schema", name)
    v = obj.pop("v", None)
    if type(v) is not int or v != schema.version:
        raise WireError("version", "v", v)
    obj.pop("sig", None)
    fields = schema.fields
    for key, fld in fields.items():
        if key not in obj:
            raise WireError("missing_field", key, None)
        fld.check(key, obj[key], lim)
    if len(obj) != len(fields):
        extra = next(k for k in obj if k not in fields)
        raise WireError("unknown_field", extra, obj[extra])
    return obj


def decode(
    text: Any, schema: Schema, lim: Mapping[str, int] | None = None, signer: Signer | None = None
) -> dict[str, Any]:
    """Parse and validate a received record text; returns its fields (without "schema", "v", "sig").

    Raises:
        WireError: naming the field and the bad value; `.reason` is one of size, signature, json, not_object,
            schema, version, missing_field, unknown_field, type, range, length.
    """
    if type(text) is not str:
        raise WireError("type", None, type(text).__name__)
    if len(text) > schema.max_bytes:
        raise WireError("size", None, f"{len(text)} characters > {schema.max_bytes}")
    if signer is not None and signer.enabled:
        text, problem = signer.verify(text)
        if problem is not None:
            raise WireError("signature", "sig", problem)
    try:
        obj = _DECODER.decode(text)
    except (ValueError, RecursionError) as e:
        raise WireError("json", None, str(e)) from None
    return check(schema, obj, lim)
