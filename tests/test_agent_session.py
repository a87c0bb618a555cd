"""The agent process's core without ROS (htlm_agent.session.core.AgentSession), driven in one process with the time
passed in: a team of sessions with a WorldProtocol, every record through the wire's encode and decode, equals the
in-process `team.rollout`; a restarted world or agent is rejoined; the outbox sends an unacknowledged transition
again after its deadline and forgets it at the acknowledgement (a duplicate one changes nothing); the trainer-lag
gate holds the actions until the weights of the lagged step arrive, or `weights_timeout`; records outside the run
or of the wrong shape are dropped or refused, and counted."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.qnet import AgentQ, layer_sizes
from htlm_agent.learning.settings import Settings
from htlm_agent.ros.settings import AgentSettings
from htlm_agent.session.core import AgentSession, SessionEffects, SessionSettings
from htlm_msgs_py import schema as S
from htlm_msgs_py.payload import seal
from htlm_world.episode import global_step
from htlm_world.protocol import LockstepSettings, world_protocol
from htlm_world.scenario import builtin
from support.team import SCHEMA, builtin_team, reference, session_team

SC = builtin()
N, H = SC.n_agents, SC.horizon
NAMES = [a.name for a in SC.agents]


def _session(i: int = 0, **kw: Any) -> AgentSession:
    """Agent i's session with the node's default parameters, greedy unless told otherwise."""
    return AgentSession(AgentSettings(**{"agent": NAMES[i], "policy": "greedy", **kw}).session())


def _announce(
    mode: str = "evaluate",
    run: str = "r1",
    seq: int = 0,
    nonce: str = "00000000000000aa",
    state: str = "running",
    episodes: int = 0,
    batch: int = 1,
    trainer_lag: int = 0,
    first: int = 0,
) -> dict[str, Any]:
    """A scenario record of the world, decoded."""
    settings = LockstepSettings(run_id=run, mode=mode, episodes=episodes, batch=batch, trainer_lag=trainer_lag)
    rec = world_protocol(SC, dataclasses.replace(settings, first_episode=first)).scenario_record(state)
    return {**rec, "seq": seq, "nonce": nonce}


def _begin(episode: int, size: int = 1) -> dict[str, Any]:
    return {"episode": episode, "size": size, "step": 0, "phase": "begin", "acted": []}


def _observation(agent: int, episode: int, t: int, acted: list[int], size: int = 1) -> dict[str, Any]:
    return {"agent": agent, "episode": episode, "step": t, "tasks": [-1] * size, "levels": [-1] * size, "acted": acted}


def _sent(eff: SessionEffects, kind: str, lim: dict[str, int] | None = None) -> list[dict[str, Any]]:
    """The records of `kind` the session published, decoded as a receiver decodes them."""
    return [S.decode(text, SCHEMA[kind], lim) for k, text in eff.publish if k == kind]


def test_the_session_settings_are_the_node_parameters() -> None:
    names = {f.name for f in dataclasses.fields(AgentSettings)}
    assert {f.name for f in dataclasses.fields(SessionSettings)} <= names
    s = AgentSettings(agent="agent2", resend_period=0.25).session()
    assert (s.agent, s.resend_period, s.policy) == ("agent2", 0.25, "auto")


# ----- a team of sessions and the world in one process -----------------------------------------------------------


@pytest.mark.parametrize(
    ("team", "name", "seed", "first", "episodes", "batch"),
    [("heterogeneous", "greedy", 11, 0, 2, 1), ("homogeneous", "random", 3, 8, 6, 4)],
)
def test_a_team_of_sessions_equals_team_rollout(
    team: str, name: str, seed: int, first: int, episodes: int, batch: int
) -> None:
    sc = builtin(team)
    net = session_team(sc, seed, episodes, name, batch=batch, first=first)
    net.run()
    assert [w["metrics"]["episode"] for w in net.world_log] == list(range(first, first + episodes))
    assert all(w["metrics"]["absent"] == [0] * sc.n_agents for w in net.world_log)
    assert not any(e.drops or e.rejects or e.counters or e.fatal for e in net.effects)
    pols, eps = builtin_team(sc, name)
    last = first + episodes
    for w in net.world_log:
        e = w["metrics"]["episode"]
        b = e // batch
        tr, j = reference(sc, pols, seed, eps, b, min(batch, last - b * batch)), e - b * batch
        assert np.array_equal(tr.actions[:, j], w["actions"]), f"episode {e}: actions"
        for i, logs in net.agent_logs.items():
            (rec,) = [x for x in logs if x["episode"] == e]
            assert rec["run"] == "run" and rec["rewards"] == tr.rewards[:, j, i].tolist()
    assert all(s.episodes_done == episodes and s.stopping and s.finished(net.now) for s in net.sessions)
    assert net.transitions == []  # evaluate mode: transitions off


def test_an_agent_restarted_mid_run_rejoins_at_the_worlds_next_begin() -> None:
    net = session_team(SC, 5, 3, "greedy")
    net.run(until=lambda: net.world.episode == 0 and net.world.t == 3)
    # agent 2's process restarts: a fresh session hears the run's announcement (transient local) and the steps of
    # an episode it never began; it answers from the next begin on, and the world idles it meanwhile
    fresh = _session(2)
    net.sessions[2] = fresh
    net.from_agent(2, fresh.on_scenario(net.world.scenario_record("running"), net.now))
    assert fresh.id != net.sessions[0].id and fresh.run == "run" and fresh.mind is None
    net.run()
    absent = [w["metrics"]["absent"][2] for w in net.world_log]
    assert absent[0] > 0 and absent[1:] == [0, 0]
    assert fresh.episodes_done == 2 and fresh.mind is not None and fresh.mind.episode == 2


def test_a_restarted_world_is_rejoined_at_its_begin_even_mid_batch() -> None:
    s = _session(0)
    s.on_scenario(_announce(episodes=2), 0.0)
    first = _sent(s.on_step(_begin(0), 10.0), "action")
    assert [a["step"] for a in first] == [1]
    s.on_observation(_observation(0, 0, 1, [0]), 10.1)  # alone in `acted`: the step is done, the action of step 2
    assert s.mind is not None and s.mind.current == 2
    # a second begin of the batch we play is a duplicate ...
    assert s.on_step(_begin(0), 10.2).drops == [("step", "duplicate")]
    # ... until the world restarts (a newer announcement of our run with another nonce): its next begin is taken
    eff = s.on_scenario(_announce(episodes=2, seq=1, nonce="00000000000000bb"), 10.3)
    assert eff.heard_world and eff.log == [("warning", "run r1: the world restarted (announcement 1); rejoining")]
    again = _sent(s.on_step(_begin(0), 10.4), "action")
    assert again == first and s.mind.current == 1 and not s.rejoin  # the same streams: the same action
    # a replayed announcement of the run is refused
    assert s.on_scenario(_announce(episodes=2, seq=1, nonce="00000000000000bb"), 10.5).rejects == [
        ("scenario", "replay", "run r1 announcement 1 (we follow r1)")
    ]


def test_the_world_ahead_of_a_batch_we_cannot_finish_is_rejoined_at_once() -> None:
    """Observations lost while a restarted agent's subscriptions were being matched: the world's step records say it
    is ahead of us, and its begin of the next batch is taken at once instead of after resync_timeout."""
    s = _session(0)
    s.on_scenario(_announce(episodes=4), 0.0)
    s.on_step(_begin(0), 1.0)
    for t in (1, 2, 3):  # the world applied steps 1-3 without us hearing the observations
        s.on_step({"episode": 0, "size": 1, "step": t, "phase": "step", "acted": [1]}, 1.0 + t)
    assert s.world_ahead == (0, 3)
    eff = s.on_step(_begin(1), 5.0)
    assert [a["episode"] for a in _sent(eff, "action")] == [1]
    assert [tr for k, tr in eff.publish if k == "transition"] == []  # transitions are off outside training
    # without the world ahead, the next begin of an unfinished batch waits (future) until resync_timeout
    q = _session(0, resync_timeout=10.0)
    q.on_scenario(_announce(episodes=4), 0.0)
    q.on_step(_begin(0), 1.0)
    assert q.on_step(_begin(1), 5.0).drops == [("step", "future")]
    assert [a["episode"] for a in _sent(q.on_step(_begin(1), 11.5), "action")] == [1]


# ----- the outbox -------------------------------------------------------------------------------------------------


def _trained_step(s: AgentSession, t: int, now: float) -> SessionEffects:
    """The world's observation of step t of episode 0 with only this agent acting: the step is done at once."""
    return s.on_observation(_observation(s.index, 0, t, [s.index]), now)


