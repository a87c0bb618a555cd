"""Checkpoints of a team of Q-learning agents.

A checkpoint is a directory (a training run keeps it at RUN/checkpoint/):

- ``meta.json``: format name and version, the scenario (plain data), the settings, the seed, the layout hash of the
  knowledge state and actions (`Scenario.layout_hash`), episodes done, the agent count and names, the SHA-256 of every
  other file, and `info` (training counters and replay sampling generator states);
- ``agents.pt``: every agent's own network, ``{"agents": [{"W0", "b0", "W1", ...}, ...]}`` with W (in, out) and
  b (out,) float32 tensors, read with ``torch.load(weights_only=True)``;
- ``train_state.pt`` (optional): target networks and optimizer state, to continue training exactly;
- ``replay.npz`` (optional): the replay memories.

A checkpoint is written into a temporary directory and then moved into place, so an interrupted write never leaves a
half-written checkpoint behind. Loading checks everything and raises `CheckpointError` naming the file and what is
wrong: missing, corrupt (unreadable, checksum mismatch), layout hash mismatch, wrong agent count, wrong shapes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from htlm_agent.learning.qnet import network_shapes, pack_weights
from htlm_agent.learning.settings import Settings
from htlm_world.scenario import Scenario, ScenarioError, from_dict

FORMAT = "htlm-checkpoint"
VERSION = 1
META, AGENTS, TRAIN_STATE, REPLAY = "meta.json", "agents.pt", "train_state.pt", "replay.npz"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: the message names the file and what is wrong."""


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint (weights loaded; training state and replay loaded on demand)."""

    path: Path
    """The checkpoint directory."""
    scenario: Scenario
    settings: Settings
    seed: int
    layout_hash: str
    episodes_done: int
    weights: list[list[NDArray[np.float32]]]
    """Per agent, its parameters in `qnet.param_shapes` order."""
    info: dict[str, Any] = field(default_factory=dict)
    created: str = ""

    @property
    def n_agents(self) -> int:
        """N."""
        return len(self.weights)

    def agent_weights(self, agent: int) -> bytes:
        """One agent's network as bytes (`qnet.pack_weights`)."""
        return pack_weights(self.weights[agent])

    def train_state(self) -> dict[str, Any] | None:
        """Target networks and optimizer state, or None when not saved."""
        f = self.path / TRAIN_STATE
        if not f.exists():
            return None
        _verify(self.path, TRAIN_STATE)
        try:
            st: dict[str, Any] = torch.load(f, weights_only=True)
        except Exception as e:
            raise CheckpointError(f"{f}: corrupt training state: {e}") from None
        return st

    def replay_state(self) -> dict[str, Any] | None:
        """Replay memory arrays, or None when not saved."""
        f = self.path / REPLAY
        if not f.exists():
            return None
        _verify(self.path, REPLAY)
        try:
            with np.load(f, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except Exception as e:
            raise CheckpointError(f"{f}: corrupt replay memory: {e}") from None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _read_meta(d: Path) -> dict[str, Any]:
    meta_path = d / META
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{meta_path}: corrupt checkpoint metadata (not valid JSON: {e})") from None
    except OSError as e:
        raise CheckpointError(f"{meta_path}: cannot read checkpoint metadata: {e.strerror}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{meta_path}: not an HTLM checkpoint (format {meta.get('format') if isinstance(meta, dict) else None!r})"
        )
    if meta.get("version") != VERSION:
        raise CheckpointError(f"{meta_path}: checkpoint version {meta.get('version')!r}, this build reads {VERSION}")
    for key in ("scenario", "settings", "seed", "layout_hash", "episodes_done", "n_agents", "files"):
        if key not in meta:
            raise CheckpointError(f"{meta_path}: corrupt checkpoint metadata: missing {key!r}")
    return meta


def _verify(d: Path, name: str) -> None:
    meta = _read_meta(d)
    f = d / name
    want = meta["files"].get(name)
    if want is None:
        raise CheckpointError(f"{f}: not listed in {d / META}")
    if not f.exists():
        raise CheckpointError(f"{f}: missing checkpoint file")
    if _sha256(f) != want:
        raise CheckpointError(f"{f}: corrupt checkpoint file (checksum mismatch: changed or truncated)")


def resolve(path: str | Path) -> Path:
    """The checkpoint directory of `path`: the directory itself, or RUN/checkpoint of a run directory."""
    p = Path(path)
    if (p / META).exists():
        return p
    if (p / "checkpoint" / META).exists():
        return p / "checkpoint"
    if not p.exists():
        raise CheckpointError(f"{p}: missing checkpoint (no such file or directory)")
    raise CheckpointError(f"{p}: missing checkpoint (no {META} in it or in {p / 'checkpoint'})")


def load_checkpoint(path: str | Path, scenario: Scenario | None = None) -> Checkpoint:
    """Load and check a checkpoint directory (or a run directory holding checkpoint/).

    Args:
        path: the checkpoint or run directory.
        scenario: when given, the checkpoint must fit it (same layout hash and agent count), e.g. an agent node's.

    Raises:
        CheckpointError: naming the file and what is wrong.
    """
    d = resolve(path)
    meta = _read_meta(d)
    meta_path = d / META
    try:
        sc = from_dict(meta["scenario"], f"{meta_path}: scenario")
    except ScenarioError as e:
        raise CheckpointError(f"corrupt checkpoint metadata: {e}") from None
    try:
        settings = Settings.from_dict(meta["settings"], f"{meta_path}: settings")
    except ValueError as e:
        raise CheckpointError(f"corrupt checkpoint metadata: {e}") from None
    if sc.layout_hash() != meta["layout_hash"]:
        raise CheckpointError(
            f"{meta_path}: layout hash mismatch: the checkpoint was written for knowledge-state layout "
            f"{meta['layout_hash']}, its scenario has layout {sc.layout_hash()} in this build; retrain"
        )
    if scenario is not None:
        if scenario.n_agents != meta["n_agents"]:
            raise CheckpointError(
                f"{meta_path}: wrong agent count: the checkpoint holds {meta['n_agents']} agents, the scenario "
                f"{scenario.name!r} has {scenario.n_agents}"
            )
        if scenario.layout_hash() != meta["layout_hash"]:
            raise CheckpointError(
                f"{meta_path}: layout hash mismatch: checkpoint {meta['layout_hash']}, scenario {scenario.name!r} "
                f"({scenario.mode} mode) has {scenario.layout_hash()}"
            )
    _verify(d, AGENTS)
    agents_path = d / AGENTS
    try:
        blob = torch.load(agents_path, weights_only=True)
        agents = blob["agents"]
    except Exception as e:
        raise CheckpointError(f"{agents_path}: corrupt agent networks: {e}") from None
    if not isinstance(agents, list) or len(agents) != meta["n_agents"] or len(agents) != sc.n_agents:
        got = len(agents) if isinstance(agents, list) else agents
        raise CheckpointError(
            f"{agents_path}: wrong agent count: {got} networks, the checkpoint's scenario has {sc.n_agents} agents"
        )
    shapes = network_shapes(sc, settings)
    weights: list[list[NDArray[np.float32]]] = []
    for i, a in enumerate(agents):
        try:
            params = [
                a[f"{kind}{li}"].detach().numpy().astype(np.float32)
                for li in range(len(shapes) // 2)
                for kind in ("W", "b")
            ]
        except (KeyError, TypeError, AttributeError) as e:
            raise CheckpointError(f"{agents_path}: agent {i}: corrupt network (missing {e})") from None
        got = [tuple(p.shape) for p in params]
        if got != shapes:
            raise CheckpointError(f"{agents_path}: agent {i}: parameter shapes {got} do not match {shapes}")
        if not all(np.isfinite(p).all() for p in params):
            raise CheckpointError(f"{agents_path}: agent {i}: network holds NaN or infinity")
        weights.append(params)
    return Checkpoint(
        path=d,
        scenario=sc,
        settings=settings,
        seed=int(meta["seed"]),
        layout_hash=str(meta["layout_hash"]),
        episodes_done=int(meta["episodes_done"]),
        weights=weights,
        info=dict(meta.get("info") or {}),
        created=str(meta.get("created", "")),
    )


def save_checkpoint(
    directory: str | Path,
    scenario: Scenario,
    settings: Settings,
    seed: int,
    episodes_done: int,
    weights: Sequence[Sequence[NDArray[np.float32]]],
    train_state: dict[str, Any] | None = None,
    replay_state: dict[str, Any] | None = None,
    info: dict[str, Any] | None = None,
) -> Path:
    """Write a checkpoint directory atomically (replacing an existing one); returns its path.

    Args:
        directory: the checkpoint directory to create or replace.
        weights: per agent, its parameters in `qnet.param_shapes` order.
        train_state: tensors for train_state.pt (target networks, optimizer), optional.
        replay_state: arrays for replay.npz, optional.
        info: JSON-able extras (training counters, generator states).
    """
    d = Path(directory)
    assert len(weights) == scenario.n_agents
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{d.name}.", dir=d.parent))
    try:
        agents = [
            {
                f"{'W' if j % 2 == 0 else 'b'}{j // 2}": torch.from_numpy(np.ascontiguousarray(p, dtype=np.float32))
                for j, p in enumerate(w)
            }
            for w in weights
        ]
        torch.save({"agents": agents}, tmp / AGENTS)
        files = [AGENTS]
        if train_state is not None:
            torch.save(train_state, tmp / TRAIN_STATE)
            files.append(TRAIN_STATE)
        if replay_state is not None:
            np.savez(tmp / REPLAY, **replay_state)
            files.append(REPLAY)
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "scenario": scenario.to_dict(),
            "settings": settings.to_dict(),
            "seed": int(seed),
            "layout_hash": scenario.layout_hash(),
            "episodes_done": int(episodes_done),
            "n_agents": scenario.n_agents,
            "agents": [a.name for a in scenario.agents],
            "files": {name: _sha256(tmp / name) for name in files},
            "info": info or {},
        }
        (tmp / META).write_text(json.dumps(meta, indent=1) + "\n")
        old = None
        if d.exists():
            old = d.with_name(f".{d.name}.old-{os.getpid()}")
            if old.exists():
                shutil.rmtree(old)
            d.rename(old)
        tmp.rename(d)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return d
