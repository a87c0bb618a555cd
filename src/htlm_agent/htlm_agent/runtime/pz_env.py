"""A PettingZoo ParallelEnv over the in-process `Team` (one episode at a time), for the MARL tools users know.

Every agent of the scenario is a PettingZoo agent. Its observation is its knowledge state K = {b, a_o} (docs/model.md,
Knowledge state) with the reduced action space Â(a_o) as an action mask, in PettingZoo's convention::

    {"observation": Box(0, 1, (p·L + |Ḡ|,), float64), "action_mask": MultiBinary(|Ḡ|)}

Its action is an index into Ḡ (Discrete(|Ḡ|)), its reward its own f_R (docs/model.md, Reward). Episodes always run the
whole horizon: terminations are always False and every agent is truncated at step h.

Actions outside Â(a_o). Â excludes only the idle locations at other sites than a_o's, so the one kind of action
that is in the action space but not in Â is "idle somewhere else". Tools that sample the action space without the
mask (e.g. `pettingzoo.test.parallel_seed_test`) send such actions, so by default (``invalid_action="idle_here"``)
such an action is mapped deterministically to the idle location at the site of a_o (the agent idles where it is),
and ``infos[agent]["action_mapped"]`` is True. With ``invalid_action="raise"`` it is rejected with a ValueError
naming the agent and the action instead. Anything that is not an element of the action space always raises.

Seeding. ``reset(seed=s)`` sets the master seed s and starts episode 0; each later ``reset()`` without a seed starts
the next episode of the same master seed, whose world and channel generators are the streams of (s, episode) in
`htlm_world.seeds`, exactly as the in-process runtime takes them (`Team(scenario, 1, s, episode=e)`). A first
``reset()`` without any seed draws the master seed from the operating system's entropy (`seeds.fresh_seed`). No
global random state is used.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.scenario import Scenario, builtin
from htlm_world.types import IntArray

ObsDict = dict[str, np.ndarray]
"""One agent's observation: {"observation": (K,) float64 knowledge state, "action_mask": (|Ḡ|,) int8}."""