def test_an_unacknowledged_transition_is_sent_again_after_its_deadline() -> None:
    s = _session(1, transitions="on", resend_period=1.0, resend_batch=2)
    s.on_scenario(_announce(episodes=1), 0.0)
    s.on_step(_begin(0), 0.0)
    eff = _trained_step(s, 1, 0.5)
    (tr,) = _sent(eff, "transition", s.lim)
    assert (tr["agent"], tr["session"], tr["seq"], tr["step"]) == (1, s.id, 0, 1) and not tr["done"]
    assert s.resend(1.4).publish == []  # not yet: sent 0.9 s ago
    eff = s.resend(1.5)
    assert [k for k, _ in eff.publish] == ["transition"] and eff.counters["resent"] == 1
    assert eff.publish[0][1] == s.outbox.waiting[0].text  # the very same record
    _trained_step(s, 2, 1.6)
    _trained_step(s, 3, 1.7)
    assert list(s.outbox.waiting) == [0, 1, 2]
    eff = s.resend(2.7)  # all three are due: at most resend_batch per pass, oldest first
    assert [S.decode(text, S.TRANSITION, s.lim)["seq"] for _, text in eff.publish] == [0, 1]
    assert eff.counters["resent"] == 2
    # the trainer acknowledges up to seq 1: those leave the outbox; a duplicate acknowledgement changes nothing
    ack = {"agent": 1, "session": s.id, "upto": 1}
    assert s.on_ack(ack, 2.8) == SessionEffects() and list(s.outbox.waiting) == [2] and s.outbox.acked == 2
    assert s.on_ack(ack, 2.9) == SessionEffects() and list(s.outbox.waiting) == [2] and s.outbox.acked == 2
    # an acknowledgement of another session (our process before a restart) is dropped, another agent's ignored
    assert s.on_ack({**ack, "session": "0" * 16, "upto": 9}, 3.0).drops == [("transition_ack", "session")]
    assert s.on_ack({**ack, "agent": 0, "upto": 9}, 3.0) == SessionEffects() and list(s.outbox.waiting) == [2]
    # the run stops: the process waits for the acknowledgements at most stop_timeout
    eff = s.on_scenario(_announce(episodes=1, seq=1, state="stopped"), 3.0)
    assert eff.log == [("info", "run r1 stopped by the world; 1 transitions unacknowledged")]
    assert not s.finished(3.1) and s.finished(3.0 + s.settings.stop_timeout)
    s.on_ack({**ack, "upto": 2}, 3.2)
    assert s.finished(3.2) and s.values()["transitions_acked"] == "3" and s.values()["outbox"] == "0"


