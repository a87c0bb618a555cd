"""The trainer lag has one default (`htlm_world.episode.TRAINER_LAG`): the world node, the lockstep protocol and the
learner start from it, so a run launched without the setting paces its world by the lag its learner acts with."""

from __future__ import annotations

from htlm_agent.learning.settings import Settings
from htlm_world.episode import TRAINER_LAG
from htlm_world.protocol import LockstepSettings
from htlm_world.ros.settings import WorldSettings


def test_every_trainer_lag_defaults_to_the_one_default() -> None:
    assert {s().trainer_lag for s in (WorldSettings, LockstepSettings, Settings)} == {TRAINER_LAG}
