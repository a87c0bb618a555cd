"""What the operation looks like in RViz2 or Foxglove, without ROS: the world's state of one episode as a plain list
of markers (`Mark`), which htlm_world.ros.markers turns into a visualization_msgs/MarkerArray on /htlm/markers.

Every marker has a stable id in its namespace, so a marker of an update replaces the one a viewer shows:

- `sites`, `site_labels`: a flat disc at every site's position of the scenario (`site_positions`), with its name;
- `tasks`, `task_labels`: every task of every site in a row above its centre (a cube or a sphere, alternating with
  the kind: the first kind of the scenario a cube, the second a sphere, ...), coloured by their true level (green,
  done, at level 0 through yellow to red at level L-1; grey when unknown), labelled with its kind and level;
- `agents`, `agent_labels`: every agent (a cylinder) at the site of its assignment, in a column below the site's
  tasks; opaque blue while working on a task, pale and translucent while idle, labelled with its name and what it
  does (and "absent" when the world idled it for a missing action); with travel (docs/model.md, Travel) an agent on
  its way is drawn where it is between the sites, orange, labelled with the site it drives to and the steps left;
- `status`: the episode and step shown.

`MarkerView` follows the world protocol's records (htlm_world.protocol.WorldEffects.publish) and says when the scene
changed: the initial state when a batch begins, the state after every step of the chosen episode of the batch (the
levels and actions of the protocol's ground truth record), and a single DELETEALL when the run stops. Following a
record costs next to nothing; building the scene (only when someone looks) is O(sites + tasks + agents) dictionary
look-ups, as the markers are cached by what they show.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from htlm_world.scenario import Scenario
from htlm_world.travel import TravelState

FRAME = "map"
"""Fixed frame of every marker: the frame of the scenario's site positions and of the agents' goal poses."""

# Marker types and actions: the values of the visualization_msgs/Marker constants (tests/test_markers.py checks them)
CUBE = 1
SPHERE = 2
CYLINDER = 3
TEXT = 9  # TEXT_VIEW_FACING
ADD = 0
DELETEALL = 3

NAMESPACES = ("sites", "site_labels", "tasks", "task_labels", "agents", "agent_labels", "status")
"""Every namespace of an update, in the order of its markers."""

Rgba = tuple[float, float, float, float]

WORKING: Rgba = (0.10, 0.35, 0.95, 1.0)
"""Colour of an agent working on a task."""
IDLE: Rgba = (0.55, 0.62, 0.75, 0.45)
"""Colour of an idle agent (translucent)."""
DRIVING: Rgba = (0.95, 0.55, 0.10, 1.0)
"""Colour of an agent on its way to its assignment's site (with travel)."""
UNKNOWN: Rgba = (0.6, 0.6, 0.6, 1.0)
"""Colour of a task whose level is unknown."""
SITE: Rgba = (0.75, 0.75, 0.75, 0.35)
TEXT_COLOUR: Rgba = (0.05, 0.05, 0.05, 1.0)
CHAR_WIDTH = 0.8
"""Width of a character of a TEXT marker, roughly, in units of its height (to place labels beside shapes)."""


@dataclass(frozen=True)
class Mark:
    """One marker, in the fields of visualization_msgs/Marker (frame FRAME, lifetime 0, identity orientation)."""

    ns: str
    """Namespace (one of NAMESPACES)."""
    id: int
    """Id within the namespace, stable from update to update (site, task or agent index)."""
    type: int
    """CUBE, SPHERE, CYLINDER or TEXT."""
    x: float = 0.0
    """Position in the map frame, metres."""
    y: float = 0.0
    z: float = 0.0
    sx: float = 0.0
    """Scale, metres (TEXT: only sz, the height of a capital letter)."""
    sy: float = 0.0
    sz: float = 0.0
    rgba: Rgba = (1.0, 1.0, 1.0, 1.0)
    """Colour and opacity, each 0..1."""
    text: str = ""
    """Text of a TEXT marker."""
    action: int = ADD
    """ADD (add or replace) or DELETEALL (every marker of the topic is removed)."""


