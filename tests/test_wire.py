"""The wire contract (htlm_msgs_py) without ROS: schemas, validation on receipt, signing, the topic table."""

from __future__ import annotations

import base64
import contextlib
import json
import math
import random
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from htlm_msgs_py import qos, topics
from htlm_msgs_py import schema as S
from htlm_msgs_py.signing import Signer, SigningError, load_key
from wire_fuzz import PAPER_LIMITS, VALID, malformed, packed, plain, unpacked, valid

KEY = b"0123456789abcdef-team-key"


@pytest.mark.parametrize("name", sorted(S.SCHEMAS))
def test_valid_record_round_trips(name: str) -> None:
    schema = S.SCHEMAS[name]
    text = S.encode(schema, unpacked(valid(schema)))
    assert json.loads(text)["schema"] == name
    assert text == _with(schema)  # binary arrays too: exactly the bytes the example writes by hand
    assert plain(S.decode(text, schema, PAPER_LIMITS)) == VALID[name]


@pytest.mark.parametrize("name", sorted(S.SCHEMAS))
def test_valid_record_round_trips_signed(name: str) -> None:
    schema = S.SCHEMAS[name]
    signer = Signer(KEY)
    text = S.encode(schema, unpacked(valid(schema)), signer)
    assert json.loads(text)["sig"]
    assert plain(S.decode(text, schema, PAPER_LIMITS, signer)) == VALID[name]


def test_every_schema_has_a_valid_example() -> None:
    assert set(VALID) == set(S.SCHEMAS)


def _reason(text: str, schema: S.Schema, signer: Signer | None = None) -> tuple[str, str | None]:
    with pytest.raises(S.WireError) as e:
        S.decode(text, schema, PAPER_LIMITS, signer)
    return e.value.reason, e.value.where


def _with(schema: S.Schema, **changes: object) -> str:
    return json.dumps(
        {"schema": schema.name, "v": schema.version, **{**valid(schema), **changes}}, separators=(",", ":")
    )


@pytest.mark.parametrize(
    ("changes", "reason", "where"),
    [
        ({"agent": 5}, "range", "agent"),  # 5 agents: 0..4
        ({"agent": -1}, "range", "agent"),
        ({"agent": True}, "type", "agent"),
        ({"agent": 1.0}, "type", "agent"),
        ({"agent": "1"}, "type", "agent"),
        ({"actions": [6, 0]}, "range", "actions"),  # |G| = 6
        ({"actions": [0, -1]}, "range", "actions"),
        ({"before": [0, 6]}, "range", "before"),
        ({"before": [-1] * 31}, "length", "before"),  # h = 30: at most the steps of an episode
        ({"actions": []}, "length", "actions"),  # one action per episode of the batch, at least one
        ({"actions": 2}, "type", "actions"),
        ({"actions": [[2]]}, "type", "actions"),
        ({"step": 0}, "range", "step"),  # actions are for steps 1..h
        ({"step": 31}, "range", "step"),
        ({"episode": -3}, "range", "episode"),
        ({"extra": 1}, "unknown_field", "extra"),
    ],
)
def test_action_rejections_name_the_field_and_value(changes: dict[str, object], reason: str, where: str) -> None:
    got = _reason(_with(S.ACTION, **changes), S.ACTION)
    assert got == (reason, where)
    with pytest.raises(S.WireError, match=where):
        S.decode(_with(S.ACTION, **changes), S.ACTION, PAPER_LIMITS)


