"""The trainer's core without ROS (htlm_agent.learning.trainer.TrainerCore): the training schedule (rounds per
received transitions, the backlog limit, weights and checkpoints when due) is deterministic, and a trainer started
again on its run directory resumes from the checkpoint and the store's later records."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.trainer import Schedule, TrainerCore, TrainerEffects, load_learner_data
from htlm_world.model import Model
from htlm_world.scenario import builtin

SC = builtin()
N = SC.n_agents
LEARNER = {
    "hidden": [16],
    "learning_starts": 4,
    "batch_size": 4,
    "memory": 200,
    "envs": 1,
    "updates_per_step": 2,
    "episodes": 10,
}
EVERY = Schedule(train_every=5, train_budget=1e9, max_backlog=500, publish_every=1, checkpoint_every=0)


def _scenario(mode: str = "train", run: str = "r1", state: str = "running", episodes: int = 0) -> dict[str, Any]:
    return {
        "run": run,
        "seed": 7,
        "mode": mode,
        "clock": "lockstep",
        "first_episode": 0,
        "episodes": episodes,
        "state": state,
        "layout": SC.layout_hash(),
        "scenario": SC.to_dict(),
    }


def _transitions(count: int, episode: int = 0, seed: int = 0, start: int = 0) -> list[dict[str, Any]]:
    """`count` valid transition records, round robin over the agents (session per agent, seq from `start`)."""
    rng = np.random.default_rng(seed)
    model = Model.build(SC)
    out = []
    for i in range(count):
        agent = i % N
        a = int(rng.integers(SC.n_tasks))
        out.append(
            {
                "agent": agent,
                "session": f"{agent:016x}",
                "seq": start + i // N,
                "episode": episode,
                "step": i // N % SC.horizon + 1,
                "k": rng.random(SC.knowledge_size).tolist(),
                "a": a,
                "r": float(rng.normal()),
                "k2": rng.random(SC.knowledge_size).tolist(),
                "mask2": model.action_mask(np.int64(a)).tolist(),
                "done": False,
            }
        )
    return out


def _core(run_dir: Path, schedule: Schedule = EVERY, resume: bool = True, mode: str = "train") -> TrainerCore:
    core = TrainerCore(run_dir, schedule, dict(LEARNER), "test", resume)
    eff = core.on_scenario(_scenario(mode), 0.0)
    assert eff.fatal is None, eff.fatal
    return core


def _feed(core: TrainerCore, recs: list[dict[str, Any]]) -> TrainerEffects:
    out = TrainerEffects()
    for r in recs:
        eff = core.on_transition(r, 1.0)
        out.drops += eff.drops
        out.rejects += eff.rejects
    return out


def _metrics(episode: int) -> dict[str, Any]:
    return {"episode": episode, "completion": 30, "failed": True, "absent": [0] * N}


def test_start_publishes_the_first_weights_and_settings(tmp_path: Path) -> None:
    core = TrainerCore(tmp_path, EVERY, dict(LEARNER), "test")
    assert core.epoch == 1 and core.on_transition(_transitions(1)[0], 0.0).counters == {
        "ignored/transitions/no_scenario": 1
    }
    eff = core.on_scenario(_scenario(), 0.0)
    assert [w["agent"] for w in eff.weights] == list(range(N))
    assert all(w["version"] == 2**32 + 1 and w["settings"]["seed"] == 7 for w in eff.weights)
    assert (tmp_path / "settings.json").exists() and core.learner.settings.hidden == (16,)
    assert any("training 5 agents" in text for _, text in eff.log)
    assert core.publish_weights() == []  # nothing changed since


def test_schedule_one_round_per_train_every_transitions(tmp_path: Path) -> None:
    core = _core(tmp_path)
    assert _feed(core, _transitions(4)).drops == []
    assert core.train(lambda: 0.0).counters == {}  # fewer than train_every: nothing owed yet
    _feed(core, _transitions(56, start=1))
    eff = core.train(lambda: 0.0)
    assert eff.counters == {"train_calls": 1, "train_rounds": 12}  # 60 // 5 rounds
    assert core.new_transitions == 0
    assert core.updates == int(np.asarray(core.learner.updates).max()) > 0
    assert core.updates <= 12 * LEARNER["updates_per_step"]


def test_schedule_skips_rounds_beyond_the_backlog_and_respects_the_budget(tmp_path: Path) -> None:
    core = _core(tmp_path, Schedule(train_every=5, train_budget=1e9, max_backlog=3))
    _feed(core, _transitions(60))
    eff = core.train(lambda: 0.0)
    assert eff.counters == {"skipped_rounds": 9, "train_calls": 1, "train_rounds": 3}
    ticks = iter(range(100))
    core2 = _core(tmp_path / "b", Schedule(train_every=5, train_budget=2.5))
    _feed(core2, _transitions(60))
    eff = core2.train(lambda: float(next(ticks)))  # each look at the clock is one second later
    assert eff.counters["train_rounds"] == 2 and core2.new_transitions == 50  # the rest waits for later calls


def test_schedule_is_deterministic(tmp_path: Path) -> None:
    runs = []
    for name in ("a", "b"):
        core = _core(tmp_path / name)
        for chunk in range(4):
            _feed(core, _transitions(23, seed=chunk, start=chunk * 5))
            core.train(lambda: 0.0)
        runs.append((core.updates, core.last_loss, [core.learner.agent_weights(i) for i in range(N)]))
    assert runs[0] == runs[1]


def test_weights_and_checkpoints_when_due(tmp_path: Path) -> None:
    core = _core(tmp_path, Schedule(train_every=5, train_budget=1e9, publish_every=2, checkpoint_every=3))
    _feed(core, _transitions(40))
    core.train(lambda: 0.0)
    first = core.on_metrics(_metrics(0))
    assert first.weights == [] and first.acks == [] and first.counters == {}
    second = core.on_metrics(_metrics(1))
    assert [w["version"] for w in second.weights] == [2**32 + 2] * N  # publish_every 2
    third = core.on_metrics(_metrics(2))
    assert third.counters["checkpoints"] == 1 and (tmp_path / "checkpoint" / "meta.json").exists()
    # the checkpoint flushed the store first: every agent session is acknowledged up to its last seq
    assert sorted((a["agent"], a["upto"]) for a in third.acks) == [(i, 7) for i in range(N)]
    assert core.on_metrics(_metrics(9)).drops == []  # episodes 0 (unbounded run): in the run
    lines = (tmp_path / "train_log.jsonl").read_text().splitlines()
    assert len(lines) == 4


def test_transitions_outside_the_run_duplicates_and_empty_masks(tmp_path: Path) -> None:
    core = TrainerCore(tmp_path, EVERY, dict(LEARNER), "test")
    core.on_scenario(_scenario(episodes=2), 0.0)
    rec = _transitions(1)[0]
    assert _feed(core, [rec]).drops == []
    assert _feed(core, [rec]).drops == [("transitions", "duplicate")]
    assert _feed(core, [{**rec, "seq": 1, "episode": 2}]).drops == [("transitions", "outside_run")]
    assert _feed(core, [{**rec, "seq": 1, "mask2": [False] * SC.n_actions}]).rejects[0][:2] == ("transitions", "range")
    acks = core.flush().acks
    assert acks == [{"agent": 0, "session": rec["session"], "upto": 0}]  # the duplicate asks for an ack again
    assert core.on_metrics(_metrics(5)).drops == [("episode_metrics", "outside_run")]


def test_the_run_stopping_another_layout_and_recording_only(tmp_path: Path) -> None:
    core = _core(tmp_path / "a")
    assert core.quiet_for(100.0) == 0.0
    eff = core.on_scenario(_scenario(state="stopped"), 10.0)
    assert core.stopping and eff.log == [("info", "run r1 stopped by the world")]
    assert core.quiet_for(12.5) == pytest.approx(2.5)
    other = builtin("homogeneous")
    rec = {**_scenario(run="r2"), "layout": other.layout_hash(), "scenario": other.to_dict()}
    if other.layout_hash() != SC.layout_hash():
        assert core.on_scenario(rec, 11.0).fatal is not None
    bad = {**_scenario(run="r3"), "layout": "0" * 16}
    assert core.on_scenario(bad, 11.0).rejects[0][:2] == ("scenario", "layout")
    rec_only = _core(tmp_path / "b", mode="evaluate")
    assert rec_only.learner is None and rec_only.store is not None
    _feed(rec_only, _transitions(10))
    assert rec_only.train(lambda: 0.0).counters == {} and rec_only.on_metrics(_metrics(0)).weights == []
    assert len((tmp_path / "b" / "train_log.jsonl").read_text().splitlines()) == 1


def test_resume_from_the_checkpoint_and_the_later_records(tmp_path: Path) -> None:
    core = _core(tmp_path, Schedule(train_every=5, train_budget=1e9, checkpoint_every=1))
    _feed(core, _transitions(40))
    core.train(lambda: 0.0)
    eff = core.on_metrics(_metrics(0))
    assert eff.counters["checkpoints"] == 1
    at_checkpoint = (core.updates, [core.learner.agent_weights(i) for i in range(N)])
    later = _transitions(15, episode=1, seed=3, start=8)  # stored after the checkpoint, never trained on
    _feed(core, later)
    core.flush()
    del core  # killed: no shutdown, no final checkpoint

    again = TrainerCore(tmp_path, EVERY, dict(LEARNER), "test")
    assert again.epoch == 2
    eff = again.on_scenario(_scenario(), 0.0)
    assert eff.fatal is None
    assert any(text.startswith("resumed from") and "1 episodes" in text for _, text in eff.log), eff.log
    assert any("55 transitions" in text and "15 fed to the learner" in text for _, text in eff.log), eff.log
    assert (again.updates, [again.learner.agent_weights(i) for i in range(N)]) == at_checkpoint
    assert again.episodes_seen == 1 and again.episodes_stored == {0, 1}
    assert int(again.learner.replay.size.sum()) == 55
    assert all(w["version"] == 2 * 2**32 + 1 for w in eff.weights)  # versions grow across restarts
    # an agent resending what was stored before the kill gets its acknowledgement, nothing is stored twice
    assert _feed(again, later[:1]).drops == [("transitions", "duplicate")]
    assert again.flush().acks == [{"agent": 0, "session": later[0]["session"], "upto": 10}]
    again.shutdown(lambda: 0.0)
    assert again.store is None

    fresh = TrainerCore(tmp_path, EVERY, dict(LEARNER), "test", resume=False)
    eff = fresh.on_scenario(_scenario(), 0.0)
    assert eff.fatal is not None and "resume is off" in eff.fatal and fresh.fatal == eff.fatal


def test_learner_data_from_a_file_and_json(tmp_path: Path) -> None:
    f = tmp_path / "l.yaml"
    f.write_text("learning_starts: 9\nhidden: [8]\n")
    data = load_learner_data(str(f), '{"learning_starts": 11}')
    assert data == {"learning_starts": 11, "hidden": [8]}
    core = TrainerCore(tmp_path / "run", EVERY, data, str(f))
    assert core.learner_settings(3).seed == 3 and core.learner_settings(3).learning_starts == 11
    with pytest.raises(ValueError, match="settings_json"):
        load_learner_data("", "[1]")
    with pytest.raises(ValueError, match="cannot read"):
        load_learner_data(str(tmp_path / "missing.json"), "")
    f.write_text("a: [1\n")
    with pytest.raises(ValueError, match="not YAML"):
        load_learner_data(str(f), "")
