"""The trainer's core without ROS: the run it serves, resuming from its run directory, and the training schedule.

The trainer node (htlm_agent.ros.trainer_node) only decodes messages, feeds them and the time to `TrainerCore` and
publishes what it returns. The core keeps every transition in the durable store (transition_store.py) and feeds it
to the learner of `htlm train` (htlm_agent.learning.dqn.Learner); it decides when to train (a round of
`updates_per_step` updates per `train_every` transitions received, within a time budget, skipping rounds when far
behind), when to publish weights (every `publish_every` episodes) and when to checkpoint (every `checkpoint_every`
episodes and at shutdown). On start it resumes from run_dir: it loads run_dir/checkpoint (written by
Learner.save), feeds the learner the store's records that came after it, and counts its starts (`epoch`) so that
weight versions grow across restarts.
"""

from __future__ import annotations

import base64
import hashlib
import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.learning.settings import Settings
from htlm_agent.learning.transition_store import StoreError, TransitionStore
from htlm_world.scenario import Scenario, ScenarioError, from_dict

CATCH_UP = 3.0
"""Seconds the trainer may spend at shutdown on the rounds of updates still owed."""


@dataclass(frozen=True)
class Schedule:
    """When the trainer trains, publishes weights and checkpoints."""

    train_every: int = 5
    """Transitions received per round of learner updates (0: store only, never train)."""
    train_budget: float = 0.005
    """Longest stretch of training in one call of `TrainerCore.train`, seconds."""
    max_backlog: int = 500
    """Most rounds of updates the trainer may lag behind the transitions it received; older rounds are skipped."""
    publish_every: int = 1
    """Episodes between weight publications."""
    checkpoint_every: int = 10
    """Episodes between checkpoints (0: only at shutdown)."""


@dataclass
class TrainerEffects:
    """What the node must do after feeding the core one message or one timer."""

    acks: list[dict[str, Any]] = field(default_factory=list)
    """transition_ack records {agent, session, upto} to publish."""
    weights: list[dict[str, Any]] = field(default_factory=list)
    """weights records, one per agent in agent order, to publish on each agent's weights topic."""
    log: list[tuple[str, str]] = field(default_factory=list)
    """Log lines as (level, text), level info, warning or error."""
    counters: Counter[str] = field(default_factory=Counter)
    """Counters to add to the node's diagnostics."""
    drops: list[tuple[str, str]] = field(default_factory=list)
    """Well-formed records dropped, as (topic, reason): outside_run, duplicate."""
    rejects: list[tuple[str, str, str]] = field(default_factory=list)
    """Records refused, as (topic, reason, detail)."""
    fatal: str | None = None
    """The trainer cannot go on (another layout, a store it must not resume): why."""


def load_learner_data(settings_file: str, settings_json: str) -> dict[str, Any]:
    """The learner settings given to the trainer: the file's (JSON or YAML), then the JSON overrides.

    Raises:
        ValueError: an unreadable file or JSON, naming it.
    """
    data: dict[str, Any] = {}
    if settings_file:
        p = Path(settings_file)
        try:
            text = p.read_text()
        except OSError as e:
            raise ValueError(f"settings_file {p}: cannot read: {e.strerror}") from None
        if p.suffix in (".yaml", ".yml"):
            import yaml

            try:
                loaded = yaml.safe_load(text) or {}
            except yaml.YAMLError as e:
                raise ValueError(f"settings_file {p}: not YAML: {e}") from None
        else:
            try:
                loaded = json.loads(text)
            except ValueError as e:
                raise ValueError(f"settings_file {p}: not JSON: {e}") from None
        if not isinstance(loaded, dict):
            raise ValueError(f"settings_file {p}: must hold a mapping")
        data.update(loaded)
    if settings_json:
        try:
            extra = json.loads(settings_json)
        except ValueError as e:
            raise ValueError(f"settings_json: {settings_json!r} is not JSON: {e}") from None
        if not isinstance(extra, dict):
            raise ValueError(f"settings_json: {settings_json!r} must be a JSON object")
        data.update(extra)
    return data


