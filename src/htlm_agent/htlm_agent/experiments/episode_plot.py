"""One episode of a run as a picture (`htlm show`): the true severity of every task over the steps as coloured bands,
and every agent's decision at every step as a line over them (the paper's behaviour figure, for any logged episode).

Reading and drawing are apart: `read_episode` finds the run's episode log and returns one episode (`LoggedEpisode`),
checked against the run's scenario; `decision_rows` says on which row of the picture each decision lies;
`episode_figure` draws a LoggedEpisode and nothing else, so what the picture shows is what the log holds.

The episode log is the world's: one JSON line per finished episode, {"run", "metrics": {"episode", "completion",
...}, "levels": (h+1, p) true levels, "actions": (h, N) applied actions, "observations": (h, N)}. The world node
writes it over ROS (RUN/world.jsonl of `htlm launch`; the evaluation that follows `htlm launch train` in
RUN/evaluate/), and `htlm evaluate` writes the same lines for its in-process episodes (OUT/world.jsonl; `htlm train`
in RUN/eval/).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from htlm_agent.experiments.recording import episode_log, records
from htlm_msgs_py.topics import SCENARIO
from htlm_world.metrics import completion_step
from htlm_world.scenario import Scenario, ScenarioError, ScenarioRecordError, builtin, from_record, load
from htlm_world.travel import TravelState
from htlm_world.types import FloatArray, IntArray

if TYPE_CHECKING:
    from matplotlib.figure import Figure

LOG_NAME = "world.jsonl"
"""File name of an episode log."""

EVALUATION_DIRS = ("evaluate", "eval")
"""Folders of a run that hold the evaluation of its trained team: `htlm launch train` (evaluate/, over ROS) and
`htlm train` (eval/, in process). A run directory's evaluation is shown before its training episodes, which explore."""

AGENT_STYLES = (
    ("#1f4e9c", "o"),
    ("#2a9d3a", "s"),
    ("#7b3fa0", "^"),
    ("#111111", "D"),
    ("#0fa3b1", "v"),
    ("#8c564b", "P"),
    ("#e377c2", "X"),
    ("#7f7f7f", "*"),
)
"""Colour and marker of agent i (cycled): dark or cool colours that stand out on the yellow-to-red bands."""


class EpisodeLogError(ValueError):
    """An episode log that cannot be found or read, or an episode it does not hold (the message says which)."""


@dataclass(frozen=True)
class LoggedEpisode:
    """One episode as its log records it."""

    source: Path
    """The episode log the episode was read from."""
    line: int
    """Its line in the log (1-based)."""
    run: str
    """Run identifier recorded with the episode."""
    episode: int
    """Episode index."""
    scenario: Scenario
    """The scenario of the run (names of the tasks, idle locations and agents; levels)."""
    scenario_source: str
    """Where the scenario came from (a file, or the built-in scenario with a team)."""
    levels: IntArray  # (t+1, p) true levels, levels[0] the initial ones; -1: not reported (external operation)
    actions: IntArray  # (t, N) applied actions (index in G-bar; -1: none, HT mode)
    metrics: dict[str, Any]
    """The metrics recorded with the episode (completion, failed, ...)."""
    events: tuple[tuple[int, str], ...] = ()
    """(step, label) of every scenario event that happened in the episode."""


def find_log(path: str | Path) -> Path:
    """The episode log of a run: `path` itself when it is a file, else the log of the run's evaluation
    (`EVALUATION_DIRS`), else path/world.jsonl.

    Raises:
        EpisodeLogError: the path does not exist or holds no log (the message lists the files looked for).
    """
    p = Path(path)
    if p.is_file():
        return p
    if not p.exists():
        raise EpisodeLogError(f"{str(p)!r}: no such run directory or episode log")
    if not p.is_dir():
        raise EpisodeLogError(f"{str(p)!r}: neither a run directory nor an episode log file")
    tried = [p / d / LOG_NAME for d in EVALUATION_DIRS] + [p / LOG_NAME]
    for f in tried:
        if f.is_file():
            return f
    raise EpisodeLogError(
        f"{str(p)!r} holds no episode log: looked for {', '.join(str(f) for f in tried)} (written by `htlm launch` "
        "and by `htlm evaluate`)"
    )


