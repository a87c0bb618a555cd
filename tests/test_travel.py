"""Travel (docs/model.md, Travel): drives that take steps, the same in the world, the minds and the in-process team;
baselines that price the drive; metrics in seconds and metres; the paper without speeds unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy
from htlm_agent.mind import knowledge
from htlm_agent.runtime.evaluate import evaluate_run
from htlm_agent.runtime.team import Team, rollout
from htlm_world.metrics import drives
from htlm_world.scenario import Scenario, ScenarioError, builtin, from_dict, load
from htlm_world.travel import Travel, TravelState, drive_steps, working_actions
from support.team import assert_loopback_equals_team


def paper_with_travel(step: float = 2.0, speed: float = 10.0, fast: float | None = None) -> Scenario:
    """The paper's operation (two sites 50 m apart) with drives: 50 m at `speed` m/s in steps of `step` s."""
    sc = builtin()
    agents = [a.name for a in sc.agents]
    team = [{"name": n, **sc.agents[i].capabilities} for i, n in enumerate(agents)]
    if fast is not None:
        team[0]["speed"] = fast
    return from_dict({"step_seconds": step, "speed": speed, "agents": team}, "<travel>")


def test_drive_steps_round_a_drive_up_to_whole_steps() -> None:
    assert drive_steps(np.array([0.0, 1e-12, 20.0, 20.5, 40.0]), np.array(20.0)).tolist() == [0, 0, 1, 2, 2]


def test_the_paper_has_no_travel_and_keeps_its_knowledge_layout() -> None:
    sc = builtin()
    assert not sc.travel
    assert sc.knowledge_size == sc.n_tasks * sc.levels + sc.n_actions
    assert Team(sc, 2, 0).travel is None
    moved = paper_with_travel()
    assert moved.knowledge_size == sc.knowledge_size + 2 * sc.n_agents
    assert moved.layout_hash() != sc.layout_hash()


def test_an_agent_sent_to_another_site_drives_and_works_on_nothing_until_it_arrives() -> None:
    sc = paper_with_travel(step=2.0, speed=10.0)  # 50 m at 20 m a step: 3 steps
    state = TravelState(sc, 1)
    far = np.array([[2, 4, 4, 4, 4]])  # agent1 to fire@site2, the others idle at site1
    worked = [bool(state.step(far)[0, 0]) for _ in range(4)]
    assert worked == [False, False, False, True]
    assert state.driven[0, 0] == pytest.approx(50.0)
    assert state.moves[0].tolist() == [1, 0, 0, 0, 0]
    assert state.driven[0, 1:].tolist() == [0.0] * 4


def test_a_new_assignment_during_a_drive_turns_the_agent_from_where_it_is() -> None:
    sc = paper_with_travel(step=2.0, speed=10.0)
    state = TravelState(sc, 1)
    state.step(np.array([[2, 4, 4, 4, 4]]))  # 20 m towards site2
    assert state.eta()[0, 0] == 2
    there = state.step(np.array([[0, 4, 4, 4, 4]]))  # back to site1: 20 m, one step
    assert not there[0, 0]
    assert state.step(np.array([[0, 4, 4, 4, 4]]))[0, 0]
    assert state.driven[0, 0] == pytest.approx(40.0)
    assert state.moves[0, 0] == 2


def test_a_driving_agent_brings_no_capability_and_observes_nothing() -> None:
    sc = paper_with_travel(step=2.0, speed=10.0)
    team = Team(sc, 4, 0)
    team.reset()
    joint = np.tile(np.array([2, 2, 2, 3, 3]), (4, 1))  # everyone to site2: nobody there before step 4
    for _ in range(3):
        _, _, info = team.step(joint)
        assert info.working is not None and (info.working == -1).all()
        assert (info.observations == -1).all()
        assert (info.levels[:, 2:] >= 4).all()  # nothing worked on site2's tasks
    _, _, info = team.step(joint)
    assert info.working is not None and (info.working == joint).all()
    assert (info.observations >= 0).all()


def test_knowledge_holds_every_agents_place_and_arrival() -> None:
    sc = paper_with_travel(step=2.0, speed=10.0)
    team = Team(sc, 3, 0)
    team.reset()
    team.step(np.tile(np.array([2, 0, 0, 1, 4]), (3, 1)))
    place, eta = knowledge.places(team.knowledge(), sc)
    assert place.shape == (3, sc.n_agents, sc.n_agents)
    assert (place == np.array([1, 0, 0, 0, 0])).all()
    assert (eta == np.array([2, 0, 0, 0, 0])).all()


def test_the_runtimes_agree_on_every_drive_bit_for_bit() -> None:
    """The lockstep protocol with one AgentMind per agent equals the in-process team (drivers, their silence)."""
    sc = paper_with_travel(step=2.0, speed=10.0, fast=50.0)
    for name in ("greedy", "auction", "random"):
        team, _ = assert_loopback_equals_team(sc, name, 3, 0, 2)
        assert team.travel is not None and team.travel.driven.sum() > 0, name


