"""Run control over real processes and real DDS (docs/ros.md, Run control):

- forged and replayed run announcements: without a team key, a `stopped` record of another run and a record of
  another run and seed published mid-run stop and switch nobody (the run ends with all its episodes and the
  trajectories of the in-process run; the agents and the trainer count them as other_run), and every node says at
  start that it runs unsigned; with a key, a signed announcement captured from an earlier run and an older signed
  announcement of the same run are rejected (other_run, replay) and change nothing;
- the trainer stores nothing in an evaluate run (the transitions agents send anyway are dropped as not_training) and
  logs each episode of a training run once and in order, also when a stranger replays metrics of an earlier episode
  and of another run;
- no transition is lost when the trainer is away at the end of a training run: the world holds the end until the
  restarted trainer has every step, then stops the run;
- a world SIGKILLed mid-run is reported silent by the agents and the trainer, and a restarted world continues the
  run at its next unlogged episode: every episode is logged exactly once and the agents rejoin;
- under the free clock a dead agent costs its teammates no step, and `htlm launch` exits 0 when an agent process
  died and a restarted one rejoined.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.learning.transition_store import read_store
from htlm_world.scenario import builtin
from support.ros import assert_same_as_in_process, next_domain, read_json

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

SEED, B = 8, 4
AGENTS = [f"agent{i}" for i in range(1, 6)]
DIAG = {"diagnostics_period": 0.2}
"""Every node reports its counters five times a second: a short run's last counts reach the listener."""


def _stop(p: subprocess.Popen[bytes]) -> None:
    p.send_signal(signal.SIGTERM)
    p.wait(timeout=10)


def _status(diag: Path) -> dict[str, dict[str, Any]]:
    """The latest /diagnostics status of every node, by node name (world, trainer, agent1, ...)."""
    return {k.split(": ", 1)[1]: v for k, v in read_json(diag).items() if k.startswith("htlm: ")}


def _count(st: dict[str, Any], key: str) -> int:
    return int(st.get(key, 0))


def _publisher(
    team: Any,
    name: str,
    source: Path,
    index: int,
    go: Path,
    fields: dict[str, Any] | None = None,
    topic: str = "scenario",
    readers: int = 7,
) -> Any:
    """A helper that publishes record `index` of `source` (read when `go` exists) on a topic: replayed as it was, or
    with `fields` changed (unsigned). It first waits for `readers` readers (scenario: five agents, the trainer and
    a recorder). Its report is TMP/`name`.json."""
    args = ["publish", "--topic", topic, "--source", str(source), "--index", str(index), "--go", str(go)]
    if fields is not None:
        args += ["--set", json.dumps(fields)]
    return team.helper(*args, "--subscribers", str(readers), "--linger", "0.2", "--out", str(team.tmp / f"{name}.json"))


def _published(team: Any, name: str, readers: int) -> dict[str, Any]:
    """The report of publisher `name` once it has published (it matched every reader first)."""
    out = str(team.tmp / f"{name}.json")
    p = next(h for h in team.helpers if out in h.args)
    assert p.wait(timeout=40) == 0, f"publisher {name} failed"
    rep: dict[str, Any] = read_json(Path(out))
    assert rep["matched"] >= readers, f"publisher {name} matched {rep['matched']} readers of {readers}"
    return rep


def _ended_ok(team: Any, world_timeout: float = 90.0) -> None:
    assert team.wait("world", world_timeout) == 0
    codes = team.wait_all(40)
    assert codes == dict.fromkeys(codes, 0), codes


OPEN = 100_000
"""Episodes of a run the test ends itself (`_end_after`) once what it tests has happened during it."""


def _end_after(team: Any, episodes: int) -> int:
    """Give the running world its end (its `episodes` parameter, tunable while running: the run ends after that
    many, or after the batch in progress when it is past them), wait for every process to exit 0 and return the
    episodes the world logged."""
    out = team.tmp / "setparam.json"
    setp = team.helper("setparam", "--out", str(out), "--name", "episodes", "--value", str(episodes))
    assert setp.wait(timeout=30) == 0 and read_json(out)["successful"], f"the world took no end: {read_json(out)}"
    _ended_ok(team)
    return len(team.world_episodes())


