"""Files in a run directory that processes write while others read them."""

from __future__ import annotations

import os
from pathlib import Path


def write_atomic(path: Path, text: str, durable: bool = False) -> Path:
    """Write `text` to `path` so that a reader in another process sees the old file or the new one, whole, never a
    part: into a file of this process's own beside it, then renamed over it. Several processes may write the same
    path at once (every `htlm launch --only ...` of a team writes its run's parameter files); the last rename wins.
    `durable`: the text is on disk (fsync) before the rename, so a crash leaves the old file or the new one too."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        if durable:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)
    return path
