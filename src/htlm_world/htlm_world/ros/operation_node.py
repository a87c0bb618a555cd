"""operation_node: the stand-in operation of the simulated robots, the outside truth an external-operation world
does not simulate (docs/ros.md, Connecting your robots).

It keeps the true task levels of the current episode and steps on the run's clock (htlm_world.clock: the epoch and
period of the run announcement, no record of the world needed): at the instant of step t it applies the model's T
to the capabilities of the robots that are at the site of the assignment their agent sent for step t (an agent not
heard idles at its site) (their nav_msgs/Odometry on /htlm/<agent>/odom, within
`arrival_radius`): a robot on its way works on nothing; an agent a person plays (`people`) works where it is sent.
It publishes the levels on /htlm/severity, where the
simulated robots read the true level of the task they observe and the world takes the levels for its logs and
metrics. Run: `python -m htlm_world.ros.operation_node` (or `htlm launch deploy --robots sim`).
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Any

import numpy as np
from nav_msgs.msg import Odometry

from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.ros import (
    EVENTS,
    POSE_READER,
    String,
    run_node,
    spin_until_finished,
    string,
    subscribe_records,
)
from htlm_msgs_py.schema import encode
from htlm_world.clock import StepClock
from htlm_world.robots import StandInOperation, action_distance
from htlm_world.ros.follower import RunFollower
from htlm_world.ros.robot_settings import OperationSettings, validate_operation_settings


class OperationNode(RunFollower):
    """The true levels of the simulated robots' world."""

    def __init__(self) -> None:
        """Parameters, the severity publisher, the world's records; the robots' poses once the run is known."""
        super().__init__("htlm_operation", OperationSettings, validate_operation_settings, "htlm: operation")
        self.op: StandInOperation | None = None
        self.positions: dict[int, tuple[float, float]] = {}
        self.actions: dict[tuple[int, int], dict[int, int]] = {}  # (episode, step) -> agent -> action
        self.applied = -1
        """The run-wide index of the last step applied (htlm_world.clock)."""
        self.prev: Any = None
        self.pub = self.create_publisher(String, topics.SEVERITY, EVENTS)
        subscribe_records(self, topics.ACTION, EVENTS, self._on_action)
        self.create_timer(0.02, self._flush)

    def on_run(self, rec: dict[str, Any]) -> None:
        """Follow every robot's odometry."""
        assert self.scenario is not None
        if rec["batch"] != 1:
            self.fail(f"batch {rec['batch']}: the stand-in operation runs one episode at a time (batch 1)")
            return
        for k, a in enumerate(self.scenario.agents):
            self.create_subscription(
                Odometry, topics.odometry(a.name), functools.partial(self._on_odom, k), POSE_READER
            )
        self.get_logger().info(f"run {self.run}: the stand-in operation of {len(self.scenario.agents)} robots")

    def _on_odom(self, k: int, msg: Odometry) -> None:
        self.positions[k] = (float(msg.pose.pose.position.x), float(msg.pose.pose.position.y))

    def _on_action(self, msg: bytes) -> None:
        rec = self.health.decode("action", msg, S.ACTION, self.lim)
        if rec is None or self.future("action", rec):
            return
        self.actions.setdefault((rec["episode"], rec["step"]), {})[rec["agent"]] = int(rec["actions"][0])
        while len(self.actions) > 64:
            del self.actions[min(self.actions)]
        self._flush()

    def _flush(self) -> None:
        """Apply every step whose instant has passed on the run's clock, with the actions heard for it."""
        if self.scenario is None or self.model is None or self.epoch <= 0.0 or self.stopped:
            return
        sc, model = self.scenario, self.model
        clock = StepClock(self.epoch, self.period, sc.horizon, self.first_episode, self.episodes)
        target = clock.last(time.time())
        if self.applied < 0 and target >= 0:  # (re)started mid-run: join at the step in progress
            self.applied = target - 1
            e, t = clock.step(target)
            self.get_logger().info(f"joined the team's clock at episode {e} step {t}")
        while self.applied < target and clock.in_run(self.applied + 1):
            self.applied += 1
            e, t = clock.step(self.applied)
            if self.op is None or self.op.episode != e:
                self.op = StandInOperation(sc, model, self.seed, e)
                self.prev = np.full(sc.n_agents, sc.start_assignment, dtype=np.int64)
                if t > 1:
                    self.op.t = t - 1
                    self.get_logger().warning(
                        f"episode {e}: the levels start again from the scenario's initial ones at step {t}"
                    )
            heard = self.actions.get((e, t), {})
            n = sc.n_agents
            joint = np.array(
                [heard[k] if k in heard else int(model.idle_action(self.prev[k])) for k in range(n)], dtype=np.int64
            )
            people = {x.strip() for x in self.settings.people.split(",") if x.strip()}
            arrived = np.array(
                [
                    sc.agents[k].name in people
                    or (
                        k in self.positions
                        and action_distance(model, int(joint[k]), *self.positions[k]) <= self.settings.arrival_radius
                    )
                    for k in range(n)
                ]
            )
            self.health.counters["robot_steps_on_the_way"] += int((~arrived).sum())
            levels = self.op.step(joint, arrived)
            self.prev = joint
            self.pub.publish(
                string(encode(S.SEVERITY, {"episode": e, "step": t, "levels": [levels.tolist()]}, self.signer))
            )

    def health_values(self) -> tuple[str, dict[str, str]]:
        """The episode, step and levels."""
        if self.op is None:
            return "waiting for an episode", {}
        lv = ",".join(str(int(x)) for x in self.op.levels[0])
        return f"episode {self.op.episode} step {self.op.t}: levels {lv}", {"levels": lv}


def main(args: list[str] | None = None) -> int:
    """Entry point of `operation_node` (exit code: 0 run over, 2 bad parameters, 130/143 SIGINT/SIGTERM)."""
    return run_node("operation_node", OperationNode, spin_until_finished, lambda node: None, args)


if __name__ == "__main__":
    sys.exit(main())
