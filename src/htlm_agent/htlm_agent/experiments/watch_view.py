"""`htlm watch` without ROS: the state of a running team built from decoded records, and its rich rendering.

`WatchState` is fed the record texts of the monitoring topics (/htlm/scenario, /htlm/step, /htlm/ground_truth,
/htlm/<agent>/belief, /htlm/episode_metrics) and the statuses of /diagnostics, with the time they arrived. Every
record is decoded and validated with the wire contract (`htlm_msgs_py.schema.decode`, the scenario's limits, the
team key when one is set); a record that fails is counted under `rejected` and changes nothing. `render` builds a
rich renderable of the state (what the terminal shows), `snapshot` the same as plain text (pipes, logs, tests).
The ROS node `htlm_agent.ros.watch_node` only moves messages into the state (`feed`) and draws it with `show`, the
drawing loop `replay` uses too (`htlm watch --replay`: a recording of `htlm launch --record` fed to the same state
at the pace it was recorded).
"""

from __future__ import annotations

import math
import statistics
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path
from typing import IO, Any

import numpy as np
from rich import box
from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.table import Table
from rich.text import Text

from htlm_agent.experiments.recording import messages
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics
from htlm_msgs_py.params import setting
from htlm_msgs_py.schema import Arrival, WireError, decode, limits
from htlm_msgs_py.signing import Signer
from htlm_world.scenario import Scenario, ScenarioRecordError, from_record
from htlm_world.travel import drive_steps

LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
"""diagnostic_msgs/DiagnosticStatus levels."""


@dataclass(frozen=True)
class WatchSettings:
    """Settings of `htlm watch` (the command line's options)."""

    episode_in_batch: int = setting(0, lo=0, hi=4095)
    """Which episode of the world's batch to show (its index in the batch; the last one when the batch is smaller)."""
    refresh: float = setting(4.0, lo=0.1, hi=60.0)
    """Redraws per second on a terminal."""
    every: float = setting(5.0, lo=0.1, hi=3600.0)
    """Seconds between plain snapshots with `plain`."""
    duration: float = setting(0.0, lo=0.0, hi=1e7)
    """Exit after this many seconds (0: run until Ctrl-C)."""
    plain: bool = False
    """Print a plain text snapshot every `every` seconds and at exit instead of redrawing in place."""
    once: bool = False
    """Print one plain text snapshot at exit only (after `duration` or Ctrl-C)."""
    stale_after: float = setting(5.0, lo=0.1, hi=3600.0)
    """A node whose last /diagnostics message is older than this many seconds is shown as silent."""
    width: int = setting(120, lo=40, hi=1000)
    """Characters per line of a plain snapshot."""
    executor: str = setting("single", choices=("single", "events"))
    """rclpy executor of the watch node."""


@dataclass
class NodeStatus:
    """The latest /diagnostics status of one node."""

    level: int
    """0 OK, 1 WARN, 2 ERROR, 3 STALE."""
    message: str
    """The node's status message."""
    values: dict[str, str]
    """Its key/values (counters such as rejected/<topic>/<reason>)."""
    heard: float
    """Monotonic time it arrived."""

    def count(self, prefix: str) -> int:
        """The node's counter `prefix` (e.g. "rejected"), or the sum of its `prefix/...` counters when it has none."""
        if prefix in self.values:
            return _int(self.values[prefix])
        return sum(_int(v) for k, v in self.values.items() if k.startswith(prefix + "/"))

    def breakdown(self, prefix: str) -> dict[str, int]:
        """The non-zero `prefix/<topic>/<reason>` counters without the prefix."""
        out = {k[len(prefix) + 1 :]: _int(v) for k, v in self.values.items() if k.startswith(prefix + "/")}
        return {k: v for k, v in out.items() if v}


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        return 0


def _float(text: str, default: float) -> float:
    try:
        return float(text)
    except ValueError:
        return default


