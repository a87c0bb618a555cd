"""The ROS runtime's core without ROS: the lockstep protocol in one process equals the in-process Team step for
step; the agent's mind drops what the protocol says to drop; the trainer's durable store; node settings."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import GreedyPolicy
from htlm_agent.learning.transition_store import StoreError, TransitionStore, read_store
from htlm_agent.mind.agent import AgentMind
from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.ros.launch import LaunchConfig, process_specs, ros_env, write_params
from htlm_agent.ros.settings import AgentSettings, TrainerSettings, validate_agent_settings, validate_trainer_settings
from htlm_agent.runtime.team import Team, rollout
from htlm_agent.session.builtin import builtin_policy
from htlm_world.episode import WorldEpisode
from htlm_world.model import Model
from htlm_world.ros.settings import WorldSettings, validate_world_settings
from htlm_world.scenario import builtin
from support.team import FIELDS, builtin_team, loopback_episode, reference


@pytest.mark.parametrize("team", ["heterogeneous", "semi-heterogeneous", "homogeneous"])
@pytest.mark.parametrize("name", ["greedy", "random"])
def test_loopback_equals_team_rollout(team: str, name: str) -> None:
    sc = builtin(team)
    pols, eps = builtin_team(sc, name)
    for seed, episode in [(0, 0), (3, 7), (11, 2)]:
        tr = reference(sc, pols, seed, eps, episode)
        lb = loopback_episode(sc, seed, episode, pols, epsilon=eps)
        for f in FIELDS:
            assert np.array_equal(getattr(tr, f)[:, 0], lb[f]), (f, seed, episode)


@pytest.mark.parametrize("name", ["greedy", "random"])
@pytest.mark.parametrize("batch", [16, 5])
def test_a_batch_through_the_protocol_equals_team_of_that_batch(name: str, batch: int) -> None:
    """B episodes at once: every agent keeps B beliefs and acts for all of them in one call; the result equals the
    in-process Team(scenario, B, seed, b) of batch b bit for bit."""
    sc = builtin()
    pols, eps = builtin_team(sc, name)
    for seed, b in [(0, 0), (7, 3)]:
        tr = reference(sc, pols, seed, eps, b, batch)
        lb = loopback_episode(sc, seed, b * batch, pols, epsilon=eps, batch=batch)
        for f in FIELDS:
            assert np.array_equal(getattr(tr, f), lb[f]), (f, seed, b)


def test_train_mode_streams_are_those_of_htlm_train() -> None:
    """In train mode the world and the agents draw from the training streams of batch b (seeds.train_*)."""
    from htlm_world import seeds

    sc = builtin()
    pols, eps = builtin_team(sc, "random")
    team = Team(sc, 8, 3)
    team.sim.rng = seeds.train_world(3, 2)
    team.sim.channel_rngs = [seeds.train_channel(3, i, 2) for i in range(sc.n_agents)]
    dp = DecentralizedPolicy(pols, 3, eps)
    dp.rngs = [seeds.train_explore(3, i, 2) for i in range(sc.n_agents)]
    team.reset()
    levels, acts = [team.sim.levels.copy()], []
    for _ in range(sc.horizon):
        a = dp.act(team.context())
        _, _, info = team.step(a)
        levels.append(info.levels)
        acts.append(a)
    lb = loopback_episode(sc, 3, 16, pols, epsilon=eps, batch=8, mode="train")
    assert np.array_equal(np.stack(levels), lb["levels"]) and np.array_equal(np.stack(acts), lb["actions"])


def test_mind_rejects_arrays_of_another_length_and_waits_for_its_gate() -> None:
    sc = builtin()
    pol, _ = builtin_policy(sc, "greedy", 0)
    ready: dict[int, bool] = {1: False}
    m = AgentMind(sc, 0, 0, pol, batch=4, gate=lambda e, t: pol if ready.get(t, True) else None)
    eff = m.begin(0, size=4)
    assert eff.action is None and m.deferred == 1  # no policy for step 1 yet
    assert m.act_now().action is None
    ready[1] = True
    eff = m.act_now()
    assert eff.action is not None and eff.action[0] == 1 and eff.action[1].shape == (4,) and m.deferred is None
    assert m.observe(0, 1, [3, 3, 3], [0]).drop == "length"
    assert m.hear(1, 0, 1, [0, 0, 0, 0], [1, 1]).drop == "length"
    out = m.observe(0, 1, [3, 3, 2, 4], [0])
    assert out.transition is not None and out.transition.k.shape == (4, sc.knowledge_size)
    assert out.transition.r.shape == (4,) and out.action is not None and out.action[1].shape == (4,)


def test_row_policy_is_the_team_greedy_policy() -> None:
    sc = builtin()
    pols, _ = builtin_team(sc, "greedy")
    a = reference(sc, pols, 5, 0.0, 4)
    b = rollout(Team(sc, 1, 5, episode=4), GreedyPolicy(sc))
    for f in FIELDS:
        assert np.array_equal(getattr(a, f), getattr(b, f))


def test_ht_mode_loopback_equals_team() -> None:
    sc = builtin(mode="ht")
    pols, _ = builtin_team(sc, "random")
    tr = reference(sc, pols, 2, 1.0, 1)
    lb = loopback_episode(sc, 2, 1, pols, epsilon=1.0)
    for f in FIELDS:
        assert np.array_equal(getattr(tr, f)[:, 0], lb[f]), f


def test_an_absent_agent_is_idle_like_an_inactive_one() -> None:
    """Agent 2 silent for the whole episode: the world idles it at its site, its teammates assume its last known
    assignment (idle@site1); the result is the in-process Team with agent 2 inactive."""
    sc = builtin()
    pols, _ = builtin_team(sc, "greedy")
    absent = {t: {2} for t in range(1, sc.horizon + 1)}
    lb = loopback_episode(sc, 4, 3, pols, absent=absent)
    tr = reference(sc, pols, 4, 0.0, 3, inactive=(2,))
    for f in FIELDS:
        assert np.array_equal(getattr(tr, f)[:, 0], lb[f]), f
    world = WorldEpisode(sc, Model.build(sc), 4, 3)
    for _ in range(3):
        world.step({0: np.array([0]), 1: np.array([1])})
    (m,) = world.metrics()
    assert m["absent"] == [0, 0, 3, 3, 3]


def _mind(seed: int = 0) -> AgentMind:
    sc = builtin()
    pol, _ = builtin_policy(sc, "greedy", 0)
    return AgentMind(sc, 0, seed, pol)


def test_mind_drops_past_future_and_duplicates() -> None:
    m = _mind()
    assert m.observe(0, 1, [3], [0]).drop == "no_episode"
    eff = m.begin(5)
    assert eff.action is not None and eff.action[0] == 1
    again = m.begin(5)  # the world asks again: same answer, nothing changes
    assert again.action is not None and again.action[0] == 1 and again.drop is None
    assert np.array_equal(again.action[1], eff.action[1])
    assert m.begin(4).drop == "past"
    assert m.begin(6).drop == "future"  # the episode is not over
    assert m.observe(4, 1, [3], [0]).drop == "past"
    assert m.observe(6, 1, [3], [0]).drop == "future"
    assert m.observe(5, 3, [3], [0]).drop == "future"
    assert m.hear(1, 5, 9, [2], [3]).drop == "future"
    assert m.hear(0, 5, 1, [2], [3]).drop == "self"
    state = (m.t, m.current, m.belief.copy(), m.prev)
    out = m.observe(5, 1, [3], [0, 1])  # agent 1 acted: wait for its broadcast
    assert out.broadcast is not None and out.transition is None
    assert m.observe(5, 1, [3], [0, 1]).drop == "duplicate"
    assert state[0] == m.t and np.array_equal(state[2], m.belief)
    done = m.hear(1, 5, 1, [2], [3])
    assert done.transition is not None and done.action is not None and done.action[0] == 2
    assert m.hear(1, 5, 1, [2], [3]).drop == "past"


def test_mind_buffers_a_broadcast_ahead_of_its_observation() -> None:
    m = _mind()
    m.begin(0)
    assert m.hear(1, 0, 1, [0], [4]).drop is None  # before our own observation of step 1
    out = m.observe(0, 1, [3], [0, 1])
    assert out.transition is not None  # nothing left to wait for


def test_mind_times_out_on_a_missing_broadcast_and_catches_up() -> None:
    m = _mind()
    m.begin(0)
    m.observe(0, 1, [3], [0, 1], now=10.0)
    assert m.tick(10.5, 1.0).transition is None
    out = m.tick(11.5, 1.0)
    assert out.transition is not None and out.action is not None and m.timeouts == 1
    # the world went on without our action of step 3: the mind closes step 2 and idles in step 3
    out = m.observe(0, 3, [-1], [1])
    assert out.transition is not None and out.transition.step == 2 and m.current == 3
    assert m.missed_steps == 1


def test_mind_random_policy_uses_the_exploration_generator() -> None:
    sc = builtin()
    pol, eps = builtin_policy(sc, "random", 1)
    assert eps == 1.0
    a = [AgentMind(sc, 1, 9, pol).begin(e, eps).action for e in range(5)]
    b = [AgentMind(sc, 1, 9, pol).begin(e, eps).action for e in range(5)]
    assert all(x is not None and y is not None and np.array_equal(x[1], y[1]) for x, y in zip(a, b, strict=True))
    assert len({int(x[1][0]) for x in a if x}) > 1


def _rec(agent: int, session: str, seq: int, batch: int = 3) -> dict[str, object]:
    """One agent's transitions of one step in a batch of `batch` episodes (from episode 4): one row each."""
    return {
        "agent": agent,
        "session": session,
        "seq": seq,
        "episode": 4,
        "step": seq % 30 + 1,
        "k": np.full((batch, 26), 0.5) + np.arange(batch)[:, None],
        "a": np.arange(batch) % 6,
        "r": -1.25 * np.arange(1, batch + 1),
        "k2": np.full((batch, 26), 0.25),
        "mask2": np.tile([True] * 5 + [False], (batch, 1)),
        "done": seq % 30 == 29,
    }