def test_greedy_takes_the_nearest_open_task_it_can_work_on() -> None:
    sc = load("facility-20-travel")
    team = Team(sc, 1, 0)
    team.reset()
    ctx = team.context()
    # everyone starts at zone1, the depot: every agent able to work there takes a task of zone1
    acts = GreedyPolicy(sc).act(ctx)[0]
    model_sites = np.array(sc.action_sites)
    able = [i for i in range(sc.n_agents) if any(sc.agents[i].capability(k.uses) for k in sc.kinds[:3])]
    assert (model_sites[acts[able]] == 0).all()


def test_the_auction_bids_finish_times_and_sends_the_fast_drone_farther() -> None:
    sc = load("facility-20-travel")
    ev = {p: evaluate_run(pol, sc, episodes=16, seed=1) for p, pol in (("a", AuctionPolicy(sc)),)}
    tr = ev["a"].metrics["travel"]
    assert tr["step_seconds"] == 10.0
    assert tr["metres_per_agent"]["mean"] > 0
    agents = {a["agent"]: a for a in ev["a"].metrics["agents"]}
    assert agents["scout1"]["metres"]["mean"] > agents["fixer1"]["metres"]["mean"]


def test_mission_time_is_completion_steps_times_the_step_length() -> None:
    sc = paper_with_travel(step=2.0, speed=10.0)
    ev = evaluate_run(GreedyPolicy(sc), sc, episodes=8, seed=0)
    m = ev.metrics
    assert m["travel"]["mission_seconds"]["mean"] == pytest.approx(2.0 * m["completion"]["mean"])
    metres, driving = drives(sc, ev.actions)
    assert metres.shape == (8, sc.n_agents)
    assert np.all(driving <= sc.horizon)


def test_speeds_without_a_step_length_are_refused() -> None:
    with pytest.raises(ScenarioError, match="step_seconds"):
        from_dict({"speed": 2.0}, "<t>")


def test_working_actions_leave_out_who_is_on_the_way() -> None:
    out = working_actions(np.array([[0, 1, 4]]), np.array([[True, False, True]]))
    assert out.tolist() == [[0, -1, 4]]


def test_drive_steps_follow_each_agents_speed() -> None:
    tr = Travel.of(load("facility-20-travel"))
    scout, fixer = 0, 1
    assert tr.steps[scout].max() == 2  # a drone crosses the site in 2 steps of 10 s
    assert tr.steps[fixer].max() == 9  # a ground robot in 9
    assert tr.steps[fixer, 0, 1] == 3  # 40 m at 1.5 m/s: 27 s


def test_rollout_with_travel_finishes_with_the_nearest_greedy() -> None:
    sc = paper_with_travel(step=1.0, speed=50.0)
    tr = rollout(Team(sc, 8, 0), GreedyPolicy(sc))
    assert (tr.levels[-1] == 0).all(axis=-1).mean() >= 0.5


def test_watch_shows_when_a_robot_on_its_way_arrives() -> None:
    from htlm_agent.experiments.watch_view import Belief, _robot
    from htlm_msgs_py.schema import Arrival

    sc = load("facility-20-travel")
    b = Belief(0, 3, [], [], Arrival.NO, 40.0)
    assert _robot(b, sc, 1) == "40.0 m away, arrives in 3 steps (27 s)"  # a ground robot at 1.5 m/s, 10 s steps
    assert _robot(b, sc, 0) == "40.0 m away, arrives in 1 steps (5 s)"  # a drone at 8 m/s
    assert _robot(b, builtin(), 0) == "40.0 m away"


def test_a_travel_blind_team_acts_on_the_knowledge_layout_it_learned() -> None:
    from htlm_agent.experiments.market import TravelBlind
    from htlm_agent.mind.context import Context

    sc = paper_with_travel()
    blind = sc.without_travel()
    assert not blind.travel and blind.knowledge_size == sc.knowledge_size - 2 * sc.n_agents
    seen: list[int] = []

    class Rest:
        def act(self, ctx: Context) -> np.ndarray:
            seen.append(ctx.knowledge.shape[-1])
            return np.full(ctx.prev.shape, sc.n_tasks, dtype=np.int64)

    ev = evaluate_run(TravelBlind(Rest(), blind), sc, episodes=2, seed=0)
    assert set(seen) == {blind.knowledge_size}
    assert ev.metrics["travel"]["metres_per_agent"]["mean"] == 0.0


def test_markers_draw_an_agent_on_its_way_between_the_sites() -> None:
    from htlm_world.markers import DRIVING, MarkerView

    sc = paper_with_travel(step=2.0, speed=10.0)  # 20 m a step, sites at x = 0 and 50
    view = MarkerView(sc)
    view.begin(0)
    view.after_step(0, 1, sc.initial_levels, [2, 4, 4, 4, 4])  # agent1 to fire@site2
    marks = {(m.ns, m.id): m for m in view.marks()}
    drone = marks[("agents", 0)]
    assert drone.rgba == DRIVING and drone.x == pytest.approx(20.0)
    assert marks[("agent_labels", 0)].text == "agent1: to site2 (2 steps)"
    assert marks[("agents", 1)].rgba != DRIVING