@dataclass
class Belief:
    """An agent's latest belief summary (one episode)."""

    episode: int
    """Episode it describes."""
    step: int
    """Step after which it was taken."""
    confident: list[int]
    """Confident level of every task."""
    probability: list[float]
    """The marginal probability of that level, per task."""
    arrived: Arrival = Arrival.UNKNOWN
    """Whether the agent's robot is at the site of its assignment (unknown without a pose topic)."""
    distance: float = -1.0
    """How far it is from that site, metres (-1: unknown)."""


@dataclass
class Stats:
    """Running completion statistics over the episodes whose metrics arrived."""

    metrics: dict[int, dict[str, Any]] = field(default_factory=dict)
    """Episode -> its metrics record (a repeated record replaces the first)."""

    @property
    def known(self) -> list[dict[str, Any]]:
        """Metrics of the episodes whose true levels were known (completion -1: nobody knew the severities)."""
        return [m for m in self.metrics.values() if m.get("severity", "simulated") != "unknown"]

    @property
    def n(self) -> int:
        """Episodes finished."""
        return len(self.metrics)

    def mean_se(self, key: str) -> tuple[float, float]:
        """Mean and standard error of a metric over the episodes (NaN when there are none)."""
        xs = [float(m[key]) for m in self.known]
        if not xs:
            return math.nan, math.nan
        mean = sum(xs) / len(xs)
        if len(xs) < 2:
            return mean, math.nan
        var = sum((x - mean) ** 2 for x in xs) / (len(xs) - 1)
        return mean, math.sqrt(var / len(xs))

    def failed(self) -> float:
        """Fraction of failed episodes."""
        known = self.known
        return sum(bool(m["failed"]) for m in known) / len(known) if known else math.nan

    def absent(self) -> list[int]:
        """Steps each agent missed, summed over the episodes."""
        out: list[int] = []
        for m in self.metrics.values():
            if len(out) < len(m["absent"]):
                out += [0] * (len(m["absent"]) - len(out))
            for k, x in enumerate(m["absent"]):
                out[k] += int(x)
        return out


