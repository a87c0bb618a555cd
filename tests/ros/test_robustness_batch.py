"""Faults of a real deployment with B > 1 episodes at once (real processes over real DDS): an agent SIGKILLed
mid-batch is idle in all B episodes of the steps it misses and rejoins later; the trainer killed and restarted
mid-training loses no acknowledged transition and trains on; records with arrays of the wrong length (an action
record with B - 1 actions, a broadcast with B + 1 levels) from a stranger are rejected, counted on /diagnostics,
and change nothing."""

from __future__ import annotations

import json
import signal
import time
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.transition_store import read_store
from htlm_world.model import Model
from htlm_world.scenario import builtin
from support.ros import assert_same_as_in_process, read_json

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

B = 8
FAST = {"act_deadline": 2.0, "update_deadline": 2.0, "begin_deadline": 2.0}


@pytest.mark.slow  # CI budget: the default run keeps the records of the wrong length; this one with -m slow
def test_agent_killed_mid_batch_is_idle_in_every_episode_then_rejoins(ros_team: Any) -> None:
    sc = builtin().replace(horizon=150)  # long batches: the kill lands mid-batch
    team = ros_team(
        scenario=sc, episodes=6 * B, batch=B, seed=2, world_params=FAST, agent_params={"broadcast_timeout": 0.5}
    )
    scen = team.tmp / "long.yaml"
    scen.write_text("horizon: 150\n")
    team.cfg.scenario_file = str(scen)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 90, "the first batch")
    time.sleep(0.3)  # inside batch 1
    team.kill("agent3", signal.SIGKILL)
    killed_in = len(team.world_episodes())
    team.wait_for(lambda: len(team.world_episodes()) > killed_in, 60, "the batch of the kill to finish")
    # restarted: it rejoins at the begin of a later batch; a restart takes 2-4 s under load (imports, discovery), about
    # one batch: the run leaves it four batch begins to rejoin at (a begin it answers too late, it plays in part)
    team.start("agent3")
    assert team.wait("world", 120) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    eps = {w["metrics"]["episode"]: w for w in team.world_episodes()}
    assert sorted(eps) == list(range(6 * B)), "every episode ran"
    hit = [eps[e] for e in range(killed_in, killed_in + B)]
    absent = hit[0]["metrics"]["absent"]
    assert all(w["metrics"]["absent"] == absent for w in hit), "one absence count for the whole batch"
    assert absent[2] > 0 and max(absent[:2] + absent[3:]) <= 2, absent
    missed = absent[2]
    model = Model.build(sc)
    for w in hit:
        acts = np.array(w["actions"])[:, 2]
        assert len(acts) == sc.horizon, "the batch of the kill ran all h steps"
        first = sc.horizon - missed
        prev = acts[first - 1] if first > 0 else sc.start_assignment
        idle = int(model.idle_action(np.array(prev)))
        # in every episode of the batch, the missed steps are its idle action at the site of its last assignment
        assert (acts[first:] == idle).all(), (w["metrics"]["episode"], acts[first:].tolist(), idle)
    rejoined = [e for e in sorted(eps) if e >= killed_in + B and eps[e]["metrics"]["absent"][2] == 0]
    assert rejoined, f"agent3 never rejoined: {[eps[e]['metrics']['absent'] for e in range(0, 6 * B, B)]}"
    assert rejoined[0] % B == 0 and set(range(rejoined[0], 6 * B)) <= set(rejoined), "rejoined whole batches"
    assert {x["episode"] for x in team.agent_episodes("agent3")} >= set(rejoined)
    print(f"killed in batch {killed_in // B} after {sc.horizon - missed} steps; rejoined at episode {rejoined[0]}")


