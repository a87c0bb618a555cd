"""Settings of the agent node and the trainer node: one ROS parameter per field, with its range and whether it may
change at run time.

Plain dataclasses (no rclpy): `htlm_msgs_py.ros.declare_settings` declares the parameters from them, the unit tests
check them without ROS, and the nodes hand the ROS-free cores (htlm_agent.session.core.AgentSession,
htlm_agent.trainer.core.TrainerCore) what they need.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from htlm_agent.session.builtin import BUILTIN_POLICIES
from htlm_agent.session.core import SessionSettings
from htlm_agent.trainer.core import Schedule, load_learner_data
from htlm_msgs_py.params import SECONDS, problems, setting

EXECUTORS = ("events", "single")
"""events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


@dataclass(frozen=True)
class AgentSettings:
    """Parameters of the agent node (one ROS parameter per field)."""

    agent: str = setting("")
    """This agent's name in the scenario (agent1, agent2, ...); required."""
    policy: str = setting("auto", choices=("auto", "checkpoint", "trainer", *BUILTIN_POLICIES))
    """auto (train: from the trainer; else the checkpoint), checkpoint, trainer, or a built-in baseline: greedy,
    auction, qmdp (where the optimum can be computed), lookahead or random."""
    checkpoint: str = setting("")
    """Checkpoint directory of `htlm train` (policy checkpoint, or auto outside training)."""
    epsilon: float = setting(-1.0, lo=-1.0, hi=1.0)
    """ε of ε-greedy, -1 or in [0, 1]; -1: the learner's schedule while training, 0 otherwise."""
    transitions: str = setting("auto", choices=("auto", "on", "off"))
    """Send transitions to the trainer: auto (in train mode), on, off."""
    resend_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds before an unacknowledged transition is sent again."""
    resend_batch: int = setting(200, lo=1, hi=1_000_000)
    """Most transitions sent again per resend period (oldest first), so a restarted trainer is not flooded."""
    outbox_limit: int = setting(100_000, lo=1, hi=100_000_000)
    """Most unacknowledged transitions kept; the oldest are dropped (counted) beyond it."""
    belief_every: int = setting(1, lo=0, hi=1_000_000)
    """Publish the belief summary every this many steps (0: never)."""
    broadcast_timeout: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds to wait for the broadcasts of the teammates that acted before updating without them (keep it below
    the world's act_deadline)."""
    action_resend: float = setting(0.5, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds after which the agent sends its action of a step again while the world has not applied the step."""
    resync_timeout: float = setting(10.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds without any accepted world message after which the agent rejoins at the next episode start."""
    discovery_grace: float = setting(3.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds after the scenario arrives during which the agent answers the world only once it is matched with
    the world and every teammate on the step topics."""
    stop_timeout: float = setting(5.0, lo=0.0, hi=600.0)
    """Seconds to wait for the trainer's acknowledgements when the run stops."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run."""
    frame_id: str = setting("map")
    """Frame of the goal poses."""
    run_dir: str = setting("")
    """Directory for this agent's episode log (<agent>.jsonl); empty: no file."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    executor: str = setting("events", choices=EXECUTORS)
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""
    weights_timeout: float = setting(60.0, lo=SECONDS[0], hi=SECONDS[1])
    """Training: longest wait for the trainer's weights of a step (the fixed cadence), seconds; then the agent acts
    with the newest weights it has (counted as stale_weights)."""
    run: str = setting("")
    """The run to join (its id); empty: the first the world announces. Announcements of any other run are rejected
    while the joined one goes on."""
    world_timeout: float = setting(5.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds without a record or status from the world after which the agent reports it silent (WARN)."""
    belief_episode: int = setting(0, lo=0, hi=4095)
    """Which episode of a batch the belief summary and the goal pose follow (its index in the batch)."""
    pose_topic: str = setting("")
    """The robot's pose topic (e.g. /robot1/odom): the agent reports whether the robot has reached the site of its
    assignment (/diagnostics, belief record); empty: unknown."""
    pose_type: str = setting("odometry", choices=("odometry", "pose"))
    """Message type of pose_topic: odometry (nav_msgs/Odometry) or pose (geometry_msgs/PoseStamped)."""
    arrival_radius: float = setting(2.0, lo=0.0, hi=1e6)
    """Metres from the site within which the robot has arrived."""
    observation_wait: float = setting(-1.0, lo=-1.0, hi=SECONDS[1])
    """External operation: seconds after the instant of a step to wait for the robot's observation before
    updating without one; -1: a quarter of the clock period."""
    person: bool = setting(False)
    """A person plays this agent: serve the person's page (docs/usage.md, A person in the team); the person's reports
    become the agent's observations."""
    page_address: str = setting("127.0.0.1")
    """Address the person's page listens on (127.0.0.1: this machine only; 0.0.0.0: every interface)."""
    page_port: int = setting(0, lo=0, hi=65535)
    """Port of the person's page (0: any free port, logged)."""
    page_token_file: str = setting("")
    """File holding the page's token (one line); required with person."""

    def session(self) -> SessionSettings:
        """The agent session's settings from these parameters."""
        return SessionSettings(**{f.name: getattr(self, f.name) for f in dataclasses.fields(SessionSettings)})


def validate_agent_settings(s: AgentSettings) -> list[str]:
    """Problems of an AgentSettings, each naming the parameter and the value (empty when valid)."""
    bad: list[str] = []
    if not s.agent or not s.agent.replace("_", "").isalnum() or not s.agent[0].isalpha():
        bad.append(f"agent: {s.agent!r} must be an agent name of the scenario (letters, digits, _)")
    bad += problems(s)
    if s.policy == "checkpoint" and not s.checkpoint:
        bad.append("checkpoint: '' : policy checkpoint needs a checkpoint directory")
    if -1.0 < s.epsilon < 0.0:
        bad.append(f"epsilon: {s.epsilon!r} must be -1 or in [0, 1]")
    if not s.frame_id:
        bad.append("frame_id: '' must not be empty")
    if -1.0 < s.observation_wait < 0.0:
        bad.append(f"observation_wait: {s.observation_wait!r} must be -1 or >= 0")
    if s.person and not s.page_token_file:
        bad.append("page_token_file: '' : a person's page needs its token file")
    if not s.page_address:
        bad.append("page_address: '' must not be empty")
    if s.pose_topic and not _topic_name(s.pose_topic):
        bad.append(f"pose_topic: {s.pose_topic!r} is not a valid topic name")
    return bad


def _topic_name(name: str) -> bool:
    """Whether `name` is a plausible ROS topic name (letters, digits, _ and / separators, ~ for private)."""
    body = name.lstrip("/~")
    parts = body.split("/")
    return bool(body) and all(p and (p[0].isalpha() or p[0] == "_") and p.replace("_", "").isalnum() for p in parts)


@dataclass(frozen=True)
class TrainerSettings:
    """Parameters of the trainer node (one ROS parameter per field)."""

    run: str = setting("")
    """The run to join (its id); empty: the first the world announces."""
    world_timeout: float = setting(5.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds without a record or status from the world after which the trainer reports it silent (WARN)."""

    run_dir: str = setting("")
    """Directory of the store (transitions.bin), the checkpoint (checkpoint/) and the training log; required."""
    settings_file: str = setting("")
    """Learner settings file (JSON or YAML, the fields of htlm_agent.learning.settings.Settings); empty: the
    defaults."""
    settings_json: str = setting("")
    """Learner settings overriding the file, as one JSON object, e.g. {"learning_starts": 500}."""
    resume: bool = setting(True)
    """Continue from run_dir's checkpoint and store when they exist."""
    ack_period: float = setting(0.05, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between store flushes (fsync) and acknowledgements."""
    weights_every: int = setting(1, lo=1, hi=1_000_000)
    """Steps between weight publications (the fixed cadence W): the agents act at step g with the weights taken
    after the updates of the steps before max(g0, g - trainer_lag), rounded down to a multiple of W."""
    round_deadline: float = setting(5.0, lo=SECONDS[0], hi=SECONDS[1], tunable=True)
    """Longest wait for the transitions of a step from every agent that acted in it, seconds; then the round of
    updates of the step runs with those that came (a late one joins the next round)."""
    checkpoint_every: int = setting(4096, lo=0, hi=1_000_000_000, tunable=True)
    """Episodes between checkpoints (0: only when the run stops; always one then)."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run."""
    stop_grace: float = setting(3.0, lo=SECONDS[0], hi=SECONDS[1])
    """After the run stopped, seconds without a transition before exiting (agents resend unacknowledged ones)."""
    diagnostics_period: float = setting(1.0, lo=SECONDS[0], hi=SECONDS[1])
    """Seconds between /diagnostics messages."""
    executor: str = setting("single", choices=EXECUTORS)
    """single (SingleThreadedExecutor) or events (rclpy's EventsExecutor). Under the EventsExecutor of the Jazzy
    wheels the trainer, whose transition callbacks train for long stretches, ran the episode-metrics callbacks only
    once the run was over (all 32 episodes of a 32-episode run logged at its last update count); the
    SingleThreadedExecutor logs each batch's metrics within a batch of its arrival, at the same training speed."""

    def schedule(self) -> Schedule:
        """The trainer core's schedule from these settings."""
        return Schedule(**{f.name: getattr(self, f.name) for f in dataclasses.fields(Schedule)})


def validate_trainer_settings(s: TrainerSettings) -> list[str]:
    """Problems of a TrainerSettings, each naming the parameter and the value (empty when valid)."""
    bad: list[str] = []
    if not s.run_dir:
        bad.append("run_dir: '' : the trainer needs a directory for its store and checkpoints")
    if s.settings_json:
        try:
            load_learner_data("", s.settings_json)
        except ValueError as e:
            bad.append(str(e))
    return bad + problems(s)


@dataclass(frozen=True)
class CommanderSettings:
    """Parameters of the commander node: the commander's page of the whole operation (read-only)."""

    people: str = setting("")
    """Comma-separated agents that people play (their reports and availability are shown)."""
    page_address: str = setting("127.0.0.1")
    """Address the commander's page listens on (127.0.0.1: this machine only; 0.0.0.0: every interface)."""
    page_port: int = setting(0, lo=0, hi=65535)
    """Port of the commander's page (0: any free port, logged)."""
    page_token_file: str = setting("")
    """File holding the page's token (one line); required."""
    exit_on_stop: bool = setting(True)
    """Exit when the world announces the end of the run."""
    executor: str = setting("single", choices=EXECUTORS)
    """events (rclpy's EventsExecutor) or single (SingleThreadedExecutor)."""


def validate_commander_settings(s: CommanderSettings) -> list[str]:
    """Problems of a CommanderSettings, each naming the parameter and the value (empty when valid)."""
    bad = problems(s)
    if not s.page_token_file:
        bad.append("page_token_file: '' : the commander's page needs its token file")
    if not s.page_address:
        bad.append("page_address: '' must not be empty")
    return bad
