"""The core of `htlm watch` without ROS: records in, rendered text out; bad and unsigned records are counted, never
shown."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from htlm_agent.experiments.watch_view import WatchState, render, snapshot
from htlm_msgs_py import schema as S
from htlm_msgs_py.signing import Signer
from htlm_world.scenario import EventSpec, Scenario, builtin

SC = builtin()
KEY = b"0123456789abcdef-team-key"
OPTIONAL = {
    "period": 0.5,
    "operation": "simulated",
    "nonce": "00112233aabbccdd",
    "seq": 0,
    "run": "watch-test",
    "severity": "simulated",
    "arrived": "unknown",
    "distance": -1.0,
}
"""Values of fields some versions of the schemas have, used when a test does not name them."""


def encode(schema: S.Schema, fields: dict[str, Any], signer: Signer | None = None) -> str:
    """The record text of `fields`, completed with OPTIONAL for the fields of `schema` they leave out."""
    full = {**{k: v for k, v in OPTIONAL.items() if k in schema.fields}, **fields}
    return S.encode(schema, full, signer)


def scenario_record(run: str = "watch-test", batch: int = 2, signer: Signer | None = None, sc: Scenario = SC) -> str:
    return encode(
        S.SCENARIO,
        {
            "run": run,
            "seed": 7,
            "mode": "evaluate",
            "clock": "lockstep",
            "first_episode": 0,
            "episodes": 6,
            "batch": batch,
            "trainer_lag": 0,
            "epoch": 0.0,
            "state": "running",
            "layout": sc.layout_hash(),
            "scenario": sc.to_dict(),
        },
        signer,
    )


def metrics(episode: int, completion: int, failed: bool = False, absent: list[int] | None = None) -> str:
    return encode(
        S.EPISODE_METRICS,
        {
            "episode": episode,
            "completion": completion,
            "failed": failed,
            "unused_capability": 1.0,
            "unused_fraction": 0.5,
            "idle_before": 0,
            "reassign_before": 0,
            "absent": absent or [0] * SC.n_agents,
            "seconds": 0.1,
        },
    )


def belief(agent: int, episode: int, step: int, confident: list[int]) -> str:
    L = SC.levels
    marg = []
    for c in confident:
        row = [0.0] * L
        row[c] = 0.75
        row[(c + 1) % L] = 0.25
        marg += row
    return encode(
        S.BELIEF, {"agent": agent, "episode": episode, "step": step, "marginals": marg, "confident": confident}
    )


def fed_state(**kw: Any) -> WatchState:
    """A state of a run in batches of 2 at step 3 of episodes 2..3, with two finished episodes."""
    st = WatchState(**kw)
    st.on_scenario(scenario_record())
    st.on_step(encode(S.STEP, {"episode": 2, "size": 2, "step": 3, "phase": "step", "acted": [0, 1, 2, 4]}))
    st.on_ground_truth(
        encode(
            S.GROUND_TRUTH,
            {
                "episode": 2,
                "step": 3,
                "levels": [[4, 3, 2, 1], [0, 1, 2, 3]],
                "actions": [[0, 1, 2, 4, 5], [3] * 5],
                "events": [[], []],
            },
        )
    )
    st.on_belief("agent1", belief(0, 2, 3, [4, 3, 2, 0]))
    st.on_metrics(metrics(0, 8))
    st.on_metrics(metrics(1, 11, failed=True, absent=[0, 0, 0, 2, 0]))
    st.on_diagnostics(
        [
            ("htlm: world", 1, "act episode 2 step 3: agents [3] absent", {"rejected": "0", "dropped": "4"}),
            ("htlm: agent2", 0, "running", {"rejected": "3", "rejected/broadcast/range": "3"}),
        ],
        now=100.0,
    )
    return st


def text(st: WatchState, now: float = 101.0) -> str:
    return snapshot(st, now, width=160)


def test_the_view_shows_run_episode_truth_assignments_beliefs_and_statistics() -> None:
    out = text(fed_state())
    assert "run watch-test" in out and "mode evaluate" in out and "batch 2" in out
    assert "episode 2" in out and "step 3/30" in out
    assert "episode 2  step 3/30  phase step  (index 0 of the batch 2..3: --episode-in-batch)" in out
    lines = out.splitlines()
    fire1 = next(ln for ln in lines if ln.strip().startswith("fire@site1"))
    assert "4 ####" in fire1  # true level 4 of episode 2 (row 0 of the batch)
    assert "4 (0.75)" in fire1  # agent1's confident level and its probability
    agent1 = next(ln for ln in lines if ln.strip().startswith("agent1 "))
    assert "fire@site1" in agent1 and "acting" in agent1
    agent4 = next(ln for ln in lines if ln.strip().startswith("agent4 "))
    assert "absent" in agent4 and "idle@site1" in agent4  # not in `acted` of the last step
    assert "2 episodes finished" in out and "completion 9.50 ± 1.50 (mean ± SE)" in out
    assert "failed 50.0%" in out and "absent steps agent4 2" in out
    assert "last episode 1: completion 11 (failed)" in out
    assert "WARN world: act episode 2 step 3: agents [3] absent" in out
    assert "agent2 rejected: broadcast/range 3" in out
    assert "watch: " in out and "0 rejected" in out


def test_another_episode_of_the_batch() -> None:
    out = text(fed_state(episode_in_batch=1))
    assert "episode 3  step 3/30  phase step  (index 1 of the batch 2..3" in out
    fire1 = next(ln for ln in out.splitlines() if ln.strip().startswith("fire@site1"))
    assert fire1.split()[1] == "0"  # row 1 of the ground truth
    # agent1's belief is of episode 2, so it is not compared with episode 3's truth, but still shown
    assert "4 (0.75)" in fire1
    st = fed_state(episode_in_batch=9)  # beyond the batch: its last episode
    assert "episode 3  step 3/30  phase step  (index 1 of the batch 2..3" in text(st)


def test_bad_records_are_counted_and_change_nothing() -> None:
    st = fed_state()
    before = text(st)
    st.on_step("{not json")
    st.on_step(encode(S.STEP, {"episode": 2, "size": 2, "step": 99, "phase": "step", "acted": []}))  # > horizon
    st.on_ground_truth(
        encode(
            S.GROUND_TRUTH, {"episode": 2, "step": 4, "levels": [[9, 9, 9, 9]], "actions": [[0] * 5], "events": [[]]}
        )
    )
    st.on_belief("agent2", belief(0, 2, 3, [1, 1, 1, 1]))  # agent1's record on agent2's topic
    st.on_metrics(42)
    assert st.rejected == {"step/json": 1, "step/range": 1, "ground_truth/range": 1, "agent2/belief/agent": 1,
                           "episode_metrics/type": 1}  # fmt: skip
    after = text(st)
    assert "5 rejected (agent2/belief/agent 1, episode_metrics/type 1, ground_truth/range 1" in after
    assert before.split("watch:")[0] == after.split("watch:")[0]


def test_records_before_the_scenario_are_not_shown() -> None:
    st = WatchState()
    st.on_metrics(metrics(0, 8))
    assert st.rejected == {"episode_metrics/no_scenario": 1}
    out = text(st)
    assert "waiting for a team" in out and "no episode finished yet" in out


def test_a_new_run_starts_over() -> None:
    st = fed_state()
    st.on_scenario(scenario_record(run="next-run", batch=1))
    out = text(st)
    assert "run next-run" in out and "no episode finished yet" in out and "waiting for the world's clock" in out


def test_signed_records_with_the_key_and_unsigned_ones_rejected() -> None:
    signer = Signer(KEY)
    st = WatchState(signer=signer)
    st.on_scenario(scenario_record())  # unsigned: rejected
    assert st.scenario is None and st.rejected == {"scenario/signature": 1}
    st.on_scenario(scenario_record(signer=Signer(b"another-key-of-16-bytes")))
    assert st.scenario is None and st.rejected["scenario/signature"] == 2
    st.on_scenario(scenario_record(signer=signer))
    assert st.scenario is not None and st.run is not None and st.run["run"] == "watch-test"


def test_a_silent_node_and_the_rich_renderable() -> None:
    st = fed_state(stale_after=5.0)
    out = text(st, now=130.0)  # 30 s after the last /diagnostics
    world = next(ln for ln in out.splitlines() if ln.strip().startswith("world "))
    assert "SILENT" in world and "30 s ago" in world
    agent2 = next(ln for ln in out.splitlines() if ln.strip().startswith("agent2 "))
    assert "silent 30 s" in agent2
    buf = io.StringIO()
    Console(file=buf, width=100, force_terminal=True, color_system="standard").print(render(st, 101.0))
    assert "\x1b[" in buf.getvalue() and "fire@site1" in buf.getvalue()  # coloured on a terminal


@pytest.mark.skipif("severity" not in S.EPISODE_METRICS.fields, reason="episode metrics without a severity source")
def test_episodes_of_unknown_severity_are_left_out_of_the_completion_statistics() -> None:
    st = fed_state()
    unknown = {"completion": -1, "failed": False, "unused_capability": -1.0, "unused_fraction": -1.0}
    st.on_metrics(
        encode(
            S.EPISODE_METRICS,
            {
                **unknown,
                "episode": 2,
                "idle_before": -1,
                "reassign_before": -1,
                "absent": [0] * SC.n_agents,
                "seconds": 0.1,
                "severity": "unknown",
            },
        )
    )
    out = text(st)
    assert "3 episodes finished" in out and "completion 9.50 ± 1.50" in out and "(2 with known severities)" in out
    assert "last episode 2: completion unknown" in out


@pytest.mark.skipif("run" not in S.EPISODE_METRICS.fields, reason="episode metrics without a run id")
def test_metrics_of_another_run_are_rejected() -> None:
    st = fed_state()
    st.on_metrics(encode(S.EPISODE_METRICS, {**S.decode(metrics(5, 3), S.EPISODE_METRICS, st.lim), "run": "old-run"}))
    out = text(st)
    assert "2 episodes finished" in out and "rejected (episode_metrics/other_run 1)" in out


def test_the_view_names_the_events_of_the_shown_episode() -> None:
    """The ground truth's events (indices into the announced scenario's `events`) show under the episode line."""
    sc = SC.with_events(
        [EventSpec("dropout", agent="agent3", at=2), EventSpec("surge", site="site1", task="fire", level=3)]
    )
    st = WatchState()
    st.on_scenario(scenario_record(sc=sc))
    st.on_step(encode(S.STEP, {"episode": 2, "size": 2, "step": 2, "phase": "step", "acted": [0, 1, 3, 4]}))
    truth = {"episode": 2, "step": 2, "levels": [[4, 3, 2, 1]] * 2, "actions": [[0, 1, 4, 4, 5]] * 2}
    st.on_ground_truth(encode(S.GROUND_TRUTH, {**truth, "events": [[0, 1], [1]]}))
    assert "events: dropout agent3 (step 2), surge fire@site1 to 3 (step 2)" in text(st)


def test_under_the_agents_own_clock_each_agent_shows_how_far_its_clock_is_ahead_of_the_teams_median_clock() -> None:
    st = fed_state()
    assert "clock ahead" not in text(st)  # the lockstep: no offsets measured, no column
    names = st.agent_names
    offsets = {"agent4": 0.1, "agent5": 0.3}  # ahead of the others, who agree with each other
    for me in names:
        mine = offsets.get(me, 0.0)
        vals = {f"clock_offset/{k}": f"{offsets.get(k, 0.0) - mine:+.3f}" for k in names if k != me}
        vals["clock_tolerance"] = "0.125"
        st.on_diagnostics([(f"htlm: {me}", 0, "running", vals)], now=100.0)
    rows: dict[str, str] = {}
    for ln in text(st).splitlines():  # the agents table comes before the nodes table
        if ln.split()[:1] and ln.split()[0] in names:
            rows.setdefault(ln.split()[0], ln)
    assert "clock ahead" in text(st)
    assert "+0.300 s" in rows["agent5"] and "+0.100 s" in rows["agent4"]  # ahead of the team's median clock
    assert "+0.000 s" in rows["agent1"]  # agent4 and agent5 see it behind, the other two do not
    assert st.clock_offset("agent5") == (0.3, True)  # beyond the tolerance 0.125
    assert st.clock_offset("agent4") == (0.1, False)  # although agent5 sees it 0.2 s behind
    assert st.clock_offset("agent1") == (0.0, False)


def test_replay_names_a_missing_recording_and_a_bad_speed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from htlm_agent.cli import main

    assert main(["watch", "--replay", str(tmp_path), "--once"]) == 2
    assert f"--replay {tmp_path}: no recording there" in capsys.readouterr().err
    (tmp_path / "recording").mkdir()
    (tmp_path / "recording" / "metadata.yaml").write_text("{}\n")
    assert main(["watch", "--replay", str(tmp_path), "--speed", "-1", "--once"]) == 2
    assert "--speed: -1.0 must be a number >= 0" in capsys.readouterr().err