class WatchState:
    """What `htlm watch` knows of the running team, fed decoded records."""

    def __init__(self, episode_in_batch: int = 0, signer: Signer | None = None, stale_after: float = 5.0) -> None:
        """Start empty.

        Args:
            episode_in_batch: which episode of the world's batch to show (index in the batch).
            signer: the team key's signer (records must carry a valid signature when it has a key).
            stale_after: seconds without /diagnostics after which a node is shown silent.
        """
        self.episode_in_batch = episode_in_batch
        self.signer = signer if signer is not None else Signer(None)
        self.stale_after = stale_after
        self.rejected: Counter[str] = Counter()
        """The watch's own rejections, by "<topic>/<reason>"."""
        self.received: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        """Well-formed records of another run, by "<topic>/<reason>"."""
        self.nodes: dict[str, NodeStatus] = {}
        self.scenario: Scenario | None = None
        self.run: dict[str, Any] | None = None
        self._reset()

    def _reset(self) -> None:
        self.step: dict[str, Any] | None = None
        self.acted: set[int] | None = None
        self.truth: dict[str, Any] | None = None
        self.events: list[tuple[int, int, int]] = []
        """(episode, step, event index) of the scenario's events the ground truth reported, latest last."""
        self.beliefs: dict[str, Belief] = {}
        self.stats = Stats()

    # ----- records in ---------------------------------------------------------------------------------------------
    @property
    def lim(self) -> dict[str, int] | None:
        """The scenario's limits for decoding (None before the scenario is known)."""
        sc = self.scenario
        if sc is None or self.run is None:
            return None
        return limits(
            sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, int(self.run["batch"]), sc.knowledge_size
        )

    @property
    def agent_names(self) -> list[str]:
        """Names of the team's agents (empty before the scenario is known)."""
        return [a.name for a in self.scenario.agents] if self.scenario is not None else []

    def _decode(self, topic: str, text: Any, schema: S.Schema) -> dict[str, Any] | None:
        try:
            rec = decode(text, schema, self.lim, self.signer)
        except WireError as e:
            self.rejected[f"{topic}/{e.reason}"] += 1
            return None
        self.received[topic] += 1
        return rec

    def _needs_run(self, topic: str) -> bool:
        if self.scenario is None:
            self.rejected[f"{topic}/no_scenario"] += 1
            return False
        return True

    def on_scenario(self, text: Any) -> None:
        """A /htlm/scenario record: a new run resets what was shown of the previous one."""
        rec = self._decode("scenario", text, S.SCENARIO)
        if rec is None:
            return
        if self.run is not None and rec["run"] == self.run["run"]:
            self.run = rec
            return
        try:
            sc = from_record(rec)
        except ScenarioRecordError as e:
            self.rejected[f"scenario/{e.reason}"] += 1
            return
        self.scenario, self.run = sc, rec
        self.signer.run = rec["run"]  # records of other runs are rejected from now on
        self._reset()

    def on_step(self, text: Any) -> None:
        """A /htlm/step record (the world's clock)."""
        if self._needs_run("step"):
            rec = self._decode("step", text, S.STEP)
            if rec is not None:
                self.step = rec
                if rec["phase"] == "step":
                    self.acted = set(rec["acted"])

    def on_ground_truth(self, text: Any) -> None:
        """A /htlm/ground_truth record: true levels and applied assignments of every episode of the batch."""
        if self._needs_run("ground_truth"):
            rec = self._decode("ground_truth", text, S.GROUND_TRUTH)
            if rec is not None:
                self.truth = rec
                happened = [(rec["episode"] + i, rec["step"], j) for i, js in enumerate(rec["events"]) for j in js]
                self.events = (self.events + happened)[-1000:]

    def on_metrics(self, text: Any) -> None:
        """A /htlm/episode_metrics record of a finished episode."""
        if self._needs_run("episode_metrics"):
            rec = self._decode("episode_metrics", text, S.EPISODE_METRICS)
            if rec is None:
                return
            if self.run is not None and rec.get("run", self.run["run"]) != self.run["run"]:
                self.dropped["episode_metrics/other_run"] += 1
                return
            self.stats.metrics[rec["episode"]] = rec

    def on_belief(self, agent: str, text: Any) -> None:
        """A /htlm/<agent>/belief record."""
        topic = f"{agent}/belief"
        if not self._needs_run(topic):
            return
        rec = self._decode(topic, text, S.BELIEF)
        if rec is None:
            return
        sc = self.scenario
        assert sc is not None
        if agent not in self.agent_names or rec["agent"] != self.agent_names.index(agent):
            self.rejected[f"{topic}/agent"] += 1
            return
        L = sc.levels
        marg = rec["marginals"]
        conf = rec["confident"]
        prob = [float(marg[j * L + c]) for j, c in enumerate(conf)]
        arrived = Arrival(rec.get("arrived", Arrival.UNKNOWN))
        self.beliefs[agent] = Belief(rec["episode"], rec["step"], list(conf), prob, arrived, rec.get("distance", -1.0))

    def on_diagnostics(self, statuses: Iterable[tuple[str, int, str, Mapping[str, str]]], now: float) -> None:
        """The statuses of a /diagnostics message: (name, level, message, key/values) each."""
        for name, level, message, values in statuses:
            self.nodes[name] = NodeStatus(int(level), message, dict(values), now)

    # ----- derived ------------------------------------------------------------------------------------------------
    def shown_index(self) -> int:
        """Index in the current batch of the episode shown (the requested one, or the batch's last)."""
        size = int(self.step["size"]) if self.step is not None else int(self.run["batch"]) if self.run else 1
        return min(self.episode_in_batch, size - 1)

    def shown_episode(self) -> int | None:
        """Number of the episode shown, once the clock has been heard."""
        return None if self.step is None else int(self.step["episode"]) + self.shown_index()

    def absent(self) -> list[str]:
        """Agents whose actions the world did not apply at the last step it announced (they idled in their absence)."""
        if self.acted is None:
            return []
        return [a for k, a in enumerate(self.agent_names) if k not in self.acted]

    def clock_offset(self, agent: str) -> tuple[float, bool] | None:
        """How far `agent`'s wall clock is ahead of the team's median clock, seconds, and whether that is more than
        the teammates tolerate (`clock_tolerance`, a quarter of the period); None when no teammate reports it (the
        lockstep clock, or no broadcast heard yet). Each teammate j measures o_agent - o_j (`clock_offset/<agent>`
        on its /diagnostics); their median with the agent's own 0 is o_agent - median(o): one teammate whose own
        clock is off moves it little."""
        seen: list[float] = []
        limit = math.inf
        for name, s in self.nodes.items():
            raw = s.values.get(f"clock_offset/{agent}")
            if name == f"htlm: {agent}" or raw is None:
                continue
            x = _float(raw, math.nan)
            if math.isfinite(x):
                seen.append(x)
                limit = min(limit, _float(s.values.get("clock_tolerance", "inf"), math.inf))
        if not seen:
            return None
        median = statistics.median([0.0, *seen])
        return median, abs(median) > limit

    def silent(self, now: float) -> list[str]:
        """Nodes whose last /diagnostics is older than `stale_after`."""
        return sorted(n for n, s in self.nodes.items() if now - s.heard > self.stale_after)