def test_record_text_is_compact_json_in_field_order() -> None:
    # the exact bytes on the wire (and so the signatures): schema, version, then the fields in order, no spaces
    fields = {"agent": 1, "episode": 2, "step": 3, "actions": [4, 0], "before": []}
    signer = Signer(None)
    signer.run = "r1"  # a record bound to its run carries the run its sender follows, first
    text = S.encode(S.ACTION, fields, signer)
    assert (
        text == '{"schema":"htlm/action","v":4,"run":"r1","agent":1,"episode":2,"step":3,"actions":[4,0],"before":[]}'
    )
    fields = {"marginals": [0.1, 1e-07, 1.0, 0.25] + [0.0] * 16, "distance": 250000.0}
    text = S.encode(S.BELIEF, {**VALID["htlm/belief"], **fields})
    assert " " not in text and '"marginals":[0.1,1e-7,1.0,0.25,' in text  # msgspec: shortest round-trip floats
    assert '"distance":250000.0' in text
    k = np.array([[0.1, 1e-07, 1.0, -2.5e5] + [0.0] * 22] * 2)
    rec = {**unpacked(VALID["htlm/transition"]), "k": k, "r": np.array([-1.25, 2.0])}
    text = S.encode(S.TRANSITION, rec)
    assert json.loads(text) == {"schema": "htlm/transition", "v": 4, **plain(rec), "k": packed("<f4", k)}
    assert list(json.loads(text)) == ["schema", "v", *S.TRANSITION.fields]
    # the header of every binary array before its bytes, so a cut `ros2 topic echo` still says what it holds
    assert '"step":3,"k":{"shape":[2,26],"dtype":"<f4","data":"' in text
    got = S.decode(text, S.TRANSITION, PAPER_LIMITS)
    assert got["k"].dtype == np.float32 and (got["k"] == k.astype(np.float32)).all()  # knowledge travels as float32
    assert plain(got) == {**plain(rec), "k": packed("<f4", k)}


def test_nan_is_encoded_as_null_and_rejected_on_receipt() -> None:
    text = S.encode(S.BELIEF, {**VALID["htlm/belief"], "marginals": [float("nan")] + [0.0] * 19})
    assert '"marginals":[null,0.0' in text
    assert _reason(text, S.BELIEF) == ("type", "marginals")
    # in a binary array the NaN travels as it is and the receiver rejects it
    text = S.encode(S.TRANSITION, {**unpacked(VALID["htlm/transition"]), "r": [1.0, float("nan")]})
    with pytest.raises(S.WireError) as e:
        S.decode(text, S.TRANSITION, PAPER_LIMITS)
    assert (e.value.reason, e.value.where, e.value.path) == ("range", "r", "r[1]") and math.isnan(e.value.value)
    with pytest.raises(ValueError, match="cannot encode"):
        S.encode(S.STEP, {**VALID["htlm/step"], "size": object()})
    with pytest.raises(ValueError, match="cannot encode"):
        S.encode(S.TRANSITION, {**unpacked(VALID["htlm/transition"]), "a": object()})


def test_rejections_name_the_place_inside_a_list() -> None:
    with pytest.raises(S.WireError) as e:
        S.decode(_with(S.GROUND_TRUTH, levels=[[1, 2, 3, 4], [0, "x", 2, 4]]), S.GROUND_TRUTH, PAPER_LIMITS)
    assert (e.value.reason, e.value.where, e.value.path, e.value.value) == ("type", "levels", "levels[1][1]", "x")
    assert str(e.value).startswith("field 'levels[1][1]': type: 'x'")
    k = np.zeros((2, 26))
    k[1, 5] = np.inf
    with pytest.raises(S.WireError) as e:
        S.decode(_with(S.TRANSITION, k=packed("<f4", k)), S.TRANSITION, PAPER_LIMITS)
    assert (e.value.reason, e.value.where, e.value.path, e.value.value) == ("range", "k", "k[1, 5]", math.inf)
    assert str(e.value) == "field 'k[1, 5]': range: inf (expected values in [-1e+06, 1e+06])"


def test_numbers_keep_their_json_type() -> None:
    rec = S.decode(_with(S.BELIEF, marginals=[1] + [0.5] * 19, distance=2), S.BELIEF, PAPER_LIMITS)
    assert type(rec["marginals"][0]) is int and type(rec["marginals"][1]) is float and type(rec["distance"]) is int


