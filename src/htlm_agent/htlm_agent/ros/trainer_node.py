"""trainer_node: collects every agent's transitions in a durable store, trains each agent's own Q-network with the
learner of `htlm train` (htlm_agent.learning.dqn.Learner), publishes weights and writes checkpoints in the same format.

Transitions are acknowledged only after the store has fsynced them; an agent keeps every unacknowledged transition
and sends it again, so a trainer killed and restarted loses nothing an agent had sent. On restart the trainer
loads its checkpoint (run_dir/checkpoint, written by Learner.save) and feeds the learner the store's records that
came after it. Run: `ros2 run htlm_agent trainer_node --ros-args -p run_dir:=runs/x` or
`python -m htlm_agent.ros.trainer_node ...`.
"""

from __future__ import annotations

import base64
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.node import Node

from htlm_agent.learning.transition_store import (
    StoreError,
    TrainerSettings,
    TransitionStore,
    load_learner_settings,
    validate_trainer_settings,
)
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    EVENTS,
    STATE,
    STATE_READER,
    Health,
    SettingsError,
    String,
    declare_settings,
    run_node,
    spin_until_finished,
    string,
)
from htlm_msgs_py.schema import encode, limits
from htlm_msgs_py.signing import SigningError, signer_from_env
from htlm_world.scenario import Scenario, ScenarioError, from_dict


def _validate(s: TrainerSettings) -> None:
    bad = validate_trainer_settings(s)
    if bad:
        raise SettingsError("; ".join(bad))