def test_a_full_outbox_drops_its_oldest_transition() -> None:
    s = _session(0, transitions="on", outbox_limit=2)
    s.on_scenario(_announce(episodes=1), 0.0)
    s.on_step(_begin(0), 0.0)
    counts = [_trained_step(s, t, 0.1 * t).counters["outbox_dropped"] for t in (1, 2, 3, 4)]
    assert counts == [0, 0, 1, 1] and list(s.outbox.waiting) == [2, 3] and s.outbox.seq == 4


def test_an_action_the_world_has_not_applied_is_sent_again() -> None:
    s = _session(0, action_resend=0.5)
    s.on_scenario(_announce(episodes=1), 0.0)
    (text,) = [t for k, t in s.on_step(_begin(0), 1.0).publish if k == "action"]
    assert s.tick(1.4).publish == []
    eff = s.tick(1.5)
    assert eff.publish == [("action", text)] and eff.counters["actions_resent"] == 1
    assert s.tick(1.9).publish == [] and s.tick(2.0).publish == [("action", text)]
    _trained_step(s, 1, 2.1)  # the world applied step 1; step 2's action is new
    assert s.tick(2.2).publish == []


# ----- the trainer's weights and the gate -------------------------------------------------------------------------


LEARNER = Settings.from_dict({"hidden": [8]}, "test")


