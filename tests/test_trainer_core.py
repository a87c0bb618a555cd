"""The trainer's core without ROS (htlm_agent.trainer.core.TrainerCore): rounds of updates per step of the
batched lockstep (run in step order once every agent that acted sent its transitions, or after the deadline) are
deterministic and equal `htlm train`'s store_batch + train_steps; progress after every round, weights on a fixed
cadence, checkpoints every few episodes; a trainer started again on its run directory resumes from the checkpoint
and the store's later records."""

from __future__ import annotations

import itertools
import json
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.settings import Settings
from htlm_agent.trainer.core import Schedule, TrainerCore, TrainerEffects, load_learner_data
from htlm_msgs_py import schema as S
from htlm_world.model import Model
from htlm_world.scenario import builtin

SC = builtin()
N = SC.n_agents
H = SC.horizon
LEARNER = {
    "hidden": [16],
    "learning_starts": 4,
    "batch_size": 4,
    "memory": 200,
    "updates_per_step": 2,
    "episodes": 10,
    "validate_every": 0,
}
SCHED = Schedule(weights_every=1, round_deadline=5.0, checkpoint_every=0)
MODEL = Model.build(SC)


_SEQ = itertools.count()
"""Announcements only grow (a repeated sequence number is a replay)."""


def _scenario(
    mode: str = "train", run: str = "r1", state: str = "running", episodes: int = 0, first: int = 0, batch: int = 2
) -> dict[str, Any]:
    return {
        "run": run,
        "nonce": "00000000000000aa",
        "seq": next(_SEQ),
        "seed": 7,
        "mode": mode,
        "clock": "lockstep",
        "period": 0.5,
        "operation": "simulated",
        "first_episode": first,
        "episodes": episodes,
        "batch": batch,
        "trainer_lag": 0,
        "epoch": 0.0,
        "state": state,
        "layout": SC.layout_hash(),
        "scenario": SC.to_dict(),
    }


def _step(g: int, batch: int = 2, seed: int = 0) -> list[dict[str, Any]]:
    """The N transition records (agent order) of global step g = batch index * H + t - 1 in batches of `batch`
    episodes; each agent's seq is g (one record per step from its first)."""
    b, t = divmod(g, H)
    rng = np.random.default_rng((seed, g))
    out = []
    for agent in range(N):
        a = rng.integers(SC.n_actions, size=batch)
        out.append(
            {
                "agent": agent,
                "session": f"{agent:016x}",
                "seq": g,
                "episode": b * batch,
                "step": t + 1,
                "k": rng.random((batch, SC.knowledge_size)).tolist(),
                "a": a.tolist(),
                "r": rng.normal(size=batch).tolist(),
                "k2": rng.random((batch, SC.knowledge_size)).tolist(),
                "mask2": MODEL.action_mask(a).tolist(),
                "done": t + 1 == H,
            }
        )
    return out


def _steps(lo: int, hi: int, batch: int = 2, seed: int = 0) -> list[dict[str, Any]]:
    """The records of global steps lo .. hi - 1, step by step in agent order."""
    return [r for g in range(lo, hi) for r in _step(g, batch, seed)]


def _core(
    run_dir: Path,
    schedule: Schedule = SCHED,
    batch: int = 2,
    resume: bool = True,
    learner: dict[str, Any] | None = None,
    **scenario: Any,
) -> TrainerCore:
    core = TrainerCore(run_dir, schedule, {**(learner or LEARNER), "envs": batch}, "test", resume)
    eff = core.on_scenario(_scenario(batch=batch, **scenario), 0.0)
    assert eff.fatal is None, eff.fatal
    return core


def _merge(out: TrainerEffects, eff: TrainerEffects) -> TrainerEffects:
    out.acks += eff.acks
    out.weights += eff.weights
    out.progress += eff.progress
    out.log += eff.log
    out.counters.update(eff.counters)
    out.drops += eff.drops
    out.rejects += eff.rejects
    return out