def _short(team: Any, horizon: int) -> None:
    """Run the built-in scenario with a shorter horizon (the world reads it from a file)."""
    f = team.tmp / f"h{horizon}.yaml"
    f.write_text(f"horizon: {horizon}\n")
    team.cfg.scenario, team.cfg.scenario_file = builtin().replace(horizon=horizon), str(f)


# ----- 1. forgery and replay of run control -----------------------------------------------------------------------
def test_unsigned_announcements_of_another_run_stop_and_switch_nobody(ros_team: Any) -> None:
    # open-ended: the forgeries come while the run goes on, however slow the machine makes the test's helpers
    team = ros_team(seed=SEED, episodes=OPEN, batch=B, world_params=DIAG, agent_params=DIAG, trainer_params=DIAG)
    diag, rec, go = team.tmp / "diag.json", team.tmp / "scenario.json", team.tmp / "go"
    team.helper("diag", "--out", str(diag))
    team.helper("record", "--topic", "scenario", "--out", str(rec))
    other = f"{team.run_dir.name}-other"
    forged = {  # the run's own announcement with another run id: a stop, and a switch to another seed
        "stop": {"run": other, "state": "stopped", "seq": 1000},
        "switch": {"run": other, "seed": SEED + 1, "state": "running", "seq": 1001, "nonce": "f" * 16},
    }
    for what, fields in forged.items():
        _publisher(team, what, rec, 0, go, fields)
    time.sleep(1.5)  # the strangers are up before the team starts
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 60, "the first batch")
    team.wait_for(
        lambda: len(read_json(rec)) >= 1, 30, "the run's announcement at the recorder (the publishers' source)"
    )
    go.touch()
    for what in forged:
        _published(team, what, 7)
    at = len(team.world_episodes())
    episodes = _end_after(team, at + 2 * B)
    time.sleep(0.5)
    _stop(team.helpers[0])
    assert assert_same_as_in_process(team, SEED, "greedy") == episodes
    status = _status(diag)
    other_run = {n: _count(status[n], "rejected/scenario/other_run") for n in [*AGENTS, "trainer"]}
    assert all(c >= 2 for c in other_run.values()), other_run
    # without a key every node says so at start
    unsigned = {n: "unsigned: no team key" in team.log(n) for n in team.procs}
    assert all(unsigned.values()), unsigned
    print(
        f"forged stop and switch of run {other} after {at} of {episodes} episodes; rejected as other_run: {other_run}"
    )