def _weights(agent: int, version: int, trained: int, every: int = 1, seed: int = 0) -> dict[str, Any]:
    """A weights record of the trainer: agent's network taken after the updates of the steps before `trained`."""
    data = AgentQ(layer_sizes(SC, LEARNER.hidden), seed=seed).get_weights()
    rec = {"agent": agent, "version": version, "episode": 0, "trained": trained, "every": every}
    return {**rec, **seal(data), "settings": LEARNER.to_dict()}


def test_the_gate_holds_the_actions_until_the_weights_of_the_lagged_step() -> None:
    s = _session(0, policy="auto", epsilon=0.0, weights_timeout=30.0)
    eff = s.on_scenario(_announce(mode="train", episodes=2, trainer_lag=1), 0.0)
    assert eff.subscribe_weights and s.policies.kind == "trainer" and s.carrier.send_transitions
    assert s.on_step(_begin(0), 0.1).publish == []  # no weights yet: the world asks again
    g0 = global_step(0, 1, 1, H)
    assert s.on_weights(_weights(0, 0, g0), 0.2) == SessionEffects()
    eff = s.on_step(_begin(0), 0.3)  # step 1 acts with the weights of g0 (T = max(g0, g0 - 1))
    assert [a["step"] for a in _sent(eff, "action")] == [1] and eff.goals
    eff = _trained_step(s, 1, 0.4)  # step 2: T = g0 (lag 1): still the first weights
    assert [a["step"] for a in _sent(eff, "action")] == [2]
    eff = _trained_step(s, 2, 0.5)  # step 3: T = g0 + 1: they are on their way; the action waits
    assert (
        [k for k, _ in eff.publish] == ["broadcast", "transition", "belief"]
        and s.mind is not None
        and s.mind.deferred == 3
    )
    assert s.tick(10.0).publish == []  # within weights_timeout
    eff = s.on_weights(_weights(0, 1, g0 + 1, seed=1), 10.1)  # they arrive: the action goes
    assert [a["step"] for a in _sent(eff, "action")] == [3] and s.mind.deferred is None
    assert s.mind.policy is s.weights.versions[g0 + 1]
    # older and foreign weights, and weights whose data do not unpack, are counted and change nothing
    assert s.on_weights(_weights(0, 1, g0 + 1), 10.2).drops == [("weights", "past")]
    assert s.on_weights(_weights(3, 2, g0 + 2), 10.2).rejects == [
        ("weights", "agent", f"weights for agent 3 on {NAMES[0]}'s topic")
    ]
    bad = {**_weights(0, 2, g0 + 2), "sha256": "0" * 64}
    assert [r[:2] for r in s.on_weights(bad, 10.2).rejects] == [("weights", "data")]
    assert s.weights.version == 1
    # step 4 waits for the weights of g0 + 2, which never come: after weights_timeout it acts with the newest
    _trained_step(s, 3, 10.3)
    assert s.mind.deferred == 4
    assert s.tick(40.3).publish == []
    eff = s.tick(40.4)
    assert eff.counters["stale_weights"] == 1 and [a["step"] for a in _sent(eff, "action")] == [4]
    assert eff.log == [("warning", "no weights for step 4 of episode 0 within 30 s; acting with the newest (1)")]


def test_the_cadence_of_the_weights_is_followed() -> None:
    """With weights every 2 steps and no lag, step g acts with the version taken after g rounded down to the
    cadence: steps g0 and g0 + 1 with that of g0, step g0 + 2 waits for that of g0 + 2."""
    s = _session(0, policy="trainer", epsilon=0.0)
    s.on_scenario(_announce(mode="train", episodes=1), 0.0)
    g0 = global_step(0, 1, 1, H)
    s.on_weights(_weights(0, 0, g0, every=2), 0.0)
    assert [a["step"] for a in _sent(s.on_step(_begin(0), 0.1), "action")] == [1]
    assert [a["step"] for a in _sent(_trained_step(s, 1, 0.2), "action")] == [2]
    assert _sent(_trained_step(s, 2, 0.3), "action") == []
    assert s.mind is not None and s.mind.deferred == 3
    s.on_weights(_weights(0, 1, g0 + 1, every=2), 0.4)  # not the cadence's version: still waiting
    assert s.mind.deferred == 3
    assert [a["step"] for a in _sent(s.on_weights(_weights(0, 2, g0 + 2, every=2), 0.5), "action")] == [3]


