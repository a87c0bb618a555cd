"""Optional message authentication: HMAC-SHA256 with a team key.

With a team key configured, every record is sent as its JSON text with one last member `"sig"` holding the
hex HMAC-SHA256 of the text without that member, and every received record must carry a valid signature:
unsigned or wrongly signed records are rejected. A node on the same ROS domain without the key can then neither
inject nor alter observations, assignments, transitions or weights. The key comes from the environment:

- `HTLM_TEAM_KEY`: the key itself (at least 16 characters), or
- `HTLM_TEAM_KEY_FILE`: a file holding it (trailing whitespace stripped; at least 16 bytes).

The signature covers the exact bytes sent, so no canonical re-serialisation is needed on receipt. Every record
but the run announcement also carries the run id (`run`, unique per run) under the signature: the signer knows the
run its node follows (`run`, set once the node joined it), `schema.encode` writes it and `schema.decode` rejects a
record of another run (`other_run`), so a record captured in one run is refused in every other. Within its run, the
protocol drops every record of a past step or a past episode and every duplicate.
"""

from __future__ import annotations

import hashlib
import hmac
import os
from collections.abc import Mapping
from pathlib import Path

ENV_KEY = "HTLM_TEAM_KEY"
ENV_KEY_FILE = "HTLM_TEAM_KEY_FILE"
MIN_KEY_BYTES = 16
SIG_HEX = 64
_SUFFIX_HEAD = ',"sig":"'
_SUFFIX_LEN = len(_SUFFIX_HEAD) + SIG_HEX + 2  # ,"sig":"<64 hex>"}


class SigningError(ValueError):
    """A team key that cannot be used (unreadable, too short, set twice)."""


class Signer:
    """Signs outgoing record texts and checks incoming ones with one team key (or does nothing without one)."""

    def __init__(self, key: bytes | None) -> None:
        """Create a signer; `key` None disables signing and checking."""
        if key is not None and len(key) < MIN_KEY_BYTES:
            raise SigningError(f"team key too short: {len(key)} bytes, need at least {MIN_KEY_BYTES}")
        self._key = key
        self.run: str | None = None
        """The run the node follows: records it sends carry it, records of another run are rejected (None: not
        joined yet, every run is taken)."""

    @property
    def enabled(self) -> bool:
        """Whether a team key is configured."""
        return self._key is not None

    def digest(self, body: str) -> str:
        """Hex HMAC-SHA256 of a record's JSON text."""
        assert self._key is not None
        return hmac.new(self._key, body.encode(), hashlib.sha256).hexdigest()

    def sign(self, body: str) -> str:
        """The record text to send: `body` (a JSON object) with the member "sig" appended when a key is set."""
        if self._key is None:
            return body
        assert body.endswith("}") and len(body) > 2, body[:80]
        return f'{body[:-1]}{_SUFFIX_HEAD}{self.digest(body)}"}}'

    def verify(self, text: str) -> tuple[str, str | None]:
        """Split a received text into (signed body, problem); problem is None when the record may be parsed.

        Without a key every text passes unchanged (a "sig" member is then ignored by the decoder).
        """
        if self._key is None:
            return text, None
        n = len(text)
        if (
            n < _SUFFIX_LEN + 2
            or not text.endswith('"}')
            or text[n - _SUFFIX_LEN : n - _SUFFIX_LEN + 8] != _SUFFIX_HEAD
        ):
            return text, "missing signature"
        sig = text[n - SIG_HEX - 2 : n - 2]
        body = text[: n - _SUFFIX_LEN] + "}"
        if not hmac.compare_digest(sig, self.digest(body)):
            return text, "bad signature"
        return body, None


def load_key(env: Mapping[str, str] | None = None) -> bytes | None:
    """The team key from HTLM_TEAM_KEY or HTLM_TEAM_KEY_FILE, or None when neither is set.

    Raises:
        SigningError: both are set, the file cannot be read, or the key is too short.
    """
    env = os.environ if env is None else env
    direct = env.get(ENV_KEY, "")
    path = env.get(ENV_KEY_FILE, "")
    if direct and path:
        raise SigningError(f"both {ENV_KEY} and {ENV_KEY_FILE} are set; set only one")
    if path:
        try:
            key = Path(path).read_bytes().strip()
        except OSError as e:
            raise SigningError(f"{ENV_KEY_FILE}={path}: cannot read team key file: {e.strerror}") from None
        if len(key) < MIN_KEY_BYTES:
            raise SigningError(f"{ENV_KEY_FILE}={path}: key too short ({len(key)} bytes, need {MIN_KEY_BYTES})")
        return key
    if direct:
        key = direct.encode()
        if len(key) < MIN_KEY_BYTES:
            raise SigningError(f"{ENV_KEY}: key too short ({len(key)} bytes, need {MIN_KEY_BYTES})")
        return key
    return None


def signer_from_env(env: Mapping[str, str] | None = None) -> Signer:
    """A Signer with the team key of the environment (disabled when none is configured)."""
    return Signer(load_key(env))
