"""The world's markers over real DDS (/htlm/markers, visualization_msgs/MarkerArray): a recorder subscribes during a
greedy run of a batch of two episodes showing the batch's second one (marker_episode 1), and every update equals the
world's log of that episode at that step (task colours and labels from the true levels, agents at the site of their
applied assignment, sites at the scenario's positions, frame map); the run ends with a DELETEALL, also when the
world is stopped by SIGINT."""

from __future__ import annotations

import math
import signal
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.ros.launch import process_specs
from htlm_world import markers as M
from htlm_world.model import Model
from support.ros import read_json

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]


def _record(team: Any, out: Path) -> Any:
    """Start the marker recorder and wait until it listens."""
    h = team.helper("markers", "--out", str(out))
    team.wait_for(out.exists, 30, "the marker recorder to subscribe")
    return h


def _stop(h: Any, out: Path) -> list[dict[str, Any]]:
    h.send_signal(signal.SIGTERM)
    h.wait(timeout=10)
    return list(read_json(out))


def _ended(out: Path) -> bool:
    try:
        got = read_json(out, timeout=1.0)
    except (OSError, ValueError):
        return False
    return bool(got) and got[-1]["marks"][0]["action"] == M.DELETEALL


def test_markers_show_the_chosen_episode_as_the_world_logged_it(ros_team: Any, tmp_path: Path) -> None:
    team = ros_team(policy="greedy", seed=4, episodes=2, batch=2, world_params={"marker_episode": 1})
    sc = team.cfg.scenario
    model = Model.build(sc)
    out = tmp_path / "markers.json"
    h = _record(team, out)
    # The world publishes markers only to subscribers it has discovered, and the run lasts about a second: start the
    # world alone, wait until it has shown the recorder its first scene (so it has matched it), then the team.
    team.start("world")
    team.wait_for(lambda: len(read_json(out)) > 0, 30, "the world's first scene at the marker recorder")
    team.start(*[name for name, _, _ in process_specs(team.cfg) if name != "world"])
    assert team.wait("world", 60) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    team.wait_for(lambda: _ended(out), 10, "the DELETEALL of the end of the run")
    got = _stop(h, out)
    while got and M.parse_status(got[0]["marks"][-1]["text"]) != (1, 0):  # the scene before the batch began
        got.pop(0)
    (logged,) = [w for w in team.world_episodes() if w["metrics"]["episode"] == 1]
    assert got[-1]["marks"] == [{**got[-1]["marks"][0], "action": M.DELETEALL}] and len(got[-1]["marks"]) == 1
    seen = set()
    by: dict[tuple[str, int], M.Mark] = {}  # the scene as RViz shows it: each update replaces markers by (ns, id)
    assert len(got[0]["marks"]) == 2 * sc.n_sites + 2 * sc.n_tasks + 2 * sc.n_agents + 1  # the whole scene first
    for rec in got[:-1]:
        assert rec["frames"] == [M.FRAME] and rec["lifetimes"] == [0.0] and rec["stamps"][0] > 0
        M.accumulate(by, [M.Mark(**{**m, "rgba": tuple(m["rgba"])}) for m in rec["marks"]])
        assert len(by) == 2 * sc.n_sites + 2 * sc.n_tasks + 2 * sc.n_agents + 1
        shown = M.parse_status(by[("status", 0)].text)
        assert shown is not None and shown[0] == 1, shown  # the batch's second episode
        t = shown[1]
        seen.add(t)
        for s, xy in enumerate(sc.site_positions):
            assert (by[("sites", s)].x, by[("sites", s)].y) == tuple(map(float, xy))
        levels = logged["levels"][t]
        for j, lv in enumerate(levels):
            assert by[("tasks", j)].rgba == pytest.approx(M.level_colour(lv, sc.levels), abs=1e-6), (t, j)
            assert by[("task_labels", j)].text.endswith("done" if lv == 0 else f"level {lv}"), (t, j)
        actions = logged["actions"][t - 1] if t else [sc.start_assignment] * sc.n_agents
        for k, a in enumerate(actions):
            m = by[("agents", k)]
            near = min(range(sc.n_sites), key=lambda s: math.dist((m.x, m.y), sc.site_positions[s]))
            assert near == model.action_site[a], (t, k, a)
            does = sc.kinds[model.task_kind[a]].name if a < sc.n_tasks else "idle"
            assert by[("agent_labels", k)].text == f"{sc.agents[k].name}: {does}", (t, k, a)
            assert m.rgba == pytest.approx(M.WORKING if a < sc.n_tasks else M.IDLE, abs=1e-6)
    # the writer keeps only the latest scene (a late RViz needs no more), so a slow reader may miss a few updates
    assert len(seen & set(range(1, sc.horizon + 1))) >= sc.horizon // 2, sorted(seen)
    steps = [M.parse_status(r["marks"][-1]["text"]) for r in got[:-1]]
    assert steps == sorted(steps)  # in order, each with its status line
    assert min(len(r["marks"]) for r in got[:-1]) < len(got[0]["marks"])  # later updates carry what changed


@pytest.mark.slow  # CI budget: the default run keeps the markers of an episode; this one with -m slow
def test_a_stopped_world_deletes_its_markers(ros_team: Any, tmp_path: Path) -> None:
    team = ros_team(policy="greedy", seed=2, episodes=0)  # until stopped
    out = tmp_path / "markers.json"
    h = _record(team, out)
    team.start()
    team.wait_for(lambda: len(read_json(out)) > 5, 60, "a few marker updates")
    team.kill("world", signal.SIGINT)
    assert team.procs["world"].popen.returncode == 130
    team.wait_for(lambda: _ended(out), 10, "the DELETEALL after SIGINT")
    got = _stop(h, out)
    assert len(got[-1]["marks"]) == 1 and got[-1]["marks"][0]["action"] == M.DELETEALL
    assert all(m["action"] == M.ADD for r in got[:-1] for m in r["marks"])