def test_levels_and_lists_are_range_checked() -> None:
    assert _reason(_with(S.OBSERVATION, levels=[3, 5]), S.OBSERVATION) == ("range", "levels")
    assert _reason(_with(S.OBSERVATION, tasks=[4, -1]), S.OBSERVATION) == ("range", "tasks")
    assert _reason(_with(S.OBSERVATION, levels=[]), S.OBSERVATION) == ("length", "levels")
    assert _reason(_with(S.OBSERVATION, acted=[0, 0]), S.OBSERVATION) == ("range", "acted")
    assert _reason(_with(S.OBSERVATION, acted=[0, 7]), S.OBSERVATION) == ("range", "acted")
    assert _reason(_with(S.TRANSITION, k=[[0.0] * 26] * 2), S.TRANSITION) == ("type", "k")  # no JSON lists
    assert _reason(_with(S.TRANSITION, k=packed("<f4", [[0.0] * 25] * 2)), S.TRANSITION) == ("length", "k")
    assert _reason(_with(S.TRANSITION, k=packed("<f4", [0.0] * 26)), S.TRANSITION) == ("length", "k")  # rows
    assert _reason(_with(S.TRANSITION, mask2=packed("<u1", [[1, 0, 0, 0, 0, 0]] * 2)), S.TRANSITION) == (
        "type",
        "mask2",
    )
    assert _reason(_with(S.TRANSITION, r=packed("<f8", [1.0, 1e7])), S.TRANSITION) == ("range", "r")
    assert _reason(_with(S.TRANSITION, r=1.5), S.TRANSITION) == ("type", "r")
    assert _reason(_with(S.GROUND_TRUTH, levels=[[1, 2, 3, 4], [1, 2, 3]]), S.GROUND_TRUTH) == ("length", "levels")
    assert _reason(_with(S.GROUND_TRUTH, actions=[[0, 1, 2, 3, 6]]), S.GROUND_TRUTH) == ("range", "actions")
    assert _reason(_with(S.STEP, size=0), S.STEP) == ("range", "size")
    assert _reason(_with(S.STEP, phase="middle"), S.STEP) == ("range", "phase")
    assert _reason(_with(S.BELIEF, marginals=[1.5] * 20), S.BELIEF) == ("range", "marginals")


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_nan_and_infinity_are_rejected(literal: str) -> None:
    body = json.dumps(
        {
            "schema": "htlm/belief",
            "v": S.BELIEF.version,
            **{k: v for k, v in VALID["htlm/belief"].items() if k != "distance"},
        }
    )
    text = body[:-1] + f',"distance":{literal}}}'
    assert _reason(text, S.BELIEF)[0] in ("json", "range")
    text = _with(S.BELIEF).replace('"marginals":[0.2,', f'"marginals":[{literal},')
    assert '"marginals":[0.2,' not in text
    assert _reason(text, S.BELIEF)[0] in ("json", "range")
    for key, dtype in (("r", "<f8"), ("k", "<f4")):  # the same numbers in binary
        bad = unpacked(VALID["htlm/transition"])[key].astype(dtype)
        bad.flat[-1] = float(literal)
        assert _reason(_with(S.TRANSITION, **{key: packed(dtype, bad)}), S.TRANSITION) == ("range", key)


def test_wrong_schema_version_and_shape() -> None:
    assert _reason(_with(S.ACTION).replace("htlm/action", "htlm/broadcast"), S.ACTION)[0] == "schema"
    assert _reason(_with(S.ACTION).replace('"v":4', '"v":3'), S.ACTION)[0] == "version"  # v3: no run
    assert _reason("[1, 2]", S.ACTION)[0] == "not_object"
    assert _reason("{not json", S.ACTION)[0] == "json"
    assert _reason("[" * 100_000, S.ACTION)[0] in ("json", "size")
    assert _reason("x" * (S.ACTION.max_bytes + 1), S.ACTION)[0] == "size"
    missing = json.dumps({"schema": "htlm/action", "v": 4, "agent": 1})
    assert _reason(missing, S.ACTION)[0] == "missing_field"


def test_static_limits_apply_without_a_scenario() -> None:
    text = _with(S.ACTION, agent=100, actions=[50] * 4096)
    assert S.decode(text, S.ACTION)["agent"] == 100  # plausible before the scenario is known
    with pytest.raises(S.WireError):
        S.decode(_with(S.ACTION, agent=10_000), S.ACTION)
    assert _reason_under(_with(S.ACTION, actions=[0] * 4097), S.ACTION) == ("length", "actions")