# ----- rendering --------------------------------------------------------------------------------------------------


def _fmt(x: float, spec: str) -> str:
    return "-" if x != x else format(x, spec)


def _level_text(level: int, levels: int) -> Text:
    """A severity level as its number and a bar, coloured from green (0) to red (L - 1)."""
    style = "green" if level == 0 else "red" if level >= levels - 1 else "yellow"
    return Text(f"{level} " + "#" * level, style=style)


def _header(state: WatchState) -> Text:
    run = state.run
    if run is None or state.scenario is None:
        return Text("htlm watch: waiting for a team (/htlm/scenario)", style="bold")
    sc = state.scenario
    t = Text()
    t.append(f"run {run['run']}", style="bold")
    t.append(
        f"  scenario {sc.name}/{sc.team}  mode {run['mode']}  seed {run['seed']}  "
        f"episodes {run['first_episode']}..{run['first_episode'] + run['episodes'] - 1 if run['episodes'] else 'inf'}"
        f"  batch {run['batch']}"
        + (f"  operation {run['operation']}" if run.get("operation", "simulated") != "simulated" else "")
        + f"  [{run['state']}]"
    )
    st = state.step
    t.append("\n")
    if st is None:
        t.append("waiting for the world's clock (/htlm/step)")
        return t
    first, size = int(st["episode"]), int(st["size"])
    shown = state.shown_episode()
    t.append(f"episode {shown}", style="bold")
    t.append(f"  step {st['step']}/{sc.horizon}  phase {st['phase']}")
    if size > 1 or int(run["batch"]) > 1:
        t.append(f"  (index {state.shown_index()} of the batch {first}..{first + size - 1}: --episode-in-batch)")
    events = [(step, j) for e, step, j in state.events if e == shown and j < len(sc.events)]
    if events:
        t.append("\nevents: ", style="bold")
        t.append(", ".join(f"{sc.events[j].label} (step {step})" for step, j in events), style="magenta")
    return t


def _truth_row(state: WatchState) -> int | None:
    """The row of the shown episode in the last ground-truth record (its levels and actions), None if not there."""
    tr, shown = state.truth, state.shown_episode()
    if tr is not None and shown is not None and 0 <= shown - tr["episode"] < len(tr["levels"]):
        return int(shown - tr["episode"])
    return None