def _feed(core: TrainerCore, recs: list[dict[str, Any]], now: float = 1.0) -> TrainerEffects:
    out = TrainerEffects()
    for r in recs:
        _merge(out, core.on_transition(r, now))
    return out


def _weights(core: TrainerCore) -> list[bytes]:
    return [core.learner.agent_weights(i) for i in range(N)]


def test_start_publishes_the_first_weights_progress_and_settings(tmp_path: Path) -> None:
    core = TrainerCore(tmp_path, SCHED, {**LEARNER, "envs": 2}, "test")
    assert core.epoch == 1 and core.on_transition(_step(0)[0], 0.0).counters == {"ignored/transitions/no_scenario": 1}
    eff = core.on_scenario(_scenario(), 0.0)
    assert [w["agent"] for w in eff.weights] == list(range(N))
    assert all(w["version"] == 2**32 + 1 and w["trained"] == 0 and w["settings"]["seed"] == 7 for w in eff.weights)
    assert eff.progress == [{"run": "r1", "trained": 0, "updates": 0, "finished": False}]
    assert (tmp_path / "settings.json").exists() and core.learner.settings.hidden == (16,) and core.batch == 2
    assert any("training 5 agents" in text and "batches of 2" in text for _, text in eff.log), eff.log
    assert core.publish_weights() == []  # nothing trained since


def test_rounds_run_in_step_order_once_every_agent_sent_its_step(tmp_path: Path) -> None:
    core = _core(tmp_path)
    s0, s1, s2 = _step(0), _step(1), _step(2)
    eff = _feed(core, s0[:-1])
    assert eff.progress == [] and eff.counters == {} and core.trained == 0  # agent 4 missing
    eff = _feed(core, s0[-1:])
    assert eff.progress == [{"run": "r1", "trained": 1, "updates": 0, "finished": False}] and eff.counters == {
        "train_rounds": 1
    }
    assert [w["trained"] for w in eff.weights] == [1] * N
    eff = _feed(core, s2)  # complete, but step 1 is not: it waits
    assert eff.progress == [] and core.trained == 1 and core.values()["rounds_waiting"] == "1"
    eff = _feed(core, s1)
    assert [p["trained"] for p in eff.progress] == [2, 3]  # one progress record per round, in step order
    assert eff.counters == {"train_rounds": 2}
    assert core.updates == int(np.asarray(core.learner.updates).max()) > 0  # 30 transitions per agent by now
    assert eff.progress[-1]["updates"] == core.updates <= 3 * LEARNER["updates_per_step"]
    assert int(core.learner.replay.size.sum()) == 3 * N * 2


def test_rounds_are_deterministic_whatever_the_arrival_order(tmp_path: Path) -> None:
    recs = _steps(0, 40, seed=1)
    by_agent = sorted(recs, key=lambda r: (r["agent"], r["seq"]))  # each agent sends all its steps in turn
    shuffled = []
    for g in range(40):  # agents in a random order within each step, now and then a step ahead of another's
        step = recs[g * N : (g + 1) * N]
        random.Random(g).shuffle(step)
        shuffled += step
    shuffled[5 * N : 7 * N] = sorted(shuffled[5 * N : 7 * N], key=lambda r: -r["seq"])
    runs = []
    for name, order in (("a", recs), ("b", by_agent), ("c", shuffled)):
        core = _core(tmp_path / name)
        eff = _feed(core, order)
        assert eff.counters["train_rounds"] == 40 and "partial_rounds" not in eff.counters
        assert [p["trained"] for p in eff.progress] == list(range(1, 41))
        runs.append((core.trained, core.updates, core.last_loss, core.episodes_seen, _weights(core)))
    assert runs[0] == runs[1] == runs[2]
    assert runs[0][3] == 2  # the first batch of 2 episodes is done


WARM_START = {**LEARNER, "learner": "tokens", "hidden": [8, 8], "imitate": "auction", "imitate_episodes": 4}
"""Token networks whose first batch of 4 episodes is a warm start on the auction."""