def _reason_under(
    text: str, schema: S.Schema, lim: dict[str, int] | None = None, signer: Signer | None = None
) -> tuple[str, str | None]:
    with pytest.raises(S.WireError) as e:
        S.decode(text, schema, lim, signer)
    return e.value.reason, e.value.where


def test_a_batched_transition_of_128_episodes_round_trips() -> None:
    rng = np.random.default_rng(128)
    b, lim = 128, S.limits(5, 4, 6, 5, 30, batch=128)
    rec = {
        **VALID["htlm/transition"],
        "k": rng.uniform(-1.0, 1.0, (b, 26)),  # float64, as an agent's belief makes them
        "a": rng.integers(0, 6, b),
        "r": rng.uniform(-100.0, 100.0, b),
        "k2": rng.random((b, 26)),
        "mask2": rng.random((b, 6)) < 0.5,
        "done": True,
    }
    # what arrives: K and K' rounded to float32 (as the learner's memories hold them), the rest exactly
    want = {**rec, "k": rec["k"].astype(np.float32), "k2": rec["k2"].astype(np.float32), "a": rec["a"].astype("<i2")}
    text = S.encode(S.TRANSITION, rec)
    assert plain(S.decode(text, S.TRANSITION, lim)) == plain(want)  # every number bit for bit
    assert plain(S.decode(text, S.TRANSITION, PAPER_LIMITS)) == plain(want)
    signer = Signer(KEY)
    signed = S.encode(S.TRANSITION, rec, signer)
    assert plain(S.decode(signed, S.TRANSITION, lim, signer)) == plain(want)
    # the signature covers the whole text, the bytes of the arrays too
    head, data = signed.split('"r":{"shape":[128],"dtype":"<f8","data":"', 1)
    flipped = head + '"r":{"shape":[128],"dtype":"<f8","data":"' + ("B" if data[0] == "A" else "A") + data[1:]
    assert _reason_under(flipped, S.TRANSITION, lim, signer) == ("signature", "sig")
    assert _reason_under(_with(S.TRANSITION, k=packed("<f4", rec["k"][:1].repeat(129, 0))), S.TRANSITION, lim) == (
        "length",
        "k",
    )


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("htlm/action", "actions"),
        ("htlm/observation", "levels"),
        ("htlm/broadcast", "actions"),
        ("htlm/transition", "k"),
        ("htlm/transition", "mask2"),
        ("htlm/ground_truth", "levels"),
    ],
)
def test_a_per_episode_array_longer_than_the_batch_is_rejected(name: str, key: str) -> None:
    schema = S.SCHEMAS[name]
    lim = S.limits(5, 4, 6, 5, 30, batch=4)

    def rows(n: int) -> object:  # the example's first row, n times
        value = VALID[name][key]
        if isinstance(value, dict):  # a binary array
            a = unpacked({key: value})[key]
            return packed(value["dtype"], np.repeat(a[:1], n, axis=0))
        return value[:1] * n

    for b in (1, 4):
        assert plain(S.decode(_with(schema, **{key: rows(b)}), schema, lim))[key] == rows(b)
    assert _reason_under(_with(schema, **{key: rows(5)}), schema, lim) == ("length", key)
    assert _reason_under(_with(schema, **{key: rows(0)}), schema, lim) == ("length", key)


def _raw(dtype: str, shape: list[int], data: bytes) -> dict[str, object]:
    """A binary array with any header and any bytes."""
    return {"shape": shape, "dtype": dtype, "data": base64.b64encode(data).decode()}


_K2 = [[0.0] * 26, [0.25] * 26]
_MASK = [[True] * 5 + [False], [False] * 4 + [True] * 2]


