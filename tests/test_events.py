"""Events of an operation (docs/model.md, Events): the scenario language refuses bad events, `EventRun` decides them
by the rules, and both runtimes (the in-process Team and the lockstep protocol of the ROS nodes, here in one process)
produce the same episodes under them, bit for bit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.events import EventRun
from htlm_world.metrics import completion_step
from htlm_world.model import Model
from htlm_world.scenario import EventSpec, ScenarioError, builtin, from_dict, load, read_events
from support.events import MIXED
from support.team import assert_loopback_equals_team


def _with(events: list[dict[str, object]], **more: object) -> object:
    return from_dict({"events": events, **more}, "<test>")


@pytest.mark.parametrize(
    ("event", "message"),
    [
        ({"event": "surge", "site": "site9", "task": "fire", "level": 3}, "events[0].site: 'site9' is not a site"),
        ({"event": "surge", "site": "site1", "task": "water", "level": 3}, "events[0].task: 'water' is not a task"),
        ({"event": "surge", "site": "site1", "task": "fire", "level": 5}, "events[0].level: 5 is out of range 1..4"),
        ({"event": "new_task", "site": "site1", "task": "fire", "level": 3}, "the task starts at level 4"),
        ({"event": "dropout", "agent": "agent9"}, "events[0].agent: 'agent9' is not an agent"),
        ({"event": "dropout", "agent": "most_important"}, "only in a stress set"),
        ({"event": "dropout", "agent": "agent1", "at": 31}, "events[0].at: 31 is out of range 1..30"),
        ({"event": "dropout", "agent": "agent1", "probability": 0.0}, "could never happen"),
        ({"event": "dropout", "agent": "agent1", "once_done": "x"}, "events[0].once_done: 'x' is not a site"),
        ({"event": "explode", "agent": "agent1"}, "events[0].event"),
    ],
)
def test_a_bad_event_stops_loading_naming_the_field_and_value(event: dict[str, object], message: str) -> None:
    with pytest.raises(ScenarioError, match="<test>") as e:
        _with([event])
    assert message in str(e.value)


def test_events_and_stress_sets_belong_to_their_operation(tmp_path: Path) -> None:
    """A file with its own sites does not inherit the paper's stress sets (they name the paper's sites); an events
    file is read against the operation, and a stress set is found by name."""
    assert set(load("warehouse").stress) == {"relapse", "new-task", "lose-most-important", "random-events"}
    sc = builtin()
    assert set(sc.stress) >= {"flare-up", "new-fire", "lose-most-important"} and sc.events == ()
    (ev := tmp_path / "ev.yaml").write_text("events:\n  - {event: surge, site: site2, task: fire, level: 2, at: 4}\n")
    assert read_events(ev, sc) == (EventSpec("surge", site="site2", task="fire", level=2, at=4),)
    (bad := tmp_path / "bad.yaml").write_text("- {event: surge, site: site2, task: fire, level: 9}\n")
    with pytest.raises(ScenarioError, match=r"bad.yaml: events\[0\].level: 9"):
        read_events(bad, sc)
    with pytest.raises(ScenarioError, match="flare-up"):
        read_events("no-such-set", sc)


def test_a_new_task_is_dormant_until_it_appears() -> None:
    sc = from_dict(
        {
            "sites": [{"name": "a", "tasks": {"fire": 3, "rescue": 0}}, {"name": "b", "tasks": {"fire": 2}}],
            "events": [{"event": "new_task", "site": "a", "task": "rescue", "level": 3, "at": 4}],
        },
        "<test>",
    )
    run = EventRun(sc, 2, np.random.default_rng(0))
    levels = np.array([[3, 0, 2], [1, 0, 0]])
    for t in range(1, 4):
        out, fired = run.begin_step(t, levels)
        assert np.array_equal(out, levels) and not fired.any()
    out, fired = run.begin_step(4, levels)
    assert out[:, 1].tolist() == [3, 3] and fired.all()
    out, fired = run.begin_step(5, levels)  # an event happens once
    assert not fired.any()
    assert run.log == [(4, 0, 0), (4, 1, 0)]


def test_an_event_waits_for_its_condition_and_a_dropout_ends_with_a_return() -> None:
    sc = _with(
        [
            {"event": "surge", "site": "site1", "task": "fire", "level": 4, "at": 2, "once_done": "site1"},
            {"event": "dropout", "agent": "agent3", "at": 2},
            {"event": "return", "agent": "agent3", "at": 5},
        ]
    )
    model = Model.build(sc)  # type: ignore[arg-type]
    run = EventRun(sc, 2, np.random.default_rng(0))  # type: ignore[arg-type]
    open_, done = np.array([4, 4, 4, 4]), np.array([0, 0, 3, 1])
    levels = np.stack([open_, done])
    out, fired = run.begin_step(1, levels)
    assert not fired.any() and not run.out.any()
    out, fired = run.begin_step(2, levels)  # site1 done in episode 1 only
    assert fired[:, 0].tolist() == [False, True] and out[1].tolist() == [4, 0, 3, 1]
    assert run.out[:, 2].all()
    prev = np.array([[0, 1, 2, 3, 0], [0, 1, 2, 3, 0]])
    forced = run.force(model, prev, prev)
    assert forced[:, 2].tolist() == [5, 5] and np.array_equal(np.delete(forced, 2, 1), np.delete(prev, 2, 1))
    run.begin_step(5, levels)
    assert not run.out.any()


def test_completion_is_the_step_from_which_every_task_stays_done() -> None:
    """A surge reopens a finished mission: completion is when it is done for good, failure when it is not at h."""
    levels = np.array([[[2]], [[0]], [[3]], [[0]], [[0]]])  # done at 1, reopened at 2, done for good from 3
    comp, failed = completion_step(levels)
    assert comp.tolist() == [3] and failed.tolist() == [False]
    comp, failed = completion_step(np.array([[[2]], [[0]], [[0]], [[1]]]))
    assert comp.tolist() == [3] and failed.tolist() == [True]


@pytest.mark.parametrize("batch", [1, 6])
@pytest.mark.parametrize("name", ["greedy", "random"])
def test_both_runtimes_give_the_same_episodes_under_events(batch: int, name: str) -> None:
    """Surges, a dropout and a return (some by chance, one on a condition): the lockstep protocol in one process
    (WorldEpisode and one AgentMind per agent, as the ROS nodes run them) equals the in-process Team bit for bit, and
    the events happen in some episodes and not in others."""
    sc = _with(MIXED)
    steps = set()
    for seed, b in [(0, 0), (5, 3)]:
        team, tr = assert_loopback_equals_team(sc, name, seed, b, batch)  # type: ignore[arg-type]
        assert team.events.happened[:, 0].all(), "the surge at step 6 happens in every episode"
        steps |= {t for t, _, j in team.events.log if j == 3}
        assert (tr.actions[2:8, :, 1] >= sc.n_tasks).all(), "agent2 is out from step 3 to 8 at least"  # type: ignore[attr-defined]
    assert len(steps) > 1, "the chance surge happens at different steps in different episodes"


def test_events_draw_from_their_own_stream() -> None:
    """The same seed gives the same events, and a scenario without events draws nothing from it (the paper's
    numbers stay what they were)."""
    sc = _with([{"event": "surge", "site": "site1", "task": "fire", "level": 4, "probability": 0.2}])
    a, b = (Team(sc, 50, 3, episode=2) for _ in range(2))  # type: ignore[arg-type]
    for team in (a, b):
        for _ in range(10):
            team.step(team.force_inactive(np.zeros((50, 5), dtype=np.int64)))
    assert np.array_equal(a.events.happened, b.events.happened) and 0 < a.events.happened.sum() < 50
    plain = Team(builtin(), 4, 3)
    plain.step(np.zeros((4, 5), dtype=np.int64))
    assert plain.event_rng.bit_generator.state == seeds.events(3, 0).bit_generator.state


def test_recovery_counts_the_steps_until_the_event_s_tasks_are_done() -> None:
    from htlm_agent.experiments.stress import recoveries

    sc = _with(
        [
            {"event": "surge", "site": "site2", "task": "fire", "level": 3, "at": 2},
            {"event": "dropout", "agent": "agent1", "at": 3},
        ]
    )
    # two episodes, four tasks, steps 0..4: fire@site2 is task 2
    levels = np.zeros((5, 2, 4), dtype=np.int64)
    levels[:, 0, 2] = [0, 0, 3, 1, 0]  # surge at step 2, done after step 4: 3 steps
    levels[:, 1, 2] = [0, 0, 3, 3, 3]  # never
    levels[:, 1, 0] = [4, 4, 4, 4, 4]
    rec = recoveries(sc, levels, [(2, 0, 0), (2, 1, 0), (3, 0, 1)])  # type: ignore[arg-type]
    assert rec.steps.tolist() == [3, -1, 2]
    assert rec.first_step.tolist() == [2, 2] and rec.recovered_at.tolist() == [4, 5]


def test_htlm_stress_runs_a_team_under_a_stress_set_and_writes_its_reports(tmp_path: Path) -> None:
    """The shipped stress set naming the most important agent is resolved; the table, JSON, CSV and PNG are
    written, and an episode's log lists its events for `htlm show`."""
    import json

    from htlm_agent.cli import main

    data = Path(__file__).parent / "data" / "policy_heterogeneous_seed0"
    out = tmp_path / "stress"
    assert main(["stress", "--policy", str(data), "--events", "lose-most-important", "new-fire", "--episodes", "20",
                 "--baselines", "greedy", "--out", str(out)]) == 0  # fmt: skip
    rows = json.loads((out / "stress.json").read_text())
    assert [(r["set"], r["policy"]) for r in rows] == [
        ("lose-most-important", "learned"),
        ("lose-most-important", "greedy"),
        ("new-fire", "learned"),
        ("new-fire", "greedy"),
    ]
    assert rows[0]["events"] == ["most important agent drops out"]
    assert all(r["with"]["episodes_with_events"] == 1.0 for r in rows)
    assert rows[0]["with"]["completion"]["mean"] > rows[0]["without"]["completion"]["mean"]
    assert (out / "stress.png").stat().st_size > 10_000 and len((out / "stress.csv").read_text().splitlines()) == 5
    line = json.loads((out / "new-fire" / "learned-with" / "world.jsonl").read_text().splitlines()[0])
    assert line["events"] == [[5, "new fire at site2"]]
    assert (
        main(["show", str(out / "new-fire" / "learned-with"), "--episode", "0", "--out", str(tmp_path / "e.png")]) == 0
    )