class TrainerCore:
    """The trainer of one run directory: store, learner, schedule, weights and checkpoints."""

    def __init__(
        self,
        run_dir: str | Path,
        schedule: Schedule,
        learner_data: dict[str, Any] | None = None,
        learner_source: str = "settings",
        resume: bool = True,
    ) -> None:
        """The trainer of `run_dir` (created if missing); `learner_data` are the learner's settings as plain data
        (the run's seed unless they give one), `learner_source` names where they come from for messages; with
        `resume` off, a run_dir that already holds a store or a checkpoint is refused when the run starts."""
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.schedule = schedule
        self.learner_data = dict(learner_data or {})
        self.learner_source = learner_source
        self.resume = resume
        self.epoch = self._next_epoch()
        self.run: str | None = None
        self.mode = ""
        self.run_range = (0, 0)
        self.stopping = False
        self.stop_at = 0.0
        self.last_transition_at = 0.0
        self.fatal: str | None = None
        self.scenario: Scenario | None = None
        self.learner: Any = None
        self.store: TransitionStore | None = None
        self.log_file: Any = None
        self.reack: set[tuple[int, str]] = set()
        self.new_transitions = 0
        self.updates = 0
        self.last_loss: float | None = None
        self.episodes_seen = 0
        self.episodes_stored: set[int] = set()
        self.published_updates = -1
        self.version = 0

    def _next_epoch(self) -> int:
        """A counter of trainer starts in this run directory, so weight versions grow across restarts."""
        f = self.dir / "trainer_epoch"
        try:
            epoch = int(f.read_text().strip()) + 1
        except (OSError, ValueError):
            epoch = 1
        f.write_text(f"{epoch}\n")
        return epoch

    @property
    def weights_version(self) -> int:
        """Version of the latest weights published (grows across restarts of the trainer)."""
        return self.epoch * 2**32 + self.version

    # ----- the run ------------------------------------------------------------------------------------------------
    def on_scenario(self, rec: dict[str, Any], now: float) -> TrainerEffects:
        """A decoded /htlm/scenario record: start on the first run, follow later announcements of the same layout."""
        out = TrainerEffects()
        if rec["run"] == self.run:
            if rec["state"] == "stopped" and not self.stopping:
                out.log.append(("info", f"run {self.run} stopped by the world"))
                self.stopping = True
                self.stop_at = now
            return out
        try:
            sc = from_dict(rec["scenario"], "/htlm/scenario")
        except ScenarioError as e:
            out.rejects.append(("scenario", "scenario", str(e)))
            return out
        if sc.layout_hash() != rec["layout"]:
            out.rejects.append(("scenario", "layout", f"layout {rec['layout']} != {sc.layout_hash()}"))
            return out
        if self.scenario is not None:
            if sc.layout_hash() != self.scenario.layout_hash():
                self._fail(f"run {rec['run']} has another layout than the learner's; use a new run_dir", out)
            else:
                self.run = rec["run"]
                self.run_range = (rec["first_episode"], rec["episodes"])
                self.stopping = rec["state"] == "stopped"
                self.stop_at = now
            return out
        self.run = rec["run"]
        self.mode = rec["mode"]
        self.run_range = (rec["first_episode"], rec["episodes"])
        self.stopping = rec["state"] == "stopped"
        self.stop_at = now
        try:
            self.start(sc, rec["seed"], out)
        except (StoreError, ValueError, OSError) as e:
            self._fail(str(e), out)
        return out

    def _fail(self, why: str, out: TrainerEffects) -> None:
        self.fatal = why
        out.fatal = why
        out.log.append(("error", why))

    def learner_settings(self, seed: int) -> Settings:
        """The learner Settings of the run with master seed `seed` (the seed of `learner_data` if it gives one).

        Raises:
            ValueError: a bad field, naming the source and the field.
        """
        return Settings.from_dict({"seed": seed, **self.learner_data}, self.learner_source)

    def start(self, sc: Scenario, seed: int, out: TrainerEffects) -> None:
        """Open the store and, in train mode, the learner: resumed from the checkpoint when there is one, fed the
        stored transitions the checkpoint does not hold, and its first weights published.

        Raises:
            StoreError: a store of another layout, or a store or checkpoint while `resume` is off.
            ValueError: bad learner settings, or a checkpoint that cannot be resumed.
        """
        from htlm_agent.learning.checkpoint import CheckpointError
        from htlm_agent.learning.dqn import Learner

        settings = self.learner_settings(seed)
        self.scenario = sc
        store_path = self.dir / "transitions.bin"
        ckpt = self.dir / "checkpoint"
        if not self.resume and (store_path.exists() or ckpt.exists()):
            raise StoreError(f"{self.dir}: holds a store or checkpoint and resume is off; use a new run_dir")
        self.store = TransitionStore(store_path, sc.knowledge_size, sc.n_actions)
        self.log_file = open(self.dir / "train_log.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        if self.mode != "train":  # evaluate, deploy: record metrics and any transitions, learn nothing
            out.log.append(("info", f"run {self.run}: mode {self.mode}: recording only (store {store_path})"))
            return
        fed = 0
        if (ckpt / "meta.json").exists():
            try:
                self.learner = Learner.load(ckpt, settings)
            except CheckpointError as e:
                raise ValueError(f"cannot resume: {e}") from None
            if self.learner.scenario.layout_hash() != sc.layout_hash():
                raise ValueError(f"{ckpt}: the checkpoint's layout differs from the run's scenario")
            info = json.loads((ckpt / "meta.json").read_text()).get("info", {})
            fed = int(info.get("store_records", 0))
            self.episodes_seen = int(self.learner.episodes_done)
            self.updates = int(np.asarray(self.learner.updates).max())
            out.log.append(
                (
                    "info",
                    f"resumed from {ckpt}: {self.episodes_seen} episodes, {self.updates} updates, "
                    f"{fed} stored transitions",
                )
            )
        else:
            self.learner = Learner(sc, settings, seed)
        replayed = 0
        for i, r in enumerate(self.store.records(0)):
            if i < fed:  # already in the checkpoint's replay memory
                self.episodes_stored.add(int(r["episode"]))
                continue
            self._learn(
                r["agent"], r["k"], r["a"], r["r"], r["k2"], r["mask2"].astype(bool), bool(r["done"]), int(r["episode"])
            )
            replayed += 1
        (self.dir / "settings.json").write_text(json.dumps(settings.to_dict(), indent=1) + "\n")
        out.weights.extend(self.publish_weights())
        out.log.append(
            (
                "info",
                f"run {self.run}: training {sc.n_agents} agents of {sc.name}/{sc.team}; store {store_path} holds "
                f"{self.store.count} transitions ({self.store.truncated} torn records cut, {replayed} fed to the "
                "learner)",
            )
        )

    def in_run(self, episode: int) -> bool:
        """Whether `episode` is one of the current run's."""
        lo, n = self.run_range
        return episode >= lo and (n == 0 or episode < lo + n)

    def quiet_for(self, now: float) -> float:
        """Seconds since the run stopped or the last transition arrived, whichever came later (0 while running)."""
        if not self.stopping:
            return 0.0
        return now - max(self.stop_at, self.last_transition_at)

    # ----- messages in --------------------------------------------------------------------------------------------
    def on_transition(self, rec: dict[str, Any], now: float) -> TrainerEffects:
        """A decoded transition record: store it (acknowledged at the next flush) and feed it to the learner."""
        out = TrainerEffects()
        if self.store is None:  # no scenario yet: the agents send it again until acknowledged
            out.counters["ignored/transitions/no_scenario"] += 1
            return out
        self.last_transition_at = now
        if not self.in_run(rec["episode"]):
            out.drops.append(("transitions", "outside_run"))
            return out
        agent, session = rec["agent"], rec["session"]
        if not any(rec["mask2"]):
            out.rejects.append(("transitions", "range", "mask2 allows no action"))
            return out
        if not self.store.append(rec):
            out.drops.append(("transitions", "duplicate"))
            self.reack.add((agent, session))
            return out
        if self.learner is not None:
            self._learn(agent, rec["k"], rec["a"], rec["r"], rec["k2"], rec["mask2"], rec["done"], rec["episode"])
            self.new_transitions += 1
        return out

    def _learn(self, agent: Any, k: Any, a: Any, r: Any, k2: Any, mask2: Any, done: bool, episode: int) -> None:
        self.episodes_stored.add(int(episode))
        self.learner.store(
            int(agent),
            np.asarray(k, dtype=np.float64),
            int(a),
            float(r),
            np.asarray(k2, dtype=np.float64),
            np.asarray(mask2, dtype=bool),
            bool(done),
        )

    def on_metrics(self, rec: dict[str, Any]) -> TrainerEffects:
        """A decoded episode_metrics record: log the episode; publish weights and checkpoint when they are due."""
        out = TrainerEffects()
        if self.store is None:
            return out
        if not self.in_run(rec["episode"]):
            out.drops.append(("episode_metrics", "outside_run"))
            return out
        s = self.schedule
        self.episodes_seen += 1
        if self.learner is None:
            self._write_log(rec)
            return out
        self.learner.episodes_done = self.episodes_seen
        eps = float(self.learner.settings.epsilon(rec["episode"]))
        self._write_log(
            {"episode": rec["episode"], "updates": self.updates, "loss": self.last_loss, "epsilon": eps, **rec}
        )
        loss = self.last_loss if self.last_loss is None else round(self.last_loss, 4)
        out.log.append(
            (
                "info",
                f"episode {rec['episode']}: completion {rec['completion']}, {self.updates} updates, loss {loss}, "
                f"epsilon {eps:.3f}, store {self.store.count}",
            )
        )
        if self.episodes_seen % s.publish_every == 0:
            out.weights.extend(self.publish_weights())
        if s.checkpoint_every and self.episodes_seen % s.checkpoint_every == 0:
            self.checkpoint(out)
        return out

    def _write_log(self, line: dict[str, Any]) -> None:
        if self.log_file is not None:
            self.log_file.write(json.dumps(line) + "\n")
            self.log_file.flush()

    # ----- the schedule -------------------------------------------------------------------------------------------
    def flush(self) -> TrainerEffects:
        """Write and fsync the buffered transitions; acknowledge every agent session whose durable prefix grew (and
        those that sent a duplicate)."""
        out = TrainerEffects()
        self._flush(out)
        return out

    def _flush(self, out: TrainerEffects) -> None:
        store = self.store
        if store is None:
            return
        touched = set(store.flush()) | self.reack
        self.reack = set()
        for agent, session in sorted(touched):
            out.acks.append({"agent": agent, "session": session, "upto": store.acked_upto(agent, session)})

    def train(self, clock: Callable[[], float] = time.monotonic) -> TrainerEffects:
        """The rounds of updates owed: one round of `updates_per_step` updates per `train_every` transitions
        received, for at most `train_budget` seconds of `clock`; more than `max_backlog` rounds behind, the oldest
        rounds are skipped (counted)."""
        out = TrainerEffects()
        s = self.schedule
        if self.learner is None or not s.train_every or self.new_transitions < s.train_every:
            return out
        backlog = self.new_transitions // s.train_every
        if backlog > s.max_backlog:  # far behind (a burst of resent transitions): skip rounds, do not fall further
            out.counters["skipped_rounds"] += backlog - s.max_backlog
            self.new_transitions -= (backlog - s.max_backlog) * s.train_every
        start = clock()
        out.counters["train_calls"] += 1
        while self.new_transitions >= s.train_every and clock() - start < s.train_budget:
            self.new_transitions -= s.train_every
            out.counters["train_rounds"] += 1
            for _ in range(self.learner.settings.updates_per_step):
                loss = self.learner.train_step()
                if loss is not None:
                    self.last_loss = loss
                    self.updates += 1
        return out

    def publish_weights(self) -> list[dict[str, Any]]:
        """Every agent's weights record, when the networks changed since the last ones (else nothing)."""
        if self.learner is None or self.updates == self.published_updates:
            return []
        self.published_updates = self.updates
        self.version += 1
        settings = self.learner.settings.to_dict()
        out = []
        for i in range(self.learner.n_agents):
            data = self.learner.agent_weights(i)
            out.append(
                {
                    "agent": i,
                    "version": self.weights_version,
                    "episode": self.episodes_seen,
                    "encoding": "base64",
                    "data": base64.b64encode(data).decode(),
                    "sha256": hashlib.sha256(data).hexdigest(),
                    "settings": settings,
                }
            )
        return out

    def checkpoint(self, out: TrainerEffects) -> None:
        """Flush the store (acknowledging) and write the learner's checkpoint with the number of records it holds."""
        if self.learner is None or self.store is None:
            return
        self._flush(out)
        self.learner.episodes_done = max(self.episodes_seen, len(self.episodes_stored))
        t0 = time.monotonic()
        path = self.learner.save(self.dir / "checkpoint", extra={"store_records": self.store.count, "run": self.run})
        out.counters["checkpoints"] += 1
        out.log.append(("info", f"checkpoint {path} ({self.store.count} transitions, {time.monotonic() - t0:.2f} s)"))

    def shutdown(self, clock: Callable[[], float] = time.monotonic) -> TrainerEffects:
        """Flush the store and acknowledge, catch up briefly on the rounds still owed, write the final checkpoint,
        close the files."""
        out = TrainerEffects()
        if self.store is not None:
            self._flush(out)
            if self.fatal is None:
                end = clock() + CATCH_UP
                every = self.schedule.train_every
                while self.learner is not None and every and self.new_transitions >= every:
                    if clock() > end:
                        break
                    more = self.train(clock)
                    out.counters.update(more.counters)
                self.checkpoint(out)
            self.store.close()
            self.store = None
        if self.log_file is not None:
            self.log_file.close()
            self.log_file = None
        return out

    def values(self) -> dict[str, str]:
        """The trainer's state for the node's diagnostics."""
        return {
            "run": str(self.run),
            "stored": str(self.store.count if self.store else 0),
            "updates": str(self.updates),
            "loss": str(self.last_loss),
            "episodes_seen": str(self.episodes_seen),
            "weights_version": str(self.weights_version),
            "epoch": str(self.epoch),
        }
