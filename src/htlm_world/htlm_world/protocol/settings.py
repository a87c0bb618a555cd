"""The run's settings as the world's protocols read them (`LockstepSettings`), what a protocol returns to its node
(`WorldEffects`), and the phases of a world's episode (`Phase`)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from htlm_world.episode import TRAINER_LAG


class Phase(StrEnum):
    """Where the world is in the run; the values are what its diagnostics and status show."""

    IDLE = "idle"
    """Not started."""
    ACT = "act"
    """Waiting for the agents' actions of step t (or, observing a deployed team, for the instant of step t)."""
    END = "end"
    """Waiting for the agents' readies after the last step of a batch."""
    HOLDING = "holding"
    """The run's last step is done: waiting for the trainer's updates before announcing the stop."""
    STOPPED = "stopped"
    """The run is over."""


@dataclass(frozen=True)
class LockstepSettings:
    """What the world's side of the protocol needs to know about the run (the world node's parameters)."""

    seed: int = 0
    """Master seed of the run."""
    mode: str = "evaluate"
    """train, evaluate or deploy (announced to the agents and the trainer)."""
    episodes: int = 10
    """Episodes to run; 0 runs until stopped (read again after every episode)."""
    first_episode: int = 0
    """Index of the first episode."""
    clock: str = "lockstep"
    """lockstep: advance as soon as every live agent answered; free: one step every `period` seconds."""
    period: float = 0.5
    """Step period of the free-running clock, seconds."""
    act_deadline: float = 2.0
    """Longest wait for the agents' actions of a step, seconds."""
    update_deadline: float = 2.0
    """Longest wait for the agents' ready after the last step, seconds."""
    begin_deadline: float = 3.0
    """Longest wait at the start of an episode for every agent to answer, seconds."""
    join_timeout: float = 60.0
    """Longest wait at the start of the first episode for every agent to answer, seconds."""
    linger: float = 1.0
    """Seconds between the end of the last episode and the end of the run."""
    run_id: str = "run"
    """Run identifier announced on /htlm/scenario."""
    batch: int = 1
    """B, episodes run at once; every per-step record carries B values (first_episode must be a multiple of B)."""
    pace: bool = False
    """Wait for the trainer (train mode): step g is applied only once the trainer has finished the gradient updates
    of every step before g - trainer_lag (its /htlm/trainer/progress records)."""
    trainer_lag: int = TRAINER_LAG
    """k of the rate limiter: how many steps the trainer's updates may lag behind the world (0: the agents act with
    the networks of every update before the step, exactly as `htlm train`)."""
    trainer_deadline: float = 30.0
    """Longest wait for the trainer's progress, seconds; then the world goes on without it until it is heard."""
    end_hold: float = 60.0
    """With `pace` (training): longest wait after the last step for the trainer to report the updates of every step
    of the run before the run is announced stopped, seconds (so that no agent stops with transitions the trainer has
    not stored, also when the trainer was away and comes back)."""
    operation: str = "simulated"
    """simulated: the world simulates the severities and sends the observations (`LockstepProtocol`); external: a
    deployed team, the operation is outside (robots observe and publish the observations themselves, an outside
    source may report the true levels; `DeployProtocol`)."""


@dataclass
class WorldEffects:
    """What the node must do after feeding the protocol one message or one look at the clock, in this order."""

    publish: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    """Records to publish, in order, as (kind, fields): kind is scenario, step, observation (fields name the
    agent), ground_truth (only worth publishing when someone listens) or episode_metrics."""
    log: list[tuple[str, str]] = field(default_factory=list)
    """Log lines as (level, text), level info or warning."""
    counters: Counter[str] = field(default_factory=Counter)
    """Counters to add to the node's diagnostics (absent_agent_steps, late_ready)."""
    drops: list[tuple[str, str]] = field(default_factory=list)
    """Well-formed records the protocol dropped, as (topic, reason): past, future, duplicate."""
    rejects: list[tuple[str, str, str]] = field(default_factory=list)
    """Records refused as invalid for the state of the episode, as (topic, reason, detail)."""
    episode_log: list[dict[str, Any]] = field(default_factory=list)
    """Finished episodes for the world's episode log (world.jsonl): run, metrics, levels, actions, observations."""
    status_changed: bool = False
    """The run ended (or stopped): publish the node's status now."""