@pytest.mark.parametrize(
    ("key", "value", "reason", "path"),
    [
        # wrong length: bytes short of the shape, a byte too many, more than a batch can hold
        ("k2", _raw("<f4", [2, 26], bytes(2 * 26 * 4 - 4)), "length", "k2.data"),
        ("a", _raw("<i2", [2], bytes(5)), "length", "a.data"),
        ("r", _raw("<f8", [2], bytes(8 * 4097)), "length", "r.data"),  # beyond 4096 rows
        # wrong dtype: another type, the same in the other byte order, a name numpy would take but the schema not
        ("k2", packed("<f8", _K2), "type", "k2.dtype"),
        ("k2", packed(">f4", _K2), "type", "k2.dtype"),
        ("k2", packed("<f4", _K2) | {"dtype": "float32"}, "type", "k2.dtype"),
        ("mask2", packed("<u1", _MASK), "type", "mask2.dtype"),
        ("a", packed("<i8", [2, 5]), "type", "a.dtype"),
        # wrong shape against the scenario's limits: knowledge 26, 6 actions, at least one row, rank
        ("k2", packed("<f4", [[0.0] * 27] * 2), "length", "k2.shape[1]"),
        ("mask2", packed("|b1", [[True] * 7] * 2), "length", "mask2.shape[1]"),
        ("k2", packed("<f4", np.zeros((0, 26))), "length", "k2.shape[0]"),
        ("k2", packed("<f4", [0.0] * 52), "length", "k2.shape"),
        ("a", packed("<i2", [[2], [5]]), "length", "a.shape"),
        ("a", packed("<i2", [2, 5], shape=[-2]), "length", "a.shape[0]"),
        ("a", packed("<i2", [2, 5], shape=[1.0]), "type", "a.shape[0]"),
        # NaN and infinities where numbers must be finite
        ("r", packed("<f8", [1.0, float("nan")]), "range", "r[1]"),
        ("k2", packed("<f4", [[0.0] * 26, [0.0] * 25 + [float("-inf")]]), "range", "k2[1, 25]"),
        # out of range: an action beyond |G-bar| - 1 or below 0, a mask byte that is not 0 or 1, a huge reward
        ("a", packed("<i2", [2, 6]), "range", "a[1]"),
        ("a", packed("<i2", [-1, 5]), "range", "a[0]"),
        ("mask2", _raw("|b1", [2, 6], bytes([1] * 7 + [2] + [0] * 4)), "range", "mask2[1, 1]"),
        ("r", packed("<f8", [1.0, -2e6]), "range", "r[1]"),
        # bad base64, a missing or an unknown member, not an object
        ("k2", packed("<f4", _K2) | {"data": "!!!!"}, "encoding", "k2.data"),
        ("k2", packed("<f4", _K2) | {"data": "AAA"}, "encoding", "k2.data"),
        ("r", {"shape": [2], "dtype": "<f8"}, "missing_field", "r.data"),
        ("r", packed("<f8", [1.0, 2.0]) | {"order": "C"}, "unknown_field", "r.order"),
        ("r", [1.0, 2.0], "type", "r"),
    ],
)
def test_malformed_binary_arrays_are_rejected_naming_the_field(key: str, value: object, reason: str, path: str) -> None:
    text = _with(S.TRANSITION, **{key: value})
    with pytest.raises(S.WireError) as e:
        S.decode(text, S.TRANSITION, PAPER_LIMITS)
    assert (e.value.reason, e.value.where, e.value.path) == (reason, key, path)
    assert str(e.value).startswith(f"field {path!r}: {reason}: ")
    good = S.decode(_with(S.TRANSITION), S.TRANSITION, PAPER_LIMITS)  # the decoder is not left broken
    assert plain(good) == VALID["htlm/transition"]


def test_decoded_arrays_are_read_only_numpy_arrays_of_the_declared_dtype() -> None:
    rec = S.decode(_with(S.TRANSITION), S.TRANSITION, PAPER_LIMITS)
    dtypes = {k: (rec[k].dtype.str, rec[k].shape) for k in ("k", "a", "r", "k2", "mask2")}
    assert dtypes == {
        "k": ("<f4", (2, 26)),
        "a": ("<i2", (2,)),
        "r": ("<f8", (2,)),
        "k2": ("<f4", (2, 26)),
        "mask2": ("|b1", (2, 6)),
    }
    assert not rec["k"].flags.writeable
    assert rec["a"].tolist() == [2, 5] and rec["mask2"].tolist() == _MASK


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(["<f4", "<f8", "<i2", "|b1", "<u1"]),
    st.lists(st.integers(-2, 30), min_size=0, max_size=3),
    st.binary(max_size=300),
)
def test_arbitrary_binary_arrays_only_ever_raise_wire_error(dtype: str, shape: list[int], data: bytes) -> None:
    for key in ("k", "a", "r", "mask2"):
        try:
            rec = S.decode(_with(S.TRANSITION, **{key: _raw(dtype, shape, data)}), S.TRANSITION, PAPER_LIMITS)
        except S.WireError:
            continue
        a = rec[key]  # accepted: then it is exactly what the header says
        assert a.dtype.str == dtype and list(a.shape) == shape and a.tobytes() == data


