"""The world's side of the lockstep protocol without ROS (htlm_world.protocol.WorldProtocol): phases, deadlines,
presence, late and duplicate answers, the free-running clock, the end of episodes and of the run, driven in one
process with the time passed in; batches of B episodes (a short last one), arrays of the wrong length, the pace
gate on the trainer's progress; and the protocol with one AgentMind per agent, every message delivered in one
process, equal to the in-process `team.rollout`."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import pytest

from htlm_world.model import Model
from htlm_world.protocol import LockstepSettings, WorldEffects, WorldProtocol, world_protocol
from htlm_world.scenario import builtin
from support.team import assert_logs_equal_rollout, builtin_team, loopback_run, reference

SC = builtin()
N, H = SC.n_agents, SC.horizon


def _protocol(listening: Any = None, **kw: Any) -> WorldProtocol:
    settings = LockstepSettings(**{"episodes": 1, "linger": 0.0, "run_id": "test", **kw})
    return world_protocol(SC, settings, listening=listening)


def _records(eff: WorldEffects, kind: str) -> list[dict[str, Any]]:
    return [fields for k, fields in eff.publish if k == kind]


def _act(
    p: WorldProtocol,
    agent: int,
    action: int | list[int],
    now: float,
    episode: int | None = None,
    step: int | None = None,
) -> WorldEffects:
    """Agent `agent` sends `action` for `step` of `episode` (default: the protocol's current ones): a list of
    actions, or one action for every episode of the current batch."""
    e = p.episode if episode is None else episode
    actions = [action] * p.size if isinstance(action, int) else action
    rec = {"agent": agent, "episode": e, "step": p.t if step is None else step, "actions": actions}
    return p.on_action(rec, now)


def _step(episode: int, step: int, phase: str, acted: Iterable[int] = (), size: int = 1) -> dict[str, Any]:
    """A step record of the world."""
    return {"episode": episode, "size": size, "step": step, "phase": phase, "acted": list(acted)}


def _ready(p: WorldProtocol, agent: int, now: float, episode: int = 0, step: int = H) -> WorldEffects:
    return p.on_ready({"agent": agent, "episode": episode, "step": step}, now)


def _everyone_acts(p: WorldProtocol, now: float, agents: range | list[int] = range(N)) -> WorldEffects:
    """Every agent in `agents` sends a task (its own index mod p) for the current step; the effects of the last."""
    eff = WorldEffects()
    for k in agents:
        eff = _act(p, k, k % SC.n_tasks, now)
    return eff


def test_begin_then_a_normal_step() -> None:
    p = _protocol()
    eff = p.start(0.0)
    assert [k for k, _ in eff.publish] == ["scenario", "step"]
    assert eff.publish[0][1]["state"] == "running" and eff.publish[0][1]["run"] == "test"
    assert eff.publish[1][1] == _step(0, 0, "begin")
    assert p.joining and p.next_wakeup() == pytest.approx(0.5)  # the begin is announced again after NUDGE
    assert _records(p.tick(0.5), "step") == [_step(0, 0, "begin")]
    for k in range(N - 1):
        assert _act(p, k, k % SC.n_tasks, 0.6).publish == []  # waiting for the last agent
    eff = _act(p, N - 1, (N - 1) % SC.n_tasks, 0.6)  # everyone answered: step 1 goes at once
    # the observations, then the step record (after every applied step), then the ground truth
    assert [k for k, _ in eff.publish] == ["observation"] * N + ["step", "ground_truth"]
    assert _records(eff, "step") == [_step(0, 1, "step", range(N))]
    obs = _records(eff, "observation")
    assert [o["agent"] for o in obs] == list(range(N)) and all(o["step"] == 1 for o in obs)
    assert all(o["acted"] == list(range(N)) and o["tasks"] == [k % SC.n_tasks] for k, o in enumerate(obs))
    assert all(len(o["levels"]) == 1 for o in obs)
    (truth,) = _records(eff, "ground_truth")
    assert truth["actions"] == [[k % SC.n_tasks for k in range(N)]] and len(truth["levels"][0]) == SC.n_tasks
    assert (p.phase, p.t, p.joining, p.present) == ("act", 2, False, set(range(N)))
    assert p.next_wakeup() == pytest.approx(0.6 + p.settings.act_deadline)
    eff = _everyone_acts(p, 0.7)  # step 2 as soon as the live agents answered, long before the deadline
    assert [o["step"] for o in _records(eff, "observation")] == [2] * N and p.t == 3
    assert _records(eff, "step") == [_step(0, 2, "step", range(N))]
    assert not eff.counters and not eff.drops


def test_begin_waits_for_listeners_then_the_deadline() -> None:
    listens = {k: k != 3 for k in range(N)}
    p = _protocol(listening=lambda k: listens[k], join_timeout=5.0)
    p.start(0.0)
    eff = _everyone_acts(p, 0.1)
    assert _records(eff, "observation") == [] and p.joining  # agent 3 does not read its observations yet
    listens[3] = True
    assert len(_records(p.tick(0.2), "observation")) == N and p.t == 2
    q = _protocol(join_timeout=5.0)
    q.start(0.0)
    _everyone_acts(q, 0.1, agents=[0, 1])
    assert _records(q.tick(4.9), "observation") == []
    eff = q.tick(5.0)  # the join timeout: the episode starts with the agents that answered
    assert eff.log == [("warning", "starting without agents [2, 3, 4]")]
    assert _records(eff, "observation")[0]["acted"] == [0, 1] and q.present == {0, 1}
    assert _records(eff, "step") == [_step(0, 1, "step", [0, 1])]


def test_a_silent_agent_idles_at_its_site_and_is_counted() -> None:
    p = _protocol()
    p.start(0.0)
    _everyone_acts(p, 0.0)  # step 1: agent 4 works on task 4 % p
    assert p.ep is not None
    prev4 = int(p.ep.prev[0, 4])
    assert _everyone_acts(p, 0.1, agents=range(N - 1)).publish == []  # step 2: agent 4 is silent; wait for it
    eff = p.tick(0.1 + p.settings.act_deadline)  # the deadline: go on without it
    (truth,) = _records(eff, "ground_truth")
    assert truth["actions"][0][4] == int(Model.build(SC).idle_action(np.int64(prev4))) >= SC.n_tasks
    assert _records(eff, "observation")[4]["tasks"] == [-1] and _records(eff, "observation")[4]["levels"] == [-1]
    assert _records(eff, "observation")[0]["acted"] == [0, 1, 2, 3]
    assert _records(eff, "step") == [_step(0, 2, "step", [0, 1, 2, 3])]
    assert eff.counters["absent_agent_steps"] == 1 and p.absent_total == 1
    assert eff.log and eff.log[0][0] == "warning" and "agents [4]" in eff.log[0][1]
    assert p.status() == (False, "act episode 0 step 3: agents [4] absent")
    # no longer waited for: step 3 goes as soon as the others answered, and it is not counted again
    eff = _everyone_acts(p, 2.2, agents=range(N - 1))
    assert _records(eff, "ground_truth")[0]["actions"][0][4] >= SC.n_tasks and not eff.counters
    assert p.ep.absent.tolist() == [0, 0, 0, 0, 2]


def test_late_duplicate_future_and_misplaced_answers_are_dropped() -> None:
    p = _protocol()
    assert _act(p, 0, 0, 0.0, step=1).drops == [("action", "future")]  # nothing started yet
    p.start(0.0)
    _everyone_acts(p, 0.0)
    _act(p, 0, 1, 0.1)
    assert _act(p, 0, 2, 0.1).drops == [("action", "duplicate")]
    assert p.answers[0].tolist() == [1]  # the first answer stands
    assert _act(p, 1, 0, 0.1, step=3).drops == [("action", "future")]
    assert _act(p, 1, 0, 0.1, episode=1, step=1).drops == [("action", "future")]
    assert _ready(p, 1, 0.1, step=2).drops == [("ready", "past")]  # a ready is for the end phase only
    assert p.ep is not None
    idle_elsewhere = next(a for a in range(SC.n_tasks, SC.n_actions) if not p.model.action_mask(p.ep.prev[:, 2])[0, a])
    eff = _act(p, 2, idle_elsewhere, 0.1)
    assert eff.rejects and eff.rejects[0][:2] == ("action", "range") and 2 not in p.answers
    # agent 4 misses step 2; its action for step 2 arrives after the step was applied: dropped, but it is
    # waited for again from then on
    _everyone_acts(p, 0.2, agents=[1, 2, 3])
    p.tick(10.0)
    assert p.t == 3 and 4 not in p.present
    assert _act(p, 4, 0, 10.1, step=2).drops == [("action", "past")] and 4 in p.present
    _everyone_acts(p, 10.2, agents=range(N - 1))
    assert p.t == 3  # waits for agent 4 again
    _act(p, 4, 0, 10.3)
    assert p.t == 4


def _play_to_the_end(p: WorldProtocol, now: float, episode: int = 0) -> WorldEffects:
    eff = WorldEffects()
    while p.phase == "act" and p.episode == episode:
        eff = _everyone_acts(p, now)
    return eff


def test_episode_end_late_ready_and_the_end_of_the_run() -> None:
    p = _protocol(episodes=2, linger=0.5, first_episode=3)
    p.start(0.0)
    _play_to_the_end(p, 0.0, episode=3)
    assert (p.phase, p.t) == ("end", H)
    for k in range(N - 1):
        assert _ready(p, k, 1.0, episode=3).publish == []
    assert _ready(p, 0, 1.0, episode=3).drops == [("ready", "duplicate")]
    eff = p.tick(1.0 + p.settings.update_deadline)  # agent 4's ready never came
    assert eff.counters["late_ready"] == 1
    kinds = [k for k, _ in eff.publish]
    assert kinds == ["step", "episode_metrics", "step"]
    assert eff.publish[0][1] == _step(3, H, "end")
    m = eff.publish[1][1]
    assert m["episode"] == 3 and m["absent"] == [0] * N and m["seconds"] == pytest.approx(3.0)
    assert eff.publish[2][1] == _step(4, 0, "begin")
    (line,) = eff.episode_log
    assert line["run"] == "test" and line["metrics"] == m and len(line["levels"]) == H + 1 and len(line["actions"]) == H
    assert any(text.startswith("episode 3: completion") for _, text in eff.log)
    assert _ready(p, 4, 3.1, episode=3).drops == [("ready", "past")]  # too late: the next episode began
    assert p.deadline == pytest.approx(3.0 + p.settings.begin_deadline)  # later episodes: begin_deadline
    assert p.next_wakeup() == pytest.approx(3.0 + 0.5)  # the next announcement of the begin
    _play_to_the_end(p, 4.0, episode=4)
    eff = WorldEffects()
    for k in range(N):
        eff = _ready(p, k, 5.0, episode=4)
    assert [k for k, _ in eff.publish] == ["step", "episode_metrics", "scenario"]
    assert eff.publish[2][1]["state"] == "stopped" and eff.status_changed
    assert p.phase == "stopped" and not p.done and p.episodes_done == 2
    assert _act(p, 0, 0, 5.1, episode=5, step=1).drops == [("action", "future")]
    p.tick(5.4)
    assert not p.done
    p.tick(5.5)  # after `linger`
    assert p.done and p.next_wakeup() == float("inf")


def test_episodes_can_change_while_running_and_stop_ends_at_once() -> None:
    p = _protocol(episodes=1)
    p.start(0.0)
    _play_to_the_end(p, 0.0)
    p.settings = LockstepSettings(**{**p.settings.__dict__, "episodes": 2})
    eff = WorldEffects()
    for k in range(N):
        eff = _ready(p, k, 1.0)
    assert eff.publish[-1] == ("step", _step(1, 0, "begin"))  # one more episode
    eff = p.stop(1.5)
    assert eff.publish[0][0] == "scenario" and eff.publish[0][1]["state"] == "stopped" and p.done
    assert p.stop(1.6).publish == []


def test_free_running_clock_steps_every_period() -> None:
    p = _protocol(clock="free", period=0.1)
    p.start(0.0)
    eff = _everyone_acts(p, 0.0)
    assert p.t == 2 and len(_records(eff, "observation")) == N  # step 1 goes as soon as the begin is over
    assert _everyone_acts(p, 0.01).publish == []  # everyone answered step 2: the clock still waits
    assert p.next_wakeup() == pytest.approx(0.1)
    assert p.tick(0.09).publish == []
    eff = p.tick(0.1)
    assert [o["step"] for o in _records(eff, "observation")] == [2] * N and p.t == 3
    assert _records(eff, "observation")[0]["acted"] == list(range(N))
    eff = p.tick(0.35)  # the node looked late: the steps due at 0.2 and 0.3 go now, nobody answered them
    assert [t["step"] for t in _records(eff, "ground_truth")] == [3, 4] and p.t == 5
    assert _records(eff, "step") == [_step(0, 3, "step", []), _step(0, 4, "step", [])]
    assert eff.counters["absent_agent_steps"] == N  # counted once: absent agents are no longer live
    assert p.next_wakeup() == pytest.approx(0.4)


# ----- batches, arrays of the wrong length, the pace gate ---------------------------------------------------------


def _finish_batch(p: WorldProtocol, now: float) -> WorldEffects:
    """Every agent plays the current batch to its last step and sends its ready; the effects of the last ready."""
    e = p.episode
    _play_to_the_end(p, now, episode=e)
    assert (p.phase, p.t) == ("end", H)
    eff = WorldEffects()
    for k in range(N):
        eff = _ready(p, k, now, episode=e)
    return eff


def test_an_agent_late_for_a_later_begin_is_warned_about_and_counted() -> None:
    p = _protocol(episodes=2)
    p.start(0.0)
    _everyone_acts(p, 0.0)
    _finish_batch(p, 1.0)
    assert p.episode == 1 and p.joining
    _everyone_acts(p, 1.1, agents=range(N - 1))  # agent 4 misses the begin of episode 1
    eff = p.tick(1.0 + p.settings.begin_deadline)
    assert eff.log == [("warning", "episode 1 begin: no first action from agents [4] within the deadline; idle")]
    assert _records(eff, "step")[0] == _step(1, 1, "step", range(N - 1))
    assert p.ep is not None and p.ep.absent.tolist() == [0, 0, 0, 0, 1]


def test_a_batch_of_4_runs_10_episodes_as_4_4_2() -> None:
    p = _protocol(episodes=10, batch=4)
    eff = p.start(0.0)
    assert eff.publish[0][1]["batch"] == 4
    begins, metrics, logs = _records(eff, "step"), [], []
    assert [p.batch_size(e) for e in (0, 4, 8)] == [4, 4, 2]
    while p.phase != "stopped":
        e, size = p.episode, p.size
        eff = _everyone_acts(p, 1.0)  # step 1 of the batch: one action per episode
        (truth,) = _records(eff, "ground_truth")
        assert len(truth["actions"]) == len(truth["levels"]) == size and truth["episode"] == e
        assert all(len(o["tasks"]) == len(o["levels"]) == size for o in _records(eff, "observation"))
        assert _records(eff, "step") == [_step(e, 1, "step", range(N), size=size)]
        eff = _finish_batch(p, 1.0)
        assert _records(eff, "step")[0] == _step(e, H, "end", size=size)
        metrics += _records(eff, "episode_metrics")
        logs += eff.episode_log
        begins += [r for r in _records(eff, "step") if r["phase"] == "begin"]
    assert [(b["episode"], b["size"]) for b in begins] == [(0, 4), (4, 4), (8, 2)]
    assert all(b["step"] == 0 and b["acted"] == [] for b in begins)
    assert [m["episode"] for m in metrics] == list(range(10)) and p.episodes_done == 10
    assert [line["metrics"] for line in logs] == metrics
    assert all(len(line["levels"]) == H + 1 and len(line["actions"]) == H for line in logs)
    assert all(np.shape(line["actions"]) == (H, N) for line in logs)
    assert p.phase == "stopped" and _records(eff, "scenario")[0]["state"] == "stopped"


def test_actions_of_another_length_are_rejected_and_the_agent_is_still_waited_for() -> None:
    p = _protocol(episodes=4, batch=4)
    p.start(0.0)
    eff = _act(p, 0, [0, 1, 2], 0.1)  # during the begin: 3 actions for a batch of 4
    assert [r[:2] for r in eff.rejects] == [("action", "length")] and "3 actions for a batch of 4" in eff.rejects[0][2]
    assert 0 not in p.answers and p.joining
    _everyone_acts(p, 0.2)
    assert p.t == 2 and p.present == set(range(N))
    for wrong in ([0, 1, 2, 3, 0], [1]):  # step 2: too many, too few
        eff = _act(p, 4, wrong, 0.3)
        assert [r[:2] for r in eff.rejects] == [("action", "length")] and not eff.publish and 4 not in p.answers
    assert _everyone_acts(p, 0.4, agents=range(N - 1)).publish == []  # agent 4 is still waited for
    assert p.t == 2 and p.next_wakeup() == pytest.approx(0.2 + p.settings.act_deadline)
    eff = _act(p, 4, [4, 4, 4, 4], 0.5)  # the right length: accepted, the step goes
    assert not eff.rejects and p.t == 3 and not eff.counters
    assert _records(eff, "step") == [_step(0, 2, "step", range(N), size=4)]


def _progress(p: WorldProtocol, trained: int, now: float, run: str = "test") -> WorldEffects:
    return p.on_trainer({"run": run, "trained": trained, "updates": 10 * trained, "finished": False}, now)


def test_the_pace_gate_waits_for_the_trainer_and_gives_up_on_a_silent_one() -> None:
    # batch 1 from episode 2: step t of episode 2 is global step g = 2 h + t - 1; with lag 1 it needs trained >= g - 1
    p = _protocol(pace=True, trainer_lag=1, trainer_deadline=10.0, first_episode=2, episodes=2, join_timeout=5.0)
    g1 = 2 * H
    p.start(0.0)
    assert p.gate_since == 0.0 and p.next_wakeup() == pytest.approx(0.5)  # the begin is still announced
    assert _everyone_acts(p, 0.1, agents=range(N - 1)).publish == []  # agent 4 does not answer the begin
    eff = p.tick(6.0)  # past the join timeout, but the gate is closed: the agents' deadline does not run
    assert p.joining and _records(eff, "observation") == [] and _records(eff, "step") == [_step(2, 0, "begin")]
    eff = _progress(p, g1 - 2, 6.1)  # not enough yet
    assert _records(eff, "observation") == [] and p.joining and p.trained == g1 - 2
    eff = _progress(p, g1 + 50, 6.2, run="another")
    assert eff.drops == [("trainer_progress", "other_run")] and p.trained == g1 - 2
    eff = _progress(p, g1 - 1, 7.0)  # the gate opens: the begin's deadline starts now
    assert _records(eff, "observation") == [] and p.joining and p.gate_since is None
    assert p.deadline == pytest.approx(7.0 + p.settings.join_timeout)
    assert _records(p.tick(11.9), "observation") == []
    eff = p.tick(12.0)  # the join timeout, counted from the gate's opening: start without agent 4
    assert eff.log == [("warning", "starting without agents [4]")]
    assert _records(eff, "step")[0] == _step(2, 1, "step", [0, 1, 2, 3]) and p.t == 2
    # step 2 (g1 + 1) waits for trained >= g1
    assert p.gate_since == 12.0
    assert _everyone_acts(p, 12.1, agents=range(N - 2)).publish == []  # agent 3 is late
    assert p.status() == (True, f"act episode 2 step 2: waiting for the trainer (trained up to step {g1 - 1})")
    assert p.values()["trainer_trained"] == str(g1 - 1)
    eff = p.tick(15.0)  # past the act deadline: nothing, the gate is closed
    assert eff.publish == [] and not eff.counters and p.t == 2
    eff = _progress(p, g1, 16.0)  # the gate opens; the act deadline starts now
    assert eff.publish == [] and p.deadline == pytest.approx(16.0 + p.settings.act_deadline)
    assert p.next_wakeup() == pytest.approx(18.0)
    assert p.tick(17.9).publish == []
    eff = p.tick(18.0)
    assert _records(eff, "step") == [_step(2, 2, "step", [0, 1, 2])] and eff.counters["absent_agent_steps"] == 1
    # step 3 (g1 + 2) waits for trained >= g1 + 1; the trainer stays silent and is given up after its deadline
    assert p.gate_since == 18.0 and p.next_wakeup() == pytest.approx(18.0 + p.settings.trainer_deadline)
    assert _everyone_acts(p, 18.5, agents=range(N - 2)).publish == []
    eff = p.tick(27.9)
    assert eff.publish == [] and not eff.counters
    eff = p.tick(28.0)
    assert eff.counters["trainer_timeouts"] == 1 and [level for level, _ in eff.log] == ["warning"]
    assert "no progress from the trainer for 10 s" in eff.log[0][1]
    assert _records(eff, "step") == [_step(2, 3, "step", [0, 1, 2])] and not p.trainer_live
    # the run goes on without it: steps go as soon as the live agents answered
    _everyone_acts(p, 28.1, agents=range(N - 2))
    assert p.t == 5 and p.gate_since is None
    eff = _progress(p, g1 + 1, 28.2)  # heard again: it is waited for again
    assert eff.log == [("info", f"the trainer is back (trained up to step {g1 + 1})")] and p.trainer_live
    assert _everyone_acts(p, 28.3, agents=range(N - 2)).publish == [] and p.t == 5  # step 5 (g1 + 4) waits
    eff = _progress(p, 4 * H, 28.4)  # the trainer catches up with everything: step 5 goes
    assert p.t == 6 and len(_records(eff, "observation")) == N and p.gate_since is None
    _everyone_acts(p, 28.5, agents=range(N - 2))
    assert p.t == 7
    eff = _finish_batch(p, 29.0)  # and to the next episode
    assert [m["episode"] for m in _records(eff, "episode_metrics")] == [2] and p.episode == 3
    assert _records(eff, "step")[-1] == _step(3, 0, "begin")


def test_a_trainer_that_sends_progress_is_not_silent_and_one_that_finished_ends_the_run() -> None:
    """A trainer working on a round of its own (the expert-iteration learner) sends its progress again meanwhile: the
    world keeps waiting past trainer_deadline; once it says it finished, the run ends before the batch it begins."""
    p = _protocol(pace=True, trainer_lag=0, trainer_deadline=10.0, episodes=6, batch=2, mode="train")
    p.start(0.0)
    _progress(p, 0, 0.1)
    _everyone_acts(p, 0.2)
    _progress(p, H - 1, 0.3)  # the first batch's steps trained as they go, but for its last: the round learns
    eff = _finish_batch(p, 1.0)
    assert _records(eff, "step")[-1] == _step(2, 0, "begin", size=2)
    _everyone_acts(p, 1.1)  # the begin is answered, but step g = H waits for the trainer's round
    for now in (5.0, 10.0, 15.0, 20.0, 25.0):  # a heartbeat every 5 s: never given up
        assert _records(_progress(p, H - 1, now), "observation") == []  # (the begin is announced again)
        assert p.trainer_live and p.joining and p.gate_since == now
    eff = p.on_trainer({"run": "test", "trained": H, "updates": 0, "finished": True}, 26.0)
    assert ("info", f"the trainer has finished learning (trained up to step {H}): the run ends") in eff.log
    assert p.phase == "stopped" and _records(eff, "scenario")[0]["state"] == "stopped"
    assert _records(eff, "observation") == [] and p.episodes_done == 2  # the batch that was beginning never ran


def test_a_gated_world_sleeps_until_the_trainer_or_its_deadline() -> None:
    p = _protocol(pace=True, trainer_lag=1, trainer_deadline=10.0, first_episode=2, episodes=2, join_timeout=5.0)
    p.start(0.0)
    _everyone_acts(p, 0.1)
    p.tick(6.0)  # past the join timeout, gated
    assert p.next_wakeup() > 6.0
    assert _records(p.tick(6.01), "step") == []  # no new announcement before NUDGE has passed
    _progress(p, 2 * H - 1, 7.0)  # step 1 goes; step 2 waits for the trainer
    assert p.t == 2 and p.gate_since == 7.0
    _everyone_acts(p, 7.1)
    p.tick(7.0 + p.settings.act_deadline + 1.0)  # past the act deadline, gated
    assert p.next_wakeup() > 7.0 + p.settings.act_deadline + 1.0


def test_the_pace_gate_only_applies_to_the_lockstep_clock_with_pace() -> None:
    for kw in ({"pace": False}, {"pace": True, "clock": "free", "period": 0.1}):
        p = _protocol(trainer_lag=1, first_episode=2, **kw)
        p.start(0.0)
        _everyone_acts(p, 0.0)
        assert p.t == 2 and p.gate_since is None


# ----- the protocol with the agents' minds, in one process --------------------------------------------------------


@pytest.mark.parametrize(
    ("team", "name", "seed", "first", "episodes", "batch"),
    [
        ("heterogeneous", "greedy", 11, 0, 3, 1),
        ("homogeneous", "random", 5, 40, 3, 1),
        ("heterogeneous", "random", 3, 8, 6, 4),  # batches of 4 and 2 episodes
    ],
)
def test_protocol_with_the_minds_equals_team_rollout(
    team: str, name: str, seed: int, first: int, episodes: int, batch: int
) -> None:
    sc = builtin(team)
    policies, eps = builtin_team(sc, name)
    world_log, agent_logs = loopback_run(sc, seed, first, episodes, policies, eps, batch=batch)
    assert [w["metrics"]["episode"] for w in world_log] == list(range(first, first + episodes))
    assert all(w["metrics"]["absent"] == [0] * sc.n_agents for w in world_log)
    last = first + episodes

    def ref(e: int) -> Any:
        b = e // batch
        return reference(sc, policies, seed, eps, b, min(batch, last - b * batch)), e - b * batch

    assert_logs_equal_rollout(world_log, agent_logs, ref)


def test_protocol_with_a_silent_agent_equals_an_inactive_one() -> None:
    """Agent 2's actions never reach the world: the episode starts without it at the join timeout, it idles at its
    site every step, and the run equals the in-process Team with agent 2 inactive."""
    policies, _ = builtin_team(SC, "greedy")
    world_log, agent_logs = loopback_run(SC, 4, 3, 1, policies, 0.0, silent=frozenset({2}))
    (w,) = world_log
    assert w["metrics"]["absent"] == [0, 0, H, 0, 0]

    def ref(e: int) -> Any:
        return reference(SC, policies, 4, 0.0, e, inactive=(2,)), 0

    assert_logs_equal_rollout(world_log, agent_logs, ref)