# ----- records outside the run ------------------------------------------------------------------------------------


def test_records_outside_the_run_or_out_of_shape_are_dropped_and_counted() -> None:
    s = _session(0)
    assert s.on_step(_begin(0), 0.0) == SessionEffects()  # no run yet: nothing to judge it by
    assert s.on_observation(_observation(0, 0, 1, [0]), 0.0) == SessionEffects()
    s.on_scenario(_announce(episodes=2, first=4), 0.0)
    assert s.on_step(_begin(2), 0.1).drops == [("step", "outside_run")]
    assert s.on_step(_begin(6), 0.1).drops == [("step", "outside_run")]
    assert s.on_step({**_begin(4), "step": 3}, 0.1).rejects == [("step", "range", "begin at step 3")]
    assert s.on_step(_begin(4, size=2), 0.1).rejects == [("step", "length", "batch of 2 episodes > the run's batch 1")]
    assert s.on_scenario(_announce(run="other", seq=5), 0.2).rejects == [
        ("scenario", "other_run", "run other announcement 5 (we follow r1)")
    ]
    assert [k for k, _ in s.on_step(_begin(4), 0.3).publish] == ["action"]
    assert s.on_observation(_observation(1, 4, 1, [0]), 0.4).rejects == [
        ("observation", "agent", f"observation for agent 1 on {NAMES[0]}'s topic")
    ]
    assert s.on_observation(_observation(0, 4, 1, [0], size=2), 0.4).drops == [("observation", "length")]
    eff = s.on_observation(_observation(0, 4, 2, [0, 1]), 0.4)  # the world went on without our action of step 1
    assert not eff.drops and s.mind is not None and s.mind.missed_steps == 1 and s.mind.current == 2
    assert s.on_observation(_observation(0, 4, 1, [0]), 0.5).drops == [("observation", "past")]
    assert s.on_observation(_observation(0, 4, 2, [0, 1]), 0.5).drops == [("observation", "duplicate")]
    bc = {"agent": 1, "episode": 4, "step": 3, "actions": [0, 0], "levels": [0, 0], "sent": 0.6}
    assert s.on_broadcast(bc, 0.6).drops == [("broadcast", "length")]
    assert s.on_broadcast({**bc, "agent": 0}, 0.6) == SessionEffects()  # our own, looped back
    assert s.on_broadcast({**bc, "episode": 2, "actions": [0], "levels": [0]}, 0.6).drops == [("broadcast", "past")]


def test_an_agent_outside_the_team_or_without_a_policy_fails() -> None:
    s = AgentSession(AgentSettings(agent="agent9", policy="greedy").session())
    eff = s.on_scenario(_announce(), 0.0)
    assert eff.fatal == f"agent 'agent9' is not in the scenario's team {NAMES}" and s.finished(0.0)
    t = _session(0, policy="auto")
    eff = t.on_scenario(_announce(mode="evaluate"), 0.0)
    assert eff.fatal and "no policy" in eff.fatal and eff.log == [("error", eff.fatal)]


def test_goals_follow_the_assignment_and_the_robot_s_arrival_is_logged_once() -> None:
    s = _session(0)
    assert s.arrival.arrival() == ("unknown", -1.0) and s.status() == "waiting for the world"
    s.on_scenario(_announce(episodes=1), 0.0)
    eff = s.on_step(_begin(0), 0.1)
    ((x, y),) = eff.goals
    site = s.arrival.site
    assert (x, y) == tuple(float(v) for v in SC.site_positions[site])
    assert s.on_pose(x + 100.0, y, 0.2).log == [("info", f"robot on its way to site {SC.site_names[site]} (100 m)")]
    assert s.on_pose(x + 50.0, y, 0.3).log == []  # still on its way: logged once
    assert s.on_pose(x, y + 1.0, 0.4).log == [("info", f"robot at site {SC.site_names[site]}")]
    vals = s.values()
    assert (vals["arrived"], vals["distance_to_site"], vals["episode"], vals["step"]) == ("yes", "1", "0", "1")
    assert s.status() == "episode 0 step 1"