class HTLMParallelEnv(ParallelEnv):  # type: ignore[misc]  # pettingzoo ships no type information
    """The HTLM operation as a PettingZoo ParallelEnv (batch 1, all agents act every step)."""

    metadata: ClassVar[dict[str, Any]] = {"name": "htlm_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        scenario: Scenario | None = None,
        invalid_action: Literal["idle_here", "raise"] = "idle_here",
        seed: int | None = None,
    ) -> None:
        """Create the environment; call `reset` before `step`.

        Args:
            scenario: the operation and the team; the built-in scenario "paper" (heterogeneous team) when None.
            invalid_action: what to do with an action of the action space outside Â(a_o): "idle_here" maps it to
                the idle location at the site of a_o, "raise" raises ValueError.
            seed: master seed used by a first `reset()` without a seed; OS entropy when None.

        Raises:
            ValueError: for an unknown `invalid_action`.
        """
        if invalid_action not in ("idle_here", "raise"):
            raise ValueError(f"invalid_action must be 'idle_here' or 'raise', got {invalid_action!r}")
        self.scenario = scenario if scenario is not None else builtin()
        self.invalid_action = invalid_action
        self.render_mode: str | None = None
        sc = self.scenario
        self.possible_agents: list[str] = [a.name for a in sc.agents]
        self.agents: list[str] = []
        self.observation_spaces: dict[str, spaces.Dict] = {
            name: spaces.Dict(
                {
                    "observation": spaces.Box(0.0, 1.0, shape=(sc.knowledge_size,), dtype=np.float64),
                    "action_mask": spaces.MultiBinary(sc.n_actions),
                }
            )
            for name in self.possible_agents
        }
        self.action_spaces: dict[str, spaces.Discrete] = {
            name: spaces.Discrete(sc.n_actions) for name in self.possible_agents
        }
        self.state_space = spaces.Box(0, sc.levels - 1, shape=(sc.n_tasks,), dtype=np.int64)
        self._seed = seed
        self._episode = -1
        self._team: Team | None = None

    # ----- spaces ------------------------------------------------------------------------------------------------
    def observation_space(self, agent: str) -> spaces.Dict:
        """Observation space of `agent` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        """Action space of `agent`: Discrete(|Ḡ|), the same object on every call."""
        return self.action_spaces[agent]

    # ----- episode -----------------------------------------------------------------------------------------------
    @property
    def episode(self) -> int:
        """Index of the current episode under the master seed (-1 before the first reset)."""
        return self._episode

    @property
    def master_seed(self) -> int | None:
        """The master seed the current episode derives its generators from (None before the first reset)."""
        return self._seed if self._team is not None else None

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, ObsDict], dict[str, dict[str, Any]]]:
        """Start an episode.

        Args:
            seed: master seed; starts episode 0 of it. None continues with the next episode of the current one.
            options: accepted for the PettingZoo API; unused.

        Returns:
            Every agent's observation and an empty info dict per agent.
        """
        if seed is not None:
            self._seed = int(seed)
            self._episode = 0
        else:
            if self._seed is None:
                self._seed = seeds.fresh_seed()
            self._episode += 1
        self._team = Team(self.scenario, 1, self._seed, episode=self._episode)
        self.agents = list(self.possible_agents)
        return self._observations(self._team), {name: {} for name in self.agents}

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, ObsDict],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Advance the operation one step with every live agent's action.

        Args:
            actions: one action per live agent: an integer index into Ḡ.

        Returns:
            observations, rewards (each agent's f_R), terminations (always False), truncations (True at step h)
            and infos ({"executed_action", "action_mapped", "reward_parts", "impossible_evidence"}) per agent.

        Raises:
            RuntimeError: before `reset` or after the episode ended.
            ValueError: a live agent without an action, an unknown agent, an action that is not in the action
                space, or (with invalid_action="raise") an action outside Â(a_o); naming the agent and the action.
        """
        team = self._team
        if team is None or not self.agents:
            raise RuntimeError("the episode is over or was never started; call reset() first")
        missing = [name for name in self.agents if name not in actions]
        if missing:
            raise ValueError(f"no action for live agents {missing}")
        unknown = [name for name in actions if name not in self.agents]
        if unknown:
            raise ValueError(f"actions for agents that are not live: {unknown}; live agents are {self.agents}")
        sc = self.scenario
        mask = team.mask()[0]  # (N, |G|)
        joint: IntArray = np.empty((1, sc.n_agents), dtype=np.int64)
        mapped = [False] * sc.n_agents
        for i, name in enumerate(self.possible_agents):
            a = self._as_index(name, actions[name])
            if not mask[i, a]:
                if self.invalid_action == "raise":
                    allowed = [sc.action_names[j] for j in np.flatnonzero(mask[i])]
                    raise ValueError(f"agent {name!r}: action {a} ({sc.action_names[a]}) is not in Â(a_o) = {allowed}")
                # only idle locations can be outside Â: idle at the site of a_o instead (its one idle location)
                a = int(team.model.idle_action(team.prev[0, i]))
                mapped[i] = True
            joint[0, i] = a
        _, rewards, info = team.step(joint)
        truncated = team.t >= sc.horizon
        obs = self._observations(team)
        names = self.possible_agents
        out_rew = {name: float(rewards[0, i]) for i, name in enumerate(names)}
        terminations = dict.fromkeys(names, False)
        truncations = dict.fromkeys(names, truncated)
        infos: dict[str, dict[str, Any]] = {
            name: {
                "executed_action": int(joint[0, i]),
                "action_mapped": mapped[i],
                "reward_parts": {k: float(v[0, i]) for k, v in info.parts.items()},
                "impossible_evidence": bool(info.impossible[0, i]),
            }
            for i, name in enumerate(names)
        }
        if truncated:
            self.agents = []
        return obs, out_rew, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The true severity levels (p,) of the current episode (for centralized critics; not an observation)."""
        if self._team is None:
            raise RuntimeError("call reset() first")
        return np.asarray(self._team.sim.levels[0].copy())

    def render(self) -> None:
        """No rendering (render_mode is None)."""
        return None

    def close(self) -> None:
        """Nothing to release."""

    # ----- helpers -----------------------------------------------------------------------------------------------
    def _as_index(self, agent: str, action: Any) -> int:
        """The action as an index into Ḡ, or ValueError naming the agent and the action."""
        value = action
        if isinstance(value, np.ndarray) and value.size == 1:
            value = value.reshape(()).item() if np.issubdtype(value.dtype, np.integer) else value
        if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
            raise ValueError(f"agent {agent!r}: action {action!r} is not an integer index into Ḡ")
        n = self.scenario.n_actions
        if not 0 <= int(value) < n:
            raise ValueError(f"agent {agent!r}: action {action!r} is out of the action space 0..{n - 1}")
        return int(value)

    def _observations(self, team: Team) -> dict[str, ObsDict]:
        know = np.clip(team.knowledge()[0], 0.0, 1.0)
        mask = team.mask()[0].astype(np.int8)
        return {
            name: {"observation": know[i].copy(), "action_mask": mask[i].copy()}
            for i, name in enumerate(self.possible_agents)
        }