def _tasks_table(state: WatchState) -> Table | None:
    sc = state.scenario
    if sc is None:
        return None
    shown = state.shown_episode()
    tr = state.truth
    row = _truth_row(state)
    title = "true severities" + (f" after step {tr['step']}" if tr is not None and row is not None else "")
    table = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    table.add_column("task")
    table.add_column("true level")
    names = state.agent_names
    for a in names:
        table.add_column(a)
    seen = {(b.episode, b.step) for b in state.beliefs.values()}
    if len(seen) == 1:
        ((e, t_b),) = seen
        where = f"of episode {e} after step {t_b}"
    else:
        where = "; ".join(f"{a}: episode {b.episode} step {b.step}" for a, b in sorted(state.beliefs.items()))
    caption = "beliefs: confident level (probability)" + (f", {where}" if seen else ": none yet")
    for j, task in enumerate(sc.action_names[: sc.n_tasks]):
        true = int(tr["levels"][row][j]) if tr is not None and row is not None else None
        cells: list[RenderableType] = [task, _level_text(true, sc.levels) if true is not None else Text("-")]
        for a in names:
            b = state.beliefs.get(a)
            if b is None:
                cells.append("-")
                continue
            same = true is not None and b.episode == shown
            style = "" if not same or b.confident[j] == true else "yellow"
            cells.append(Text(f"{b.confident[j]} ({b.probability[j]:.2f})", style=style))
        table.add_row(*cells)
    if tr is None:
        caption += "; no ground truth yet (/htlm/ground_truth)"
    table.caption = caption
    table.caption_justify = "left"
    return table


def _robot(b: Belief, sc: Scenario, k: int) -> str:
    """Where an agent's robot is against its site; with travel (docs/model.md, Travel) when it arrives: the distance
    it has left over its speed, in steps and seconds."""
    if b.arrived == Arrival.YES:
        return "at its site"
    if b.arrived == Arrival.NO:
        if b.distance < 0:
            return "on its way"
        if sc.travel and sc.agent_speed(k) > 0:
            steps = int(drive_steps(np.array(b.distance), np.array(sc.agent_speed(k) * sc.step_seconds)))
            return f"{b.distance:.1f} m away, arrives in {steps} steps ({b.distance / sc.agent_speed(k):.0f} s)"
        return f"{b.distance:.1f} m away"
    return "-"


def _agents_table(state: WatchState, now: float) -> Table | None:
    sc = state.scenario
    if sc is None:
        return None
    tr = state.truth
    row = _truth_row(state)
    absent = set(state.absent())
    table = Table(title="agents", title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    robots = any(b.arrived != Arrival.UNKNOWN for b in state.beliefs.values())
    clocks = {a: state.clock_offset(a) for a in state.agent_names}
    own_clock = any(c is not None for c in clocks.values())  # the deployed team's own clock: offsets are measured
    extra = (("robot",) if robots else ()) + (("clock ahead",) if own_clock else ())
    for col in ("agent", "assignment", "state", "rejected", "dropped") + extra:
        table.add_column(col)
    for k, a in enumerate(state.agent_names):
        act = int(tr["actions"][row][k]) if tr is not None and row is not None else -1
        node = state.nodes.get(f"htlm: {a}")
        if a in absent:
            status = Text("absent", style="bold red")
        elif node is not None and now - node.heard > state.stale_after:
            status = Text(f"silent {now - node.heard:.0f} s", style="red")
        elif state.step is not None:
            status = Text("acting", style="green")
        else:
            status = Text("up" if node is not None else "-")
        cells: list[RenderableType] = [
            a,
            sc.action_names[act] if 0 <= act < sc.n_actions else "-",
            status,
            str(node.count("rejected")) if node else "-",
            str(node.count("dropped")) if node else "-",
        ]
        if robots:
            b = state.beliefs.get(a)
            cells.append(_robot(b, sc, k) if b is not None else "-")
        if own_clock:
            c = clocks[a]
            cells.append(
                "-" if c is None else Text(f"{c[0]:+.3f} s", style="bold yellow" if c[1] else "")
            )  # ahead of the team's median clock
        table.add_row(*cells)
    return table


def _nodes_table(state: WatchState, now: float) -> Table:
    table = Table(
        title="nodes (/diagnostics)", title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False
    )
    for col in ("node", "level", "message", "rejected", "dropped", "heard"):
        table.add_column(col)
    for name in sorted(state.nodes):
        s = state.nodes[name]
        age = now - s.heard
        level = LEVEL_NAMES.get(s.level, str(s.level))
        style = "green" if s.level == 0 else "yellow" if s.level == 1 else "red"
        if age > state.stale_after:
            level, style = "SILENT", "red"
        table.add_row(
            name.removeprefix("htlm: "),
            Text(level, style=style),
            s.message,
            str(s.count("rejected")),
            str(s.count("dropped")),
            f"{age:.0f} s ago",
        )
    if not state.nodes:
        table.caption = "no /diagnostics yet"
    return table


def _problems(state: WatchState) -> Text:
    """Warnings and rejection counters of every node, and the watch's own rejections."""
    t = Text()
    for name in sorted(state.nodes):
        s = state.nodes[name]
        short = name.removeprefix("htlm: ")
        if s.level > 0:
            t.append(f"{LEVEL_NAMES.get(s.level, s.level)} {short}: {s.message}\n", style="yellow")
        rej = s.breakdown("rejected")
        if rej:
            t.append(f"{short} rejected: " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items())) + "\n", style="red")
    mine = sum(state.rejected.values())
    t.append(f"watch: {sum(state.received.values())} records received, {mine} rejected")
    if mine:
        t.append(" (" + ", ".join(f"{k} {v}" for k, v in sorted(state.rejected.items())) + ")", style="red")
    if state.dropped:
        t.append(", dropped " + ", ".join(f"{k} {v}" for k, v in sorted(state.dropped.items())))
    return t