DELETE_ALL: tuple[Mark, ...] = (Mark("", 0, CUBE, action=DELETEALL),)
"""The update that removes every marker (the end of a run)."""


def level_colour(level: int | None, levels: int) -> Rgba:
    """Colour of a task at `level` of 0..levels-1: green (done) at 0, through yellow, to red at levels-1; grey when
    the level is unknown (None or negative)."""
    if level is None or level < 0:
        return UNKNOWN
    f = min(1.0, level / max(1, levels - 1))
    return (min(1.0, 2.0 * f), min(1.0, 2.0 * (1.0 - f)) * 0.8, 0.1, 1.0)


_STATUS = re.compile(r"episode (\d+), step (\d+)")


def status_text(episode: int, step: int, horizon: int) -> str:
    """Text of the `status` marker."""
    return f"episode {episode}, step {step} of {horizon}"


def parse_status(text: str) -> tuple[int, int] | None:
    """(episode, step) of a `status` marker's text, None if it is not one."""
    m = _STATUS.match(text)
    return (int(m.group(1)), int(m.group(2))) if m else None


def accumulate(shown: dict[tuple[str, int], Mark], update: Sequence[Mark]) -> None:
    """Apply an update to the markers a viewer shows, as RViz does: DELETEALL removes every marker, any other marker
    is added or replaces the one of its namespace and id."""
    for m in update:
        if m.action == DELETEALL:
            shown.clear()
        else:
            shown[(m.ns, m.id)] = m