@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_signed_announcements_of_an_earlier_run_and_older_ones_are_rejected(ros_team: Any) -> None:
    # run A: an earlier run with the same key; its signed announcements (running, stopped) are recorded
    # (several batches: the recorder, discovered late on a loaded machine, still gets "running" as the latest state)
    earlier = ros_team(seed=SEED + 1, episodes=4 * B, batch=B)
    key = earlier.tmp / "team.key"
    key.write_text("a-team-key-only-the-team-knows-0123\n")
    key.chmod(0o600)
    earlier.cfg.key_file = team_key = str(key)
    rec_a = earlier.tmp / "scenario-a.json"
    earlier.helper("record", "--topic", "scenario", "--out", str(rec_a))
    time.sleep(1.0)
    earlier.start()
    _ended_ok(earlier, 60)
    earlier.wait_for(lambda: len(read_json(rec_a)) >= 2, 10, "run A's running and stopped announcements")
    _stop(earlier.helpers[0])
    recorded = [json.loads(t) for t in read_json(rec_a)]
    assert [r["state"] for r in recorded] == ["running", "stopped"] and all("sig" in r for r in recorded), recorded
    earlier_run = recorded[0]["run"]
    # run B: another run id (every launch into a new run directory gets a fresh one), the same key; its world is
    # killed and restarted mid-run, so the run announces twice; then A's two records and B's first are replayed
    # open-ended: the replays must come while the run goes on, however slow the machine makes the test's helpers;
    # the run is given its end once they are published
    team = ros_team(seed=SEED, episodes=OPEN, batch=B, world_params=DIAG, agent_params=DIAG, trainer_params=DIAG)
    team.cfg.key_file = team_key
    assert team.run_dir.name != earlier.run_dir.name
    diag, rec_b, go = team.tmp / "diag-b.json", team.tmp / "scenario-b.json", team.tmp / "go-b"
    team.helper("diag", "--out", str(diag))
    team.helper("record", "--topic", "scenario", "--out", str(rec_b))
    _publisher(team, "a-running", rec_a, 0, go)
    _publisher(team, "a-stopped", rec_a, 1, go)
    _publisher(team, "b-first", rec_b, 0, go)
    time.sleep(1.5)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 60, "the first batch")
    team.wait_for(lambda: len(read_json(rec_b)) >= 1, 30, "the run's first announcement")
    # killed as soon as the batch is in world.jsonl: maybe before its progress is saved (the restart must not log
    # the batch again)
    team.kill("world", signal.SIGKILL)
    team.start("world")
    # (DDS may hand the recorder an announcement twice: records are told apart by their nonce)
    nonces = lambda: {json.loads(t)["nonce"] for t in read_json(rec_b)}  # noqa: E731
    team.wait_for(lambda: len(nonces()) >= 2, 30, "the restarted world's announcement")
    recs = [json.loads(t) for t in read_json(rec_b)]
    first, again = recs[0], next(r for r in recs if r["nonce"] != recs[0]["nonce"])
    assert first["run"] == again["run"] != earlier_run and first["run"].startswith(team.run_dir.name + "-"), (
        first,
        again,
    )
    assert again["seq"] > first["seq"], (first["seq"], again["seq"])
    time.sleep(1.0)  # every agent took the restarted world's announcement
    keys = ("rejected/scenario/other_run", "rejected/scenario/replay")
    before = {n: tuple(_count(_status(diag).get(n, {}), k) for k in keys) for n in [*AGENTS, "trainer"]}
    go.touch()
    for name in ("a-running", "a-stopped", "b-first"):
        _published(team, name, 7)
    at = len(team.world_episodes())
    episodes = _end_after(team, at + 2 * B)
    time.sleep(0.5)
    _stop(team.helpers[0])
    eps = sorted(w["metrics"]["episode"] for w in team.world_episodes())
    assert eps == list(range(episodes)), eps
    assert assert_same_as_in_process(team, SEED, "greedy") == episodes
    status = _status(diag)
    counts = {n: tuple(_count(status[n], k) - b for k, b in zip(keys, before[n], strict=True)) for n in before}
    assert all(o >= 2 and r >= 1 for o, r in counts.values()), (counts, before)
    assert all(st.get("signed") == "true" for n, st in status.items() if n in counts), status
    assert not any("unsigned:" in team.log(n) for n in team.procs)
    print(
        f"replayed run {earlier.run_dir.name}'s 2 signed records and {team.run_dir.name}'s first (seq {first['seq']}, "
        f"after seq {again['seq']}) at episode {at} of {episodes}; (other_run, replay) counted: {counts}, before: "
        f"{before}"
    )