def _world_parameters(f: Path) -> dict[str, Any]:
    """The parameters of a ROS 2 parameters file written by the launcher ({"/**": {"ros__parameters": {...}}})."""
    data = yaml.safe_load(f.read_text())
    node = data.get("/**", {}) if isinstance(data, dict) else {}
    params = node.get("ros__parameters", {}) if isinstance(node, dict) else {}
    return params if isinstance(params, dict) else {}


def find_scenario(log: Path) -> tuple[Scenario, str]:
    """The scenario of the run that wrote `log`, from the log's folder or its parent: scenario.yaml (written by
    `htlm evaluate` and `htlm train`), else the world's parameters (parameters/world.yaml of `htlm launch`: its
    scenario file, or the built-in scenario with its team). Returns the scenario and where it came from.

    Raises:
        EpisodeLogError: no scenario found, or an invalid one.
    """
    tried: list[Path] = []
    try:
        for d in (log.parent, log.parent.parent):
            f = d / "scenario.yaml"
            tried.append(f)
            if f.is_file():
                return load(f), str(f)
            f = d / "parameters" / "world.yaml"
            tried.append(f)
            if f.is_file():
                params = _world_parameters(f)
                if params.get("scenario"):
                    return load(params["scenario"]), f"{params['scenario']} (named by {f})"
                team = params.get("team", "heterogeneous")
                return builtin(team), f"the built-in scenario, team {team} ({f})"
    except (ScenarioError, OSError, yaml.YAMLError) as e:
        raise EpisodeLogError(f"the scenario of {log}: {e}") from None
    raise EpisodeLogError(f"no scenario for {log}: looked for {', '.join(str(f) for f in tried)}")


def _episode_of(record: Any) -> int:
    """The episode index of a parsed log line; ValueError naming what is wrong."""
    if not isinstance(record, dict) or not isinstance(record.get("metrics"), dict):
        raise ValueError("not an episode record (expected an object with 'metrics')")
    e = record["metrics"].get("episode")
    if not isinstance(e, int) or isinstance(e, bool) or e < 0:
        raise ValueError(f"metrics.episode {e!r} is not an episode index")
    return e


def _ranges(xs: list[int]) -> str:
    """0-4, 7, 9-10: a sorted list of indices, compressed."""
    out: list[str] = []
    xs = sorted(set(xs))
    i = 0
    while i < len(xs):
        j = i
        while j + 1 < len(xs) and xs[j + 1] == xs[j] + 1:
            j += 1
        out.append(str(xs[i]) if i == j else f"{xs[i]}-{xs[j]}")
        i = j + 1
    return ", ".join(out)


def _table(
    record: dict[str, Any], key: str, width: int, lo: int, hi: int, where: str, unknown_rows: bool = False
) -> IntArray:
    """record[key] as an int array (rows, width) of values in lo..hi; with `unknown_rows`, a row may be null (not
    reported: an external operation's levels) and reads as -1. EpisodeLogError naming the bad value."""
    rows = record.get(key)
    unknown = [-1] * width
    if isinstance(rows, list) and unknown_rows:
        rows = [unknown if r is None else r for r in rows]
    if not isinstance(rows, list) or not all(
        isinstance(r, list) and len(r) == width and all(isinstance(v, int) and not isinstance(v, bool) for v in r)
        for r in rows
    ):
        raise EpisodeLogError(f"{where}: {key!r} is not a list of rows of {width} integers")
    arr = np.array(rows, dtype=np.int64).reshape(len(rows), width)
    bad = ((arr < lo) | (arr > hi)) & ~((arr == -1).all(axis=1, keepdims=True) & unknown_rows)
    if bad.any():
        t, k = (int(x) for x in np.argwhere(bad)[0])
        raise EpisodeLogError(f"{where}: {key}[{t}][{k}] = {int(arr[t, k])} is outside {lo}..{hi}")
    return arr


