"""Attacks on a training run, through `htlm launch train` (the entry point users run: world, five agents and the
trainer over real DDS, with a team key), by a stranger on the team's ROS domain with its own rclpy node:

- every signed transition record of an earlier training run (same key, same settings and seed, a run directory of
  the same name), recorded from /htlm/transitions as any participant of its domain could, replayed into the later run
  while it trains;
- one well-formed transition signed with the key, of the current run, holding one row for a later step of the batch
  in progress (a batch of 4 rows);
- well-formed episode metrics of the run's last batch, sent while the run is in its first batches.

Training over ROS is deterministic (tests/ros/test_training_equivalence.py), so the earlier run is the control: the
attacked run must end with exit code 0 and exactly its Q-networks (the checkpoints compared bit for bit) and its
training log, and the trainer's /diagnostics must count each attack under its reason: other_run, length, future.

Slow: two training runs of 32 episodes."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.transition_store import read_store
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.signing import Signer
from htlm_world.scenario import builtin
from support.ros import Launcher, alive_with, read_json

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(400)]

KEY = "a-team-key-only-the-team-knows-0123"
EPISODES, BATCH, HORIZON = 32, 4, 30
TRAIN = (
    *("train", "--episodes", str(EPISODES), "--eval-episodes", "0", "--seed", "5"),
    *("--set", f"envs={BATCH}", "--set", "learning_starts=60", "--set", "batch_size=32", "--set", "memory=5000"),
    *("--trainer-param", "diagnostics_period=0.2"),
)
FUTURE_METRICS = list(range(EPISODES - BATCH, EPISODES))
"""The episodes of the run's last batch: their forged metrics are sent while the run is in its first batches."""


@dataclass
class Run:
    team: Launcher
    transitions: list[str]
    """Every transition record heard on /htlm/transitions (the team's agents' and the stranger's)."""
    diag: dict[str, str]
    """The trainer's last /diagnostics values."""
    sent: dict[str, Any]


def _launch(where: Path, key: Path, attack: bool) -> Run:
    team = Launcher(where, *TRAIN, "--key-file", str(key))
    try:
        rec = where / "transitions.json"
        recorder = team.helper("record", "--out", str(rec), "--topic", "transitions")
        diag = where / "diag.json"
        team.helper("diag", "--out", str(diag))
        sent: dict[str, Any] = {}
        if attack:
            sent = _attack(team, rec, where)
        try:
            code = team.popen.wait(timeout=240)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the training run did not end within 240 s; the launcher said:\n{team.said()[-3000:]}")
        assert code == 0, f"the training run exited with {code}:\n{team.said()[-3000:]}"
        summary = json.loads(team.summary.read_text())
        assert summary["exit_code"] == 0 and summary["episodes"] == EPISODES, summary
        assert alive_with(str(team.run)) == [], "orphaned processes"
        assert "restarting it" not in team.said(), f"a process of the team died:\n{team.said()[-3000:]}"
        recorder.send_signal(signal.SIGTERM)
        recorder.wait(timeout=10)
        team.helpers[1].send_signal(signal.SIGTERM)
        team.helpers[1].wait(timeout=10)
        status = {k.removeprefix("htlm: "): v for k, v in read_json(diag).items()}
        return Run(team, read_json(rec), status.get("trainer", {}), sent)
    finally:
        team.stop()


def _episodes(team: Launcher) -> int:
    return len(team.jsonl("world"))


def _attack(team: Launcher, rec: Path, where: Path) -> dict[str, Any]:
    """While the run is in its first batches: replay the earlier run's transitions, send one one-row transition of a
    later step of the batch in progress, and the metrics of the last batch."""
    signer = Signer(KEY.encode())
    run = team.run_id()
    signer.run = run
    earlier = json.loads((where.parent / "earlier" / "transitions.json").read_text())
    # senders up and matched with the trainer before the run is far enough
    out = {n: where / f"{n}-sent.json" for n in ("replay", "one_row", "metrics")}
    go = where / "go"
    src = {n: where / f"{n}.json" for n in out}
    topic = {"replay": topics.TRANSITIONS, "one_row": topics.TRANSITIONS, "metrics": topics.EPISODE_METRICS}
    readers = {topics.TRANSITIONS: 2, topics.EPISODE_METRICS: 1}  # the trainer; on transitions also the recorder
    for n in out:
        team.helper(
            "send", "--out", str(out[n]), "--topics", topic[n], "--source", str(src[n]), "--go", str(go),
            "--subscribers", str(readers[topic[n]]),
        )  # fmt: skip
    for n in out:
        team.wait_for(lambda n=n: Path(str(out[n]) + ".ready").exists(), 60, f"the {n} sender matched")
    src["replay"].write_text(json.dumps({topics.TRANSITIONS: earlier}))
    # the batch in progress: the team's own transition records of it, then one of them cut to one row, for its last
    # step (a later step than any the batch reached), signed with the key
    team.wait_for(lambda: _episodes(team) >= BATCH, 120, "the first batch logged")

    sc = builtin()
    lim = S.limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, BATCH, sc.knowledge_size)

    def latest() -> dict[str, Any] | None:
        got = read_json(rec) if rec.exists() else []
        now = _episodes(team) // BATCH * BATCH  # the first episode of the batch the world has not logged yet
        for text in reversed(got):
            r = S.decode(text, S.TRANSITION, lim, signer)
            if r["episode"] == now and r["step"] < HORIZON - 2:
                return r
        return None

    genuine = team.wait_for(latest, 60, "an agent's transition of the batch in progress, before its last steps")
    one = dict(genuine)
    for k in ("k", "a", "r", "k2", "mask2"):
        one[k] = np.asarray(genuine[k])[:1]
    one["r"] = np.full(1, 1e6)
    one.update(step=HORIZON, seq=genuine["seq"] + 1000)
    src["one_row"].write_text(json.dumps({topics.TRANSITIONS: [S.encode(S.TRANSITION, one, signer)]}))
    metrics = {
        "run": run, "severity": "simulated", "completion": 3, "failed": False, "unused_capability": 0.0,
        "unused_fraction": 0.0, "idle_before": 0, "reassign_before": 0, "absent": [0] * 5, "seconds": 1.0,
    }  # fmt: skip
    texts = [S.encode(S.EPISODE_METRICS, {**metrics, "episode": e}, signer) for e in FUTURE_METRICS]
    src["metrics"].write_text(json.dumps({topics.EPISODE_METRICS: texts}))
    at = _episodes(team)
    go.touch()
    sent = {}
    for n in out:
        team.wait_for(lambda n=n: out[n].exists(), 120, f"the {n} sender to finish")
        got = read_json(out[n])
        assert got["acked"] == {topic[n]: True} and got["matched"][topic[n]] >= readers[topic[n]], f"{n}: {got}"
        sent[n] = got["sent"][topic[n]]
    sent["one_row_of"] = (genuine["episode"], genuine["step"], len(genuine["a"]))
    sent["at_episode"] = at
    return sent


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Run, Run]]:
    base = tmp_path_factory.mktemp("training")
    key = base / "team.key"
    key.write_text(KEY + "\n")
    key.chmod(0o600)
    earlier = _launch(base / "earlier", key, attack=False)
    later = _launch(base / "later", key, attack=True)
    yield earlier, later


