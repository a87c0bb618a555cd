"""The world's markers without ROS (htlm_world.markers): the scene of one episode's state (sites at their positions,
tasks coloured and labelled by level, agents at the site of their assignment, working or idle), `MarkerView` driven
by a real WorldProtocol's records for a batch of two episodes, and the top-view renderer."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_world import markers as M
from htlm_world.model import Model
from htlm_world.protocol import LockstepSettings, WorldEffects, WorldProtocol, world_protocol
from htlm_world.scenario import builtin

SC = builtin()
MODEL = Model.build(SC)
LAY = M.Layout(SC)
N, P, S = SC.n_agents, SC.n_tasks, SC.n_sites


def _by_ns(marks: list[M.Mark]) -> dict[str, list[M.Mark]]:
    out: dict[str, list[M.Mark]] = {}
    for m in marks:
        out.setdefault(m.ns, []).append(m)
    return out


def _nearest_site(m: M.Mark) -> int:
    return min(range(S), key=lambda s: math.dist((m.x, m.y), SC.site_positions[s]))


def test_marker_constants_are_those_of_visualization_msgs() -> None:
    msg = pytest.importorskip("visualization_msgs.msg")
    k = msg.Marker
    assert (M.CUBE, M.SPHERE, M.CYLINDER, M.TEXT) == (k.CUBE, k.SPHERE, k.CYLINDER, k.TEXT_VIEW_FACING)
    assert (M.ADD, M.DELETEALL) == (k.ADD, k.DELETEALL)


def test_scene_has_one_marker_per_site_task_and_agent_with_stable_ids() -> None:
    a = M.scene(LAY, [4, 3, 2, 0], [0, 1, 4, 2, 5], range(N), 3, 7)
    b = M.scene(LAY, [1, 1, 1, 1], [5, 5, 5, 5, 5], range(N), 3, 8)
    assert len(a) == 2 * S + 2 * P + 2 * N + 1  # O(sites + tasks + agents)
    assert [(m.ns, m.id) for m in a] == [(m.ns, m.id) for m in b]  # an update replaces the previous one
    ns = _by_ns(a)
    assert list(ns) == list(M.NAMESPACES)
    for name, count in zip(M.NAMESPACES, (S, S, P, P, N, N, 1), strict=True):
        assert [m.id for m in ns[name]] == list(range(count)), name
    assert all(m.action == M.ADD for m in a)
    assert [(m.x, m.y) for m in ns["sites"]] == [tuple(map(float, xy)) for xy in SC.site_positions]
    assert [m.text for m in ns["site_labels"]] == list(SC.site_names)
    assert M.parse_status(ns["status"][0].text) == (3, 7)


def test_an_update_builds_only_what_changed() -> None:
    a = M.scene(LAY, [4, 3, 2, 0], [0, 1, 4, 2, 5], range(N), 3, 7)
    b = M.scene(LAY, [4, 3, 2, 1], [0, 1, 4, 2, 2], range(N), 3, 8)
    same = [x is y for x, y in zip(a, b, strict=True)]
    changed = [(x.ns, x.id) for x, s in zip(a, same, strict=True) if not s]
    assert changed == [("tasks", 3), ("task_labels", 3), ("agents", 4), ("agent_labels", 4), ("status", 0)]


def test_accumulate_applies_updates_as_rviz_does() -> None:
    shown: dict[tuple[str, int], M.Mark] = {}
    a = M.scene(LAY, [4, 3, 2, 0], [0, 1, 4, 2, 5], range(N), 3, 7)
    M.accumulate(shown, a)
    b = M.scene(LAY, [4, 3, 2, 1], [0, 1, 4, 2, 2], range(N), 3, 8)
    M.accumulate(shown, [y for x, y in zip(a, b, strict=True) if x is not y])  # only what changed
    assert list(shown.values()) == b
    M.accumulate(shown, M.DELETE_ALL)
    assert shown == {}


def test_tasks_show_their_level_by_colour_and_label() -> None:
    levels = [4, 3, 2, 0]
    ns = _by_ns(M.scene(LAY, levels, [0] * N, range(N), 0, 1))
    for j, (m, lab) in enumerate(zip(ns["tasks"], ns["task_labels"], strict=True)):
        assert m.rgba == M.level_colour(levels[j], SC.levels)
        assert _nearest_site(m) == j // 2 and _nearest_site(lab) == j // 2
        assert lab.text == f"{('fire', 'rescue')[j % 2]}\n" + ("done" if levels[j] == 0 else f"level {levels[j]}")
    colours = [M.level_colour(lv, 5) for lv in range(5)]
    assert len(set(colours)) == 5
    assert colours[0][1] > colours[0][0] and colours[4][0] > colours[4][1]  # green when done, red at the worst
    reds = [c[0] - c[1] for c in colours]
    assert reds == sorted(reds)  # redder with every level
    for unknown in (None, [-1] * P):  # no levels, or -1 (external operation)
        ns = _by_ns(M.scene(LAY, unknown, [0] * N, range(N), 0, 1))
        assert all(m.rgba == M.UNKNOWN for m in ns["tasks"])
        assert all(m.text.endswith("level ?") for m in ns["task_labels"])


def test_agents_stand_at_the_site_of_their_assignment_working_or_idle() -> None:
    actions = [0, 1, 4, 2, 5]  # fire@site1, rescue@site1, idle@site1, fire@site2, idle@site2
    ns = _by_ns(M.scene(LAY, [4, 4, 4, 4], actions, [0, 1, 2, 3], 0, 1))
    agents, labels = ns["agents"], ns["agent_labels"]
    for k, a in enumerate(actions):
        site = int(MODEL.action_site[a])
        assert _nearest_site(agents[k]) == site
        assert math.dist((agents[k].x, agents[k].y), SC.site_positions[site]) < LAY.radius
        assert labels[k].text.startswith(SC.agents[k].name + ": ")
        assert abs(labels[k].y - agents[k].y) < 1e-9 and labels[k].x > agents[k].x  # beside its agent
    assert len({(m.x, m.y) for m in agents}) == N  # agents that share a site do not overlap
    assert [m.rgba for m in agents] == [M.WORKING, M.WORKING, M.IDLE, M.WORKING, M.IDLE]
    assert [m.text.split(": ")[1] for m in labels] == ["fire", "rescue", "idle", "fire", "idle (absent)"]


def test_without_an_action_an_agent_stays_where_it_was() -> None:
    ht = M.Layout(SC.replace(mode="ht"))
    ns = _by_ns(M.scene(ht, [4, 4, 4, 4], [-1, 2, -1, -1, 0], range(N), 0, 1, sites=[1, 0, 0, 1, 1]))
    assert [_nearest_site(m) for m in ns["agents"]] == [1, 1, 0, 1, 0]
    assert ns["agent_labels"][0].text == "agent1: no action" and ns["agents"][0].rgba == M.IDLE


def _drive(index: int, batch: int = 2, episodes: int = 2) -> tuple[list[tuple[Any, ...]], WorldProtocol]:
    """Run a WorldProtocol (every agent works on task k mod p) and feed every record to a MarkerView: the updates it
    returned, as (record kind, marks)."""
    p = world_protocol(SC, LockstepSettings(episodes=episodes, batch=batch, linger=0.0, run_id="t"))
    view = M.MarkerView(SC)
    updates: list[tuple[Any, ...]] = []

    def feed(eff: WorldEffects) -> None:
        for kind, fields in eff.publish:
            if view.on_record(kind, fields, index):
                updates.append((kind, view.marks()))

    feed(p.start(0.0))
    feed(p.tick(0.5))  # the begin announced again: no new update
    now = 1.0
    while not p.done:
        if p.phase == "act":
            for k in range(N):
                feed(p.on_action({"agent": k, "episode": p.episode, "step": p.t, "actions": [k % P] * p.size}, now))
        elif p.phase == "end":
            for k in range(N):
                feed(p.on_ready({"agent": k, "episode": p.episode, "step": p.t}, now))
        else:
            feed(p.tick(now))
        now += 0.01
    return updates, p


@pytest.mark.parametrize("index", [1, 7])  # 7: clipped to the batch's last episode
def test_view_follows_the_chosen_episode_of_a_batch_and_clears_at_the_end(index: int) -> None:
    updates, p = _drive(index)
    assert p.ep is not None
    traj = p.ep.trajectory(1)
    kinds = [k for k, _ in updates]
    assert kinds == ["step"] + ["ground_truth"] * SC.horizon + ["scenario"]
    assert updates[-1][1] == M.DELETE_ALL
    for t, (_, marks) in enumerate(updates[:-1]):
        ns = _by_ns(list(marks))
        assert M.parse_status(ns["status"][0].text) == (1, t)
        assert [m.rgba for m in ns["tasks"]] == [M.level_colour(lv, SC.levels) for lv in traj["levels"][t]]
        actions = traj["actions"][t - 1] if t else [SC.start_assignment] * N
        assert [_nearest_site(m) for m in ns["agents"]] == [int(MODEL.action_site[a]) for a in actions]
    assert np.array_equal(traj["levels"][0], SC.initial_levels)


def test_render_draws_the_scene_from_above(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread

    out = tmp_path / "m.png"
    M.render(M.scene(LAY, [4, 0, 4, 0], [0, 1, 4, 2, 5], range(N), 0, 3), str(out), "test")
    img = imread(str(out))
    assert img.shape[0] > 100 and img.shape[1] > 100
    rgb = img[..., :3].reshape(-1, 3)
    red, green = M.level_colour(4, 5)[:3], M.level_colour(0, 5)[:3]
    for colour in (red, green, M.WORKING[:3]):  # the tasks at level 4 and done, a working agent
        assert (np.abs(rgb - np.array(colour)).max(axis=1) < 0.02).sum() > 50, colour
    M.render(M.DELETE_ALL, str(tmp_path / "empty.png"))  # nothing to draw: an empty picture, no error
    assert (tmp_path / "empty.png").stat().st_size > 0


def test_the_status_line_names_the_events_of_the_shown_episode() -> None:
    """A scenario event (docs/model.md, Events) reaches the markers through the world's ground truth, and the world
    logs it."""
    from htlm_world.scenario import EventSpec

    sc = SC.with_events([EventSpec("surge", site="site2", task="fire", level=4, at=2, name="flare")])
    p = world_protocol(sc, LockstepSettings(episodes=1, linger=0.0, run_id="t"))
    view = M.MarkerView(sc)
    logs: list[str] = []

    def feed(eff: WorldEffects) -> None:
        logs.extend(text for _, text in eff.log)
        for kind, fields in eff.publish:
            view.on_record(kind, fields, 0)

    feed(p.start(0.0))
    feed(p.tick(0.5))
    now = 1.0
    while p.t < 3 or p.phase != "act":
        for k in range(N):
            feed(p.on_action({"agent": k, "episode": 0, "step": p.t, "actions": [P]}, now))
        now += 0.01
    (status,) = [m for m in view.marks() if m.ns == "status"]
    assert status.text == "episode 0, step 2 of 30; flare" and M.parse_status(status.text) == (0, 2)
    assert "episode 0, step 2: event 'flare'" in logs
