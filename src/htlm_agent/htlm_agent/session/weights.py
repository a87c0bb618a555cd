"""The trainer's weights as one agent takes them, without ROS (`WeightsClient`): the versions it keeps, the gate
that picks the version to act with at each step under the trainer lag, and the learner settings that come with
them (the ε schedule, the warm start)."""

from __future__ import annotations

from typing import Any

from htlm_agent.mind.policies import AgentPolicy
from htlm_agent.session.builtin import builtin_policy
from htlm_agent.session.effects import SessionEffects
from htlm_msgs_py.payload import PayloadError, unseal
from htlm_world.episode import global_step
from htlm_world.scenario import Scenario

WEIGHTS_KEPT = 16
"""Most weight versions the client keeps (the newest; the gate picks one per step)."""


class WeightsClient:
    """The trainer's weights of one agent: cached by the step they were taken after (`take`), picked per step by the
    fixed cadence (`gate`), and the wait for a version that has not arrived (`hold`, `overdue`).

    In training the trainer publishes a new network for every agent after its updates; the agent acts at global step
    g only with the version of the cadence (`trainer_lag`, `every`, htlm_agent.learning.loop.acting_weights), so its
    actions wait until that version arrives or `timeout` is over. The cache outlives a run: a process that stays up
    into the next run keeps what it has.
    """

    def __init__(self, agent: str, timeout: float) -> None:
        """The client of agent `agent` (its name, for the log); `timeout`: the longest wait for the weights of a
        step, seconds (then the actions go with the newest)."""
        self.agent = agent
        self.timeout = timeout
        self.version = -1
        """The newest version taken (-1: none yet)."""
        self.every = 1
        """The trainer's cadence: a version every this many steps."""
        self.versions: dict[int, AgentPolicy] = {}
        """trained -> AgentQ: the weights the trainer took after the updates of the steps before `trained`."""
        self.learner: Any = None
        """The learner settings that came with the weights (or with the checkpoint the agent acts with)."""
        self._learner_data: Any = None
        self.expert: AgentPolicy | None = None
        """The baseline the agent acts with in the warm start of a training run (`Settings.imitate`)."""
        self.deferred_since = 0.0
        """Since when the step in progress waits for its weights."""
        self.scenario: Scenario | None = None
        self.index = -1
        self.batch = 1
        self.first_step = 0
        self.trainer_lag = 0
        self.training = False

    def join(
        self, scenario: Scenario, index: int, batch: int, first_step: int, trainer_lag: int, training: bool
    ) -> None:
        """A run is joined: agent `index` of `scenario`, batches of `batch`, the run's first global step, the
        trainer lag, and whether the run trains."""
        self.scenario, self.index, self.batch = scenario, index, batch
        self.first_step, self.trainer_lag, self.training = first_step, trainer_lag, training

    def take(self, rec: dict[str, Any], out: SessionEffects) -> AgentPolicy | None:
        """The trainer's weights record for this agent (decoded): the network made of them, cached by the step it
        was taken after; None when the record is refused (counted in `out`)."""
        assert self.scenario is not None
        if rec["agent"] != self.index:
            out.rejects.append(("weights", "agent", f"weights for agent {rec['agent']} on {self.agent}'s topic"))
            return None
        if rec["version"] <= self.version:
            out.drops.append(("weights", "past"))
            return None
        try:
            data = unseal(rec)
        except PayloadError as e:
            out.rejects.append(("weights", "data", str(e)))
            return None
        try:
            from htlm_agent.learning.qnet import AgentQ, network_shapes, unpack_weights
            from htlm_agent.learning.settings import Settings

            if self.learner is None or rec["settings"] != self._learner_data:
                ls = Settings.from_dict(rec["settings"], "weights.settings")
                self._learner_data = rec["settings"]
            else:
                ls = self.learner
            params = unpack_weights(data, network_shapes(self.scenario, ls))
            net = AgentQ.for_agent(self.scenario, ls, self.index, params)  # every version its own network
        except ValueError as e:
            out.rejects.append(("weights", "data", str(e)))
            return None
        self.learner = ls
        self.version = rec["version"]
        self.every = rec["every"]
        self.versions[rec["trained"]] = net
        while len(self.versions) > WEIGHTS_KEPT:
            del self.versions[min(self.versions)]
        return net

    def gate(self, episode: int, t: int) -> AgentPolicy | None:
        """The trainer's weights to act with at step t of the batch from `episode` on (the fixed cadence): those
        taken after the updates of the steps before T = max(g0, g - lag), the newest at or below T; None while the
        newest at or below T is older than the cadence's last version R <= T (they are on their way). In the warm
        start of a training run (`Settings.warm_start`) the baseline it imitates, as `htlm train` acts."""
        assert self.scenario is not None
        ls = self.learner
        if ls is not None and self.training and ls.warm_start(episode):  # episode: as `epsilon` counts
            return self._expert(ls.warm_baseline)  # the warm start: the baseline acts, no weights needed
        from htlm_agent.learning.loop import acting_weights  # gated: a training run on the trainer's weights (torch)

        g = global_step(episode, self.batch, t, self.scenario.horizon)
        target, need = acting_weights(g, self.first_step, self.trainer_lag, self.every)
        have = [v for v in self.versions if v <= target]
        if not have or max(have) < need:
            return None
        return self.versions[max(have)]

    def _expert(self, name: str) -> AgentPolicy:
        """The warm start's baseline `name` as this agent runs it on its own knowledge (made once)."""
        if self.expert is None:
            assert self.scenario is not None
            self.expert = builtin_policy(self.scenario, name, self.index)[0]
        return self.expert

    def epsilon(self, episode: int, size: int) -> Any:
        """ε of the batch from `episode` on under the learner's schedule while training (per episode with
        eps_spread, as `htlm train` does); None before the learner settings are known or outside training."""
        if self.learner is None or not self.training:
            return None
        from htlm_agent.learning.loop import episode_epsilons

        return episode_epsilons(self.learner, episode, size)[1]

    def hold(self, now: float) -> None:
        """A step starts waiting for its weights now."""
        self.deferred_since = now

    def overdue(self, now: float) -> bool:
        """Whether the step waiting for its weights has waited longer than `timeout`."""
        return now - self.deferred_since > self.timeout