def read_episode(path: str | Path, episode: int) -> LoggedEpisode:
    """Episode `episode` of the run at `path` (a run directory or an episode log, `find_log`), checked against the
    run's scenario (`find_scenario`).

    Raises:
        EpisodeLogError: no log, a malformed line (file:line), no such episode (the message lists those the log
            holds), or an episode that does not fit the scenario.
    """
    if (Path(path) / "metadata.yaml").is_file():  # a recording (`htlm launch --record`: RUN/recording)
        return _recorded_episode(Path(path), episode)
    log = find_log(path)
    seen: list[int] = []
    found: tuple[int, dict[str, Any]] | None = None
    with log.open() as f:
        for n, text in enumerate(f, start=1):
            if not text.strip():
                continue
            try:
                record = json.loads(text)
                e = _episode_of(record)
            except ValueError as err:  # json.JSONDecodeError is a ValueError
                raise EpisodeLogError(f"{log}:{n}: malformed episode record: {err}") from None
            if e == episode:
                found = (n, record)
                break
            seen.append(e)
    if found is None:
        held = f"it holds episodes {_ranges(seen)}" if seen else "it holds no episode"
        raise EpisodeLogError(f"episode {episode!r} is not in {log}: {held}")
    n, record = found
    sc, sc_source = find_scenario(log)
    return _logged_episode(record, log, n, f"{log}:{n}", sc, sc_source)


def _recorded_episode(bag: Path, episode: int) -> LoggedEpisode:
    """Episode `episode` of a recording, from its episode log rebuilt (`recording.episode_log`) and the scenario of
    its run announcement."""
    try:
        announced = records(bag, SCENARIO)
        lines = episode_log(bag)
        sc = from_record(announced[0]) if announced else None
    except (OSError, ValueError, ScenarioRecordError) as e:
        raise EpisodeLogError(f"{bag}: not a readable recording: {e}") from None
    if sc is None:
        raise EpisodeLogError(f"{bag}: the recording holds no run announcement (/htlm/scenario)")
    for n, record in enumerate(lines, start=1):
        if record["metrics"]["episode"] == episode:
            return _logged_episode(record, bag, n, f"{bag} (recorded episode {episode})", sc, f"{bag} (/htlm/scenario)")
    held = _ranges([r["metrics"]["episode"] for r in lines])
    raise EpisodeLogError(f"episode {episode!r} is not in {bag}: it holds episodes {held or 'none'}")


def _logged_episode(
    record: dict[str, Any], source: Path, n: int, where: str, sc: Scenario, sc_source: str
) -> LoggedEpisode:
    """One episode record checked against its scenario."""
    log = source
    levels = _table(record, "levels", sc.n_tasks, 0, sc.levels - 1, where, unknown_rows=True)
    actions = _table(record, "actions", sc.n_agents, -1, sc.n_actions - 1, where)
    if levels.shape[0] != actions.shape[0] + 1 or actions.shape[0] == 0:
        raise EpisodeLogError(
            f"{where}: {levels.shape[0]} rows of levels for {actions.shape[0]} steps of actions (expected steps + 1, "
            "at least one step)"
        )
    events = record.get("events", [])
    if not isinstance(events, list) or not all(
        isinstance(e, list) and len(e) == 2 and isinstance(e[0], int) and isinstance(e[1], str) for e in events
    ):
        raise EpisodeLogError(f"{where}: events: {events!r} is not a list of [step, label]")
    return LoggedEpisode(
        source=log,
        line=n,
        run=str(record.get("run", "")),
        episode=int(record["metrics"]["episode"]),
        scenario=sc,
        scenario_source=sc_source,
        levels=levels,
        actions=actions,
        metrics=dict(record["metrics"]),
        events=tuple((int(t), str(label)) for t, label in events),
    )


def run_label(ep: LoggedEpisode) -> str:
    """The run in the picture's title: the log's folder and its parent (RUN/eval, RUN/evaluate, runs/OUT), and the
    run identifier the log records when it is not the folder's name."""
    folder = ep.source.resolve().parent
    label = "/".join(folder.parts[-2:])
    return label if ep.run in ("", folder.name) else f"{label} (run {ep.run})"