@pytest.mark.parametrize(("wire", "settings"), [(False, LEARNER), (True, LEARNER), (True, WARM_START)])
def test_trainer_rounds_equal_the_in_process_learner(tmp_path: Path, wire: bool, settings: dict[str, Any]) -> None:
    """Round by round the trainer does what `htlm train` does per step: store_batch of every agent's transitions,
    then train_steps(updates_per_step); the networks are identical. Also when the records went through the wire
    (`wire`: K and K' as float32, the rest exactly) while the in-process learner gets the float64 originals, and in
    a warm start (the imitation update of `imitate_step` on the step's knowledge states first)."""
    from htlm_agent.learning.loop import imitate_step, warm_start_expert

    batch, steps = 4, 2 * H + 5
    core = _core(tmp_path, batch=batch, learner=settings)
    recs = _steps(0, steps, batch, seed=2)
    # each agent's records of a batch before the next agent's (a trainer takes at most two horizons ahead)
    sent = sorted(recs, key=lambda r: (r["seq"] // H, r["agent"], r["seq"]))
    if wire:
        lim = S.limits(SC.n_agents, SC.n_tasks, SC.n_actions, SC.levels, SC.horizon, batch)
        sent = [S.decode(S.encode(S.TRANSITION, {"run": "r1", **r}), S.TRANSITION, lim) for r in sent]
        assert sent[0]["k"].dtype == np.float32 and not np.array_equal(sent[0]["k"], np.asarray(recs[0]["k"]))
    _feed(core, sent)
    assert core.trained == steps
    learner = Learner(SC, Settings.from_dict({"seed": 7, **settings, "envs": batch}, "test"), 7)
    expert = warm_start_expert(SC, learner.settings)
    assert (expert is None) == (settings is LEARNER)
    for g in range(steps):
        step = recs[g * N : (g + 1) * N]

        def col(f: str, step: list[dict[str, Any]] = step) -> np.ndarray:
            return np.stack([np.asarray(r[f]) for r in step], axis=1)  # (B, N, ...)

        if expert is not None and learner.settings.warm_start(learner.episodes_done):
            imitate_step(learner, expert, col("k"))
        learner.store_batch(col("k"), col("a"), col("r"), col("k2"), col("mask2").astype(bool), bool(step[0]["done"]))
        learner.train_steps(LEARNER["updates_per_step"])
        if g % H == H - 1:
            learner.episodes_done += batch
    assert core.learner.episodes_done == learner.episodes_done == 2 * batch
    assert np.array_equal(np.asarray(core.learner.updates), np.asarray(learner.updates))
    assert _weights(core) == [learner.agent_weights(i) for i in range(N)]


def test_a_round_waits_for_the_agents_that_acted_or_the_deadline(tmp_path: Path) -> None:
    core = _core(tmp_path)
    s0 = _step(0)
    assert core.on_step({"episode": 0, "size": 2, "step": 1, "phase": "step", "acted": [0, 1, 2]}, 1.0).progress == []
    eff = _feed(core, s0[:2])
    assert eff.progress == []  # agent 2 acted too: its transitions are missing
    eff = _feed(core, s0[2:3])
    assert eff.counters == {"partial_rounds": 1, "train_rounds": 1} and [p["trained"] for p in eff.progress] == [1]
    assert int(core.learner.replay.size.sum()) == 3 * 2
    eff = _feed(core, s0[3:])  # the absent agents' records after all: into the memories, no round
    assert eff.counters == {"late_transitions": 2} and eff.progress == []
    assert int(core.learner.replay.size.sum()) == N * 2

    s1 = _step(1)
    _feed(core, s1[:4], now=10.0)  # no step record, agent 4 silent: the deadline decides
    assert core.tick(14.0).progress == [] and core.trained == 1
    eff = core.tick(15.5)
    assert eff.counters == {"partial_rounds": 1, "train_rounds": 1} and [p["trained"] for p in eff.progress] == [2]

    eff = _feed(core, _step(3), now=20.0)  # step 2 never comes: skipped once step 3 waited past the deadline
    assert eff.progress == [] and core.tick(24.0).progress == []
    eff = core.tick(25.5)
    assert eff.counters == {"empty_rounds": 1, "train_rounds": 1} and [p["trained"] for p in eff.progress] == [4]
    # a step record of a step already trained, or outside the run, changes nothing
    assert core.on_step({"episode": 0, "size": 2, "step": 2, "phase": "step", "acted": [0]}, 30.0).progress == []
    assert core.values()["rounds_waiting"] == "0"


@pytest.mark.parametrize(("every", "first"), [(3, 0), (4, 2)])
def test_weights_on_their_cadence_and_progress_after_every_round(tmp_path: Path, every: int, first: int) -> None:
    """Weights when trained - first_step is a multiple of weights_every (first_step: the run's first step; with
    first episode 2 in batches of 2 it is H = 30, not a multiple of 4), and once at start."""
    core = TrainerCore(tmp_path, Schedule(weights_every=every, round_deadline=5.0), {**LEARNER, "envs": 2}, "test")
    eff = core.on_scenario(_scenario(first=first), 0.0)
    lo = core.first_step
    assert lo == first // 2 * H and [w["trained"] for w in eff.weights] == [lo] * N
    assert eff.progress == [{"run": "r1", "trained": lo, "updates": 0, "finished": False}]
    eff = _feed(core, _steps(lo, lo + 13))
    assert [p["trained"] for p in eff.progress] == list(range(lo + 1, lo + 14))
    due = [g for g in range(lo + 1, lo + 14) if (g - lo) % every == 0]
    assert [w["trained"] for w in eff.weights] == [g for g in due for _ in range(N)]
    assert [w["version"] for w in eff.weights[::N]] == [2**32 + 2 + i for i in range(len(due))]
    assert all(w["every"] == every and w["agent"] == i % N for i, w in enumerate(eff.weights))
    assert core.publish_weights() != []  # asked for: the latest networks, once


def test_batches_are_counted_logged_and_checkpointed(tmp_path: Path) -> None:
    core = _core(tmp_path, Schedule(weights_every=1, round_deadline=5.0, checkpoint_every=4))
    eff = _feed(core, _steps(0, H))
    assert core.episodes_seen == 2 and "checkpoints" not in eff.counters
    eff = _feed(core, _steps(H, 2 * H))
    assert core.episodes_seen == 4 and eff.counters["checkpoints"] == 1
    assert (tmp_path / "checkpoint" / "meta.json").exists()
    # the checkpoint flushed the store first: every agent session is acknowledged up to its last seq
    assert sorted((a["agent"], a["upto"]) for a in eff.acks) == [(i, 2 * H - 1) for i in range(N)]
    assert core.on_metrics({"run": "r1", "episode": 1, "completion": 30, "failed": True, "absent": [0] * N}).drops == []
    repeat = core.on_metrics({"run": "r1", "episode": 1, "completion": 30, "failed": True, "absent": [0] * N})
    assert repeat.drops == [("episode_metrics", "past")]  # logged once
    other = core.on_metrics({"run": "r9", "episode": 2, "completion": 30, "failed": True, "absent": [0] * N})
    assert other.drops == [("episode_metrics", "other_run")]
    core.flush()
    lines = [json.loads(x) for x in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert [x.get("episodes") for x in lines] == [2, 4, None] and lines[-1]["episode"] == 1


def test_validation_at_the_end_of_a_batch(tmp_path: Path) -> None:
    core = TrainerCore(tmp_path, SCHED, {**LEARNER, "envs": 2, "validate_every": 2, "validate_episodes": 2}, "t")
    core.on_scenario(_scenario(), 0.0)
    eff = _feed(core, _steps(0, H))
    assert any(text.startswith("validation after 2 episodes") for _, text in eff.log), eff.log
    core.flush()
    (row,) = [json.loads(x) for x in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert row["episodes"] == 2 and 0 < row["val_completion"] <= H + 1


def test_transitions_outside_the_run_duplicates_and_bad_arrays(tmp_path: Path) -> None:
    core = _core(tmp_path, episodes=4)
    rec = _step(0)[0]
    assert _feed(core, [rec]).drops == []
    assert _feed(core, [rec]).drops == [("transitions", "duplicate")]
    assert _feed(core, [{**rec, "seq": 1, "episode": 4}]).drops == [("transitions", "outside_run")]
    for bad in (
        {"r": rec["r"][:1]},
        {"k2": rec["k2"] * 2},
        {"mask2": rec["mask2"][:1]},
        {"a": rec["a"] * 2, "r": rec["r"] * 2, "k": rec["k"] * 2, "k2": rec["k2"] * 2, "mask2": rec["mask2"] * 2},
    ):
        rejects = _feed(core, [{**rec, "seq": 1, **bad}]).rejects
        assert [x[:2] for x in rejects] == [("transitions", "length")], bad  # the last: more rows than the batch
    no_action = [[False] * SC.n_actions, rec["mask2"][1]]
    assert _feed(core, [{**rec, "seq": 1, "mask2": no_action}]).rejects[0][:2] == ("transitions", "range")
    acks = core.flush().acks
    assert acks == [{"agent": 0, "session": rec["session"], "upto": 0}]  # the duplicate asks for an ack again
    assert core.on_metrics({"run": "r1", "episode": 5, "completion": 30, "failed": True, "absent": [0] * N}).drops == [
        ("episode_metrics", "outside_run")
    ]
    assert core.on_step({"episode": 4, "size": 2, "step": 1, "phase": "step", "acted": []}, 1.0).progress == []
    assert core.store is not None and core.store.count == 2  # one record of two rows


def test_the_run_stopping_another_layout_and_recording_only(tmp_path: Path) -> None:
    core = _core(tmp_path / "a")
    assert core.quiet_for(100.0) == 0.0
    assert core.on_scenario(_scenario(run="r2", state="stopped"), 9.0).rejects[0][:2] == ("scenario", "other_run")
    assert not core.stopping, "a stop of another run while ours goes on"
    replayed = _scenario(state="stopped")
    eff = core.on_scenario(replayed, 10.0)
    assert core.stopping and eff.log == [("info", "run r1 stopped by the world")]
    assert core.quiet_for(12.5) == pytest.approx(2.5)
    assert core.on_scenario(replayed, 10.5).rejects[0][:2] == ("scenario", "replay")
    other = builtin("homogeneous")
    rec = {**_scenario(run="r2"), "layout": other.layout_hash(), "scenario": other.to_dict()}
    if other.layout_hash() != SC.layout_hash():
        assert core.on_scenario(rec, 11.0).fatal is not None
    bad = {**_scenario(run="r3"), "layout": "0" * 16}
    assert core.on_scenario(bad, 11.0).rejects[0][:2] == ("scenario", "layout")
    rec_only = _core(tmp_path / "b", mode="evaluate")
    assert rec_only.learner is None and rec_only.store is not None
    eff = _feed(rec_only, _steps(0, 3))
    assert eff.progress == [] and eff.weights == [] and rec_only.tick(100.0).progress == []
    assert eff.drops == [("transitions", "not_training")] * (3 * N)  # only a training run is training data
    rec_only.flush()
    assert rec_only.store.count == 0
    assert len((tmp_path / "b" / "train_log.jsonl").read_text().splitlines()) == 0


# validated and selected after the first batch, so that the checkpoint records a best score
SELECTING = {**LEARNER, "envs": 2, "episodes": 4, "validate_every": 2, "validate_episodes": 2}


def test_resume_from_the_checkpoint_and_the_later_records(tmp_path: Path) -> None:
    sched = Schedule(weights_every=1, round_deadline=5.0, checkpoint_every=2)
    core = TrainerCore(tmp_path, sched, SELECTING, "test")
    core.on_scenario(_scenario(), 0.0)
    eff = _feed(core, _steps(0, H))
    assert eff.counters["checkpoints"] == 1
    at_checkpoint = (core.updates, _weights(core))
    later = _steps(H, H + 10)  # stored and trained after the checkpoint
    _feed(core, later)
    core.flush()
    assert core.trained == H + 10
    del core  # killed: no shutdown, no final checkpoint

    again = TrainerCore(tmp_path, sched, SELECTING, "test")
    assert again.epoch == 2
    eff = again.on_scenario(_scenario(), 0.0)
    assert eff.fatal is None
    assert any(text.startswith("resumed from") and "2 episodes" in text for _, text in eff.log), eff.log
    rows = (H + 10) * N * 2
    assert any(f"{rows} transitions" in text and f"{10 * N * 2} fed to the learner" in text for _, text in eff.log)
    # what the store holds counts as trained: the world goes on from step H + 10
    assert again.trained == H + 10 and eff.progress == [
        {"run": "r1", "trained": H + 10, "updates": at_checkpoint[0], "finished": False}
    ]
    assert (again.updates, _weights(again)) == at_checkpoint
    assert again.episodes_seen == 2 and int(again.learner.replay.size.sum()) == rows
    assert again.selection.episode == 2 and again.selection.flat is not None
    assert all(w["version"] == 2 * 2**32 + 1 and w["trained"] == H + 10 for w in eff.weights)  # versions grow
    # an agent resending what was stored before the kill gets its acknowledgement, nothing is stored twice
    assert _feed(again, later[-1:]).drops == [("transitions", "duplicate")]
    assert again.flush().acks == [{"agent": N - 1, "session": later[-1]["session"], "upto": H + 9}]
    eff = _feed(again, _step(H + 10))
    assert [p["trained"] for p in eff.progress] == [H + 11] and again.updates > at_checkpoint[0]
    eff = again.shutdown(lambda: 0.0)
    assert eff.counters["checkpoints"] == 1 and again.store is None

    fresh = TrainerCore(tmp_path, sched, {**LEARNER, "envs": 2}, "test", resume=False)
    eff = fresh.on_scenario(_scenario(), 0.0)
    assert eff.fatal is not None and "resume is off" in eff.fatal and fresh.fatal == eff.fatal


def test_resume_from_a_checkpoint_before_any_validation(tmp_path: Path) -> None:
    sched = Schedule(weights_every=1, round_deadline=5.0, checkpoint_every=2)
    core = _core(tmp_path, sched)  # validate_every 0
    assert _feed(core, _steps(0, H)).counters["checkpoints"] == 1
    del core
    again = TrainerCore(tmp_path, sched, {**LEARNER, "envs": 2}, "test")
    eff = again.on_scenario(_scenario(), 0.0)
    assert eff.fatal is None and again.episodes_seen == 2


def test_resume_keeps_records_gathered_for_a_later_round_at_the_checkpoint(tmp_path: Path) -> None:
    sched = Schedule(weights_every=1, round_deadline=5.0, checkpoint_every=2)
    core = TrainerCore(tmp_path, sched, SELECTING, "test")
    core.on_scenario(_scenario(), 0.0)
    last = _step(H - 1)
    _feed(core, _steps(0, H - 1) + last[:-1] + _step(H))  # step H + 1 arrives before agent 4's step H
    eff = _feed(core, last[-1:])  # round H - 1 ends the batch and checkpoints; round H runs after it
    assert eff.counters["checkpoints"] == 1 and core.trained == H + 1
    core.flush()
    del core
    again = TrainerCore(tmp_path, sched, SELECTING, "test")
    assert again.on_scenario(_scenario(), 0.0).fatal is None
    assert int(again.learner.replay.size.sum()) == (H + 1) * N * 2


def test_learner_data_from_a_file_and_json(tmp_path: Path) -> None:
    f = tmp_path / "l.yaml"
    f.write_text("learning_starts: 9\nhidden: [8]\n")
    data = load_learner_data(str(f), '{"learning_starts": 11}')
    assert data == {"learning_starts": 11, "hidden": [8]}
    core = TrainerCore(tmp_path / "run", SCHED, data, str(f))
    assert core.learner_settings(3).seed == 3 and core.learner_settings(3).learning_starts == 11
    with pytest.raises(ValueError, match="settings_json"):
        load_learner_data("", "[1]")
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 'missing.json'}: cannot read")):
        load_learner_data(str(tmp_path / "missing.json"), "")
    f.write_text("a: [1\n")
    with pytest.raises(ValueError, match=re.escape(f"{f}: not YAML")):
        load_learner_data(str(f), "")
    bad = TrainerCore(tmp_path / "run2", SCHED, {"hidden": [16], "memory": 0}, str(f))
    eff = bad.on_scenario(_scenario(), 0.0)
    assert eff.fatal is not None and str(f) in eff.fatal and "memory" in eff.fatal
    inproc = TrainerCore(tmp_path / "run3", SCHED, {"learner": "lookahead"}, str(f))
    eff = inproc.on_scenario(_scenario(), 0.0)  # a learner with nothing to learn from the agents' transitions
    assert eff.fatal is not None and "learns in process only" in eff.fatal and "htlm train" in eff.fatal


def test_no_transition_record_can_break_a_round(tmp_path: Path) -> None:
    """A well-formed record whose rows do not fit the batch it names, or that begins no batch, or lies far ahead of
    the rounds done, or another session's record of a step the agent sent, is rejected or dropped and counted; the
    rounds go on with the genuine records, as if it had never come."""
    core = _core(tmp_path, episodes=8)
    ref = _core(tmp_path / "ref", episodes=8)
    one_row = {**_step(3)[1], "session": "ffffffffffffffff", "seq": 0}
    one_row = {**one_row, **{k: one_row[k][:1] for k in ("k", "a", "r", "k2", "mask2")}}
    reasons = []
    for bad in (
        one_row,  # one row for a later step of the current batch of 2: np.stack would meet rows of 2 and 1
        {**_step(1)[0], "session": "eeeeeeeeeeeeeeee", "episode": 1},  # begins no batch
        {**_step(H + 2)[0], "session": "dddddddddddddddd", "r": [1e6, 1e6], "episode": 6},  # 3 horizons ahead
    ):
        eff = _feed(core, [bad])
        reasons += [r[:2] for r in eff.rejects] + eff.drops
    assert reasons == [("transitions", "length"), ("transitions", "episode"), ("transitions", "future")]
    first = _step(0)
    _feed(core, first[:2])
    eff = _feed(core, [{**first[1], "session": "cccccccccccccccc", "r": [1e6, 1e6]}])  # the step again, another session
    assert eff.drops == [("transitions", "duplicate_step")]
    for c in (core, ref):
        _feed(c, [r for r in _steps(0, H + 4) if c is ref or r not in first[:2]])
    assert core.trained == ref.trained == H + 4
    assert _weights(core) == _weights(ref)
    assert core.store is not None and ref.store is not None and core.store.count == ref.store.count


def test_step_records_of_another_batch_size_or_far_ahead_are_rejected(tmp_path: Path) -> None:
    core = _core(tmp_path, episodes=8)
    eff = core.on_step({"episode": 2, "size": 1, "step": 1, "phase": "step", "acted": [0]}, 1.0)
    assert [r[:2] for r in eff.rejects] == [("step", "length")]
    eff = core.on_step({"episode": 6, "size": 2, "step": 1, "phase": "step", "acted": [0]}, 1.0)
    assert [r[:2] for r in eff.rejects] == [("step", "future")]  # step 90: three horizons ahead of step 0
    assert core.rounds == {}


def test_future_episode_metrics_are_rejected_and_the_genuine_logged(tmp_path: Path) -> None:
    """Metrics of an episode two batches beyond what the run has reached are rejected (`future`), so they cannot
    make the genuine episodes look past."""
    core = _core(tmp_path, mode="evaluate", episodes=0)
    m = {"run": "r1", "completion": 30, "failed": True, "absent": [0] * N}
    eff = core.on_metrics({**m, "episode": 1003})
    assert [r[:2] for r in eff.rejects] == [("episode_metrics", "future")]
    core.on_step({"episode": 2, "size": 2, "step": 0, "phase": "begin", "acted": []}, 1.0)
    for e in (0, 1, 2, 3):
        assert core.on_metrics({**m, "episode": e}).drops == [], e
    assert core.logged_upto == 3
    assert [r[:2] for r in core.on_metrics({**m, "episode": 8}).rejects] == [("episode_metrics", "future")]
    eff = core.on_step({"episode": 1000, "size": 2, "step": 0, "phase": "begin", "acted": []}, 1.0)
    assert [r[:2] for r in eff.rejects] == [("step", "future")]


EXPERT = {
    "learner": "expert",
    "episodes": 4,
    "rounds": 2,
    "envs": 2,
    "policy_updates": 2,
    "value_updates": 2,
    "validate_episodes": 8,
}
"""Two rounds of one batch of 2 episodes: the auction plays the first."""


def _truth(core: TrainerCore, b: int, batch: int = 2) -> None:
    """The world's true levels of every step of batch b (nothing finishes: every task stays at its start level)."""
    for t in range(1, H + 1):
        levels = [list(SC.initial_levels)] * batch
        core.on_ground_truth(
            {"run": "r1", "episode": b * batch, "step": t, "levels": levels, "actions": [], "events": []}
        )


def test_the_expert_learner_learns_a_round_in_the_worker_while_the_world_waits(tmp_path: Path) -> None:
    """A round's last step is announced only once its learning is done (a heartbeat meanwhile says the trainer
    lives); then new weights on the round's cadence; after the last round the trainer says it finished."""
    import time

    core = TrainerCore(tmp_path / "t", SCHED, EXPERT, "test")
    eff = core.on_scenario(_scenario(batch=2), 0.0)
    assert eff.fatal is None and [w["every"] for w in eff.weights] == [H] * N  # a round: 1 batch of H steps
    assert eff.progress == [{"run": "r1", "trained": 0, "updates": 0, "finished": False}]
    eff = _feed(core, _steps(0, H - 1))
    assert [p["trained"] for p in eff.progress] == list(range(1, H))  # every step announced as it comes
    eff = _feed(core, _steps(H - 1, H))  # the round's last step: held
    assert [p["trained"] for p in eff.progress] == [H - 1] and core.held and not eff.weights
    _truth(core, 0)
    deadline = time.monotonic() + 120
    got = TrainerEffects()
    while not got.weights:
        assert time.monotonic() < deadline, "the first round's learning did not end within 120 s"
        _merge(got, core.tick(time.monotonic()))
        time.sleep(0.05)
    assert got.fatal is None and [w["trained"] for w in got.weights] == [H] * N
    assert got.progress[-1] == {"run": "r1", "trained": H, "updates": 2, "finished": False}
    assert all(p["trained"] == H - 1 for p in got.progress[:-1])  # the heartbeats
    assert any("expert: round 1: validation completion" in text for _, text in got.log)
    _feed(core, _steps(H, 2 * H))
    _truth(core, 1)
    got = TrainerEffects()
    while not got.progress or not got.progress[-1]["finished"]:
        assert time.monotonic() < deadline, "the second round's learning did not end"
        _merge(got, core.tick(time.monotonic()))
        time.sleep(0.05)
    assert got.progress[-1]["trained"] == 2 * H and core.finished
    core.shutdown()
    rounds = json.loads((tmp_path / "t" / "checkpoint" / "meta.json").read_text())["info"]["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2] and (tmp_path / "t" / "rounds.csv").exists()
    again = TrainerCore(tmp_path / "t", SCHED, EXPERT, "test")  # a restarted trainer does not resume the rounds
    eff = again.on_scenario(_scenario(batch=2), 0.0)
    assert eff.fatal is not None and "does not resume" in eff.fatal
