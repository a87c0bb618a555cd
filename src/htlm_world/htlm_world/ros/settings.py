"""Settings of the world node: one ROS parameter per field, with its range and whether it may change at run time.

Plain dataclasses (no rclpy): `htlm_msgs_py.ros.declare_settings` declares the parameters from them, the unit tests
check them without ROS, and the node hands the ROS-free protocol (htlm_world.protocol) what it needs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from htlm_msgs_py.params import INT64_MAX, SECONDS, problems, setting
from htlm_msgs_py.schema import EPISODE_MAX
from htlm_world.episode import TRAINER_LAG
from htlm_world.protocol import LockstepSettings
from htlm_world.scenario import Scenario, builtin, load, team_names

EXECUTORS = ("events", "single")
"""events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


@dataclass(frozen=True)
class WorldSettings:
    """Parameters of the world node (one ROS parameter per field)."""

    scenario: str = setting("")
    """Scenario YAML file; empty: the built-in scenario "paper" with `team`."""
    team: str = setting("heterogeneous")
    """Built-in team when `scenario` is empty (heterogeneous, semi-heterogeneous, homogeneous)."""
    seed: int = setting(0, lo=0, hi=INT64_MAX)
    """Master seed of the run: the world and every agent derive their generators from it."""
    mode: str = setting("evaluate", choices=("train", "evaluate", "deploy"))
    """train (agents explore and send transitions), evaluate or deploy (greedy policies)."""
    episodes: int = setting(10, lo=0, hi=EPISODE_MAX, tunable=True)
    """Episodes to run; 0 runs until stopped (may be changed while running: the run ends after that many)."""
    first_episode: int = setting(0, lo=0, hi=EPISODE_MAX)
    """Index of the first episode (seeds are derived from the episode index)."""
    clock: str = setting("lockstep", choices=("lockstep", "free"))
    """lockstep: advance as soon as every live agent answered; free: one step every `period` seconds."""
    period: float = setting(0.5, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Step period of the free-running clock, seconds."""
    operation: str = setting("simulated", choices=("simulated", "external"))
    """simulated: the world simulates the severities and sends every observation; external: the operation is outside
    (clock free, batch 1): the robots publish the observations, an outside source may report the true levels on
    /htlm/severity, the world keeps the clock, the assignments and the logs (docs/ros.md, Connecting your robots)."""
    act_deadline: float = setting(2.0, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Longest wait for the agents' actions of a step, seconds; a silent agent is idle for that step."""
    update_deadline: float = setting(2.0, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Longest wait for the agents' ready after their belief update, seconds."""
    begin_deadline: float = setting(3.0, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Longest wait at the start of an episode for agents to reset (a restarted agent rejoins here), seconds."""
    join_timeout: float = setting(60.0, lo=SECONDS[0], hi=SECONDS[1])
    """Longest wait at the start of the run for every agent to be up, seconds."""
    linger: float = setting(1.0, lo=0.0, hi=60.0)
    """Seconds to keep running after the last episode so every node sees the run stop."""
    run_id: str = setting("")
    """Run identifier announced on /htlm/scenario (letters, digits, _.:-); empty: derived from the seed and the time."""
    run_dir: str = setting("")
    """Directory for the world's episode log (world.jsonl); empty: no file."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    executor: str = setting("events", choices=EXECUTORS)
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""
    batch: int = setting(1, lo=1, hi=4096)
    """B, episodes run at once: every per-step record carries B values, every agent acts for B episodes per step
    (first_episode must be a multiple of B; the last batch is shorter when `episodes` is not)."""
    pace: str = setting("auto", choices=("auto", "on", "off"))
    """Wait for the trainer's updates before each step (auto: in train mode with the lockstep clock)."""
    trainer_lag: int = setting(TRAINER_LAG, lo=0, hi=1000)
    """k of the rate limiter: step g waits until the trainer has done the updates of every step before g - k; the
    agents act with the networks k steps old. It must be the learner's trainer_lag (the default is the learner's
    default, `htlm launch train` passes the learner's, and the trainer warns when they differ)."""
    trainer_deadline: float = setting(30.0, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Longest wait for the trainer's progress, seconds; then the world goes on without it until it is heard."""
    end_hold: float = setting(60.0, lo=0.0, hi=SECONDS[1], tunable=True)
    """Training: longest wait after the last step for the trainer's updates of every step before the run is announced
    stopped, seconds (no agent stops with transitions the trainer has not stored)."""
    markers: bool = setting(True)
    """Publish the operation on /htlm/markers (visualization_msgs/MarkerArray, frame map) for RViz2 and Foxglove."""
    marker_episode: int = setting(0, lo=0, hi=4095, tunable=True)
    """Which episode of a batch the markers show (its index in the batch; the batch's last when the batch is
    smaller)."""

    def lockstep(self, run_id: str) -> LockstepSettings:
        """What the world's side of the protocol takes from these settings, for the run `run_id`."""
        skip = ("run_id", "pace")
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(LockstepSettings) if f.name not in skip}
        pace = self.pace == "on" or (self.pace == "auto" and self.mode == "train" and self.clock == "lockstep")
        return LockstepSettings(run_id=run_id, pace=pace, **kw)


def validate_world_settings(s: WorldSettings) -> list[str]:
    """Problems of a WorldSettings, each naming the parameter and the value (empty when valid)."""
    bad = problems(s)
    if s.scenario == "" and s.team not in team_names():
        bad.append(f"team: {s.team!r} is not one of {team_names()}")
    if s.operation == "external" and s.clock != "free":
        bad.append(f"clock: {s.clock!r}: operation external needs clock free (the robots' world does not wait)")
    if s.operation == "external" and s.batch != 1:
        bad.append(f"batch: {s.batch!r}: operation external runs one episode at a time (batch 1)")
    if s.batch >= 1 and s.first_episode % s.batch:
        bad.append(f"first_episode: {s.first_episode!r} must be a multiple of batch ({s.batch})")
    if s.run_id and (len(s.run_id) > 64 or not all(c.isalnum() or c in "_.:-" for c in s.run_id)):
        bad.append(f"run_id: {s.run_id!r} may hold only letters, digits and _.:- (at most 64)")
    return bad


def load_scenario(s: WorldSettings) -> Scenario:
    """The scenario the settings name (a file, else the built-in one with the team).

    Raises:
        ScenarioError: the file is missing or invalid.
    """
    if s.scenario:
        return load(s.scenario)
    return builtin(s.team)