# ----- 2. what the trainer stores and logs ----------------------------------------------------------------------------
@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_the_trainer_stores_nothing_in_an_evaluate_run(ros_team: Any) -> None:
    episodes = 2 * B
    team = ros_team(
        seed=SEED,
        episodes=episodes,
        batch=B,
        world_params=DIAG,
        trainer_params=DIAG,
        agent_params={**DIAG, "transitions": "on", "stop_timeout": 1.0},  # agents send transitions anyway
    )
    diag = team.tmp / "diag.json"
    team.helper("diag", "--out", str(diag))
    team.start()
    _ended_ok(team, 60)
    time.sleep(0.5)
    _stop(team.helpers[0])
    store = team.run_dir / "trainer" / "transitions.bin"
    rows = len(read_store(store)) if store.exists() else 0
    assert rows == 0, f"{rows} rows stored in an evaluate run"
    trainer = _status(diag)["trainer"]
    dropped = _count(trainer, "dropped/transitions/not_training")
    assert dropped > 0, trainer
    print(f"store exists: {store.exists()}, rows {rows}; dropped/transitions/not_training {dropped}")


LEARNER = {"envs": B, "learning_starts": 60, "batch_size": 32, "memory": 20000}


@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_the_training_log_holds_each_episode_once_in_order_despite_replayed_metrics(ros_team: Any) -> None:
    episodes = 8 * B
    team = ros_team(
        mode="train",
        policy="auto",
        seed=SEED,
        episodes=episodes,
        batch=B,
        learner=LEARNER,
        world_params=DIAG,
        agent_params=DIAG,
        trainer_params=DIAG,
        grace=40.0,
    )
    diag, rec, go = team.tmp / "diag.json", team.tmp / "metrics.json", team.tmp / "go"
    team.helper("diag", "--out", str(diag))
    team.helper("record", "--topic", "episode_metrics", "--out", str(rec))
    # the trainer and the recorder read episode_metrics: an earlier episode's record replayed, and the record of
    # another run whose episode is the run's last (taken, it would make the trainer drop every real one after it)
    _publisher(team, "replay", rec, 0, go, topic="episode_metrics", readers=2)
    other = {"run": f"{team.run_dir.name}-other", "episode": episodes - 1}
    _publisher(team, "other", rec, 0, go, other, topic="episode_metrics", readers=2)
    time.sleep(1.5)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 90, "the first training batch")
    team.wait_for(lambda: len(read_json(rec)) >= 1, 30, "an episode_metrics record at the recorder (the source)")
    go.touch()
    for name in ("replay", "other"):
        _published(team, name, 2)
    at = len(team.world_episodes())
    assert at < episodes, "the records came after the run"
    _ended_ok(team, 120)
    time.sleep(0.5)
    _stop(team.helpers[0])
    lines = [json.loads(x) for x in (team.run_dir / "trainer" / "train_log.jsonl").read_text().splitlines()]
    logged = [x["episode"] for x in lines if "severity" in x]
    assert logged == list(range(episodes)), logged
    trainer = _status(diag)["trainer"]
    past = _count(trainer, "dropped/episode_metrics/past")
    # another run's record is refused by the run binding of the wire contract (rejected), or by the core (dropped)
    other_run = sum(_count(trainer, f"{k}/episode_metrics/other_run") for k in ("rejected", "dropped"))
    assert past >= 1 and other_run >= 1, trainer
    print(f"replayed episode 0 and forged another run's episode {episodes - 1} after {at} episodes; logged {logged}")
    print(f"trainer dropped episode_metrics: past {past}, other_run {other_run}")


