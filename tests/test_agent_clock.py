"""The agents' own step clock in an external operation (deployment), in one process without ROS: every agent steps
on the epoch of the run announcement with no record of any other node, a dead teammate costs the others no step,
and a session started mid-run joins at the next instant (docs/ros.md, Connecting your robots)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from htlm_agent.ros.settings import AgentSettings
from htlm_agent.session.core import AgentSession
from htlm_msgs_py import schema as S
from htlm_msgs_py.schema import limits
from htlm_world.clock import StepClock
from htlm_world.protocol import LockstepSettings, world_protocol
from htlm_world.scenario import builtin

SC = builtin()
PERIOD = 1.0
EPOCH = 1000.0
DT = 0.05
LIM = limits(SC.n_agents, SC.n_tasks, SC.n_actions, SC.levels, SC.horizon, 1)


def _run_record(episodes: int, epoch: float = EPOCH) -> dict[str, Any]:
    settings = LockstepSettings(
        run_id="d1", mode="deploy", episodes=episodes, operation="external", clock="free", period=PERIOD
    )
    rec = world_protocol(SC, settings).scenario_record("running")
    return {**rec, "epoch": epoch}


class _Team:
    """Sessions of a deployed team on one wall clock (`wall_offset` 0: `now` is the wall clock); the broadcasts of
    the live sessions reach every other live session at once; no world, no robot (no observation)."""

    def __init__(self, episodes: int) -> None:
        self.rec = _run_record(episodes)
        self.sessions: dict[int, AgentSession] = {}
        self.actions: dict[int, list[tuple[int, int]]] = {}
        self.logs: dict[int, list[dict[str, Any]]] = {}
        """Per agent, the episodes it logged."""
        self.now = EPOCH - 2.0

    def start(self, k: int) -> AgentSession:
        s = AgentSession(AgentSettings(agent=SC.agents[k].name, policy="greedy").session())
        self.sessions[k] = s
        self.actions.setdefault(k, [])
        self.logs.setdefault(k, [])
        self._deliver(k, s.on_scenario(S.decode(S.encode(S.SCENARIO, self.rec), S.SCENARIO), self.now))
        return s

    def _deliver(self, k: int, eff: Any) -> None:
        assert eff.fatal is None, eff.fatal
        self.logs[k] += eff.episode_log
        for kind, text in eff.publish:
            if kind == "action":
                rec = S.decode(text, S.ACTION, LIM)
                self.actions[k].append((rec["episode"], rec["step"]))
            if kind == "broadcast":
                rec = S.decode(text, S.BROADCAST, LIM)
                for j, other in list(self.sessions.items()):
                    if j != k:
                        self._deliver(j, other.on_broadcast(rec, self.now))

    def run_until(self, wall: float) -> None:
        while self.now < wall:
            self.now = round(self.now + DT, 6)
            for k, s in list(self.sessions.items()):
                self._deliver(k, s.tick(self.now))


def _acted(s: AgentSession, log: list[dict[str, Any]]) -> list[list[bool]]:
    return [x["acted"] for x in log]


def test_each_agent_steps_on_its_own_clock_and_a_dead_teammate_costs_no_step() -> None:
    team = _Team(episodes=2)
    logs = team.logs
    for k in range(SC.n_agents):
        team.start(k)
    clock = StepClock(EPOCH, PERIOD, SC.horizon, 0, 2)
    team.run_until(clock.at(0, 4) + 0.5)
    del team.sessions[2]  # agent 3 dies in step 4 of episode 0
    team.run_until(clock.at(1, SC.horizon) + PERIOD)
    for k in (0, 1, 3, 4):
        assert [x["episode"] for x in logs[k]] == [0, 1], k
        assert _acted(team.sessions[k], logs[k]) == [[True] * SC.horizon] * 2, f"agent {k} missed a step"
        # an action for every step, sent before the step's instant
        assert sorted(set(team.actions[k])) == [(e, t) for e in (0, 1) for t in range(1, SC.horizon + 1)], k
        assert team.sessions[k].stopping, "the run ends on the agent's own clock"


def test_a_session_started_mid_run_joins_at_the_next_instant() -> None:
    team = _Team(episodes=2)
    for k in range(SC.n_agents):
        if k != 1:
            team.start(k)
    clock = StepClock(EPOCH, PERIOD, SC.horizon, 0, 2)
    team.run_until(clock.at(0, 5) + 0.3)  # the instant of step 5 has passed: the newcomer joins at step 6
    late = team.start(1)
    logs = team.logs[1]
    team.run_until(clock.at(1, SC.horizon) + PERIOD)
    assert late.deploy is not None and late.deploy.joined_at == (0, 6)
    assert [x["episode"] for x in logs] == [0, 1]
    assert logs[0]["acted"] == [False] * 5 + [True] * (SC.horizon - 5), "joins at step 6, not before"
    assert logs[1]["acted"] == [True] * SC.horizon
    assert min(team.actions[1]) == (0, 6)


def test_the_world_observes_the_joint_assignment_from_the_agents_actions() -> None:
    settings = LockstepSettings(
        run_id="d1", mode="deploy", episodes=1, operation="external", clock="free", period=PERIOD, join_timeout=5.0
    )
    world = world_protocol(SC, dataclasses.replace(settings))
    eff = world.start(0.0)
    assert [k for k, _ in eff.publish] == ["scenario", "step"]
    sent = []
    for k in range(SC.n_agents):
        sent += world.on_action({"agent": k, "episode": 0, "step": 1, "actions": [SC.start_assignment]}, 0.1).publish
    assert world.epoch > 0.0, "the first begin is over: the epoch is fixed and announced"
    rec = next(f for k, f in sent if k == "scenario")
    assert rec["epoch"] == world.epoch
    clock = world.clock()
    assert clock is not None
    # no agent ever sends anything again: the world still records every step at its instant, all absent
    eff = world.tick(clock.at(0, SC.horizon) + PERIOD)
    steps = [f["step"] for k, f in eff.publish if k == "step" and f["phase"] == "step"]
    assert steps == list(range(1, SC.horizon + 1))
    (line,) = eff.episode_log
    assert line["metrics"]["absent"] == [SC.horizon - 1] * SC.n_agents
    # an action that comes after the observer recorded its step (late, or resent after a loss) still tells what
    # the agent did: the step's log takes it and the agent no longer counts absent there
    assert world.ep is not None
    late = {"agent": 2, "episode": 0, "step": 3, "actions": [1], "before": [SC.start_assignment, 0]}
    eff = world.on_action(late, clock.at(0, SC.horizon) + PERIOD)
    assert eff.drops == [("action", "past")] and eff.counters["absent_rebuilt"] == 2
    assert [row[2] for row in world.ep.trajectory()["actions"][1:3]] == [0, 1]
    assert world.ep.absent[2] == SC.horizon - 3
    # a world restarted mid-run observes from the step in progress on
    again = world_protocol(SC, dataclasses.replace(settings, episodes=3))
    again.resume(5, 1, world.epoch)
    eff = again.start(clock.at(1, 4) + 0.5)
    assert (again.episode, again.t) == (1, 5)
    assert any("from episode 1 step 5" in text for _lv, text in eff.log)
    # ... and takes the agents' actions as they come: its own a_o is stale (the steps it missed were logged as
    # idle), the agent's is the truth, so it does not judge Â(a_o)
    prev = again.ep.prev[:, 0] if again.ep is not None else None
    assert prev is not None
    outside = int(np.flatnonzero(~again.model.action_mask(prev)[0])[0])
    # ... and rebuilds the steps it missed from what the agents say they did before (their `before`)
    before = [outside, -1, outside, outside]
    rec = {"agent": 0, "episode": 1, "step": 5, "actions": [outside], "before": before}
    eff = again.on_action(S.decode(S.encode(S.ACTION, {"run": "d1", **rec}), S.ACTION, LIM), clock.at(1, 5) - 0.2)
    assert any("3 missed steps of agent 0 rebuilt" in text for _lv, text in eff.log), eff.log
    assert again.ep is not None
    assert [row[0] for row in again.ep.trajectory()["actions"]] == [outside, SC.start_assignment, outside, outside]
    eff.publish += again.tick(clock.at(1, 5) + PERIOD).publish
    assert not eff.rejects, eff.rejects
    (rec,) = [f for k, f in eff.publish if k == "step" and f["step"] == 5]
    assert 0 in rec["acted"], rec


def test_a_teammate_whose_clock_is_off_by_more_than_a_quarter_period_is_reported() -> None:
    team = _Team(episodes=1)
    for k in range(SC.n_agents):
        team.start(k)
    team.run_until(EPOCH + 3.0)
    s = team.sessions[0]
    assert s.clock_warning() is None, "one clock for the whole team: no offset"
    assert all(abs(x) < 1e-6 for x in s.clock_offsets().values())
    # agent5's clock runs 0.4 periods ahead: its broadcasts look sent 0.4 s later than they arrive
    bc = {"agent": 4, "episode": 0, "step": 5, "actions": [0], "levels": [-1], "sent": team.now + 0.4 * PERIOD}
    s.on_broadcast(bc, team.now)
    assert abs(s.clock_offsets()[4] + 0.4 * PERIOD) < 1e-6
    warning = s.clock_warning()
    assert warning is not None and "agent5 +0.400 s" in warning, warning
    assert s.values()["clock_offset/agent5"] == "+0.400"
    assert s.values()["clock_tolerance"] == f"{0.25 * PERIOD:g}"  # what htlm watch marks the offsets against


def _stop(team: _Team, at: float) -> None:
    """Every session reads the world's announcement that the run stopped at `at`, before its timer runs again."""
    team.now = at
    stop = {**team.rec, "seq": team.rec["seq"] + 1, "state": "stopped"}
    for k, s in list(team.sessions.items()):
        team._deliver(k, s.on_scenario(S.decode(S.encode(S.SCENARIO, stop), S.SCENARIO), team.now))


