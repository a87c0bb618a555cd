"""The trainer's core without ROS: the run it serves, resuming from its run directory, and the training schedule.

The trainer node (htlm_agent.ros.trainer_node) only decodes messages, feeds them and the time to `TrainerCore` and
publishes what it returns. The core keeps every transition in the durable store (transition_store.py) and feeds it
to the learner of `htlm train` that the settings name (`LearnerKind.over_ros` of htlm_agent.learning.learners; a
deep Q-learner's htlm_agent.learning.dqn.Learner) round by round: one round of `updates_per_step`
updates per step of the batched lockstep, in step order (`TrainerCore` says when a round is complete); it publishes
its progress after every round (the world's rate limiter), the weights on a fixed cadence (every `weights_every`
steps), validates and selects as `htlm train` does, and checkpoints every `checkpoint_every` episodes and at
shutdown. On start it resumes from run_dir: it loads run_dir/checkpoint (written by
Learner.save), feeds the learner the store's records that came after it, and counts its starts (`epoch`) so that
weight versions grow across restarts. A learner in rounds (`LearnerKind.rounds`, the expert-iteration learner) takes
every step's transitions and the world's true levels, learns after a round's last step while the world waits, and
publishes its weights once a round.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from htlm_agent.learning.learners import learner
from htlm_agent.learning.settings import Settings
from htlm_agent.learning.transition_store import StoreError, TransitionStore
from htlm_msgs_py.payload import seal
from htlm_msgs_py.run_control import REFUSED, RunControl, Verdict
from htlm_world.episode import global_step
from htlm_world.scenario import Scenario, ScenarioRecordError, from_record

if TYPE_CHECKING:
    from htlm_agent.learning.expert_trainer import ExpertTrainer


HEARTBEAT = 1.0
"""Seconds between progress records while the expert's round of learning runs (the world's trainer_deadline and
end_hold count the trainer's silence)."""


@dataclass(frozen=True)
class Schedule:
    """When the trainer publishes weights and checkpoints, and how long a round of updates waits for a late agent."""

    weights_every: int = 1
    """Steps between weight publications (the fixed cadence W)."""
    round_deadline: float = 5.0
    """Longest wait for the transitions of a step from every agent that acted in it, seconds."""
    checkpoint_every: int = 4096
    """Episodes between checkpoints (0: only at shutdown)."""


@dataclass
class _Round:
    """The transitions of one step g, gathered until its round of updates can run."""

    records: dict[int, dict[str, Any]] = field(default_factory=dict)
    acted: set[int] | None = None
    since: float | None = None
    episode: int = 0
    step: int = 0
    size: int = 0


