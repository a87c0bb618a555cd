"""Faults of a real deployment, with real processes over real DDS: an agent killed mid-episode and restarted, the
trainer killed mid-training and restarted."""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.transition_store import read_store
from htlm_world.scenario import builtin
from support.ros import read_json

# batch 1: the same faults run by default with batches of 8 (test_robustness_batch.py); these with -m slow
pytestmark = [pytest.mark.ros, pytest.mark.timeout(150), pytest.mark.slow]

FAST = {"act_deadline": 2.0, "update_deadline": 2.0, "begin_deadline": 2.0}


def test_agent_killed_mid_episode_is_idle_then_rejoins(ros_team: Any) -> None:
    sc = builtin().replace(horizon=150)  # long episodes: the kill lands mid-episode
    team = ros_team(scenario=sc, episodes=5, seed=2, world_params=FAST, agent_params={"broadcast_timeout": 0.5})
    scen = team.tmp / "long.yaml"
    scen.write_text("horizon: 150\n")
    team.cfg.scenario_file = str(scen)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= 1, 60, "the first episode")
    time.sleep(0.25)  # inside episode 1 (150 steps take about a second)
    team.kill("agent3", signal.SIGKILL)
    killed_in = len(team.world_episodes())
    team.wait_for(lambda: len(team.world_episodes()) > killed_in, 60, "the episode of the kill to finish")
    team.start("agent3")  # restarted: it rejoins at the start of a later episode
    assert team.wait("world", 90) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    eps = {w["metrics"]["episode"]: w for w in team.world_episodes()}
    assert sorted(eps) == [0, 1, 2, 3, 4], "every episode ran"
    hit = eps[killed_in]
    assert len(hit["actions"]) == sc.horizon, "the episode of the kill ran all h steps"
    absent = hit["metrics"]["absent"]
    # the killed agent is absent from the kill on; a teammate waiting for its last broadcast may miss a step on a
    # loaded machine, no more
    assert absent[2] > 0 and max(absent[:2] + absent[3:]) <= 2, absent
    # its missed steps are idle at its site in the joint assignment the world applied
    steps = np.array(hit["actions"])[:, 2]
    assert (steps[-absent[2] :] >= sc.n_tasks).all()
    rejoined = [e for e in sorted(eps) if e > killed_in and eps[e]["metrics"]["absent"][2] == 0]
    assert rejoined, f"agent3 never rejoined: {[eps[e]['metrics']['absent'] for e in sorted(eps)]}"
    assert {x["episode"] for x in team.agent_episodes("agent3")} >= set(rejoined)
    print(
        f"killed in episode {killed_in} after {sc.horizon - absent[2]} steps; absent {absent[2]} steps; "
        f"rejoined at episode {rejoined[0]}"
    )


def test_trainer_killed_and_restarted_loses_no_acknowledged_transition(ros_team: Any) -> None:
    team = ros_team(
        mode="train",
        policy="auto",
        episodes=40,
        seed=4,
        learner={"learning_starts": 60, "batch_size": 32, "memory": 5000},
        trainer_params={"checkpoint_every": 2},
        agent_params={"stop_timeout": 20.0, "resend_period": 0.5},
        grace=40.0,
    )
    team.start()
    store = team.run_dir / "trainer" / "transitions.bin"
    team.wait_for(lambda: len(team.world_episodes()) >= 3, 90, "three training episodes")
    team.wait_for(lambda: (team.run_dir / "trainer" / "checkpoint" / "meta.json").exists(), 30, "a checkpoint")
    team.kill("trainer", signal.SIGKILL)
    before = read_store(store).copy()  # everything the trainer could have acknowledged: acks follow the fsync
    acked_keys = {(int(r["agent"]), bytes(r["session"]), int(r["seq"])) for r in before}
    time.sleep(1.5)  # agents keep playing; their transitions pile up unacknowledged
    team.start("trainer")
    assert team.wait("world", 120) == 0
    codes = team.wait_all(60)
    assert codes == dict.fromkeys(codes, 0), codes
    after = read_store(store)
    keys = {(int(r["agent"]), bytes(r["session"]), int(r["seq"])) for r in after}
    assert acked_keys <= keys, f"{len(acked_keys - keys)} acknowledged transitions lost"
    assert len(keys) == len(after), "no transition stored twice"
    # nothing the agents sent is lost at all: per agent session, seq 0..n-1 with n = steps played
    h = builtin().horizon
    for i in range(5):
        played = sum(1 for e in team.world_episodes() if e["metrics"]["absent"][i] == 0) * h
        seqs = sorted(int(r["seq"]) for r in after if int(r["agent"]) == i)
        assert seqs == list(range(played)), f"agent {i}: {len(seqs)} stored of {played}"
    log = team.log("trainer")
    assert "resumed from" in log, log[-2000:]
    after_restart = log.split("resumed from", 1)[1]
    rounds = re.search(r"train_rounds (\d+)", after_restart)  # the counters the restarted trainer logs at exit
    assert rounds is not None and int(rounds.group(1)) > 0, "the restarted trainer trained on"
    assert "checkpoint" in after_restart, "the restarted trainer wrote its checkpoint"
    meta = read_json(team.run_dir / "trainer" / "checkpoint" / "meta.json")
    assert meta["format"] == "htlm-checkpoint" and meta["episodes_done"] == 40
    print(
        f"store held {len(before)} transitions at the kill (all kept); {len(after)} at the end "
        f"= {len(after) // 5} per agent; checkpoint after {meta['episodes_done']} episodes"
    )
    assert Path(team.run_dir / "trainer" / "train_log.jsonl").exists()