def test_store_acknowledges_only_durable_records_and_survives_reopen(tmp_path: Path) -> None:
    path = tmp_path / "transitions.bin"
    st = TransitionStore(path, 26, 6)
    s = "0123456789abcdef"
    assert st.append(_rec(1, s, 0)) and st.append(_rec(1, s, 2))
    assert not st.append(_rec(1, s, 0))
    assert st.contains(1, s, 2) and st.count == 0 and st.acked_upto(1, s) == -1  # not flushed yet
    assert st.flush() == [(1, s)]
    assert st.acked_upto(1, s) == 0 and st.count == 6  # seq 1 is missing; 3 rows per record
    st.append(_rec(1, s, 1))
    st.flush()
    assert st.acked_upto(1, s) == 2
    st.close()
    with open(path, "ab") as f:
        f.write(b"\x01" * 100)  # a torn row
    st2 = TransitionStore(path, 26, 6)
    assert st2.count == 9 and st2.truncated == 1 and st2.acked_upto(1, s) == 2
    assert not st2.append(_rec(1, s, 1))
    recs = read_store(path)
    assert recs["seq"].tolist() == [0, 0, 0, 2, 2, 2, 1, 1, 1]
    assert recs["row"].tolist() == [0, 1, 2] * 3 and set(recs["rows"].tolist()) == {3}
    assert recs["episode"].tolist() == [4, 5, 6] * 3 and recs["step"].tolist()[3:6] == [3, 3, 3]
    assert recs["r"][:3].tolist() == [-1.25, -2.5, -3.75] and recs["k"][1, 0] == 1.5 and recs["a"][2] == 2
    assert recs["mask2"][0].tolist() == [1, 1, 1, 1, 1, 0]
    assert [r["seq"] for r in st2.records(6)] == [1, 1, 1]
    st2.close()
    with pytest.raises(StoreError, match="layout"):
        TransitionStore(path, 20, 6)