@pytest.mark.parametrize("read", [-0.2, 0.05])
def test_the_worlds_stop_at_the_end_of_the_run_leaves_the_last_episode_logged(read: float) -> None:
    # The world (observer) records the last step 0.05 s after its instant on its own clock, and announces the run
    # stopped. An agent may read that before its timer has applied the last instant (a busy host: slow soak of
    # 2026-11-27, test_clock_offset, agent3 logged no episode), or before the instant on its clock at all (the
    # world's clock ahead of ours, within the tolerance). `read`: when, in periods after the last instant.
    team = _Team(episodes=1)
    logs = team.logs
    for k in range(SC.n_agents):
        team.start(k)
    last = StepClock(EPOCH, PERIOD, SC.horizon, 0, 1).at(0, SC.horizon)
    team.run_until(last + min(read, 0.0) * PERIOD - DT)  # the timers' last look is before the last instant
    assert all(not x for x in logs.values())
    _stop(team, last + read * PERIOD)
    team.run_until(last + PERIOD)
    for k, s in team.sessions.items():
        assert s.stopping, f"agent {k} did not stop"
        assert [x["episode"] for x in logs[k]] == [0], f"agent {k} logged no episode"
        assert logs[k][0]["acted"] == [True] * SC.horizon, f"agent {k} missed a step"


