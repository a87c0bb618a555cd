"""The wire contract (htlm_msgs_py) without ROS: schemas, validation on receipt, signing, the topic table."""

from __future__ import annotations

import contextlib
import json
import random
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from htlm_msgs_py import qos, topics
from htlm_msgs_py import schema as S
from htlm_msgs_py.signing import Signer, SigningError, load_key
from wire_fuzz import PAPER_LIMITS, VALID, malformed, valid

KEY = b"0123456789abcdef-team-key"


@pytest.mark.parametrize("name", sorted(S.SCHEMAS))
def test_valid_record_round_trips(name: str) -> None:
    schema = S.SCHEMAS[name]
    text = S.encode(schema, valid(schema))
    assert json.loads(text)["schema"] == name
    assert S.decode(text, schema, PAPER_LIMITS) == VALID[name]


@pytest.mark.parametrize("name", sorted(S.SCHEMAS))
def test_valid_record_round_trips_signed(name: str) -> None:
    schema = S.SCHEMAS[name]
    signer = Signer(KEY)
    text = S.encode(schema, valid(schema), signer)
    assert json.loads(text)["sig"]
    assert S.decode(text, schema, PAPER_LIMITS, signer) == VALID[name]


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
    fields = {"agent": 1, "episode": 2, "step": 3, "actions": [4, 0]}
    text = S.encode(S.ACTION, fields)
    assert text == '{"schema":"htlm/action","v":2,"agent":1,"episode":2,"step":3,"actions":[4,0]}'
    rec = {**VALID["htlm/transition"], "k": [[0.1, 1e-07, 1.0, -2.5e5] + [0.0] * 22] * 2, "r": [-1.25, 2.0]}
    text = S.encode(S.TRANSITION, rec)
    assert json.loads(text) == {"schema": "htlm/transition", "v": 2, **rec}
    assert list(json.loads(text)) == ["schema", "v", *S.TRANSITION.fields]
    assert " " not in text and '"k":[[0.1,1e-7,1.0,-250000.0,' in text  # msgspec: shortest round-trip floats
    assert S.decode(text, S.TRANSITION, PAPER_LIMITS) == rec


def test_nan_is_encoded_as_null_and_rejected_on_receipt() -> None:
    rec = {**VALID["htlm/transition"], "r": [float("nan"), 1.0]}
    text = S.encode(S.TRANSITION, rec)
    assert '"r":[null,1.0]' in text
    assert _reason(text, S.TRANSITION) == ("type", "r")
    with pytest.raises(ValueError, match="cannot encode"):
        S.encode(S.TRANSITION, {**VALID["htlm/transition"], "a": object()})


def test_rejections_name_the_place_inside_a_list() -> None:
    with pytest.raises(S.WireError) as e:
        S.decode(_with(S.TRANSITION, k=[[0.0] * 26, [0.0] * 5 + ["x"] + [0.0] * 20]), S.TRANSITION, PAPER_LIMITS)
    assert (e.value.reason, e.value.where, e.value.path, e.value.value) == ("type", "k", "k[1][5]", "x")
    assert str(e.value).startswith("field 'k[1][5]': type: 'x'")


def test_numbers_keep_their_json_type() -> None:
    rec = S.decode(_with(S.TRANSITION, r=[2, 0.5], k=[[1] + [0.5] * 25] * 2), S.TRANSITION, PAPER_LIMITS)
    assert type(rec["r"][0]) is int and type(rec["r"][1]) is float
    assert type(rec["k"][1][0]) is int and type(rec["k"][1][1]) is float