def test_store_detects_a_corrupted_record(tmp_path: Path) -> None:
    path = tmp_path / "t.bin"
    st = TransitionStore(path, 26, 6)
    for i in range(4):
        st.append(_rec(0, "aaaaaaaaaaaaaaaa", i, batch=2))
    st.close()
    data = bytearray(path.read_bytes())
    data[-10] ^= 0xFF  # flip a bit of the last row: its whole record goes
    path.write_bytes(bytes(data))
    st2 = TransitionStore(path, 26, 6)
    assert st2.count == 6 and st2.truncated == 2 and st2.acked_upto(0, "aaaaaaaaaaaaaaaa") == 2
    st2.close()
    assert read_store(path)["seq"].tolist() == [0, 0, 1, 1, 2, 2]


@pytest.mark.parametrize("cut", ["rows", "bytes"])
def test_store_cuts_a_record_torn_in_the_middle_of_its_rows(tmp_path: Path, cut: str) -> None:
    """A crash after 2 of a record's 4 rows (or in the middle of its third row): the whole record is cut on reopen,
    its seq is not acknowledged, and the agent's resend is accepted and stored again."""
    path = tmp_path / "t.bin"
    s = "bbbbbbbbbbbbbbbb"
    st = TransitionStore(path, 26, 6)
    for i in range(3):
        st.append(_rec(2, s, i, batch=4))
    st.close()
    size = st.size
    data = path.read_bytes()
    keep = len(data) - 2 * size if cut == "rows" else len(data) - 2 * size + size // 2
    path.write_bytes(data[:keep])
    st2 = TransitionStore(path, 26, 6)
    assert st2.count == 8 and st2.acked_upto(2, s) == 1 and not st2.contains(2, s, 2)
    assert st2.truncated == (2 if cut == "rows" else 3)
    assert read_store(path)["seq"].tolist() == [0] * 4 + [1] * 4
    assert st2.append(_rec(2, s, 2, batch=4)) and st2.flush() == [(2, s)]
    assert st2.acked_upto(2, s) == 2 and st2.count == 12
    st2.close()
    st3 = TransitionStore(path, 26, 6)
    assert st3.count == 12 and st3.truncated == 0 and st3.acked_upto(2, s) == 2
    recs = read_store(path)
    assert recs["seq"].tolist()[8:] == [2] * 4 and recs["row"].tolist()[8:] == [0, 1, 2, 3]
    st3.close()


