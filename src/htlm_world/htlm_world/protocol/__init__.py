"""The world's side of the protocol, without ROS: one of two protocols over the same episode log and begin
(`base.WorldProtocol`), picked by the run's operation (`world_protocol`):

- simulated: `lockstep.LockstepProtocol` sequences batches of episodes and their steps, simulates them and sends
  the observations;
- external (a deployed team): `deploy.DeployProtocol` observes the agents, who keep the step clock themselves.

The world node (htlm_world.ros.world_node) only decodes messages, feeds them and the time to the protocol and
publishes the records it returns; everything the world decides (phases, deadlines, which agents are present, late
and duplicate answers, the free-running clock, the start and end of episodes and of the run) is decided here, so the
unit tests drive it in one process.
"""

from __future__ import annotations

from collections.abc import Callable

from htlm_world.model import Model
from htlm_world.protocol.base import WorldProtocol
from htlm_world.protocol.deploy import DeployProtocol
from htlm_world.protocol.lockstep import LockstepProtocol
from htlm_world.protocol.settings import LockstepSettings, Phase, WorldEffects
from htlm_world.scenario import Scenario

__all__ = [
    "DeployProtocol",
    "LockstepProtocol",
    "LockstepSettings",
    "Phase",
    "WorldEffects",
    "WorldProtocol",
    "world_protocol",
]


def world_protocol(
    scenario: Scenario,
    settings: LockstepSettings,
    model: Model | None = None,
    listening: Callable[[int], bool] | None = None,
) -> WorldProtocol:
    """The world's protocol of a run: the observer of a deployed team when the operation is external, else the
    lockstep sequencer (the arguments of `WorldProtocol`)."""
    kind = DeployProtocol if settings.operation == "external" else LockstepProtocol
    return kind(scenario, settings, model, listening)