class Layout:
    """Where everything of a scenario is drawn, and the markers that do not change from update to update (sizes
    follow the distance between the closest two sites). Markers are cached by what they show, so an update
    creates only what changed: building one costs a few dictionary look-ups per site, task and agent."""

    def __init__(self, scenario: Scenario) -> None:
        """The layout of `scenario`'s sites, tasks and agents."""
        self.scenario = scenario
        sc = scenario
        pos = [(float(x), float(y)) for x, y in sc.site_positions]
        gaps = [((x1 - x2) ** 2 + (y1 - y2) ** 2) ** 0.5 for i, (x1, y1) in enumerate(pos) for x2, y2 in pos[i + 1 :]]
        self.radius_units = max(4.0, 2.0 + 0.9 * sc.n_agents)
        """Radius of a site's disc, in layout units (room for a column of every agent)."""
        span = min(gaps) if gaps and min(gaps) > 0 else 50.0
        u = self.unit = span / (2.0 * self.radius_units + 2.0)
        """One layout unit, metres."""
        self.radius = self.radius_units * u
        """Radius of a site's disc, metres."""
        self.positions = pos
        """(x, y) of every site."""
        self.action_sites = list(sc.action_sites)
        """Site of every action (Scenario.action_sites)."""
        d = 2 * self.radius
        self.fixed: list[Mark] = [
            Mark("sites", s, CYLINDER, x, y, -0.05 * u, d, d, 0.1 * u, SITE) for s, (x, y) in enumerate(pos)
        ]
        """The sites' discs and names: the same in every update."""
        self.fixed += [
            Mark("site_labels", s, TEXT, x, y + 4.9 * u, 0.5 * u, sz=0.8 * u, rgba=TEXT_COLOUR, text=sc.site_names[s])
            for s, (x, y) in enumerate(pos)
        ]
        xs, ys = [x for x, _ in pos], [y for _, y in pos]
        self.status_at = ((min(xs) + max(xs)) / 2, max(ys) + self.radius + 1.0 * u)
        """Where the status line goes: above the sites."""
        self.task_place: list[tuple[int, float]] = []
        """(site, place in the site's row of tasks, of how many) of every task."""
        for s, k in sc.tasks:
            row = [kk for ss, kk in sc.tasks if ss == s]
            self.task_place.append((s, row.index(k) - (len(row) - 1) / 2))
        self.kind_of = [k for _, k in sc.tasks]
        """Kind index of every task."""
        self._tasks: dict[tuple[int, int], tuple[Mark, Mark]] = {}
        self._agents: dict[tuple[int, int, int, int, bool], tuple[Mark, Mark]] = {}

    def task(self, j: int) -> tuple[float, float]:
        """Centre of task j: the site's tasks in a row above its centre, in the order of the scenario's kinds."""
        s, place = self.task_place[j]
        x, y = self.positions[s]
        u = self.unit
        return x + 3.6 * place * u, y + 1.8 * u

    def agent(self, s: int, slot: int) -> tuple[float, float]:
        """Centre of the agent in column slot `slot` of site s (slot 0 just below the site's centre)."""
        x, y = self.positions[s]
        u = self.unit
        return x - 3.6 * u, y - (0.2 + 0.9 * slot) * u

    def task_marks(self, j: int, level: int) -> tuple[Mark, Mark]:
        """Task j at `level` (negative: unknown): its shape and its label."""
        got = self._tasks.get((j, level))
        if got is None:
            x, y = self.task(j)
            u = self.unit
            kind = self.kind_of[j]
            shape = CUBE if kind % 2 == 0 else SPHERE
            lv = None if level < 0 else level
            state = "level ?" if lv is None else ("done" if lv == 0 else f"level {lv}")
            got = (
                Mark(
                    "tasks", j, shape, x, y, 0.7 * u, 1.4 * u, 1.4 * u, 1.4 * u, level_colour(lv, self.scenario.levels)
                ),
                Mark(
                    "task_labels",
                    j,
                    TEXT,
                    x,
                    y + 1.7 * u,
                    1.6 * u,
                    sz=0.5 * u,
                    rgba=TEXT_COLOUR,
                    text=f"{self.scenario.kinds[kind].name}\n{state}",
                ),
            )
            self._tasks[(j, level)] = got
        return got

    def agent_marks(self, k: int, action: int, site: int, slot: int, absent: bool) -> tuple[Mark, Mark]:
        """Agent k carrying out `action` (-1: none) at `site`, in column slot `slot`: its shape and its label."""
        key = (k, action, site, slot, absent)
        got = self._agents.get(key)
        if got is None:
            p, u = self.scenario.n_tasks, self.unit
            x, y = self.agent(site, slot)
            working = 0 <= action < p
            does = (
                self.scenario.kinds[self.kind_of[action]].name if working else ("idle" if action >= p else "no action")
            )
            text = f"{self.scenario.agents[k].name}: {does}" + (" (absent)" if absent else "")
            # text is drawn centred on its position: put the centre so that the text starts just right of the agent
            lx = x + 0.6 * u + 0.5 * CHAR_WIDTH * 0.45 * u * len(text)
            got = (
                Mark("agents", k, CYLINDER, x, y, 0.5 * u, 0.7 * u, 0.7 * u, 1.0 * u, WORKING if working else IDLE),
                Mark("agent_labels", k, TEXT, lx, y, 1.2 * u, sz=0.45 * u, rgba=TEXT_COLOUR, text=text),
            )
            self._agents[key] = got
        return got


def scene(
    layout: Layout,
    levels: Sequence[int] | None,
    actions: Sequence[int],
    acted: Sequence[int],
    episode: int,
    step: int,
    sites: Sequence[int] | None = None,
    events: Sequence[str] = (),
    moving: dict[int, tuple[float, float, int]] | None = None,
) -> list[Mark]:
    """The markers of one episode's state.

    Args:
        layout: The scenario's layout (Layout(scenario)).
        levels: (p,) true level of every task; None or negative levels when unknown (external operation).
        actions: (N,) the assignment each agent carries out (an index into G-bar; -1: none, HT mode).
        acted: The agents whose own action was applied (any other agent was idled by the world: absent).
        episode: The episode shown.
        step: The step of `levels` (0: the initial state).
        sites: (N,) site of each agent whose action is -1 (its previous site); None: the first site.
        events: Labels of the scenario's events that happened in the episode so far (after the status text).
        moving: The agents on their way (with travel): agent -> (x, y, steps left), drawn where they are.

    Returns:
        Every marker of the scene, namespace by namespace in NAMESPACES order, ids from 0 in each.
    """
    sc = layout.scenario
    tasks = [layout.task_marks(j, -1 if levels is None else int(levels[j])) for j in range(sc.n_tasks)]
    taken = [0] * sc.n_sites
    heard = set(acted)
    agents = []
    for k, a in enumerate(actions):
        a = int(a)
        stay = int(sites[k]) if sites is not None and sites[k] >= 0 else 0  # no action: where it was
        s = layout.action_sites[a] if a >= 0 else stay
        if moving is not None and k in moving:
            agents.append(_driving(layout, k, sc.site_names[s], *moving[k]))
            continue
        agents.append(layout.agent_marks(k, a, s, taken[s], k not in heard))
        taken[s] += 1
    x, y = layout.status_at
    u = layout.unit
    status = Mark(
        "status",
        0,
        TEXT,
        x,
        y,
        2.0 * u,
        sz=0.8 * u,
        rgba=TEXT_COLOUR,
        text=status_text(episode, step, sc.horizon) + "".join(f"; {label}" for label in events),
    )
    return [
        *layout.fixed,
        *(t for t, _ in tasks),
        *(t for _, t in tasks),
        *(a for a, _ in agents),
        *(a for _, a in agents),
        status,
    ]