def test_htlm_stress_puts_a_baseline_under_stress_on_a_named_scenario(tmp_path: Path, capsys: Any) -> None:
    """`--baseline` instead of `--policy`: the baseline is the team under stress, on the scenario named, with its
    own most important agent; `--scenario` without `--baseline` is refused with a message."""
    import json

    from htlm_agent.cli import main

    out = tmp_path / "stress"
    assert main(["stress", "--baseline", "auction", "--scenario", "warehouse", "--events", "lose-most-important",
                 "--episodes", "12", "--baselines", "greedy", "--out", str(out), "--json"]) == 0  # fmt: skip
    rows = json.loads(capsys.readouterr().out)
    assert [(r["set"], r["policy"]) for r in rows] == [
        ("lose-most-important", "auction"),
        ("lose-most-important", "greedy"),
    ]
    assert rows[0]["with"]["episodes_with_events"] == 1.0
    assert (out / "lose-most-important" / "auction-with" / "world.jsonl").exists()
    data = Path(__file__).parent / "data" / "policy_heterogeneous_seed0"
    with pytest.raises(SystemExit, match="--scenario goes with --baseline"):
        main(["stress", "--policy", str(data), "--scenario", "warehouse", "--episodes", "4"])


def test_random_events_are_made_for_any_operation_at_their_rate() -> None:
    """`--events random`: every task can come back once its site is done or surge, every agent can drop out, named
    from the operation alone, at about RANDOM_EVENTS_PER_EPISODE events an episode; a stress set of that name wins."""
    from htlm_agent.baselines.heuristics import GreedyPolicy
    from htlm_world.scenario import RANDOM_EVENTS_PER_EPISODE, random_events

    for sc in (builtin(), load("warehouse")):
        ev = read_events("random", sc)
        assert ev == random_events(sc)
        assert len(ev) == 2 * sc.n_tasks + sc.n_agents
        assert {e.agent for e in ev if e.event == "dropout"} == {a.name for a in sc.agents}
        assert all(0 < e.probability < 0.05 for e in ev)
    sc = builtin()
    team = Team(sc.with_events(random_events(sc), "random"), 400, 2)
    rollout_events = 0
    team.reset()
    for _ in range(sc.horizon):
        _, _, info = team.step(GreedyPolicy(team.scenario).act(team.context()))
        rollout_events += int(np.asarray(info.events).sum())
    per_episode = rollout_events / 400
    assert 0.25 * RANDOM_EVENTS_PER_EPISODE < per_episode < 1.5 * RANDOM_EVENTS_PER_EPISODE, per_episode
    named = sc.replace(stress={"random": (EventSpec("dropout", agent="agent1", at=2),)})
    assert read_events("random", named) == named.stress["random"]