# ----- 3. the trainer away at the end of a training run ---------------------------------------------------------------
@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_no_transition_is_lost_when_the_trainer_is_away_at_the_end(ros_team: Any) -> None:
    episodes = 5 * B
    team = ros_team(
        mode="train",
        policy="auto",
        seed=4,
        episodes=episodes,
        batch=B,
        learner=LEARNER,
        trainer_params={"checkpoint_every": B, **DIAG},
        # the world goes on 3 s after the trainer went silent; agents act with the newest weights they have
        world_params={"trainer_deadline": 3.0, **DIAG},
        agent_params={"weights_timeout": 0.2, "stop_timeout": 20.0, "resend_period": 0.5, **DIAG},
        grace=40.0,
    )
    _short(team, 10)
    diag, rec = team.tmp / "diag.json", team.tmp / "scenario.json"
    team.helper("diag", "--out", str(diag))
    team.helper("record", "--topic", "scenario", "--out", str(rec))
    team.start()
    store = team.run_dir / "trainer" / "transitions.bin"
    team.wait_for(lambda: len(team.world_episodes()) >= B, 90, "the first batch")
    team.wait_for(lambda: (team.run_dir / "trainer" / "checkpoint" / "meta.json").exists(), 30, "a checkpoint")
    team.kill("trainer", signal.SIGKILL)
    killed_at = len(team.world_episodes())
    # the world plays the rest without the trainer, then holds the end of the run for the trainer's updates
    holding = "waiting for the trainer's updates"
    team.wait_for(lambda: holding in _status(diag).get("world", {}).get("message", ""), 90, "the world to hold")
    assert len(team.world_episodes()) == episodes, "the world holds only after the run's last step"
    assert killed_at < episodes
    assert [json.loads(t)["state"] for t in read_json(rec)] == ["running"], "stopped before the trainer came back"
    assert team.procs["world"].popen.poll() is None
    world_said = _status(diag)["world"]["message"]
    team.start("trainer")
    _ended_ok(team, 120)
    time.sleep(0.5)
    _stop(team.helpers[0])
    assert [json.loads(t)["state"] for t in read_json(rec)] == ["running", "stopped"]
    assert "end_hold" not in team.log("world"), "the world stopped the run at the end of its hold"
    after = read_store(store)
    keys = {(int(r["agent"]), bytes(r["session"]), int(r["seq"]), int(r["row"])) for r in after}
    assert len(keys) == len(after), "a transition stored twice"
    h = team.cfg.scenario.horizon
    counts = {}
    for i in range(5):
        played = sum(1 for e in team.world_episodes() if e["metrics"]["absent"][i] == 0) * h
        mine = after[after["agent"] == i]
        seqs = sorted(set(mine["seq"].tolist()))
        assert len(mine) == played, f"agent {i}: {len(mine)} rows stored of {played}"
        assert seqs == list(range(played // B)), f"agent {i}: records missing"
        counts[AGENTS[i]] = (len(seqs), len(mine))
    print(f"trainer killed after {killed_at} episodes; world said {world_said!r}; (records, rows) stored {counts}")


# ----- 4. the world restarted mid-run ---------------------------------------------------------------------------------
@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_a_restarted_world_continues_its_run_and_agents_rejoin(ros_team: Any) -> None:
    episodes = 12 * B
    team = ros_team(seed=SEED, episodes=episodes, batch=B, world_params=DIAG, agent_params=DIAG, trainer_params=DIAG)
    diag = team.tmp / "diag.json"
    team.helper("diag", "--out", str(diag))
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 60, "the first batch")
    time.sleep(0.3)  # inside a later batch
    team.kill("world", signal.SIGKILL)
    killed_at = len(team.world_episodes())
    assert killed_at < episodes

    def silent() -> bool:
        st = _status(diag)
        return all(
            st.get(n, {}).get("level") == 1 and "the world is silent" in st[n]["message"] for n in [*AGENTS, "trainer"]
        )

    team.wait_for(silent, 5.0 + 3.0, "every agent and the trainer to report the world silent")  # world_timeout 5 s
    said = {n: (_status(diag)[n]["message"], _status(diag)[n]["world_silent_s"]) for n in [*AGENTS, "trainer"]}
    team.start("world")
    _ended_ok(team, 90)
    time.sleep(0.5)
    _stop(team.helpers[0])
    log = team.log("world")
    assert f"continuing at episode {killed_at}" in log, log[-3000:]
    eps = [w["metrics"]["episode"] for w in team.world_episodes()]
    assert sorted(eps) == list(range(episodes)) and len(eps) == len(set(eps)), eps
    later = [w["metrics"]["absent"] for w in team.world_episodes() if w["metrics"]["episode"] >= killed_at + B]
    assert later and all(sum(a) == 0 for a in later), later
    assert assert_same_as_in_process(team, SEED, "greedy") == episodes
    st = _status(diag)
    assert all(st[n]["level"] == 0 for n in AGENTS), {n: st[n]["message"] for n in AGENTS}
    print(f"world killed after {killed_at} episodes; silent reports {said}; continued at episode {killed_at}")


# ----- 5. agents lost under the free clock; the launcher's exit code --------------------------------------------------
@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_under_the_free_clock_a_dead_agent_costs_its_teammates_no_step(ros_team: Any) -> None:
    episodes, batch = 8, 2
    team = ros_team(seed=SEED, episodes=episodes, batch=batch, world_params={"clock": "free", "period": 0.2})
    _short(team, 12)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= batch, 60, "the first batch")
    time.sleep(0.5)  # mid-batch
    team.kill("agent3", signal.SIGKILL)
    killed_at = len(team.world_episodes())
    assert team.wait("world", 90) == 0
    rest = {n: team.wait(n, 30) for n in team.procs if n not in ("world", "agent3")}
    assert rest == dict.fromkeys(rest, 0), rest
    absent = [w["metrics"]["absent"] for w in team.world_episodes()]
    assert len(absent) == episodes
    assert absent[-1][2] > 0, "agent3 was not absent after its kill"
    survivors = [a[:2] + a[3:] for a in absent]
    assert all(sum(a) == 0 for a in survivors), absent
    print(f"agent3 killed after {killed_at} episodes; absences per episode {absent}")