@pytest.mark.parametrize(
    ("cls", "check", "field", "bad"),
    [
        (WorldSettings, validate_world_settings, "team", "nope"),
        (WorldSettings, validate_world_settings, "act_deadline", 0.0),
        (WorldSettings, validate_world_settings, "clock", "sundial"),
        (WorldSettings, validate_world_settings, "episodes", -1),
        (AgentSettings, validate_agent_settings, "agent", ""),
        (AgentSettings, validate_agent_settings, "policy", "clever"),
        (AgentSettings, validate_agent_settings, "epsilon", 2.0),
        (TrainerSettings, validate_trainer_settings, "run_dir", ""),
        (TrainerSettings, validate_trainer_settings, "settings_json", "[1]"),
    ],
)
def test_settings_validation_names_the_parameter(cls: type, check, field: str, bad: object) -> None:  # type: ignore[no-untyped-def]
    base = {"agent": "agent1"} if cls is AgentSettings else {"run_dir": "x"} if cls is TrainerSettings else {}
    good = cls(**base)
    assert check(good) == []
    problems = check(dataclasses.replace(good, **{field: bad}))
    assert (problems and problems[0].startswith(f"{field}:") and repr(bad) in problems[0]) or str(bad) in problems[0]


def test_launch_specs_and_environment(tmp_path: Path) -> None:
    sc = builtin()
    cfg = LaunchConfig(mode="evaluate", scenario=sc, run_dir=tmp_path / "run", policy="greedy", domain_id=77)
    specs = process_specs(cfg)
    assert [s[0] for s in specs] == ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]
    assert specs[2][2]["agent"] == "agent1" and specs[0][2]["mode"] == "evaluate"
    env = ros_env(cfg)
    assert env["ROS_DOMAIN_ID"] == "77"
    # no shared-memory transport unless asked for: a SIGKILLed process must not freeze the others (launch.ros_env);
    # localhost discovery through the loopback-only profile, since Jazzy's LOCALHOST range brings shared memory back
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == os.environ.get("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")
    if "FASTRTPS_DEFAULT_PROFILES_FILE" not in os.environ:
        assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
        assert env["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_loopback.xml")
    wide = ros_env(dataclasses.replace(cfg, discovery="subnet"))
    assert wide["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET" and not wide["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith(
        "loopback.xml"
    )
    only = process_specs(dataclasses.replace(cfg, only=("agent2",)))
    assert [s[0] for s in only] == ["agent2"]
    p = write_params(tmp_path / "p.yaml", {"a": "x: y", "b": 1.5, "c": True})
    assert p.read_text().splitlines()[2:] == ['    a: "x: y"', "    b: 1.5", "    c: true"]
