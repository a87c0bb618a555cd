"""Which policy an agent acts with, without ROS (`PolicySource`): a built-in baseline, a checkpoint of `htlm train`,
or the trainer's weights (through `weights.WeightsClient`), and the ε it acts with."""

from __future__ import annotations

from typing import Any

from htlm_agent.mind.policies import AgentPolicy
from htlm_agent.session.builtin import BUILTIN_POLICIES, builtin_policy
from htlm_agent.session.effects import SessionEffects
from htlm_agent.session.run import JoinedRun
from htlm_agent.session.weights import WeightsClient


class PolicySource:
    """The agent's policy for the run it joined: `wanted` (auto, checkpoint, trainer, or a built-in baseline; auto:
    the trainer's weights in train mode, else the checkpoint if one is set) made at each join (`choose`); with the
    trainer's weights, each version that comes (`take`) becomes the policy."""

    def __init__(self, agent: str, wanted: str, checkpoint: str, epsilon: float, weights_timeout: float) -> None:
        """The policy source of agent `agent`: `wanted` and `checkpoint` as the node's parameters say; `epsilon`: ε
        of ε-greedy (-1: the learner's schedule while training, the policy's own otherwise); `weights_timeout`: the
        longest wait for the trainer's weights of a step, seconds."""
        self.wanted = wanted
        self.checkpoint = checkpoint
        self.fixed_epsilon = epsilon
        self.weights = WeightsClient(agent, weights_timeout)
        self.kind = ""
        """The kind of policy chosen: checkpoint, trainer or a built-in baseline (empty before a run)."""
        self.policy: AgentPolicy | None = None
        """The policy to act with (None: the trainer's first weights have not come yet)."""
        self.own_epsilon = 0.0
        """ε the policy comes with."""

    def choose(self, run: JoinedRun, out: SessionEffects) -> str | None:
        """Make the policy for `run` (`out.subscribe_weights` when it comes from the trainer); returns why there is
        none (fatal for the process), else None."""
        self.weights.join(run.scenario, run.index, run.batch, run.first_step, run.trainer_lag, run.mode == "train")
        kind = self.wanted
        if kind == "auto":
            kind = "trainer" if run.mode == "train" else ("checkpoint" if self.checkpoint else "")
            if not kind:
                names = ", ".join(BUILTIN_POLICIES)
                return f"mode {run.mode}: no policy: set checkpoint:=DIR, or policy:= one of {names}"
        self.kind = kind
        try:
            self._make(kind, run, out)
        except Exception as e:  # a checkpoint that cannot be used is fatal for this process
            return f"policy {kind}: {e}"
        return None

    def _make(self, kind: str, run: JoinedRun, out: SessionEffects) -> None:
        if kind in BUILTIN_POLICIES:
            self.policy, self.own_epsilon = builtin_policy(run.scenario, kind, run.index)
        elif kind == "checkpoint":
            from htlm_agent.learning.checkpoint import load_checkpoint
            from htlm_agent.learning.learners import agent_policy  # torch only for the policies that need it

            ck = load_checkpoint(self.checkpoint, run.scenario)
            self.policy = agent_policy(ck, run.index)
            self.weights.learner = ck.settings
            self.own_epsilon = 0.0
        else:  # trainer: the first weights record creates the network
            self.policy = None
            out.subscribe_weights = True

    def gated(self, run: JoinedRun) -> bool:
        """Whether the mind acts through the lag gate of the trainer's weights (training on them)."""
        return self.kind == "trainer" and run.mode == "train"

    def epsilon(self, episode: int, size: int) -> Any:
        """ε of the batch from `episode` on: the parameter, else the learner's schedule while training (per episode
        with eps_spread, as `htlm train` does), else the policy's own."""
        if self.fixed_epsilon >= 0.0:
            return self.fixed_epsilon
        scheduled = self.weights.epsilon(episode, size) if self.kind == "trainer" else None
        return self.own_epsilon if scheduled is None else scheduled

    def take(self, rec: dict[str, Any], out: SessionEffects) -> AgentPolicy | None:
        """The trainer's weights record for this agent (decoded, `WeightsClient.take`): the network to act with
        from now on, or None (refused, or the policy does not come from the trainer)."""
        net = self.weights.take(rec, out)
        if net is None or self.kind != "trainer":
            return None
        self.policy = net
        return net
