"""Binary payloads inside records (htlm_msgs_py.payload): what the trainer seals the agent opens; a payload that is
not base64 or does not match its digest is refused, naming why."""

from __future__ import annotations

import pytest

from htlm_msgs_py.payload import PayloadError, seal, unseal


def test_a_sealed_payload_opens_to_its_bytes() -> None:
    data = bytes(range(256)) * 3
    rec = seal(data)
    assert rec["encoding"] == "base64" and len(rec["sha256"]) == 64
    assert unseal(rec) == data


def test_tampered_and_broken_payloads_are_refused() -> None:
    rec = seal(b"weights of agent 1")
    other = seal(b"weights of agent 2")
    with pytest.raises(PayloadError, match="sha256 mismatch"):
        unseal({**rec, "data": other["data"]})
    with pytest.raises(PayloadError, match="not base64"):
        unseal({**rec, "data": "not*base64!"})
