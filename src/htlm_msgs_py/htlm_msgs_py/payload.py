"""Binary payloads inside JSON records (the weights of `htlm/weights`): sealed and opened in one place.

A payload travels as the record's fields `encoding` ("base64"), `data` (the bytes, base64) and `sha256` (of the
bytes). `seal` writes those fields; `unseal` reads them back and refuses what does not decode or does not match its
digest. What the bytes hold is the sender's business (the Q-network's layout: `htlm_agent.learning.qnet`).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
from typing import Any


class PayloadError(ValueError):
    """A payload that is not valid base64 or whose bytes do not match its digest."""


def seal(data: bytes) -> dict[str, str]:
    """The record fields that carry `data`: encoding, data (base64) and sha256."""
    return {"encoding": "base64", "data": base64.b64encode(data).decode(), "sha256": hashlib.sha256(data).hexdigest()}


def unseal(rec: dict[str, Any]) -> bytes:
    """The bytes a record's payload fields carry (the record already validated by its schema).

    Raises:
        PayloadError: naming what is wrong (not base64, digest mismatch).
    """
    try:
        data = base64.b64decode(rec["data"], validate=True)
    except (binascii.Error, ValueError) as e:
        raise PayloadError(f"not base64: {e}") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != rec["sha256"]:
        raise PayloadError(
            f"sha256 mismatch: the bytes hash to {digest[:16]}..., the record says {rec['sha256'][:16]}..."
        )
    return data