class TrainerNode(Node):
    """The trainer process."""

    def __init__(self) -> None:
        """Declare parameters, create publishers, subscriptions and timers; the learner waits for the scenario."""
        super().__init__("htlm_trainer")
        self.settings: TrainerSettings = declare_settings(self, TrainerSettings, _validate)
        s = self.settings
        try:
            self.signer = signer_from_env()
        except SigningError as e:
            raise SettingsError(str(e)) from None
        self.dir = Path(s.run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.health = Health(self, "htlm: trainer", self.signer)
        self.stop_signal = 0
        self.fatal: str | None = None
        self.stopping = False
        self.stop_at = 0.0
        self.last_transition_at = 0.0
        self.run: str | None = None
        self.mode = ""
        self.run_range = (0, 0)
        self.scenario: Scenario | None = None
        self.lim: dict[str, int] | None = None
        self.learner: Any = None
        self.store: TransitionStore | None = None
        self.pub_weights: list[Any] = []
        self.reack: set[tuple[int, str]] = set()
        self.new_transitions = 0
        self.updates = 0
        self.last_loss: float | None = None
        self.episodes_seen = 0
        self.episodes_stored: set[int] = set()
        self.published_updates = -1
        self.version = 0
        self.epoch = self._next_epoch()
        self.log_file: Any = None
        self.pub_ack = self.create_publisher(String, topics.TRANSITION_ACK, EVENTS)
        self.create_subscription(String, topics.SCENARIO, self._on_scenario, STATE_READER)
        self.create_subscription(String, topics.TRANSITIONS, self._on_transition, EVENTS)
        self.create_subscription(String, topics.EPISODE_METRICS, self._on_metrics, EVENTS)
        self.create_timer(s.diagnostics_period, self._publish_health)
        self.create_timer(s.ack_period, self._flush)
        self.create_timer(0.01, self._train)

    def _next_epoch(self) -> int:
        """A counter of trainer starts in this run directory, so weight versions grow across restarts."""
        f = self.dir / "trainer_epoch"
        try:
            epoch = int(f.read_text().strip()) + 1
        except (OSError, ValueError):
            epoch = 1
        f.write_text(f"{epoch}\n")
        return epoch

    # ----- the run ------------------------------------------------------------------------------------------------
    def _on_scenario(self, msg: String) -> None:
        rec = self.health.decode("scenario", msg, S.SCENARIO)
        if rec is None:
            return
        if rec["run"] == self.run:
            if rec["state"] == "stopped" and not self.stopping:
                self.get_logger().info(f"run {self.run} stopped by the world")
                self.stopping = True
                self.stop_at = time.monotonic()
            return
        try:
            sc = from_dict(rec["scenario"], "/htlm/scenario")
        except ScenarioError as e:
            self.health.reject("scenario", "scenario", str(e))
            return
        if sc.layout_hash() != rec["layout"]:
            self.health.reject("scenario", "layout", f"layout {rec['layout']} != {sc.layout_hash()}")
            return
        if self.scenario is not None:
            if sc.layout_hash() != self.scenario.layout_hash():
                self._fail(f"run {rec['run']} has another layout than the learner's; use a new run_dir")
            else:
                self.run = rec["run"]
                self.run_range = (rec["first_episode"], rec["episodes"])
                self.stopping = rec["state"] == "stopped"
                self.stop_at = time.monotonic()
            return
        self.run = rec["run"]
        self.mode = rec["mode"]
        self.run_range = (rec["first_episode"], rec["episodes"])
        self.stopping = rec["state"] == "stopped"
        self.stop_at = time.monotonic()
        try:
            self._start(sc, rec["seed"])
        except (StoreError, ValueError, OSError) as e:
            self._fail(str(e))

    def _start(self, sc: Scenario, seed: int) -> None:
        from htlm_agent.learning.checkpoint import CheckpointError
        from htlm_agent.learning.dqn import Learner

        s = self.settings
        self.scenario = sc
        self.lim = limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon)
        settings = load_learner_settings(s, seed)
        store_path = self.dir / "transitions.bin"
        ckpt = self.dir / "checkpoint"
        if not s.resume and (store_path.exists() or ckpt.exists()):
            raise StoreError(f"{self.dir}: holds a store or checkpoint and resume is off; use a new run_dir")
        self.store = TransitionStore(store_path, sc.knowledge_size, sc.n_actions)
        self.log_file = open(self.dir / "train_log.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        if self.mode != "train":  # evaluate, deploy: record metrics and any transitions, learn nothing
            self.get_logger().info(f"run {self.run}: mode {self.mode}: recording only (store {store_path})")
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
            self.get_logger().info(
                f"resumed from {ckpt}: {self.episodes_seen} episodes, {self.updates} updates, {fed} stored transitions"
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
        self.pub_weights = [self.create_publisher(String, topics.weights(a.name), STATE) for a in sc.agents]
        self._publish_weights()
        self.get_logger().info(
            f"run {self.run}: training {sc.n_agents} agents of {sc.name}/{sc.team}; store {store_path} holds "
            f"{self.store.count} transitions ({self.store.truncated} torn records cut, {replayed} fed to the learner)"
        )

    def _fail(self, why: str) -> None:
        self.fatal = why
        self.health.error(why)
        self.get_logger().error(why)

    def finished(self) -> bool:
        """Whether the process should exit: fatal error, or the run stopped and no transition came for a while."""
        if self.fatal is not None:
            return True
        if not (self.stopping and self.settings.exit_on_stop):
            return False
        return time.monotonic() - max(self.stop_at, self.last_transition_at) > self.settings.stop_grace

    # ----- messages in ------------------------------------------------------------------------------------------
    def _on_transition(self, msg: String) -> None:
        if self.store is None:  # no scenario yet: the agents send it again until acknowledged
            self.health.counters["ignored/transitions/no_scenario"] += 1
            return
        rec = self.health.decode("transitions", msg, S.TRANSITION, self.lim)
        if rec is None:
            return
        self.last_transition_at = time.monotonic()
        if not self._in_run(rec["episode"]):
            self.health.drop("transitions", "outside_run")
            return
        agent, session = rec["agent"], rec["session"]
        if not any(rec["mask2"]):
            self.health.reject("transitions", "range", "mask2 allows no action")
            return
        if not self.store.append(rec):
            self.health.drop("transitions", "duplicate")
            self.reack.add((agent, session))
            return
        if self.learner is not None:
            self._learn(agent, rec["k"], rec["a"], rec["r"], rec["k2"], rec["mask2"], rec["done"], rec["episode"])
            self.new_transitions += 1

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

    def _in_run(self, episode: int) -> bool:
        lo, n = self.run_range
        return episode >= lo and (n == 0 or episode < lo + n)

    def _on_metrics(self, msg: String) -> None:
        rec = self.health.decode("episode_metrics", msg, S.EPISODE_METRICS, self.lim)
        if rec is None or self.store is None:
            return
        if not self._in_run(rec["episode"]):
            self.health.drop("episode_metrics", "outside_run")
            return
        s = self.settings
        self.episodes_seen += 1
        if self.learner is None:
            if self.log_file is not None:
                self.log_file.write(json.dumps(rec) + "\n")
                self.log_file.flush()
            return
        self.learner.episodes_done = self.episodes_seen
        eps = float(self.learner.settings.epsilon(rec["episode"]))
        line = {"episode": rec["episode"], "updates": self.updates, "loss": self.last_loss, "epsilon": eps, **rec}
        if self.log_file is not None:
            self.log_file.write(json.dumps(line) + "\n")
            self.log_file.flush()
        self.get_logger().info(
            f"episode {rec['episode']}: completion {rec['completion']}, {self.updates} updates, "
            f"loss {self.last_loss if self.last_loss is None else round(self.last_loss, 4)}, epsilon {eps:.3f}, "
            f"store {self.store.count if self.store else 0}"
        )
        if self.episodes_seen % s.publish_every == 0:
            self._publish_weights()
        if s.checkpoint_every and self.episodes_seen % s.checkpoint_every == 0:
            self._checkpoint()

    # ----- timers -----------------------------------------------------------------------------------------------
    def _flush(self) -> None:
        store = self.store
        if store is None:
            return
        touched = set(store.flush()) | self.reack
        self.reack = set()
        for agent, session in sorted(touched):
            self.pub_ack.publish(
                string(
                    encode(
                        S.TRANSITION_ACK,
                        {"agent": agent, "session": session, "upto": store.acked_upto(agent, session)},
                        self.signer,
                    )
                )
            )

    def _train(self) -> None:
        s = self.settings
        if self.learner is None or not s.train_every or self.new_transitions < s.train_every:
            return
        backlog = self.new_transitions // s.train_every
        if backlog > s.max_backlog:  # far behind (a burst of resent transitions): skip rounds, do not fall further
            self.health.counters["skipped_rounds"] += backlog - s.max_backlog
            self.new_transitions -= (backlog - s.max_backlog) * s.train_every
        start = time.monotonic()
        self.health.counters["train_calls"] += 1
        while self.new_transitions >= s.train_every and time.monotonic() - start < s.train_budget:
            self.new_transitions -= s.train_every
            self.health.counters["train_rounds"] += 1
            for _ in range(self.learner.settings.updates_per_step):
                loss = self.learner.train_step()
                if loss is not None:
                    self.last_loss = loss
                    self.updates += 1

    def _publish_weights(self) -> None:
        if self.learner is None or self.updates == self.published_updates:
            return
        self.published_updates = self.updates
        self.version += 1
        version = self.epoch * 2**32 + self.version
        settings = self.learner.settings.to_dict()
        for i, pub in enumerate(self.pub_weights):
            data = self.learner.agent_weights(i)
            pub.publish(
                string(
                    encode(
                        S.WEIGHTS,
                        {
                            "agent": i,
                            "version": version,
                            "episode": self.episodes_seen,
                            "encoding": "base64",
                            "data": base64.b64encode(data).decode(),
                            "sha256": hashlib.sha256(data).hexdigest(),
                            "settings": settings,
                        },
                        self.signer,
                    )
                )
            )

    def _checkpoint(self) -> None:
        if self.learner is None or self.store is None:
            return
        self._flush()
        self.learner.episodes_done = max(self.episodes_seen, len(self.episodes_stored))
        t0 = time.monotonic()
        path = self.learner.save(self.dir / "checkpoint", extra={"store_records": self.store.count, "run": self.run})
        self.health.counters["checkpoints"] += 1
        self.get_logger().info(f"checkpoint {path} ({self.store.count} transitions, {time.monotonic() - t0:.2f} s)")

    def shutdown(self) -> None:
        """Flush the store, acknowledge, and write the final checkpoint."""
        if self.store is not None:
            self._flush()
            if self.fatal is None:
                end = time.monotonic() + 3.0  # catch up on the rounds of updates still owed, briefly
                every = self.settings.train_every
                while self.learner is not None and every and self.new_transitions >= every:
                    if time.monotonic() > end:
                        break
                    self._train()
                self._checkpoint()
            self.store.close()
            self.store = None
        if self.log_file is not None:
            self.log_file.close()
            self.log_file = None

    def _publish_health(self) -> None:
        h = self.health
        h.values.update(
            {
                "run": str(self.run),
                "stored": str(self.store.count if self.store else 0),
                "updates": str(self.updates),
                "loss": str(self.last_loss),
                "episodes_seen": str(self.episodes_seen),
                "weights_version": str(self.epoch * 2**32 + self.version),
                "epoch": str(self.epoch),
                "signed": str(self.signer.enabled).lower(),
            }
        )
        if self.fatal is None:
            h.ok("waiting for the world" if self.store is None else f"{self.updates} updates")
        h.publish()


def _cleanup(node: TrainerNode) -> None:
    node.shutdown()
    node._publish_health()


def main(args: list[str] | None = None) -> int:
    """Entry point of `trainer_node` (exit code: 0 done, 2 bad parameters or store, 130/143 SIGINT/SIGTERM)."""
    return run_node("trainer_node", TrainerNode, spin_until_finished, _cleanup, args)


if __name__ == "__main__":
    sys.exit(main())