@pytest.mark.parametrize("name", sorted(S.SCHEMAS))
def test_malformed_records_never_pass_or_crash(name: str) -> None:
    schema = S.SCHEMAS[name]
    rng = random.Random(name)
    passed = 0
    for text in malformed(schema, rng, 300, episodes=(100, 200)):
        try:
            rec = S.decode(text, schema, PAPER_LIMITS)
        except S.WireError:
            continue
        # only the well-formed records of an episode outside the run may pass validation (the nodes drop them)
        assert "episode" in rec and not 100 <= rec["episode"] < 200, text[:200]
        passed += 1
    assert passed <= 300 * 2 // 14 + 2


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=300), st.binary(max_size=300).map(lambda b: b.decode("latin-1"))))
def test_arbitrary_text_only_ever_raises_wire_error(text: str) -> None:
    for schema in S.SCHEMAS.values():
        with contextlib.suppress(S.WireError):
            S.decode(text, schema, PAPER_LIMITS, Signer(KEY))
        with contextlib.suppress(S.WireError):
            S.decode(text, schema, PAPER_LIMITS)


@settings(max_examples=200, deadline=None)
@given(
    st.dictionaries(
        st.text(max_size=8),
        st.recursive(
            st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
            lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=3), c, max_size=3),
            max_leaves=8,
        ),
        max_size=8,
    )
)
def test_arbitrary_json_objects_only_ever_raise_wire_error(obj: dict[str, object]) -> None:
    for schema in S.SCHEMAS.values():
        for extra in ({}, {"schema": schema.name, "v": schema.version}):
            try:
                S.decode(json.dumps({**obj, **extra}), schema, PAPER_LIMITS)
            except S.WireError:
                pass
            except ValueError:  # json.dumps of NaN is fine; only decode may raise, and only WireError
                raise


# ----- signing ----------------------------------------------------------------------------------------------------


def test_signed_records_are_verified() -> None:
    signer = Signer(KEY)
    text = S.encode(S.BROADCAST, valid(S.BROADCAST), signer)
    assert S.decode(text, S.BROADCAST, PAPER_LIMITS, signer)["levels"] == [3, -1]
    unsigned = S.encode(S.BROADCAST, valid(S.BROADCAST))
    assert _reason(unsigned, S.BROADCAST, signer) == ("signature", "sig")
    tampered = text.replace('"levels":[3,', '"levels":[1,')
    assert tampered != text
    assert _reason(tampered, S.BROADCAST, signer) == ("signature", "sig")
    other = S.encode(S.BROADCAST, valid(S.BROADCAST), Signer(b"another-team-key-of-16+"))
    assert _reason(other, S.BROADCAST, signer) == ("signature", "sig")
    moved = text.replace(',"sig":', ',"x":1,"sig":')
    assert _reason(moved, S.BROADCAST, signer) == ("signature", "sig")


def test_without_a_key_signatures_are_ignored() -> None:
    text = S.encode(S.STEP, valid(S.STEP), Signer(KEY))
    assert S.decode(text, S.STEP, PAPER_LIMITS, Signer(None)) == VALID["htlm/step"]


def test_key_from_environment_and_file(tmp_path: object) -> None:
    from pathlib import Path

    p = Path(str(tmp_path)) / "key"
    p.write_bytes(KEY + b"\n")
    assert load_key({"HTLM_TEAM_KEY_FILE": str(p)}) == KEY
    assert load_key({"HTLM_TEAM_KEY": KEY.decode()}) == KEY
    assert load_key({}) is None
    with pytest.raises(SigningError, match="both"):
        load_key({"HTLM_TEAM_KEY": KEY.decode(), "HTLM_TEAM_KEY_FILE": str(p)})
    with pytest.raises(SigningError, match="too short"):
        load_key({"HTLM_TEAM_KEY": "short"})
    with pytest.raises(SigningError, match="cannot read"):
        load_key({"HTLM_TEAM_KEY_FILE": str(p) + ".missing"})