@pytest.mark.slow  # CI budget: the default run keeps the records of the wrong length; this one with -m slow
def test_trainer_killed_mid_batch_loses_no_acknowledged_transition(ros_team: Any) -> None:
    team = ros_team(
        mode="train",
        policy="auto",
        episodes=6 * B,
        batch=B,
        seed=4,
        learner={"envs": B, "learning_starts": 60, "batch_size": 32, "memory": 20000},
        trainer_params={"checkpoint_every": B},
        agent_params={"stop_timeout": 20.0, "resend_period": 0.5},
        grace=40.0,
    )
    team.start()
    store = team.run_dir / "trainer" / "transitions.bin"
    team.wait_for(lambda: len(team.world_episodes()) >= 2 * B, 120, "two training batches")
    team.wait_for(lambda: (team.run_dir / "trainer" / "checkpoint" / "meta.json").exists(), 30, "a checkpoint")
    team.kill("trainer", signal.SIGKILL)
    before = read_store(store).copy()  # everything the trainer could have acknowledged: acks follow the fsync
    acked = {(int(r["agent"]), bytes(r["session"]), int(r["seq"]), int(r["row"])) for r in before}
    time.sleep(1.5)  # the world waits for the trainer (pace) or goes on after its deadline
    team.start("trainer")
    assert team.wait("world", 150) == 0
    codes = team.wait_all(60)
    assert codes == dict.fromkeys(codes, 0), codes
    after = read_store(store)
    keys = {(int(r["agent"]), bytes(r["session"]), int(r["seq"]), int(r["row"])) for r in after}
    assert acked <= keys, f"{len(acked - keys)} acknowledged transitions lost"
    assert len(keys) == len(after), "no transition stored twice"
    h = builtin().horizon
    for i in range(5):
        played = sum(1 for e in team.world_episodes() if e["metrics"]["absent"][i] == 0) * h  # rows: one per episode
        mine = after[after["agent"] == i]
        assert len(mine) == played, f"agent {i}: {len(mine)} rows stored of {played}"
        assert sorted(set(mine["seq"].tolist())) == list(range(played // B)), f"agent {i}: a record missing"
    log = team.log("trainer")
    assert "resumed from" in log, log[-2000:]
    meta = read_json(team.run_dir / "trainer" / "checkpoint" / "meta.json")
    # trained on after the restart; NOTE: the batch stored after the last checkpoint before the kill is not counted
    # (nor, it seems, trained on) by the resumed trainer: 40 of 48 episodes on 2026-11-22, reported to the lead
    assert 2 * B < meta["episodes_done"] <= 6 * B, meta["episodes_done"]
    print(f"store held {len(before)} rows at the kill (all kept); {len(after)} at the end")


def test_records_of_the_wrong_length_are_rejected_and_change_nothing(ros_team: Any) -> None:
    seed, episodes = 9, 4 * B
    team = ros_team(
        policy="greedy",
        seed=seed,
        episodes=episodes,
        batch=B,
        world_params={"diagnostics_period": 0.2},
        agent_params={"diagnostics_period": 0.2},
    )
    diag = team.tmp / "diag.json"
    team.helper("diag", "--out", str(diag))
    out = team.tmp / "rogue.json"
    rogue = team.helper(
        "rogue",
        "--out",
        str(out),
        "--wrong-lengths",
        "--kinds",
        "action,broadcast",
        "--pause",
        "0.05",
        "--seconds",
        "90",
    )
    time.sleep(1.5)  # the stranger is up before the team starts
    team.start()
    assert team.wait("world", 90) == 0
    rogue.send_signal(signal.SIGTERM)
    rogue.wait(timeout=10)
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    time.sleep(0.5)
    team.helpers[0].send_signal(signal.SIGTERM)
    team.helpers[0].wait(timeout=10)
    sent = read_json(out)
    assert sent["sent"] > 100 and set(sent["sizes"].values()) == {B}, sent
    assert assert_same_as_in_process(team, seed, "greedy") == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    status = {k.split(": ", 1)[1]: v for k, v in json.loads(diag.read_text()).items()}
    world_len = int(status["world"].get("rejected/action/length", 0))
    agent_len = {f"agent{i}": int(status[f"agent{i}"].get("rejected/broadcast/length", 0)) for i in range(1, 6)}
    assert world_len > 0, status["world"]
    assert all(n > 0 for n in agent_len.values()), agent_len
    print(
        f"{sent['sent']} records of the wrong length; world rejected {world_len} actions, "
        f"agents rejected {agent_len} broadcasts"
    )
