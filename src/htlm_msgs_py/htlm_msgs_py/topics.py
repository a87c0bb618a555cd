"""Topic names of the HTLM ROS 2 runtime, and the topic table (name, type, QoS, publisher, subscribers).

Every topic lives under the namespace /htlm except the standard /diagnostics. Per-agent topics carry the agent's
name from the scenario (letters, digits and _ only, so always a valid topic token). The table `TOPICS` is the one
source of the topic table of docs/ros.md and of the integration tests' list of subscribed topics.
"""

from __future__ import annotations

from dataclasses import dataclass

NAMESPACE = "/htlm"

SCENARIO = f"{NAMESPACE}/scenario"
"""World -> everyone (state): the scenario, run id, seed, mode and episode range of the run."""
STEP = f"{NAMESPACE}/step"
"""World -> agents and trainer: the lockstep clock, {episode, size, step, phase, acted} of a batch of episodes."""
ACTION = f"{NAMESPACE}/action"
"""Agent -> world: the agent's assignment for a step."""
BROADCAST = f"{NAMESPACE}/broadcast"
"""Agent -> agents: assignment + observed level after the agent's (simulated) channel (docs/model.md, Information I)."""
READY = f"{NAMESPACE}/ready"
"""Agent -> world: the agent finished its belief update of a step (or is ready to begin an episode)."""
TRANSITIONS = f"{NAMESPACE}/transitions"
"""Agent -> trainer: one transition (K, a, r, K', mask', done) per agent and step."""
TRANSITION_ACK = f"{NAMESPACE}/transition_ack"
"""Trainer -> agents: every transition of an agent's session up to a sequence number is stored durably."""
TRAINER_PROGRESS = f"{NAMESPACE}/trainer/progress"
"""Trainer -> world: the steps whose gradient updates are done (the world paces training by it)."""
GROUND_TRUTH = f"{NAMESPACE}/ground_truth"
"""World -> monitoring tools: true levels and the joint assignment applied (agents never read it)."""
EPISODE_METRICS = f"{NAMESPACE}/episode_metrics"
"""World -> trainer and monitoring tools: the metrics of docs/model.md of every finished episode."""
SEVERITY = f"{NAMESPACE}/severity"
"""Outside source -> world (external operation): the true levels after a step, for the logs and metrics."""
MARKERS = f"{NAMESPACE}/markers"
"""World -> RViz2 / Foxglove: visualization_msgs/MarkerArray of one episode (sites, task levels, agents), frame map."""
DIAGNOSTICS = "/diagnostics"
"""Every node: health and counters (diagnostic_msgs/DiagnosticArray), the ROS convention."""


def observation(agent: str) -> str:
    """World -> that agent: its observation of a step; the seam where a real robot's perception plugs in."""
    return f"{NAMESPACE}/{agent}/observation"


def goal_pose(agent: str) -> str:
    """Agent -> navigation: geometry_msgs/PoseStamped of the site of the agent's assignment, on change."""
    return f"{NAMESPACE}/{agent}/goal_pose"


def goal(agent: str) -> str:
    """Agent -> its robot: the goal pose as a record (`htlm/goal`), signed with the team key; the twin a robot
    stack verifies before it follows the goal."""
    return f"{NAMESPACE}/{agent}/goal"


def odometry(agent: str) -> str:
    """Simulated robot -> that agent (arrival): nav_msgs/Odometry of the robot in the frame `map`."""
    return f"{NAMESPACE}/{agent}/odom"


def belief(agent: str) -> str:
    """Agent -> monitoring tools: per-task marginals and confident levels of its belief."""
    return f"{NAMESPACE}/{agent}/belief"


def weights(agent: str) -> str:
    """Trainer -> that agent: the latest weights of its own Q-network (state)."""
    return f"{NAMESPACE}/{agent}/weights"


@dataclass(frozen=True)
class TopicSpec:
    """One row of the topic table."""

    name: str
    """Topic name; <agent> stands for an agent's name."""
    msg_type: str
    """ROS 2 interface (common_interfaces only)."""
    qos: str
    """Name of the QoS profile in htlm_msgs_py.qos."""
    schema: str | None
    """Record schema carried in std_msgs/String (htlm_msgs_py.schema), None for non-String topics."""
    publisher: str
    """Who publishes."""
    subscribers: str
    """Who subscribes."""


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(SCENARIO, "std_msgs/msg/String", "STATE", "htlm/scenario", "world", "agents, trainer"),
    TopicSpec(STEP, "std_msgs/msg/String", "EVENTS", "htlm/step", "world", "agents, trainer"),
    TopicSpec(ACTION, "std_msgs/msg/String", "EVENTS", "htlm/action", "agents", "world"),
    TopicSpec(
        observation("<agent>"), "std_msgs/msg/String", "EVENTS", "htlm/observation", "world (or robot)", "<agent>"
    ),
    TopicSpec(SEVERITY, "std_msgs/msg/String", "EVENTS", "htlm/severity", "outside source", "world (external)"),
    TopicSpec(
        odometry("<agent>"), "nav_msgs/msg/Odometry", "ODOMETRY", None, "robot (simulated)", "<agent>, operation"
    ),
    TopicSpec(BROADCAST, "std_msgs/msg/String", "EVENTS", "htlm/broadcast", "agents", "agents"),
    TopicSpec(READY, "std_msgs/msg/String", "EVENTS", "htlm/ready", "agents", "world"),
    TopicSpec(TRANSITIONS, "std_msgs/msg/String", "EVENTS", "htlm/transition", "agents", "trainer"),
    TopicSpec(TRANSITION_ACK, "std_msgs/msg/String", "EVENTS", "htlm/transition_ack", "trainer", "agents"),
    TopicSpec(weights("<agent>"), "std_msgs/msg/String", "WEIGHTS", "htlm/weights", "trainer", "<agent>"),
    TopicSpec(TRAINER_PROGRESS, "std_msgs/msg/String", "EVENTS", "htlm/trainer_progress", "trainer", "world"),
    TopicSpec(belief("<agent>"), "std_msgs/msg/String", "STATE", "htlm/belief", "<agent>", "monitoring"),
    TopicSpec(goal_pose("<agent>"), "geometry_msgs/msg/PoseStamped", "STATE", None, "<agent>", "navigation"),
    TopicSpec(goal("<agent>"), "std_msgs/msg/String", "STATE", "htlm/goal", "<agent>", "robot"),
    TopicSpec(GROUND_TRUTH, "std_msgs/msg/String", "EVENTS", "htlm/ground_truth", "world", "trainer, monitoring"),
    TopicSpec(EPISODE_METRICS, "std_msgs/msg/String", "EVENTS", "htlm/episode_metrics", "world", "trainer"),
    TopicSpec(MARKERS, "visualization_msgs/msg/MarkerArray", "STATE", None, "world", "RViz2, Foxglove"),
    TopicSpec(
        DIAGNOSTICS,
        "diagnostic_msgs/msg/DiagnosticArray",
        "DIAGNOSTICS",
        None,
        "every node",
        "agents, trainer (the world's status), monitoring",
    ),
)
"""The topic table of docs/ros.md."""