def _log(team: Launcher) -> list[dict[str, Any]]:
    return team.jsonl("trainer/train_log")


def test_replayed_transitions_of_an_earlier_run_are_rejected_and_change_no_network(runs: tuple[Run, Run]) -> None:
    earlier, later = runs
    # the recorder joined the earlier run while it started: it heard nearly all of its EPISODES / BATCH * HORIZON * 5
    assert later.sent["replay"] == len(earlier.transitions) >= 1000, later.sent
    assert int(later.diag.get("rejected/transitions/other_run", 0)) == later.sent["replay"], later.diag
    a = load_checkpoint(earlier.team.run / "trainer" / "checkpoint")
    b = load_checkpoint(later.team.run / "trainer" / "checkpoint")
    assert a.episodes_done == b.episodes_done == EPISODES
    for i, (x, y) in enumerate(zip(a.weights, b.weights, strict=True)):
        for j, (u, v) in enumerate(zip(x, y, strict=True)):
            assert np.asarray(u).tobytes() == np.asarray(v).tobytes(), f"agent {i} tensor {j} differs"
    print(
        f"{later.sent['replay']} transitions of the earlier run replayed from episode {later.sent['at_episode']} on: "
        f"rejected as other_run {later.diag.get('rejected/transitions/other_run')}; networks equal bit for bit"
    )


def test_a_one_row_transition_of_a_later_step_is_rejected_and_training_finishes(runs: tuple[Run, Run]) -> None:
    later = runs[1]
    assert later.sent["one_row"] == 1
    episode, step, rows = later.sent["one_row_of"]
    assert episode >= later.sent["at_episode"] - BATCH and step < HORIZON and rows == BATCH, later.sent
    assert int(later.diag.get("rejected/transitions/length", 0)) == 1, later.diag
    # the run exited 0 with every episode (_launch) and stored exactly the rows of the unattacked run, none forged
    store = {r.team.run.parent.name: read_store(r.team.run / "trainer" / "transitions.bin") for r in runs}
    assert len(store["later"]) == len(store["earlier"]) == EPISODES * HORIZON * 5, {k: len(v) for k, v in store.items()}
    assert not (store["later"]["r"] == 1e6).any(), "the forged row was stored"
    print(f"one row for step {HORIZON} of the batch (episode, step, rows) {later.sent['one_row_of']}: length counted")


def test_future_episode_metrics_are_rejected_and_the_genuine_episodes_logged(runs: tuple[Run, Run]) -> None:
    earlier, later = runs
    assert later.sent["metrics"] == len(FUTURE_METRICS)
    assert int(later.diag.get("rejected/episode_metrics/future", 0)) == len(FUTURE_METRICS), later.diag
    logged = [x for x in _log(later.team) if "episode" in x]
    assert [x["episode"] for x in logged] == list(range(EPISODES)), "every genuine episode logged once, in order"

    def same(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """The training log's episode lines and its loss lines (at the end of every batch), but what depends on
        timing: the run id, durations, the updates done when an episode's metrics came, and the two kinds'
        interleaving."""
        timed = ("seconds", "run", "updates")
        episodes = [{k: v for k, v in x.items() if k not in timed} for x in rows if "episode" in x]
        return episodes, [x for x in rows if "episode" not in x]

    assert same(_log(later.team)) == same(_log(earlier.team)), "the training log equals the unattacked run's"
    for run in runs:  # the trainer reads the metrics while it trains, not once the run is over
        first = next(x for x in _log(run.team) if "episode" in x)
        last_updates = max(x["updates"] for x in _log(run.team))
        assert first["updates"] < last_updates, f"episode 0's metrics were logged only at the end: {first}"
    print(f"metrics of episodes {FUTURE_METRICS} sent at episode {later.sent['at_episode']}: future counted")