@dataclass
class TrainerEffects:
    """What the node must do after feeding the core one message or one timer."""

    acks: list[dict[str, Any]] = field(default_factory=list)
    """transition_ack records {agent, session, upto} to publish."""
    weights: list[dict[str, Any]] = field(default_factory=list)
    """weights records, one per agent in agent order, to publish on each agent's weights topic."""
    progress: list[dict[str, Any]] = field(default_factory=list)
    """trainer_progress records {run, trained, updates} to publish (the world paces its steps by them)."""
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
    """The trainer of one run directory: store, learner, rounds of updates, weights, validation and checkpoints.

    Training follows `htlm train` step for step: the transitions of step g (global index, batch index x h + t - 1)
    of every agent are stored in the learner's memories in agent order, then every agent's network gets
    `updates_per_step` gradient updates (the round of step g); rounds run in the order of g, each once all the
    agents that acted in step g (the world's step record) have sent theirs, or after `round_deadline`. After round
    g the trainer announces `trained = g + 1` (the world paces its steps by it) and, on the cadence, publishes the
    weights; after the last step of a batch it counts the batch's episodes, validates and keeps the best networks
    as `htlm train` does, and checkpoints when due. With the world's trainer_lag 0 and weights every step, the
    agents act with exactly the networks the in-process loop acts with.
    """

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
        self.control = RunControl()
        """Which run the trainer follows (its `wanted` run: the node's `run` parameter)."""
        self.mode = ""
        self.logged_upto = -1
        """The last episode whose metrics are in the training log (they are logged once, in order)."""
        self.run_range = (0, 0)
        self.batch = 1
        self.first_step = 0
        self.run_lag = 0  # the announced run's trainer_lag
        self.trained = 0
        """Every round with a global step index below it is done."""
        self.rounds: dict[int, _Round] = {}
        self.stopping = False
        self.stop_at = 0.0
        self.last_transition_at = 0.0
        self.fatal: str | None = None
        self.scenario: Scenario | None = None
        self.learner: Any = None
        self.expert: Any = None
        """The baseline of the warm start while the learner's settings have one (`Settings.imitate`)."""
        self.selection: Any = None
        self.last_val = 0
        self.last_ckpt = 0
        self.store: TransitionStore | None = None
        self.log_file: Any = None
        self.reack: set[tuple[int, str]] = set()
        self.updates = 0
        self.last_loss: float | None = None
        self.episodes_seen = 0
        self.batch_metrics: list[dict[str, Any]] = []
        self.published_trained = -1
        self.version = 0
        self._settings_dict: dict[str, Any] | None = None
        self.world_episode = -1
        """The first episode of the latest batch the world's step records announced (-1: none yet in this run)."""
        self.rounds_of: ExpertTrainer | None = None
        """The expert-iteration learner (`learning.expert_trainer`; then also `learner`), None for the Q-learners."""
        self.held = False
        """Whether the last step's announcement waits for the expert's round of learning."""
        self.heard_at = 0.0
        """When the last progress record went out (the heartbeat while a round learns)."""
        self.finished = False
        """Whether the learner has finished (the expert's rounds are over): the world ends the run."""

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

    def global_step(self, episode: int, t: int) -> int:
        """The global index of step t of the batch from `episode` on (`htlm_world.episode.global_step`)."""
        assert self.scenario is not None
        return global_step(episode, self.batch, t, self.scenario.horizon)

    # ----- the run ------------------------------------------------------------------------------------------------
    def on_scenario(self, rec: dict[str, Any], now: float) -> TrainerEffects:
        """A decoded /htlm/scenario record: start on the first run, follow later announcements of the same layout."""
        out = TrainerEffects()
        verdict = self.control.take(rec)
        if verdict in REFUSED:  # nobody but our run's world stops or switches us
            out.rejects.append(("scenario", verdict, self.control.refused(rec)))
            return out
        if verdict == Verdict.STOP:
            if not self.stopping:
                out.log.append(("info", f"run {self.run} stopped by the world"))
                self.stopping = True
                self.stop_at = now
            return out
        if verdict == Verdict.UPDATE:
            return out
        if verdict == Verdict.RESTART:
            out.log.append(("warning", f"run {self.run}: the world restarted (announcement {rec['seq']})"))
            self.stopping = False
            return out
        self.logged_upto = -1  # a run joined: its episodes are logged from its first on
        self.world_episode = -1
        try:
            sc = from_record(rec)
        except ScenarioRecordError as e:
            out.rejects.append(("scenario", e.reason, str(e)))
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
        self.batch = rec["batch"]
        self.stopping = rec["state"] == "stopped"
        self.stop_at = now
        self.run_lag = rec["trainer_lag"]
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
        """The learner Settings of the run with master seed `seed` (the seed of `learner_data` if it gives one), after
        the preset of the learner they name (`Settings.with_preset`, as `htlm train --learner NAME`).

        Raises:
            ValueError: a bad field, naming the source and the field.
        """
        return Settings.from_dict(Settings.with_preset({"seed": seed, **self.learner_data}), self.learner_source)

    def start(self, sc: Scenario, seed: int, out: TrainerEffects) -> None:
        """Open the store and, in train mode, the learner: resumed from the checkpoint when there is one, fed the
        stored transitions the checkpoint does not hold, and its first weights published.

        Raises:
            StoreError: a store of another layout, or a store or checkpoint while `resume` is off.
            ValueError: bad learner settings, or a checkpoint that cannot be resumed.
        """
        import torch

        from htlm_agent.learning.checkpoint import CheckpointError
        from htlm_agent.learning.loop import Selection, warm_start_expert

        settings = self.learner_settings(seed)
        torch.set_num_threads(settings.threads)  # as `htlm train`
        self.scenario = sc
        self.first_step = self.global_step(self.run_range[0], 1)
        self.trained = self.first_step
        store_path = self.dir / "transitions.bin"
        ckpt = self.dir / "checkpoint"
        if not self.resume and (store_path.exists() or ckpt.exists()):
            raise StoreError(f"{self.dir}: holds a store or checkpoint and resume is off; use a new run_dir")
        self.store = TransitionStore(store_path, sc.knowledge_size, sc.n_actions)
        self.log_file = open(self.dir / "train_log.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        if self.mode != "train":  # evaluate, deploy: record metrics and any transitions, learn nothing
            out.log.append(("info", f"run {self.run}: mode {self.mode}: recording only (store {store_path})"))
            return
        kind = learner(settings.learner)
        if kind.in_process_only is not None:
            raise ValueError(f"{self.learner_source}: settings.learner: {settings.learner!r} {kind.in_process_only}")
        if kind.rounds:
            self._start_rounds(sc, settings, seed, ckpt, out)
            return
        fed = 0
        info: dict[str, Any] = {}
        if (ckpt / "meta.json").exists():
            try:
                self.learner = kind.over_ros(sc, settings, seed, self.batch, ckpt)
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
            self.learner = kind.over_ros(sc, settings, seed, self.batch, None)
        self.expert = warm_start_expert(sc, settings)
        if self.run_lag != settings.trainer_lag:
            out.log.append(
                (
                    "warning",
                    f"the run's trainer_lag {self.run_lag} differs from the learner's {settings.trainer_lag}: the "
                    "agents act with other networks than `htlm train` would (set both, or the learner's alone)",
                )
            )
        self.selection = Selection(self.learner, info)
        if info:
            self.selection.restore(ckpt)
        self.last_val = self.last_ckpt = self.episodes_seen
        replayed = 0
        finished: set[int] = set()  # episodes whose last step the store holds beyond the checkpoint
        pending = {(int(a), str(sess), int(q)) for a, sess, q in info.get("pending_records", [])}
        for i, r in enumerate(self.store.records(0)):
            g = self.global_step(int(r["episode"]) - int(r["row"]), int(r["step"]))
            self.trained = max(self.trained, g + 1)  # what the store holds counts as trained (a restart goes on)
            key = (int(r["agent"]), r["session"].decode(), int(r["seq"]))
            if i < fed and key not in pending:  # already in the checkpoint's replay memory
                continue
            self.learner.store(
                int(r["agent"]), r["k"], int(r["a"]), float(r["r"]), r["k2"], r["mask2"].astype(bool), bool(r["done"])
            )
            replayed += 1
            if int(r["step"]) == sc.horizon:
                finished.add(int(r["episode"]))
        if finished:  # batches finished after the checkpoint count as trained episodes (their updates are not redone)
            self.learner.episodes_done += len(finished)
            self.episodes_seen = int(self.learner.episodes_done)
            self.last_val = self.last_ckpt = self.episodes_seen
        (self.dir / "settings.json").write_text(json.dumps(settings.to_dict(), indent=1) + "\n")
        self._announce(out, force_weights=True)
        out.log.append(
            (
                "info",
                f"run {self.run}: training {sc.n_agents} agents of {sc.name}/{sc.team} in batches of {self.batch}; "
                f"store {store_path} holds {self.store.count} transitions ({self.store.truncated} torn records cut, "
                f"{replayed} fed to the learner); trained up to step {self.trained}",
            )
        )

    def _start_rounds(self, sc: Scenario, settings: Settings, seed: int, ckpt: Path, out: TrainerEffects) -> None:
        """Start a learner in rounds (`LearnerKind.rounds`: the expert-iteration learner's
        `learning.expert_trainer.ExpertTrainer`): its weights change once a round.

        Raises:
            StoreError: a run directory that already holds transitions or a checkpoint (the learner's rounds do not
                resume: they are quick to run again in a new run_dir).
        """
        assert self.store is not None
        if self.store.count or ckpt.exists():
            raise StoreError(
                f"{self.dir}: holds transitions or a checkpoint, and the expert-iteration learner does not resume a "
                "run (its rounds are quick to run again): use a new run_dir"
            )
        self.rounds_of = self.learner = learner(settings.learner).over_ros(sc, settings, seed, self.batch, None)
        self.schedule = Schedule(
            weights_every=settings.round_batches * sc.horizon,
            round_deadline=self.schedule.round_deadline,
            checkpoint_every=0,
        )
        (self.dir / "settings.json").write_text(json.dumps(settings.to_dict(), indent=1) + "\n")
        self._announce(out, force_weights=True)
        out.log.append(
            (
                "info",
                f"run {self.run}: expert iteration for {sc.n_agents} agents of {sc.name}/{sc.team}: up to "
                f"{settings.rounds} rounds of {settings.round_batches} batches of {self.batch} episodes, the first "
                f"played by the {settings.warm_baseline}",
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
    def batch_rows(self, episode: int) -> int:
        """Episodes (rows) of the run's batch whose first episode is `episode`; 0 when no batch starts there."""
        lo, n = self.run_range
        if not self.in_run(episode) or (episode - lo) % self.batch:
            return 0
        return self.batch if n == 0 else min(self.batch, lo + n - episode)

    def step_window(self) -> int:
        """How many global steps ahead of the rounds done a transition or a step record may be: the agents act at
        most the run's trainer_lag steps ahead of the trainer; two horizons leave room for a world that went on
        without the trainer for a while (their records come again once it caught up)."""
        assert self.scenario is not None
        return 2 * self.scenario.horizon + self.run_lag + 1

    def on_transition(self, rec: dict[str, Any], now: float) -> TrainerEffects:
        """A decoded transition record (one agent, one step, B episodes): store it (acknowledged at the next flush)
        and gather it for the round of its step.

        Every record is checked against the batch it names before anything is stored: its episode must begin a
        batch of the run, its arrays hold one row per episode of that batch (and of the round gathered for its
        step), and its step lie at most `step_window` steps ahead of the rounds done (`future`: the agent sends it
        again until it is acknowledged). A record that cannot be used is rejected and counted; none raises."""
        out = TrainerEffects()
        if self.store is None:  # no scenario yet: the agents send it again until acknowledged
            out.counters["ignored/transitions/no_scenario"] += 1
            return out
        self.last_transition_at = now
        if self.mode != "train":  # evaluate and deploy runs are not training data
            out.drops.append(("transitions", "not_training"))
            return out
        if not self.in_run(rec["episode"]):
            out.drops.append(("transitions", "outside_run"))
            return out
        n = len(rec["a"])
        want = self.batch_rows(rec["episode"])
        if want == 0:
            out.rejects.append(
                ("transitions", "episode", f"episode {rec['episode']} begins no batch of {self.batch} of the run")
            )
            return out
        if not (len(rec["k"]) == len(rec["r"]) == len(rec["k2"]) == len(rec["mask2"]) == n == want):
            out.rejects.append(
                (
                    "transitions",
                    "length",
                    f"arrays of {len(rec['k'])}, {n}, {len(rec['r'])}, {len(rec['k2'])}, "
                    f"{len(rec['mask2'])} rows (the batch from episode {rec['episode']} has {want})",
                )
            )
            return out
        g = self.global_step(rec["episode"], rec["step"])
        if self.learner is not None and g >= self.trained + self.step_window():
            out.rejects.append(
                ("transitions", "future", f"step {g} of the run, {g - self.trained} ahead of the rounds done")
            )
            return out
        rnd = self.rounds.get(g)
        if rnd is not None and (rnd.size != n or rnd.episode != rec["episode"]):
            out.rejects.append(
                ("transitions", "length", f"{n} rows from episode {rec['episode']} for a round of {rnd.size}")
            )
            return out
        rec = {
            **rec,
            "k": np.asarray(rec["k"], dtype=np.float64),
            "a": np.asarray(rec["a"], dtype=np.int64),
            "r": np.asarray(rec["r"], dtype=np.float64),
            "k2": np.asarray(rec["k2"], dtype=np.float64),
            "mask2": np.asarray(rec["mask2"], dtype=bool),
        }  # once, for the store and the learner
        if not rec["mask2"].any(axis=1).all():
            out.rejects.append(("transitions", "range", "mask2 allows no action"))
            return out
        agent, session = rec["agent"], rec["session"]
        if rnd is not None and agent in rnd.records and rnd.records[agent]["session"] != session:
            out.drops.append(("transitions", "duplicate_step"))  # another session's record of a step it sent
            return out
        if not self.store.append(rec):
            out.drops.append(("transitions", "duplicate"))
            self.reack.add((agent, session))
            return out
        if self.learner is None:
            return out
        if g < self.trained:  # its round is over (a late or resent record): it joins the memories now
            out.counters["late_transitions"] += 1
            if self.rounds_of is None:  # the expert's rounds take a step whole or not at all
                self._store_one(rec)
            return out
        rnd = self.rounds.setdefault(g, _Round(episode=rec["episode"], step=rec["step"], size=n))
        if rnd.since is None:
            rnd.since = now
        rnd.records[agent] = rec
        self._run_rounds(now, out)
        return out

    def on_step(self, rec: dict[str, Any], now: float) -> TrainerEffects:
        """A decoded step record of the world: which agents acted in step t (their transitions make the round), and
        how far the world is (episode metrics of later batches are `future`)."""
        out = TrainerEffects()
        if self.store is None or not self.in_run(rec["episode"]):
            return out
        want = self.batch_rows(rec["episode"])
        if want != rec["size"]:
            out.rejects.append(("step", "length", f"a batch of {rec['size']} from episode {rec['episode']}"))
            return out
        if self.learner is None:  # recording only: the world's steps say how far the run is
            if self.world_episode >= 0 and rec["episode"] > self.world_episode + 2 * self.batch:
                out.rejects.append(
                    ("step", "future", f"episode {rec['episode']}, the world was at {self.world_episode}")
                )
                return out
            self.world_episode = max(self.world_episode, rec["episode"])
            return out
        if rec["phase"] != "step":
            return out
        g = self.global_step(rec["episode"], rec["step"])
        if g < self.trained:
            return out
        if g >= self.trained + self.step_window():
            out.rejects.append(("step", "future", f"step {g} of the run, {g - self.trained} ahead of the rounds done"))
            return out
        rnd = self.rounds.get(g)
        if rnd is not None and (rnd.size != rec["size"] or rnd.episode != rec["episode"]):
            out.rejects.append(("step", "length", f"a batch of {rec['size']} for a round of {rnd.size}"))
            return out
        self.world_episode = max(self.world_episode, rec["episode"])
        rnd = self.rounds.setdefault(g, _Round(episode=rec["episode"], step=rec["step"], size=rec["size"]))
        rnd.acted = set(rec["acted"])
        if rnd.since is None:
            rnd.since = now
        self._run_rounds(now, out)
        return out

    def on_ground_truth(self, rec: dict[str, Any]) -> TrainerEffects:
        """A decoded /htlm/ground_truth record: the true levels of a step, which the expert-iteration learner's value
        learns from (the other learners do not read them)."""
        out = TrainerEffects()
        if self.rounds_of is None or self.mode != "train":
            return out
        if rec["run"] != self.run or not self.in_run(rec["episode"]) or self.batch_rows(rec["episode"]) == 0:
            out.drops.append(("ground_truth", "outside_run"))
            return out
        levels = rec["levels"]
        if rec["step"] < 1 or len(levels) != self.batch_rows(rec["episode"]):
            out.rejects.append(("ground_truth", "length", f"{len(levels)} rows at step {rec['step']}"))
            return out
        self.rounds_of.on_truth(rec["episode"], rec["step"], levels)
        return out

    def tick(self, now: float) -> TrainerEffects:
        """Run the rounds whose wait for late agents is over; the expert's round of learning: start it once the
        round's true levels are in, announce its end (new weights) when the worker is done, a heartbeat every
        `HEARTBEAT` seconds meanwhile."""
        out = TrainerEffects()
        ex = self.rounds_of
        if ex is not None and self.held and self.fatal is None:
            try:
                self._expert_tick(ex, now, out)
            except Exception as e:  # the worker's error is the trainer's
                self._fail(f"the expert-iteration learner failed: {type(e).__name__}: {e}", out)
                return out
        # while a round learns, and once finished until the world ends the run (a record may be lost): again
        if (self.held or self.finished) and not self.stopping and now - self.heard_at >= HEARTBEAT:
            self._announce(out, now=now)
        self._run_rounds(now, out)
        return out

    def _expert_tick(self, ex: ExpertTrainer, now: float, out: TrainerEffects) -> None:
        if ex.busy:
            return
        if ex.job is not None:  # round 0 done, or a round's learning
            row = ex.result()
            if row is None:
                out.log.append(("info", f"expert: round 0 (the {ex.settings.warm_baseline}): validation "
                                f"{ex.rounds.rows[0].val_completion:.2f} steps"))  # fmt: skip
            else:
                self.updates = ex.updates
                self._log_round(row, out)
                self.held = False
                self.finished = ex.finished
                if self.finished:
                    out.log.append(
                        ("info", f"expert: the rounds are over; the run's policy is round {ex.rounds.best[1]}'s")
                    )
                self._announce(out, force_weights=True, now=now)
                return
        if ex.ended and ex.rounds.rows and ex.truth_ready(now, self.schedule.round_deadline):  # round 0 is done
            ex.learn()
            out.log.append(("info", f"expert: round {ex.rounds.round} played ({ex.episodes_done} episodes): learning"))

    def _log_round(self, row: Any, out: TrainerEffects) -> None:
        self._write_log({"episodes": row.episodes, "round": row.round, "val_completion": row.val_completion,
                         "val_failure_rate": row.val_failure_rate, "val_unused_fraction": row.val_unused_fraction,
                         "loss": row.policy_loss, "updates": self.updates})  # fmt: skip
        out.log.append(
            (
                "info",
                f"expert: round {row.round}: validation completion {row.val_completion:.2f} ± {row.val_se:.2f}, "
                f"failures {row.val_failure_rate:.1%} (teacher changed {row.changed:.1%}, policy agrees with "
                f"{row.agreement:.1%}; {row.wall_s:.0f} s since the start)",
            )
        )

    def _ready(self, rnd: _Round, now: float) -> bool:
        assert self.scenario is not None
        if len(rnd.records) == self.scenario.n_agents:
            return True
        if rnd.acted is not None and rnd.acted <= rnd.records.keys():
            return True
        return rnd.since is not None and now - rnd.since > self.schedule.round_deadline

    def _run_rounds(self, now: float, out: TrainerEffects) -> None:
        """Every round that is due, in order of the global step."""
        while self.learner is not None and self.fatal is None and not self.held and not self.finished:
            rnd = self.rounds.get(self.trained)
            if rnd is None:
                later = [r for g, r in self.rounds.items() if g > self.trained]
                if later and any(r.since is not None and now - r.since > self.schedule.round_deadline for r in later):
                    out.counters["empty_rounds"] += 1  # nobody's transitions of this step came: skip it
                    self.trained += 1
                    continue
                return
            if not self._ready(rnd, now):
                return
            del self.rounds[self.trained]
            self._round(rnd, out)
            self.trained += 1
            if rnd.step == self.scenario.horizon:  # type: ignore[union-attr]
                self._batch_done(rnd, now, out)
            self._announce(out)

    def _round(self, rnd: _Round, out: TrainerEffects) -> None:
        """Store the step's transitions in the memories (agent order) and do updates_per_step updates."""
        sc = self.scenario
        assert sc is not None
        if self.rounds_of is not None:  # the expert's rounds: the step joins the round's play
            whole = len(rnd.records) == sc.n_agents
            if not whole:
                out.counters["partial_rounds"] += 1
            self.rounds_of.step(rnd.episode, rnd.step, [rnd.records[i] for i in range(sc.n_agents)] if whole else None)
            return
        if len(rnd.records) == sc.n_agents:  # everyone: exactly `htlm train`'s store_batch of the step
            recs = [rnd.records[i] for i in range(sc.n_agents)]
            k = np.stack([r["k"] for r in recs], axis=1)
            k2 = np.stack([r["k2"] for r in recs], axis=1)
            a = np.stack([r["a"] for r in recs], axis=1)
            rew = np.stack([r["r"] for r in recs], axis=1)
            m2 = np.stack([r["mask2"] for r in recs], axis=1)
            if self.expert is not None and self.learner.settings.warm_start(self.learner.episodes_done):
                from htlm_agent.learning.loop import imitate_step

                # the agents acted around the expert's choices from these knowledge states: as `htlm train`
                self.last_loss = imitate_step(self.learner, self.expert, k)
            self.learner.store_batch(k, a, rew, k2, m2, bool(recs[0]["done"]))
        else:  # a round without every agent has no warm-start update (the expert's team choice needs them all)
            out.counters["partial_rounds"] += 1
            for i in sorted(rnd.records):
                self._store_one(rnd.records[i])
        # as `htlm train`: drawn together
        losses = self.learner.train_steps(self.learner.settings.td_updates(self.learner.episodes_done))
        if losses:
            self.last_loss = losses[-1]
            self.updates += len(losses)
        out.counters["train_rounds"] += 1

    def _store_one(self, rec: dict[str, Any]) -> None:
        """One agent's B transitions, into its memory row by row."""
        for i in range(len(rec["a"])):
            self.learner.store(
                int(rec["agent"]),
                np.asarray(rec["k"][i], dtype=np.float64),
                int(rec["a"][i]),
                float(rec["r"][i]),
                np.asarray(rec["k2"][i], dtype=np.float64),
                np.asarray(rec["mask2"][i], dtype=bool),
                bool(rec["done"]),
            )

    def _announce(self, out: TrainerEffects, force_weights: bool = False, now: float | None = None) -> None:
        """The progress record, and the weights when the cadence says so; while an expert round learns (`held`),
        the progress up to the step before (a heartbeat: the world keeps waiting, and knows the trainer lives)."""
        assert self.run is not None
        self.heard_at = time.monotonic() if now is None else now
        trained = self.trained - 1 if self.held else self.trained
        out.progress.append({"run": self.run, "trained": trained, "updates": self.updates, "finished": self.finished})
        if self.held:
            return
        if force_weights or (self.trained - self.first_step) % self.schedule.weights_every == 0:
            out.weights.extend(self.publish_weights())

    def _batch_done(self, rnd: _Round, now: float, out: TrainerEffects) -> None:
        """The last round of a batch: count its episodes, validate and select as `htlm train`, checkpoint when due."""
        from htlm_agent.learning.loop import validate

        if self.rounds_of is not None:  # the expert: a round's last batch starts its learning
            self.held = self.rounds_of.end_batch(rnd.episode, rnd.size, now)  # held: the round learns (`tick`)
            self.episodes_seen = self.rounds_of.episodes_done
            self._write_log({"episodes": self.episodes_seen, "round": self.rounds_of.rounds.round})
            return
        s = self.learner.settings
        self.learner.episodes_done += rnd.size
        self.episodes_seen = int(self.learner.episodes_done)
        done = self.episodes_seen
        lo, n = self.run_range
        final = n > 0 and rnd.episode + rnd.size >= lo + n
        row: dict[str, Any] = {"episodes": done, "updates": self.updates, "loss": self.last_loss}
        if s.validate_every and s.validate_episodes and (done - self.last_val >= s.validate_every or final):
            self.last_val = done
            t0 = time.monotonic()
            vm = validate(self.learner, s.validate_episodes)
            row.update(
                val_completion=vm["completion"]["mean"],
                val_failure_rate=vm["completion"]["failure_rate"],
                val_unused_fraction=vm["unused_fraction"]["mean"],
            )
            if done >= s.selection_from:
                self.selection.offer(vm["completion"]["mean"])
            out.log.append(
                (
                    "info",
                    f"validation after {done} episodes: completion {vm['completion']['mean']:.2f}, failures "
                    f"{vm['completion']['failure_rate']:.1%} ({time.monotonic() - t0:.1f} s)",
                )
            )
        self._write_log(row)
        every = self.schedule.checkpoint_every
        if every and done - self.last_ckpt >= every and not final:
            self.last_ckpt = done
            self.checkpoint(out)

    def on_metrics(self, rec: dict[str, Any]) -> TrainerEffects:
        """A decoded episode_metrics record: log the episode (train_log.jsonl)."""
        out = TrainerEffects()
        if self.store is None:
            return out
        if rec["run"] != self.run:
            out.drops.append(("episode_metrics", "other_run"))
            return out
        if not self.in_run(rec["episode"]):
            out.drops.append(("episode_metrics", "outside_run"))
            return out
        if rec["episode"] <= self.logged_upto:  # a repeat (a replay, or a restarted world's): logged once
            out.drops.append(("episode_metrics", "past"))
            return out
        frontier = self.frontier_episode()
        if rec["episode"] >= frontier:  # no batch the run has reached: logging it would drop the genuine as past
            out.rejects.append(("episode_metrics", "future", f"episode {rec['episode']}, at most {frontier - 1} yet"))
            return out
        self.logged_upto = rec["episode"]
        if self.learner is None:
            self.episodes_seen += 1
        self._write_log({"updates": self.updates, **rec})
        return out

    def frontier_episode(self) -> int:
        """The first episode whose metrics cannot have come yet: two batches beyond the furthest the run is known to
        have reached (the rounds done, the world's step records, the episodes logged, the run's first)."""
        reached = max(self.run_range[0], self.logged_upto + 1, self.world_episode)
        if self.learner is not None and self.scenario is not None:
            reached = max(reached, self.trained // self.scenario.horizon * self.batch)
        return reached + 2 * self.batch

    def _write_log(self, line: dict[str, Any]) -> None:
        if self.log_file is not None:
            self.log_file.write(json.dumps(line) + "\n")

    # ----- the schedule -------------------------------------------------------------------------------------------
    def flush(self) -> TrainerEffects:
        """Write and fsync the buffered transitions; acknowledge every agent session whose durable prefix grew (and
        those that sent a duplicate)."""
        out = TrainerEffects()
        self._flush(out)
        if self.log_file is not None:
            self.log_file.flush()
        return out

    def _flush(self, out: TrainerEffects) -> None:
        store = self.store
        if store is None:
            return
        touched = set(store.flush()) | self.reack
        self.reack = set()
        for agent, session in sorted(touched):
            out.acks.append({"agent": agent, "session": session, "upto": store.acked_upto(agent, session)})

    def publish_weights(self) -> list[dict[str, Any]]:
        """Every agent's weights record taken now (trained = the rounds done), once per value of trained."""
        if self.learner is None or self.trained == self.published_trained:
            return []
        self.published_trained = self.trained
        self.version += 1
        if self._settings_dict is None:
            self._settings_dict = self.learner.settings.to_dict()
        settings = self._settings_dict
        out = []
        for i in range(self.learner.n_agents):
            data = self.learner.agent_weights(i)
            out.append(
                {
                    "agent": i,
                    "version": self.weights_version,
                    "episode": self.episodes_seen,
                    "trained": self.trained,
                    "every": self.schedule.weights_every,
                    **seal(data),
                    "settings": settings,
                }
            )
        return out

    def checkpoint(self, out: TrainerEffects) -> None:
        """Flush the store (acknowledging) and write the learner's checkpoint with the number of records it holds;
        with select_best its networks are the best validated ones (as `htlm train` writes them)."""
        if self.learner is None or self.store is None:
            return
        self._flush(out)
        t0 = time.monotonic()
        if self.rounds_of is not None:
            path = self.rounds_of.save(self.dir / "checkpoint", {"store_records": self.store.count, "run": self.run})
            out.counters["checkpoints"] += 1
            out.log.append(("info", f"checkpoint {path}: round {self.rounds_of.rounds.best[1]}'s policy"))
            return
        s = self.learner.settings
        policy = self.selection.flat if (s.select_best and self.selection is not None) else None
        pending = [
            [int(r["agent"]), str(r["session"]), int(r["seq"])]
            for rnd in self.rounds.values()
            for r in rnd.records.values()
        ]
        extra = {"store_records": self.store.count, "pending_records": pending, "run": self.run}
        if self.selection is not None:
            extra.update(self.selection.info())
        path = self.learner.save(self.dir / "checkpoint", replay=s.keep_replay, extra=extra, policy_flat=policy)
        out.counters["checkpoints"] += 1
        out.log.append(("info", f"checkpoint {path} ({self.store.count} transitions, {time.monotonic() - t0:.2f} s)"))

    def shutdown(self, clock: Callable[[], float] = time.monotonic) -> TrainerEffects:
        """Flush the store and acknowledge, run the rounds still gathered, write the final checkpoint, close the
        files."""
        out = TrainerEffects()
        if self.store is not None:
            self._flush(out)
            if self.fatal is None:
                self._run_rounds(clock() + 1e9, out)  # whatever came: no more waiting
                if self.rounds_of is not None:
                    self.rounds_of.finish()  # a round whose play is in is learned before the checkpoint
                self.checkpoint(out)
            self.store.close()
            self.store = None
        if self.rounds_of is not None:
            self.rounds_of.close()
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
            "trained": str(self.trained),
            "rounds_waiting": str(len(self.rounds)),
            "weights_version": str(self.weights_version),
            "epoch": str(self.epoch),
            **(
                {
                    "expert_steps_skipped": str(self.rounds_of.skipped),
                    "expert_batches_untrue": str(self.rounds_of.untrue),
                }
                if self.rounds_of is not None
                else {}
            ),
        }
