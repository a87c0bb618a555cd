"""The agent node's parameters that its session reads (`SessionSettings`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SessionSettings:
    """The agent node's parameters the session reads (htlm_agent.ros.settings.AgentSettings documents each)."""

    agent: str
    """This agent's name in the scenario."""
    run: str
    """The run to join (empty: the first announced)."""
    policy: str
    """auto, checkpoint, trainer, or a built-in baseline."""
    checkpoint: str
    """Checkpoint directory of `htlm train`."""
    epsilon: float
    """ε of ε-greedy; -1: the learner's schedule while training, the policy's own otherwise."""
    transitions: str
    """Send transitions to the trainer: auto, on, off."""
    resend_period: float
    """Seconds before an unacknowledged transition is sent again."""
    resend_batch: int
    """Most transitions sent again per resend pass."""
    outbox_limit: int
    """Most unacknowledged transitions kept."""
    belief_every: int
    """Publish the belief summary every this many steps (0: never)."""
    belief_episode: int
    """Which episode of a batch the belief summary and the goal pose follow."""
    broadcast_timeout: float
    """Seconds to wait for the teammates' broadcasts."""
    action_resend: float
    """Seconds after which an action the world has not applied is sent again."""
    resync_timeout: float
    """Seconds without an accepted world message after which the agent rejoins at the next begin."""
    discovery_grace: float
    """Seconds after the scenario during which the agent answers only once matched with world and team."""
    stop_timeout: float
    """Seconds to wait for the trainer's acknowledgements when the run stops."""
    exit_on_stop: bool
    """Exit when the world announces the end of the run."""
    weights_timeout: float
    """Training: longest wait for the trainer's weights of a step, seconds."""
    arrival_radius: float
    """Metres from the site within which the robot has arrived."""
    observation_wait: float
    """Deployed team: seconds to wait for the robot's observation of a step; -1: a quarter of the period."""