def _stats(state: WatchState) -> Text:
    st = state.stats
    t = Text()
    if not st.n:
        t.append("completion: no episode finished yet")
        return t
    mean, se = st.mean_se("completion")
    last = max(st.metrics)
    m = st.metrics[last]
    t.append(f"{st.n} episodes finished", style="bold")
    t.append(f"  completion {_fmt(mean, '.2f')} ± {_fmt(se, '.2f')} (mean ± SE)", style="bold")
    unknown = st.n - len(st.known)
    if unknown:
        t.append(f" ({len(st.known)} with known severities)")
    t.append(f"  failed {_fmt(st.failed(), '.1%')}  unused capability {_fmt(st.mean_se('unused_fraction')[0], '.1%')}")
    absent = st.absent()
    if any(absent):
        names = state.agent_names
        t.append(
            "  absent steps " + ", ".join(f"{names[k] if k < len(names) else k} {x}" for k, x in enumerate(absent) if x)
        )
    done = "unknown (severities unknown)" if m.get("severity") == "unknown" else str(m["completion"])
    t.append(f"\nlast episode {last}: completion {done}" + (" (failed)" if m["failed"] else ""))
    return t


def render(state: WatchState, now: float) -> RenderableType:
    """The whole view of the state at monotonic time `now`, as one rich renderable."""
    parts: list[RenderableType] = [_header(state)]
    for table in (_tasks_table(state), _agents_table(state, now)):
        if table is not None:
            parts.append(table)
    parts += [_stats(state), _nodes_table(state, now), _problems(state)]
    spaced: list[RenderableType] = [parts[0]]
    for p in parts[1:]:
        spaced += [Text(""), p]
    return Group(*spaced)


def snapshot(state: WatchState, now: float, width: int = 120) -> str:
    """The view as plain text (no colours, no cursor movement), `width` characters wide."""
    buf = StringIO()
    console = Console(file=buf, width=width, color_system=None, force_terminal=False, legacy_windows=False)
    console.print(render(state, now))
    return buf.getvalue()