def _driving(layout: Layout, k: int, site: str, x: float, y: float, left: int) -> tuple[Mark, Mark]:
    """Agent k on its way to `site`, at (x, y) with `left` steps to go: its shape and its label."""
    u = layout.unit
    text = f"{layout.scenario.agents[k].name}: to {site} ({left} steps)"
    lx = x + 0.6 * u + 0.5 * CHAR_WIDTH * 0.45 * u * len(text)
    return (
        Mark("agents", k, CYLINDER, x, y, 0.5 * u, 0.7 * u, 0.7 * u, 1.0 * u, DRIVING),
        Mark("agent_labels", k, TEXT, lx, y, 1.2 * u, sz=0.45 * u, rgba=TEXT_COLOUR, text=text),
    )


class MarkerView:
    """Follows the world protocol's records for one episode of each batch; `marks()` is the scene to publish."""

    def __init__(self, scenario: Scenario) -> None:
        """The view of a run of `scenario`."""
        self.scenario = scenario
        self.layout = Layout(scenario)
        n = scenario.n_agents
        start = scenario.start_assignment
        self.levels: Sequence[int] | None = scenario.initial_levels
        """True levels of the shown episode (None: unknown)."""
        self.actions: Sequence[int] = [start] * n
        """The assignment each agent carries out."""
        self.acted: Sequence[int] = range(n)
        """The agents whose actions the world applied in the latest step."""
        self.sites: list[int] = [self.layout.action_sites[start] if start >= 0 else 0] * n
        """Site of each agent's latest assignment in the shown episode (where an agent with no action stays)."""
        self.shown = (-1, -1)
        """(episode, step) of the scene."""
        self.stopped = False
        """The run is over: the scene is a DELETEALL."""
        self._marks: list[Mark] | None = None
        self.events: list[str] = []
        """Labels of the scenario's events that happened in the shown episode so far."""
        self.travel = TravelState(scenario, 1) if scenario.travel else None
        """The shown episode's drives, replayed from its assignments (docs/model.md, Travel)."""

    def on_record(self, kind: str, fields: dict[str, Any], index: int) -> bool:
        """Follow the protocol's record (kind, fields); returns whether the scene changed.

        Args:
            kind: The record's kind (scenario, step, ground_truth; the others are ignored).
            fields: Its fields as the protocol returned them.
            index: Which episode of the batch to show (clipped to the batch's size).
        """
        if kind == "scenario":
            stopped = fields.get("state") == "stopped"
            changed, self.stopped = stopped != self.stopped, stopped
            return changed
        if kind == "step":
            if fields["phase"] == "begin":
                e = int(fields["episode"]) + min(index, int(fields["size"]) - 1)
                if self.shown == (e, 0):  # the begin is announced again and again while the agents join
                    return False
                self.begin(e)
                return True
            if fields["phase"] == "step":
                self.acted = fields["acted"]
            return False
        if kind == "ground_truth":
            actions = fields["actions"]
            i = min(index, len(actions) - 1)
            levels = fields.get("levels")
            self.after_step(int(fields["episode"]) + i, int(fields["step"]), levels[i] if levels else None, actions[i])
            events = fields.get("events") or []
            self.events += [self.scenario.events[j].label for j in (events[i] if i < len(events) else [])]
            return True
        return False

    def begin(self, episode: int) -> None:
        """The scene at the begin of `episode`: initial levels, every agent at its start assignment."""
        sc = self.scenario
        start = sc.start_assignment
        self.sites = [self.layout.action_sites[start] if start >= 0 else 0] * sc.n_agents
        self.levels, self.actions, self.acted = sc.initial_levels, [start] * sc.n_agents, range(sc.n_agents)
        self.shown, self.stopped, self._marks = (episode, 0), False, None
        self.events = []
        if self.travel is not None:
            self.travel.reset()

    def after_step(self, episode: int, step: int, levels: Sequence[int] | None, actions: Sequence[int]) -> None:
        """The scene after `step` of `episode`: true levels (None: unknown) and the applied actions (N,)."""
        if len(self.sites) != len(actions):
            self.sites = [0] * len(actions)
        for k, a in enumerate(actions):
            if a >= 0:
                self.sites[k] = self.layout.action_sites[a]
        if self.travel is not None:
            self.travel.step(np.asarray(actions, dtype=np.int64)[None])
        self.levels, self.actions = levels, actions
        self.shown, self.stopped, self._marks = (episode, step), False, None

    def marks(self) -> Sequence[Mark]:
        """The markers of the current scene (DELETE_ALL once the run stopped), built when first asked for."""
        if self.stopped:
            return DELETE_ALL
        if self._marks is None:
            e, t = self.shown
            moving = None
            if self.travel is not None:
                eta = self.travel.eta()[0]
                xy = self.travel.xy[0]
                moving = {k: (float(xy[k, 0]), float(xy[k, 1]), int(eta[k])) for k in range(len(eta)) if eta[k] > 0}
            self._marks = scene(
                self.layout, self.levels, self.actions, self.acted, e, t, self.sites, self.events, moving
            )
        return self._marks