def test_the_worlds_stop_in_mid_run_costs_at_most_the_step_in_progress() -> None:
    team = _Team(episodes=2)
    for k in range(SC.n_agents):
        team.start(k)
    clock = StepClock(EPOCH, PERIOD, SC.horizon, 0, 2)
    team.run_until(clock.at(0, 10) + 0.3 * PERIOD)
    _stop(team, team.now)
    team.run_until(clock.at(0, 12))
    for k, s in team.sessions.items():
        assert s.stopping, f"agent {k} did not stop"
        assert max(team.actions[k]) == (0, 11), "no action after the one for the step after the stop"


def test_records_far_ahead_of_the_clock_take_no_place_in_the_tables() -> None:
    """A well-formed record more than FUTURE_STEPS ahead of the receiver's own step clock is rejected (`future`):
    65 of them, for any agent, leave the world's table of heard actions and an agent's table of robot
    observations to the steps in progress, and the genuine records of the step are still taken."""
    settings = LockstepSettings(
        run_id="d1", mode="deploy", episodes=3, operation="external", clock="free", period=PERIOD, join_timeout=5.0
    )
    world = world_protocol(SC, settings)
    world.start(0.0)
    for k in range(SC.n_agents):
        world.on_action({"agent": k, "episode": 0, "step": 1, "actions": [SC.start_assignment], "before": []}, 0.1)
    clock = world.clock()
    assert clock is not None
    now = clock.at(0, 3) + 0.1
    world.tick(now)
    rejects = []
    for i in range(65):
        far = {"agent": i % SC.n_agents, "episode": 2, "step": 1 + i % SC.horizon, "actions": [0], "before": []}
        rejects += world.on_action(far, now).rejects
    assert [r[:2] for r in rejects] == [("action", "future")] * 65
    assert all(e == 0 for e, _t in world.heard), world.heard.keys()
    eff = world.on_action({"agent": 1, "episode": 0, "step": 4, "actions": [0], "before": []}, now)
    assert not eff.rejects and (0, 4) in world.heard and 1 in world.heard[(0, 4)]
    # an agent under its own clock: robot observations far ahead are rejected, the step in progress is taken
    team = _Team(3)
    team.start(0)
    team.run_until(EPOCH + 2.5)
    s = team.sessions[0]
    assert s.deploy is not None and s.observations is not None
    rejects = []
    for i in range(65):
        obs = {"agent": 0, "episode": 2, "step": 1 + i % SC.horizon, "tasks": [0], "levels": [1], "acted": [0]}
        rejects += s.on_observation(obs, team.now).rejects
    assert [r[:2] for r in rejects] == [("observation", "future")] * 65
    assert s.observations.robot == {}
    ok = s.on_observation({"agent": 0, "episode": 0, "step": 3, "tasks": [0], "levels": [1], "acted": [0]}, team.now)
    assert not ok.rejects