def test_levels_and_lists_are_range_checked() -> None:
    assert _reason(_with(S.OBSERVATION, levels=[3, 5]), S.OBSERVATION) == ("range", "levels")
    assert _reason(_with(S.OBSERVATION, tasks=[4, -1]), S.OBSERVATION) == ("range", "tasks")
    assert _reason(_with(S.OBSERVATION, levels=[]), S.OBSERVATION) == ("length", "levels")
    assert _reason(_with(S.OBSERVATION, acted=[0, 0]), S.OBSERVATION) == ("range", "acted")
    assert _reason(_with(S.OBSERVATION, acted=[0, 7]), S.OBSERVATION) == ("range", "acted")
    assert _reason(_with(S.TRANSITION, k=[[0.0] * 26, [0.0] * 25]), S.TRANSITION) == ("length", "k")
    assert _reason(_with(S.TRANSITION, k=[0.0] * 26), S.TRANSITION) == ("type", "k")  # one row per episode
    assert _reason(_with(S.TRANSITION, mask2=[[1, 0, 0, 0, 0, 0]] * 2), S.TRANSITION) == ("type", "mask2")
    assert _reason(_with(S.TRANSITION, r=[1.0, 1e7]), S.TRANSITION) == ("range", "r")
    assert _reason(_with(S.TRANSITION, r=1.5), S.TRANSITION) == ("type", "r")
    assert _reason(_with(S.GROUND_TRUTH, levels=[[1, 2, 3, 4], [1, 2, 3]]), S.GROUND_TRUTH) == ("length", "levels")
    assert _reason(_with(S.GROUND_TRUTH, actions=[[0, 1, 2, 3, 6]]), S.GROUND_TRUTH) == ("range", "actions")
    assert _reason(_with(S.STEP, size=0), S.STEP) == ("range", "size")
    assert _reason(_with(S.STEP, phase="middle"), S.STEP) == ("range", "phase")
    assert _reason(_with(S.BELIEF, marginals=[1.5] * 20), S.BELIEF) == ("range", "marginals")


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_nan_and_infinity_are_rejected(literal: str) -> None:
    body = json.dumps(
        {"schema": "htlm/transition", "v": 2, **{k: v for k, v in VALID["htlm/transition"].items() if k != "r"}}
    )
    text = body[:-1] + f',"r":[1.0,{literal}]}}'
    assert _reason(text, S.TRANSITION)[0] in ("json", "range")
    text = _with(S.TRANSITION).replace('"k":[[0.0,', f'"k":[[{literal},')
    assert '"k":[[0.0,' not in text
    assert _reason(text, S.TRANSITION)[0] in ("json", "range")


def test_wrong_schema_version_and_shape() -> None:
    assert _reason(_with(S.ACTION).replace("htlm/action", "htlm/broadcast"), S.ACTION)[0] == "schema"
    assert _reason(_with(S.ACTION).replace('"v":2', '"v":1'), S.ACTION)[0] == "version"  # v1: one action
    assert _reason("[1, 2]", S.ACTION)[0] == "not_object"
    assert _reason("{not json", S.ACTION)[0] == "json"
    assert _reason("[" * 100_000, S.ACTION)[0] in ("json", "size")
    assert _reason("x" * (S.ACTION.max_bytes + 1), S.ACTION)[0] == "size"
    missing = json.dumps({"schema": "htlm/action", "v": 2, "agent": 1})
    assert _reason(missing, S.ACTION)[0] == "missing_field"


def test_static_limits_apply_without_a_scenario() -> None:
    text = _with(S.ACTION, agent=100, actions=[50] * 4096)
    assert S.decode(text, S.ACTION)["agent"] == 100  # plausible before the scenario is known
    with pytest.raises(S.WireError):
        S.decode(_with(S.ACTION, agent=10_000), S.ACTION)
    assert _reason_under(_with(S.ACTION, actions=[0] * 4097), S.ACTION) == ("length", "actions")


def _reason_under(text: str, schema: S.Schema, lim: dict[str, int] | None = None) -> tuple[str, str | None]:
    with pytest.raises(S.WireError) as e:
        S.decode(text, schema, lim)
    return e.value.reason, e.value.where


def test_a_batched_transition_of_128_episodes_round_trips() -> None:
    rng = random.Random(128)
    b, lim = 128, S.limits(5, 4, 6, 5, 30, batch=128)
    rec = {
        **VALID["htlm/transition"],
        "k": [[rng.uniform(-1.0, 1.0) for _ in range(26)] for _ in range(b)],
        "a": [rng.randrange(6) for _ in range(b)],
        "r": [rng.uniform(-100.0, 100.0) for _ in range(b)],
        "k2": [[rng.random() for _ in range(26)] for _ in range(b)],
        "mask2": [[rng.random() < 0.5 for _ in range(6)] for _ in range(b)],
        "done": True,
    }
    text = S.encode(S.TRANSITION, rec)
    assert S.decode(text, S.TRANSITION, lim) == rec  # every float bit for bit
    assert S.decode(text, S.TRANSITION, PAPER_LIMITS) == rec
    signer = Signer(KEY)
    assert S.decode(S.encode(S.TRANSITION, rec, signer), S.TRANSITION, lim, signer) == rec


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
    for b in (1, 4):
        rows = VALID[name][key][:1] * b
        assert S.decode(_with(schema, **{key: rows}), schema, lim)[key] == rows
    assert _reason_under(_with(schema, **{key: VALID[name][key][:1] * 5}), schema, lim) == ("length", key)
    assert _reason_under(_with(schema, **{key: []}), schema, lim) == ("length", key)


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
