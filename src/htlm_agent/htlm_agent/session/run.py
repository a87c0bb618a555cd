"""The run an agent joined, as its announcement describes it, without ROS (`JoinedRun`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from htlm_msgs_py.schema import limits
from htlm_world.episode import global_step
from htlm_world.model import Model
from htlm_world.scenario import Scenario, from_record


class NotInTeamError(Exception):
    """The agent is not in the team of the scenario announced."""


@dataclass(frozen=True)
class JoinedRun:
    """What an agent takes from the announcement of the run it joins (a decoded scenario record)."""

    run: str
    """The run's id."""
    mode: str
    """train, evaluate or deploy."""
    seed: int
    first_episode: int
    episodes: int
    """Episodes of the run (0: until stopped)."""
    batch: int
    trainer_lag: int
    operation: str
    """simulated, or external: a deployed team (the robots observe, the agents keep the step clock)."""
    period: float
    clock: str
    """lockstep or free."""
    scenario: Scenario
    model: Model
    index: int
    """This agent's index in the team."""
    lim: dict[str, int]
    """The run's bounds for decoding records."""
    first_step: int
    """The global index of the run's first step."""

    @classmethod
    def from_record(cls, rec: dict[str, Any], agent: str) -> JoinedRun:
        """The run `rec` announces, joined by agent `agent`.

        Raises:
            ScenarioRecordError: the scenario of the record is not valid.
            NotInTeamError: `agent` is not in the scenario's team.
        """
        sc = from_record(rec)
        names = [a.name for a in sc.agents]
        if agent not in names:
            raise NotInTeamError(f"agent {agent!r} is not in the scenario's team {names}")
        batch = rec["batch"]
        return cls(
            run=rec["run"],
            mode=rec["mode"],
            seed=rec["seed"],
            first_episode=rec["first_episode"],
            episodes=rec["episodes"],
            batch=batch,
            trainer_lag=rec["trainer_lag"],
            operation=rec["operation"],
            period=rec["period"],
            clock=rec["clock"],
            scenario=sc,
            model=Model.build(sc),
            index=names.index(agent),
            lim=limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, batch, sc.knowledge_size),
            first_step=global_step(rec["first_episode"], batch, 1, sc.horizon),
        )

    @property
    def deployed(self) -> bool:
        """Whether the team is deployed (operation external): robots observe, the agents keep the step clock."""
        return self.operation == "external"

    @property
    def names(self) -> list[str]:
        """The team's agent names, by index."""
        return [a.name for a in self.scenario.agents]

    def in_run(self, episode: int) -> bool:
        """Whether `episode` is one of the run's."""
        return episode >= self.first_episode and (self.episodes == 0 or episode < self.first_episode + self.episodes)