@pytest.mark.slow  # CI budget: the default run keeps the unsigned-forgery test; the rest with -m slow
def test_the_launcher_exits_0_when_a_restarted_agent_rejoined(tmp_path: Path) -> None:
    htlm = str(Path(sys.executable).parent / "htlm")
    run, domain = tmp_path / "launch", next_domain()
    common = ["evaluate", "--policy", "greedy", "--episodes", "64", "--batch", "4", "--seed", str(SEED)]
    common += ["--domain-id", str(domain), "--run-dir", str(run), "--quiet"]
    fast = ["--world-param", "act_deadline=2.0", "--world-param", "begin_deadline=2.0"]
    fast += ["--world-param", "update_deadline=2.0", "--agent-param", "broadcast_timeout=0.5"]

    def episodes() -> int:
        f = run / "world.jsonl"
        return len(f.read_text().splitlines()) if f.exists() else 0

    def wait_until(what: Any, timeout: float, why: str) -> None:
        end = time.monotonic() + timeout
        while not what():
            assert time.monotonic() < end, f"timed out waiting for {why}"
            time.sleep(0.1)

    out = open(tmp_path / "team.out", "wb")  # noqa: SIM115
    team = subprocess.Popen([htlm, "launch", *common, *fast], stdout=out, stderr=subprocess.STDOUT)
    try:
        wait_until(lambda: episodes() >= 4, 90, "the first batch")
        found = subprocess.run(
            ["pgrep", "-f", str(run / "parameters" / "agent3.yaml")], capture_output=True, text=True, check=False
        )
        pids = [int(x) for x in found.stdout.split()]
        assert len(pids) == 1, found
        os.kill(pids[0], signal.SIGKILL)
        killed_at = episodes()
        code = team.wait(timeout=120)  # the launcher starts agent3 again itself
    finally:
        if team.poll() is None:
            team.send_signal(signal.SIGINT)
            try:
                team.wait(timeout=15)
            except subprocess.TimeoutExpired:
                team.kill()
                team.wait()
    said = (tmp_path / "team.out").read_text(errors="replace")
    lines = [json.loads(x) for x in (run / "world.jsonl").read_text().splitlines()]
    assert code == 0, said[-3000:]
    assert "agent3 exited with -9; restarting it" in said and "restarts: agent3 1" in said, said[-3000:]
    assert lines[-1]["metrics"]["absent"][2] == 0 and max(x["metrics"]["absent"][2] for x in lines) > 0
    print(f"agent3 killed after {killed_at} episodes; launcher exit code {code}")
