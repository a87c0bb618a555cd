"""Run control without ROS: a node follows the run it joined; announcements of other runs, and announcements of its
run that are not newer than the last it took (replays), are rejected; a restarted world's newer announcement of
the run is followed; a new run is joined only once the node's run has stopped."""

from __future__ import annotations

from typing import Any

from htlm_msgs_py.run_control import RunControl


def _rec(run: str, seq: int, state: str = "running", nonce: str = "a" * 16) -> dict[str, Any]:
    return {"run": run, "nonce": nonce, "seq": seq, "state": state}


def test_a_node_follows_the_run_it_joined_and_rejects_every_other() -> None:
    rc = RunControl()
    assert rc.take(_rec("r1", 0)) == "join" and rc.run == "r1"
    assert rc.take(_rec("r2", 9)) == "other_run", "a switch while our run goes on"
    assert rc.take(_rec("r2", 10, "stopped")) == "other_run", "a stop of another run"
    assert rc.take(_rec("r1", 0)) == "replay"
    assert rc.take(_rec("r1", 1)) == "update"
    assert rc.take(_rec("r1", 1, "stopped")) == "replay", "an old sequence number cannot stop us"
    assert rc.take(_rec("r1", 2, "stopped")) == "stop" and rc.stopped
    assert rc.take(_rec("r2", 0)) == "join" and rc.run == "r2", "after the stop, the next run"


def test_a_restarted_world_continues_the_run() -> None:
    rc = RunControl()
    rc.take(_rec("r1", 0))
    assert rc.take(_rec("r1", 5, nonce="b" * 16)) == "restart"
    assert rc.take(_rec("r1", 4, nonce="a" * 16)) == "replay", "the old world's announcement"
    rc.take(_rec("r1", 6, "stopped", nonce="b" * 16))
    assert rc.take(_rec("r1", 7, nonce="c" * 16)) == "restart" and not rc.stopped


def test_a_node_told_its_run_joins_only_that_one() -> None:
    rc = RunControl(wanted="mine")
    assert rc.take(_rec("other", 0)) == "other_run" and rc.run is None
    assert rc.take(_rec("mine", 3)) == "join"
    rc.take(_rec("mine", 4, "stopped"))
    assert rc.take(_rec("next", 0)) == "other_run", "told its run: it never joins another"


def _train_world(end_hold: float) -> Any:
    from htlm_world.protocol import LockstepSettings, world_protocol
    from htlm_world.scenario import builtin

    sc = builtin().replace(horizon=2)
    s = LockstepSettings(episodes=1, mode="train", pace=True, run_id="r", end_hold=end_hold)
    return world_protocol(sc, s)


def _play(proto: Any, trained_upto: int) -> list[tuple[str, dict[str, Any]]]:
    """Play the run's steps, the trainer reporting progress as it goes but never beyond `trained_upto`."""
    n = proto.scenario.n_agents
    out = proto.start(0.0).publish
    now = 0.0
    for t in (1, 2):
        now += 0.01
        out += proto.on_trainer(
            {"run": "r", "trained": min(t - 1, trained_upto), "updates": 0, "finished": False}, now
        ).publish
        for k in range(n):
            out += proto.on_action({"agent": k, "episode": 0, "step": t, "actions": [4]}, now).publish
    for k in range(n):
        out += proto.on_ready({"agent": k, "episode": 0, "step": 2}, now + 0.01).publish
    return out


def test_the_world_holds_the_end_of_a_training_run_until_the_trainer_has_every_step() -> None:
    proto = _train_world(end_hold=30.0)
    out = _play(proto, trained_upto=1)
    assert not any(k == "scenario" and f["state"] == "stopped" for k, f in out), "stopped before the last updates"
    assert proto.phase == "holding" and "waiting for the trainer" in proto.status()[1]
    assert proto.tick(10.0).publish == []
    eff = proto.on_trainer({"run": "r", "trained": 2, "updates": 4, "finished": False}, 11.0)
    assert [f["state"] for k, f in eff.publish if k == "scenario"] == ["stopped"]


def test_the_hold_is_bounded() -> None:
    proto = _train_world(end_hold=5.0)
    _play(proto, trained_upto=1)
    eff = proto.tick(6.0)
    assert [f["state"] for k, f in eff.publish if k == "scenario"] == ["stopped"]
    assert eff.counters["end_hold_timeouts"] == 1 and "end_hold" in eff.log[0][1]