def decision_rows(ep: LoggedEpisode) -> FloatArray:
    """The row of the picture of every decision (t, N): task j on row j, idle at site s on row p + s (the idle
    rows follow the task rows, as in G-bar), no action (-1, HT mode) NaN (a gap in the agent's line)."""
    rows = ep.actions.astype(np.float64)
    rows[ep.actions < 0] = np.nan
    return rows


def on_the_way(ep: LoggedEpisode) -> np.ndarray:
    """(t, N) whether each agent was on its way at each step, working on nothing (docs/model.md, Travel): the drives
    of the logged assignments replayed; all False without travel."""
    if not ep.scenario.travel:
        return np.zeros(ep.actions.shape, dtype=bool)
    state = TravelState(ep.scenario, 1)
    return np.array([~state.step(a[None])[0] for a in ep.actions], dtype=bool).reshape(ep.actions.shape)


def shown_steps(ep: LoggedEpisode, all_steps: bool = False) -> int:
    """How many steps the picture shows: every logged step with `all_steps` or after a failure, else up to three steps
    after completion (the rest repeats the finished state)."""
    t = int(ep.actions.shape[0])
    comp, failed = completion_step(ep.levels[:, None, :])
    if all_steps or bool(failed[0]):
        return t
    return min(t, int(comp[0]) + 3)


