"""world_node: the simulated operation over ROS 2, driving the lockstep protocol (docs/ros.md).

Per episode: announce `begin` until every agent answered with its action for step 1; per step t: wait for the
actions of the live agents until the phase deadline (a silent agent idles at its site for the step and is counted
absent), apply T with the model core (htlm_world.protocol.WorldEpisode), send every agent its observation and
publish the ground truth; each agent's next action (sent after its belief update) is also its "ready"; after the
last step wait for the agents' ready, then publish `end` and the episode metrics. The free-running clock steps at a
fixed period instead of as soon as everyone answered. Run: `ros2 run htlm_world world_node` or
`python -m htlm_world.ros.world_node --ros-args -p episodes:=5`.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.executors import Executor
from rclpy.node import Node

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    EVENTS,
    STATE,
    Health,
    SettingsError,
    String,
    declare_settings,
    run_node,
    spin_until,
    string,
)
from htlm_msgs_py.schema import encode, limits
from htlm_msgs_py.signing import SigningError, signer_from_env
from htlm_world.model import Model
from htlm_world.protocol import StepOutcome, WorldEpisode, WorldSettings, load_scenario, validate_world_settings
from htlm_world.scenario import ScenarioError


def _validate(s: WorldSettings) -> None:
    bad = validate_world_settings(s)
    if bad:
        raise SettingsError("; ".join(bad))


class WorldNode(Node):
    """The world process: owns the simulated operation and the lockstep clock."""

    def __init__(self) -> None:
        """Declare parameters, load the scenario, create publishers, subscriptions and timers."""
        super().__init__("htlm_world")
        self.settings: WorldSettings = declare_settings(
            self,
            WorldSettings,
            _validate,
            tunable=("act_deadline", "update_deadline", "begin_deadline", "period", "episodes"),
            on_change=self._on_settings,
        )
        s = self.settings
        try:
            self.scenario = load_scenario(s)
        except ScenarioError as e:
            raise SettingsError(f"scenario: {e}") from None
        try:
            self.signer = signer_from_env()
        except SigningError as e:
            raise SettingsError(str(e)) from None
        sc = self.scenario
        self.model = Model.build(sc)
        self.lim = limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon)
        self.run_id = s.run_id or f"run-{s.seed}-{int(time.time())}"
        self.health = Health(self, "htlm: world", self.signer)
        self.stop_signal = 0
        # publishers (QoS profiles from htlm_msgs_py)
        self.pub_scenario = self.create_publisher(String, topics.SCENARIO, STATE)
        self.pub_step = self.create_publisher(String, topics.STEP, EVENTS)
        self.pub_obs = [self.create_publisher(String, topics.observation(a.name), EVENTS) for a in sc.agents]
        self.pub_truth = self.create_publisher(String, topics.GROUND_TRUTH, EVENTS)
        self.pub_metrics = self.create_publisher(String, topics.EPISODE_METRICS, EVENTS)
        # subscriptions
        self.create_subscription(String, topics.ACTION, self._on_action, EVENTS)
        self.create_subscription(String, topics.READY, self._on_ready, EVENTS)
        # timers
        self.create_timer(s.diagnostics_period, self._publish_health)
        # protocol state
        self.phase = "idle"
        self.joining = False
        self.episode = -1
        self.t = 0
        self.answers: dict[int, int] = {}
        self.present: set[int] = set()
        self.expected: set[int] = set()
        self.episodes_done = 0
        self.absent_total = 0
        self.log_file: Any = None
        if s.run_dir:
            Path(s.run_dir).mkdir(parents=True, exist_ok=True)
            self.log_file = open(Path(s.run_dir) / "world.jsonl", "a", encoding="utf-8")  # noqa: SIM115

    def _on_settings(self, new: WorldSettings) -> None:
        self.settings = new

    # ----- messages in ------------------------------------------------------------------------------------------
    def _accept(self, topic: str, rec: dict[str, Any], phase: str) -> bool:
        e, t = rec["episode"], rec["step"]
        if self.phase != phase or e != self.episode or t != self.t:
            if (e, t) < (self.episode, self.t) or (e == self.episode and t == self.t):
                self.health.drop(topic, "past")
                if e == self.episode and t == self.t - 1:
                    # alive but slow: wait for it again from the next phase on, or it would lose every race
                    self.present.add(rec["agent"])
            else:
                self.health.drop(topic, "future")
            return False
        return True

    def _on_action(self, msg: String) -> None:
        rec = self.health.decode("action", msg, S.ACTION, self.lim)
        if rec is None or not self._accept("action", rec, "act"):
            return
        k = rec["agent"]
        a = rec["action"]
        if k in self.answers:
            self.health.drop("action", "duplicate")
            return
        if self.scenario.n_idle and a >= self.scenario.n_tasks:
            # an idle location must be at the site of the agent's previous assignment (Â(a_o))
            prev = int(self.ep.prev[k])
            if a != self.ep.idle_action(k) and prev >= 0:
                self.health.reject("action", "range", f"agent {k} idle location {a} not at its site")
                return
        self.answers[k] = a
        self.present.add(k)

    def _on_ready(self, msg: String) -> None:
        rec = self.health.decode("ready", msg, S.READY, self.lim)
        if rec is None or not self._accept("ready", rec, "end"):
            return
        k = rec["agent"]
        if k in self.answers:
            self.health.drop("ready", "duplicate")
            return
        self.answers[k] = 0
        self.present.add(k)

    # ----- messages out -----------------------------------------------------------------------------------------
    def _scenario_record(self, state: str) -> String:
        s, sc = self.settings, self.scenario
        return string(
            encode(
                S.SCENARIO,
                {
                    "run": self.run_id,
                    "seed": s.seed,
                    "mode": s.mode,
                    "clock": s.clock,
                    "first_episode": s.first_episode,
                    "episodes": s.episodes,
                    "state": state,
                    "layout": sc.layout_hash(),
                    "scenario": sc.to_dict(),
                },
                self.signer,
            )
        )

    def _step(self, t: int, phase: str) -> None:
        self.pub_step.publish(string(encode(S.STEP, {"episode": self.episode, "step": t, "phase": phase}, self.signer)))

    def _publish_health(self) -> None:
        h = self.health
        h.values.update(
            {
                "run": self.run_id,
                "phase": self.phase,
                "episode": str(self.episode),
                "step": str(self.t),
                "present": ",".join(str(k) for k in sorted(self.present)),
                "episodes_done": str(self.episodes_done),
                "absent_agent_steps": str(self.absent_total),
                "signed": str(self.signer.enabled).lower(),
            }
        )
        n = self.scenario.n_agents
        status = f"{self.phase} episode {self.episode} step {self.t}"
        if self.joining:
            h.ok(f"episode {self.episode}: waiting for agents {sorted(set(range(n)) - self.answers.keys())} to begin")
        elif self.phase in ("act", "end") and len(self.present) < n:
            h.warn(f"{status}: agents {sorted(set(range(n)) - self.present)} absent")
        else:
            h.ok(status)
        h.publish()

    # ----- the run ------------------------------------------------------------------------------------------------
    def _stopping(self) -> bool:
        return self.stop_signal != 0

    def _discovered(self) -> bool:
        """Every agent that answered also receives its observations."""
        return all(self.pub_obs[k].get_subscription_count() > 0 for k in self.answers)

    def _begin(self, executor: Executor, wait: float) -> None:
        """Announce the episode until every agent answered with its action for step 1, or `wait` seconds."""
        everyone = set(range(self.scenario.n_agents))
        deadline = time.monotonic() + wait
        self.joining = True
        while not self._stopping():
            self._step(0, "begin")
            nudge = min(deadline, time.monotonic() + 0.5)

            def done() -> bool:
                return (everyone <= self.answers.keys() and self._discovered()) or self._stopping()

            if spin_until(executor, done, nudge) or time.monotonic() >= deadline:
                break
        self.joining = False

    def _wait_answers(self, executor: Executor, expect: set[int], deadline: float) -> None:
        """Spin until every agent in `expect` (a live set that late agents may join) answered, or the deadline."""
        spin_until(executor, lambda: expect <= self.answers.keys() or self._stopping(), deadline)

    def run(self, executor: Executor) -> int:
        """Run every episode; returns the exit code (0 done, 128 + signal number when stopped by a signal)."""
        s = self.settings
        sc = self.scenario
        n, h = sc.n_agents, sc.horizon
        self.pub_scenario.publish(self._scenario_record("running"))
        self.health.message = "running"
        self.get_logger().info(
            f"run {self.run_id}: {sc.name}/{sc.team}, {n} agents, h={h}, seed {s.seed}, mode {s.mode}, "
            f"clock {s.clock}, {s.episodes or 'unlimited'} episodes, signing {'on' if self.signer.enabled else 'off'}"
        )
        e = s.first_episode
        first = True
        while not self._stopping() and (s.episodes == 0 or e < s.first_episode + s.episodes):
            s = self.settings
            self.ep = WorldEpisode(sc, self.model, s.seed, e)
            self.episode, self.t, self.phase = e, 1, "act"
            self.answers = {}
            self._begin(executor, s.join_timeout if first else s.begin_deadline)
            if self._stopping():
                break
            self.present = set(self.answers)
            if first and len(self.present) < n:
                self.get_logger().warning(f"starting without agents {sorted(set(range(n)) - self.present)}")
            first = False
            tick = time.monotonic()
            for t in range(1, h + 1):
                s = self.settings
                if t > 1:  # the actions of step t, each sent after the agent's update of step t - 1
                    close = tick + s.period if s.clock == "free" else time.monotonic() + s.act_deadline
                    if s.clock == "free":
                        spin_until(executor, self._stopping, close)
                        tick = close
                    else:  # the live agents; with none live, anyone until the deadline (never race ahead)
                        self._wait_answers(executor, self.present or set(range(n)), close)
                if self._stopping():
                    break
                chosen = dict(self.answers)
                missing = self.present - chosen.keys()
                if missing:
                    self.absent_total += len(missing)
                    self.health.counters["absent_agent_steps"] += len(missing)
                    self.get_logger().warning(
                        f"episode {e} step {t}: no action from agents {sorted(missing)} within the deadline; idle",
                        throttle_duration_sec=5.0,
                    )
                self.present = set(chosen)
                out = self.ep.step(chosen)
                # from here on, the agents' answers are their actions of step t + 1 (ready after step h)
                self.answers = {}
                if t < h:
                    self.t, self.phase = t + 1, "act"
                else:
                    self.t, self.phase = h, "end"
                self._publish_step_result(e, t, out)
            if self._stopping():
                break
            s = self.settings
            expected = set(out.acted)
            self._wait_answers(executor, expected, time.monotonic() + s.update_deadline)
            late = expected - self.answers.keys()
            if late:
                self.health.counters["late_ready"] += len(late)
            self._step(h, "end")
            self._finish_episode()
            e += 1
        self.phase = "stopped"
        self.pub_scenario.publish(self._scenario_record("stopped"))
        self._publish_health()
        if not self._stopping():
            spin_until(executor, lambda: False, time.monotonic() + s.linger)
        if self.log_file is not None:
            self.log_file.close()
        return 128 + self.stop_signal if self.stop_signal else 0

    def _publish_step_result(self, e: int, t: int, out: StepOutcome) -> None:
        """Every agent's observation of step t, then the ground truth (only when someone listens)."""
        sc = self.scenario
        acted = out.acted
        for k in range(sc.n_agents):
            a = int(out.actions[k])
            self.pub_obs[k].publish(
                string(
                    encode(
                        S.OBSERVATION,
                        {
                            "agent": k,
                            "episode": e,
                            "step": t,
                            "task": a if 0 <= a < sc.n_tasks else -1,
                            "level": int(out.observations[k]),
                            "acted": acted,
                        },
                        self.signer,
                    )
                )
            )
        if self.pub_truth.get_subscription_count() > 0:
            self.pub_truth.publish(
                string(
                    encode(
                        S.GROUND_TRUTH,
                        {"episode": e, "step": t, "levels": out.levels.tolist(), "actions": out.actions.tolist()},
                        self.signer,
                    )
                )
            )

    def _finish_episode(self) -> None:
        m = self.ep.metrics()
        self.pub_metrics.publish(string(encode(S.EPISODE_METRICS, m, self.signer)))
        self.episodes_done += 1
        self.get_logger().info(
            f"episode {m['episode']}: completion {m['completion']}{' (failed)' if m['failed'] else ''}, "
            f"idle {m['idle_before']}, reassign {m['reassign_before']}, absent {m['absent']}, {m['seconds']:.2f} s"
        )
        if self.log_file is not None:
            self.log_file.write(json.dumps({"run": self.run_id, "metrics": m, **self.ep.trajectory()}) + "\n")
            self.log_file.flush()


def main(args: list[str] | None = None) -> int:
    """Entry point of `world_node` (exit code: 0 done, 2 bad parameters, 130/143 stopped by SIGINT/SIGTERM)."""
    return run_node("world_node", WorldNode, lambda node, executor: node.run(executor), lambda node: None, args)


if __name__ == "__main__":
    sys.exit(main())