def show(
    state: WatchState,
    settings: WatchSettings,
    out: IO[str],
    pump: Callable[[float], bool],
    state_time: Callable[[], float] = time.monotonic,
) -> int:
    """Draw `state` until `settings.duration` elapses or `pump` says to stop: in place with rich on a terminal, else a
    plain snapshot every `every` seconds and one at the end (`once`: that one only). `pump(timeout)` feeds the state
    for at most `timeout` seconds and returns whether to go on; `state_time()` is the time the view is drawn at (for
    how old each node's last status is). Returns 0."""
    s = settings
    console = Console(file=out)
    interactive = not (s.plain or s.once) and console.is_terminal
    start = time.monotonic()
    end = start + s.duration if s.duration > 0 else math.inf
    next_print = start + s.every

    def plain() -> None:
        out.write(f"--- htlm watch, {time.monotonic() - start:.1f} s ---\n")
        out.write(snapshot(state, state_time(), s.width))
        out.flush()

    live = Live(render(state, state_time()), console=console, auto_refresh=False) if interactive else None
    if live is not None:
        live.start()
    next_draw = start
    try:
        while True:
            now = time.monotonic()
            if now >= end or not pump(min(1.0 / s.refresh, end - now, 0.25)):
                break
            now = time.monotonic()
            if live is not None and now >= next_draw:
                live.update(render(state, state_time()), refresh=True)
                next_draw = now + 1.0 / s.refresh
            elif live is None and not s.once and now >= next_print:
                plain()
                next_print = now + s.every
    finally:
        if live is not None:
            live.update(render(state, state_time()), refresh=True)
            live.stop()
        else:
            plain()
    return 0


def feed(state: WatchState, topic: str, msg: Any, now: float) -> bool:
    """Hand one message of the monitoring topics to the state, received at `now`: the text of a std_msgs/String, or
    a diagnostic_msgs/DiagnosticArray (its statuses). Returns whether the topic is one the view reads."""
    handlers: dict[str, Callable[[Any], None]] = {
        topics.SCENARIO: state.on_scenario,
        topics.STEP: state.on_step,
        topics.GROUND_TRUTH: state.on_ground_truth,
        topics.EPISODE_METRICS: state.on_metrics,
    }
    if topic in handlers:
        handlers[topic](msg.data)
        return True
    if topic == topics.DIAGNOSTICS:
        statuses = [
            (st.name, _status_level(st.level), st.message, {kv.key: kv.value for kv in st.values}) for st in msg.status
        ]
        state.on_diagnostics(statuses, now)
        return True
    for name in state.agent_names:
        if topic == topics.belief(name):
            state.on_belief(name, msg.data)
            return True
    return False


def _status_level(raw: Any) -> int:
    """A DiagnosticStatus level (one byte in rclpy, an int in a recording)."""
    if isinstance(raw, bytes | bytearray):
        return raw[0] if raw else 0
    return int(raw)


def replay(bag: Path, settings: WatchSettings, signer: Signer, out: IO[str], speed: float = 1.0) -> int:
    """`htlm watch --replay`: the messages of a recording (`htlm launch --record`) fed to a WatchState in the order
    they were received, at `speed` times the pace they were recorded at (0: as fast as they are read), and drawn as
    the live view draws them (`show`); the view's time is the recording's. Returns 0 (after the last message, or
    `duration`)."""
    state = WatchState(settings.episode_in_batch, signer, settings.stale_after)
    stream = iter(messages(bag))
    pending = next(stream, None)
    first = pending.stamp_ns / 1e9 if pending is not None else 0.0
    started = time.monotonic()
    clock = [first]  # the recording's time the view has reached

    def pump(timeout: float) -> bool:
        nonlocal pending
        until = time.monotonic() + timeout
        while pending is not None:
            stamp = pending.stamp_ns / 1e9
            due = started + (stamp - first) / speed if speed > 0 else 0.0
            if due > until:
                time.sleep(max(0.0, until - time.monotonic()))
                clock[0] = first + (until - started) * speed
                return True
            time.sleep(max(0.0, due - time.monotonic()))
            feed(state, pending.topic, pending.msg, stamp)
            clock[0] = stamp
            pending = next(stream, None)
            if time.monotonic() >= until:
                return True
        return False

    return show(state, settings, out, pump, lambda: clock[0])