def episode_figure(ep: LoggedEpisode, all_steps: bool = False) -> Figure:
    """The picture of one episode: one band per task (its true level at every step, colour), one grey band per idle
    location, and every agent's decision of every step as a line (step t's decision, applied between the levels at
    t-1 and t, spans t-1..t); completion (or failure) marked.

    Args:
        ep: the episode (`read_episode`).
        all_steps: show every logged step, not only up to three steps after completion.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patheffects as pe
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap

    sc = ep.scenario
    p, q, n, nl = sc.n_tasks, sc.n_idle, sc.n_agents, sc.levels
    steps = shown_steps(ep, all_steps)
    comp, failed = completion_step(ep.levels[:, None, :])
    completion, did_fail = int(comp[0]), bool(failed[0])
    rows = decision_rows(ep)[:steps]  # (steps, N)
    driving = on_the_way(ep)[:steps]  # (steps, N)
    names = sc.action_names

    legend_rows = -(-n // 3) if n > 5 else 0
    fig, ax = plt.subplots(
        figsize=(min(16.0, max(8.0, 0.42 * steps + 4.0)), 1.0 + 0.62 * (p + q) + 1.1 + 0.25 * legend_rows)
    )
    # grey ("bad"): a level nobody reported (external operation)
    cmap = ListedColormap(plt.get_cmap("YlOrRd")(np.linspace(0.06, 0.92, nl))).with_extremes(bad="0.72")
    norm = BoundaryNorm(np.arange(nl + 1) - 0.5, nl)
    shown = np.ma.masked_less(ep.levels[: steps + 1].T, 0)  # (p, steps+1)
    x_edges = np.arange(steps + 2) - 0.5
    mesh = ax.pcolormesh(x_edges, np.arange(p + 1) - 0.5, shown, cmap=cmap, norm=norm, edgecolors="white", lw=0.6)
    for s in range(q):
        ax.axhspan(p + s - 0.5, p + s + 0.5, color="0.93", lw=0)
    if q:
        ax.axhline(p - 0.5, color="0.45", lw=1.0)
    spread = 0.56 / max(n - 1, 1) if n > 1 else 0.0
    x_line = np.arange(steps + 1)
    caps = sc.capability_table()
    for i, agent in enumerate(sc.agents):
        colour, marker = AGENT_STYLES[i % len(AGENT_STYLES)]
        y = rows[:, i] + (i - (n - 1) / 2) * spread
        ax.step(
            x_line,
            np.append(y, y[-1]),
            where="post",
            color=colour,
            lw=2.0,
            alpha=0.9,
            path_effects=[pe.Stroke(linewidth=3.6, foreground="white", alpha=0.8), pe.Normal()],
        )
        ax.plot(
            x_line[:-1] + 0.5,
            np.where(driving[:, i], np.nan, y),
            ls="none",
            marker=marker,
            ms=6,
            color=colour,
            mec="white",
            mew=0.8,
            label=f"{agent.name} ({', '.join(f'{k.name} {c}' for k, c in zip(sc.kinds, caps[i], strict=True) if c)})",
        )
        if driving[:, i].any():  # on its way: a hollow marker, it works on nothing
            ax.plot(
                x_line[:-1] + 0.5, np.where(driving[:, i], y, np.nan), ls="none", marker=marker, ms=6, mfc="white",
                mec=colour, mew=1.4,
            )  # fmt: skip
    mark = ep.actions.shape[0] if did_fail else completion  # the horizon of a failure, else the completion step
    if mark <= steps:
        text = f"horizon: not complete after {mark} steps" if did_fail else f"complete at step {mark}"
        ax.axvline(mark + 0.5, color="#b00020", ls="-" if did_fail else "--", lw=1.5)
        ax.text(
            mark + 0.5 + (-0.12 if did_fail else 0.12),
            (p - 1) / 2,
            text,
            rotation=90,
            ha="right" if did_fail else "left",
            va="center",
            color="#b00020",
            fontsize=9,
            fontweight="bold",
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "none", "alpha": 0.75},
        )
    for t, label in ep.events:  # an event of step t happens before its transition: between columns t-1 and t
        if t <= steps:
            ax.axvline(t - 0.5, color="#6a1b9a", ls=":", lw=1.8)
            ax.text(
                t - 0.45,
                -0.45,
                label,
                rotation=90,
                ha="left",
                va="top",
                color="#6a1b9a",
                fontsize=8,
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75},
            )
    ax.set_yticks(range(p + q), list(names[: p + q]))
    ax.set_ylim(p + q - 0.5, -0.5)
    ax.set_xlim(-0.5, steps + 0.5)
    ax.set_xticks(range(0, steps + 1, 1 if steps <= 30 else 5))
    hidden = ep.actions.shape[0] - steps
    ax.set_xlabel(
        "step (bands: true level after the step; lines: each agent's decision applied in the step)"
        + (f"; steps {steps + 1}-{ep.actions.shape[0]} not shown (nothing left to do)" if hidden else "")
        + ("; grey: level not reported" if np.ma.is_masked(shown) else "")
        + ("; hollow marker: on its way, working on nothing" if driving.any() else ""),
        fontsize=8.5,
    )
    outcome = f"complete at step {completion}"
    if sc.travel:
        outcome += f" ({completion * sc.step_seconds:g} s)"
    if did_fail:
        outcome = f"failed (tasks at levels {ep.levels[-1].tolist()} at the end)"
    ax.set_title(f"{run_label(ep)} · episode {ep.episode} · {sc.team} team · {outcome}", fontsize=10, pad=22)
    bar = fig.colorbar(mesh, ax=ax, ticks=range(nl), pad=0.015, fraction=0.04)
    bar.set_label("true severity level", fontsize=9)
    bar.ax.set_yticklabels([f"{k} (done)" if k == 0 else str(k) for k in range(nl)], fontsize=8)
    below = n > 5  # a large team's legend goes under the steps, in rows of three, clear of the title
    ax.legend(
        loc="upper center" if below else "lower center",
        bbox_to_anchor=(0.5, -0.09) if below else (0.5, 1.0),
        ncol=3 if below else n,
        fontsize=8,
        frameon=False,
        handletextpad=0.2,
        columnspacing=1.2,
    )
    fig.tight_layout()
    return fig


def save_episode_figure(ep: LoggedEpisode, out: str | Path, all_steps: bool = False) -> Path:
    """Draw `episode_figure(ep)` into the PNG file `out` (its folder created); returns the path."""
    import matplotlib.pyplot as plt

    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = episode_figure(ep, all_steps)
    try:
        fig.savefig(path, dpi=110, metadata={"Software": None})
    finally:
        plt.close(fig)
    return path