# ----- topics and QoS ---------------------------------------------------------------------------------------------


def test_topic_table_names_schemas_and_profiles() -> None:
    for t in topics.TOPICS:
        assert t.qos in qos.PROFILES
        assert t.schema is None or t.schema in S.SCHEMAS
        assert t.name.startswith("/htlm/") or t.name == "/diagnostics"
    assert topics.observation("agent3") == "/htlm/agent3/observation"
    assert qos.STATE.durability == "transient_local" and qos.STATE.depth == 1
    assert qos.EVENTS.durability == "volatile" and qos.EVENTS.reliability == "reliable"


def test_wire_contract_imports_without_rclpy() -> None:
    code = (
        "import sys; sys.modules['rclpy'] = None\n"
        "import htlm_msgs_py, htlm_msgs_py.schema, htlm_msgs_py.signing, htlm_msgs_py.topics, htlm_msgs_py.qos\n"
        "import htlm_world.protocol, htlm_agent.mind.agent, htlm_agent.learning.transition_store\n"
        "import htlm_agent.ros.launch\n"
        "assert 'rclpy' not in [m for m in sys.modules if sys.modules[m] is not None]\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr


def _cdr(text: str, little: bool = True) -> bytes:
    """A std_msgs/String serialized by hand: encapsulation header, uint32 length counting the NUL, bytes, NUL."""
    raw = text.encode("utf-8") + b"\0"
    return bytes([0, 1 if little else 0, 0, 0]) + len(raw).to_bytes(4, "little" if little else "big") + raw


@pytest.mark.parametrize("text", ["", '{"schema":"htlm/action"}', "niveau é, 火, 🚒"])
def test_record_text_reads_a_serialized_string(text: str) -> None:
    assert S.record_text(_cdr(text)) == text
    assert S.record_text(_cdr(text, little=False)) == text
    assert S.record_text(_cdr(text) + b"\0\0\0") == text  # padding after the string
    serialization = pytest.importorskip("rclpy.serialization")
    from std_msgs.msg import String

    assert S.record_text(serialization.serialize_message(String(data=text))) == text  # what rclpy hands over raw


@pytest.mark.parametrize(
    ("data", "shown"),
    [
        (b"", "b''"),  # empty payload
        (bytes([0, 1, 0, 0]) + (50).to_bytes(4, "little") + b"abc\0", "50"),  # length beyond the payload
        (bytes([0, 1, 0, 0]) + (4).to_bytes(4, "little") + b"abcd", "4"),  # no closing NUL
        (bytes([0, 1, 0, 0]) + (3).to_bytes(4, "little") + b"\xff\xfe\0", "b'\\xff'"),  # not UTF-8
        (bytes([7, 7, 0, 0]) + (2).to_bytes(4, "little") + b"a\0", "b'\\x07\\x07"),  # not a CDR header
    ],
)
def test_record_text_rejects_what_is_not_a_string_naming_the_bytes(data: bytes, shown: str) -> None:
    with pytest.raises(S.WireError) as e:
        S.record_text(data)
    assert e.value.reason == "encoding"
    assert shown in str(e.value)


def test_rejections_of_a_flood_of_one_record_are_explained_alike() -> None:
    # the msgspec message's parsing is cached; the value is looked up per record, when asked for
    texts = [_with(S.ACTION, agent=5), _with(S.ACTION, agent=7), _with(S.ACTION, agent=5)]
    errors = []
    for t in texts:
        with pytest.raises(S.WireError) as e:
            S.decode(t, S.ACTION, PAPER_LIMITS)
        errors.append(e.value)
    assert [(x.reason, x.where, x.value) for x in errors] == [("range", "agent", v) for v in (5, 7, 5)]
    assert "7" in str(errors[1]) and "5" in str(errors[2])