def render(marks: Sequence[Mark], path: str, title: str = "") -> None:
    """Draw an update as RViz2 would show it from straight above (top view of the map frame) into a PNG file:
    cylinders and spheres as discs, cubes as squares, text centred on its position; a DELETEALL draws nothing.

    Needs matplotlib (installed with htlm_agent), imported here so the world itself does not depend on it.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    shown = [m for m in marks if m.action == ADD]
    fig = Figure(figsize=(10, 6), dpi=120)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.9 if title else 0.96))
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_facecolor("white")
    if title:
        fig.suptitle(title, fontsize=11)
    if not shown:
        fig.savefig(path)
        return
    half = [max(m.sx, m.sy) / 2 for m in shown]
    x0 = min(m.x - h for m, h in zip(shown, half, strict=True))
    x1 = max(m.x + h for m, h in zip(shown, half, strict=True))
    y0 = min(m.y - h - m.sz for m, h in zip(shown, half, strict=True))
    y1 = max(m.y + h + m.sz for m, h in zip(shown, half, strict=True))
    pad = 0.04 * max(x1 - x0, y1 - y0)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    # points per metre, with equal aspect: the axes box is limited by its tighter side
    box = ax.get_position()
    w_pt, h_pt = box.width * fig.get_figwidth() * 72, box.height * fig.get_figheight() * 72
    per_m = min(w_pt / (x1 - x0 + 2 * pad), h_pt / (y1 - y0 + 2 * pad))
    for m in sorted(shown, key=lambda m: m.z):
        if m.type == TEXT:
            # RViz's text height is the capital letters' height; matplotlib's font size is about 1.4 times that
            ax.text(
                m.x, m.y, m.text, ha="center", va="center", fontsize=m.sz * per_m * 1.4, color=m.rgba, zorder=m.z + 10
            )
        elif m.type == CUBE:
            ax.add_patch(Rectangle((m.x - m.sx / 2, m.y - m.sy / 2), m.sx, m.sy, color=m.rgba, zorder=m.z, lw=0))
        else:
            ax.add_patch(Circle((m.x, m.y), max(m.sx, m.sy) / 2, color=m.rgba, zorder=m.z, lw=0))
    fig.savefig(path)
