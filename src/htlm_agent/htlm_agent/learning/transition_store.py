"""The trainer's durable transition store, without ROS: an append-only file of fixed-size records with checksums.

Every transition record an agent sends (its transitions of one step in the B episodes of a batch) is identified by
(agent, session, seq): `session` is random per agent process, `seq` counts that process's records from 0. The store
keeps one row per transition; the B rows of a record carry its key, their index `row` and the count `rows`, and a
record counts as stored only when all its rows are on disk. `append` buffers, `flush` writes and fsyncs; only then does
`acked_upto` move, so an acknowledgement sent to an agent always means "on disk". On opening, a torn last record
(a crash in the middle of a write) is cut off; every record's CRC-32 is checked.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

MAGIC = b"HTLMTS02"


class StoreError(ValueError):
    """A store file that cannot be used (another layout, unreadable header); names the file."""


def record_dtype(knowledge: int, actions: int) -> np.dtype[Any]:
    """The packed record of one transition for a knowledge size K and |G-bar| actions."""
    return np.dtype(
        [
            ("agent", "<u2"),
            ("session", "S16"),
            ("seq", "<u8"),
            ("row", "<u2"),
            ("rows", "<u2"),
            ("episode", "<i8"),
            ("step", "<i4"),
            ("a", "<i2"),
            ("done", "u1"),
            ("r", "<f8"),
            ("k", "<f8", (knowledge,)),
            ("k2", "<f8", (knowledge,)),
            ("mask2", "u1", (actions,)),
            ("crc", "<u4"),
        ]
    )


@dataclass
class _Session:
    upto: int = -1  # every seq <= upto is durable
    above: set[int] | None = None  # durable seqs > upto + 1 (gaps below them)


class TransitionStore:
    """Append-only durable store of transitions (one file)."""

    def __init__(self, path: str | Path, knowledge: int, actions: int) -> None:
        """Open (or create) the store at `path` for knowledge size K and |G-bar| actions.

        Raises:
            StoreError: the file exists with another layout or a bad header.
        """
        self.path = Path(path)
        self.dtype = record_dtype(knowledge, actions)
        self.size = self.dtype.itemsize
        self.knowledge, self.actions = knowledge, actions
        header = json.dumps({"knowledge": knowledge, "actions": actions, "record_bytes": self.size}).encode()
        self.header = MAGIC + len(header).to_bytes(4, "little") + header
        self.sessions: dict[tuple[int, bytes], _Session] = {}
        self.seen: set[tuple[int, bytes, int]] = set()
        self.count = 0
        self.truncated = 0
        self.buffer: list[bytes] = []
        self.buffered: list[tuple[int, bytes, int]] = []
        self.buffered_keys: set[tuple[int, bytes, int]] = set()
        self.buffered_rows = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() and self.path.stat().st_size > 0:
            self._open_existing()
        else:
            with open(self.path, "wb") as f:
                f.write(self.header)
                f.flush()
                os.fsync(f.fileno())
        self.fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)

    def _open_existing(self) -> None:
        data = self.path.read_bytes()
        if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 4:
            raise StoreError(f"{self.path}: not a transition store (bad magic)")
        n = int.from_bytes(data[len(MAGIC) : len(MAGIC) + 4], "little")
        start = len(MAGIC) + 4 + n
        try:
            head = json.loads(data[len(MAGIC) + 4 : start])
        except ValueError as e:
            raise StoreError(f"{self.path}: unreadable header: {e}") from None
        want = {"knowledge": self.knowledge, "actions": self.actions, "record_bytes": self.size}
        if head != want:
            raise StoreError(f"{self.path}: store layout {head} differs from this scenario's {want}")
        body = data[start:]
        whole = len(body) // self.size
        good = 0
        for i in range(whole):
            rec = body[i * self.size : (i + 1) * self.size]
            if zlib.crc32(rec[:-4]) != int.from_bytes(rec[-4:], "little"):
                break
            good += 1
        if good:  # a record whose rows were not all written is cut off with the torn tail
            tail = np.frombuffer(body[: good * self.size], dtype=self.dtype)
            last = tail[-1]
            if int(last["row"]) != int(last["rows"]) - 1:
                good -= int(last["row"]) + 1
        keep = start + good * self.size
        if keep < len(data):
            self.truncated = (len(data) - keep + self.size - 1) // self.size
            with open(self.path, "r+b") as f:
                f.truncate(keep)
                f.flush()
                os.fsync(f.fileno())
        if good:
            arr = np.frombuffer(body[: good * self.size], dtype=self.dtype)
            for agent, session, seq in zip(
                arr["agent"].tolist(), arr["session"].tolist(), arr["seq"].tolist(), strict=True
            ):
                self._mark(int(agent), session, int(seq))
            self.count = good

    def _mark(self, agent: int, session: bytes, seq: int) -> None:
        self.seen.add((agent, session, seq))
        st = self.sessions.setdefault((agent, session), _Session())
        if seq == st.upto + 1:
            st.upto = seq
            if st.above:
                while st.upto + 1 in st.above:
                    st.upto += 1
                    st.above.discard(st.upto)
        elif seq > st.upto + 1:
            if st.above is None:
                st.above = set()
            st.above.add(seq)

    def contains(self, agent: int, session: str, seq: int) -> bool:
        """Whether this transition is already stored or buffered."""
        key = (agent, session.encode(), seq)
        return key in self.seen or key in self.buffered_keys

    def append(self, rec: dict[str, Any]) -> bool:
        """Buffer one decoded transition record (B transitions: a, r (B,), k, k2 (B, K), mask2 (B, |G|); the rows'
        episodes are episode .. episode + B - 1); False if it is a duplicate (already stored or buffered)."""
        agent, session, seq = int(rec["agent"]), rec["session"].encode(), int(rec["seq"])
        key = (agent, session, seq)
        if key in self.seen or key in self.buffered_keys:
            return False
        n = len(rec["a"])
        rows = np.zeros(n, dtype=self.dtype)
        rows["agent"], rows["session"], rows["seq"] = agent, session, seq
        rows["row"], rows["rows"] = np.arange(n), n
        rows["episode"] = rec["episode"] + np.arange(n)
        rows["step"], rows["a"] = rec["step"], rec["a"]
        rows["done"], rows["r"] = bool(rec["done"]), rec["r"]
        rows["k"], rows["k2"], rows["mask2"] = rec["k"], rec["k2"], rec["mask2"]
        raw = bytearray(rows.tobytes())
        size = self.size
        for i in range(n):
            end = (i + 1) * size
            raw[end - 4 : end] = zlib.crc32(memoryview(raw)[i * size : end - 4]).to_bytes(4, "little")
        self.buffer.append(bytes(raw))
        self.buffered.append(key)
        self.buffered_keys.add(key)
        self.buffered_rows += n
        return True

    def flush(self) -> list[tuple[int, str]]:
        """Write and fsync the buffered records; returns the (agent, session) whose acknowledgement moved."""
        if not self.buffer:
            return []
        data = b"".join(self.buffer)
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]
        os.fsync(self.fd)
        touched = set()
        for agent, session, seq in self.buffered:
            self._mark(agent, session, seq)
            touched.add((agent, session.decode()))
        self.count += self.buffered_rows
        self.buffered_rows = 0
        self.buffer, self.buffered = [], []
        self.buffered_keys.clear()
        return sorted(touched)

    def acked_upto(self, agent: int, session: str) -> int:
        """Largest seq u of this agent session such that every seq <= u is on disk (-1: none)."""
        st = self.sessions.get((agent, session.encode()))
        return st.upto if st is not None else -1

    def records(self, start: int = 0) -> Iterator[np.void]:
        """The durable rows (one transition each) from index `start`, in the order they were stored."""
        with open(self.path, "rb") as f:
            data = f.read()
        n = int.from_bytes(data[len(MAGIC) : len(MAGIC) + 4], "little")
        body = data[len(MAGIC) + 4 + n :]
        arr = np.frombuffer(body[: (len(body) // self.size) * self.size], dtype=self.dtype)
        yield from arr[start:]

    def close(self) -> None:
        """Flush and close the file."""
        self.flush()
        os.close(self.fd)


def read_store(path: str | Path) -> np.ndarray:
    """Every record of a store file as a structured array (for tests and reports)."""
    data = Path(path).read_bytes()
    if not data.startswith(MAGIC):
        raise StoreError(f"{path}: not a transition store (bad magic)")
    n = int.from_bytes(data[len(MAGIC) : len(MAGIC) + 4], "little")
    head = json.loads(data[len(MAGIC) + 4 : len(MAGIC) + 4 + n])
    dt = record_dtype(head["knowledge"], head["actions"])
    body = data[len(MAGIC) + 4 + n :]
    return np.frombuffer(body[: (len(body) // dt.itemsize) * dt.itemsize], dtype=dt)
