"""The progress display of long jobs (`htlm train`, `htlm reproduce`, `htlm launch`): rate, ETA and a few fields.

On a terminal it is a rich progress bar, redrawn in place at most every `interval` seconds (whatever else the job
prints goes above it); elsewhere (logs, pipes, CI) it writes the plain `line()` every `log_interval` seconds, so
captured output stays short and greppable. The rate and the ETA are measured here, the same in both cases.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from typing import IO

from rich.console import Console, RenderableType
from rich.progress import BarColumn, TaskID, TextColumn
from rich.progress import Progress as RichProgress
from rich.text import Text


def format_duration(seconds: float) -> str:
    """Seconds as m:ss or h:mm:ss ("?" when unknown: NaN or infinite)."""
    if seconds != seconds or seconds == float("inf"):  # NaN or infinite
        return "?"
    s = round(seconds)
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


class _Bar(RichProgress):
    """A rich progress bar with the job's fields on a line of their own below it (they may be long)."""

    extra = ""

    def get_renderables(self) -> Iterable[RenderableType]:
        """The bar's line, then the fields."""
        yield self.make_tasks_table(self.tasks)
        if self.extra:
            yield Text(self.extra, style="dim")


class Progress:
    """Progress of a counted job: `update(done, **fields)` after every chunk, `close()` at the end."""

    def __init__(
        self,
        total: int,
        initial: int = 0,
        unit: str = "it",
        enabled: bool = True,
        stream: IO[str] | None = None,
        interval: float = 0.2,
        log_interval: float = 10.0,
        width: int = 24,
    ) -> None:
        """Start timing now.

        Args:
            total: count at completion.
            initial: count already done (a resumed job); the rate counts only what is done from here.
            unit: unit name shown after the rate.
            enabled: False shows nothing (but still measures the rate).
            stream: where to write (stderr by default).
            interval: seconds between redraws on a terminal.
            log_interval: seconds between lines when not on a terminal.
            width: characters of the bar.
        """
        self.total, self.initial, self.done = max(total, 1), initial, initial
        self.unit, self.enabled, self.width = unit, enabled, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if self.tty else log_interval
        self.t0 = time.perf_counter()
        self.last_draw = -1e9
        self.fields: dict[str, str] = {}
        self._bar: _Bar | None = None
        self._task = TaskID(0)

    @property
    def elapsed(self) -> float:
        """Seconds since start."""
        return time.perf_counter() - self.t0

    @property
    def rate(self) -> float:
        """Units per second since start (only what was done since start counts)."""
        el = self.elapsed
        return (self.done - self.initial) / el if el > 0 else 0.0

    @property
    def eta(self) -> float:
        """Estimated seconds left at the current rate (infinite before any progress)."""
        r = self.rate
        return (self.total - self.done) / r if r > 0 else float("inf")

    def _stats(self) -> str:
        r = self.rate
        rate = f"{r:.0f}" if r >= 10 else f"{r:.1f}" if r >= 1 else f"{r:.2f}"  # two digits at least
        return (
            f"{self.done}/{self.total} {min(self.done / self.total, 1.0):4.0%} {rate} {self.unit}/s "
            f"elapsed {format_duration(self.elapsed)} ETA {format_duration(self.eta)}"
        )

    def _extra(self) -> str:
        return " ".join(f"{k} {v}" for k, v in self.fields.items())

    def line(self) -> str:
        """The current status as one plain line (what is logged when not on a terminal)."""
        fill = round(min(self.done / self.total, 1.0) * self.width)
        bar = "#" * fill + "-" * (self.width - fill)
        extra = self._extra()
        return f"[{bar}] {self._stats()}" + (f" | {extra}" if extra else "")

    def update(self, done: int, **fields: object) -> None:
        """Record progress `done` (absolute) and the fields to show, redrawing when due."""
        self.done = done
        self.fields.update({k: str(v) for k, v in fields.items()})
        now = time.perf_counter()
        if self.enabled and (now - self.last_draw >= self.interval or done >= self.total):
            self.last_draw = now
            self._draw()

    def _draw(self) -> None:
        if not self.tty:
            self.stream.write(self.line() + "\n")
            self.stream.flush()
            return
        if self._bar is None:
            console = Console(file=self.stream, force_terminal=True)
            self._bar = _Bar(
                BarColumn(bar_width=self.width),
                TextColumn("{task.fields[stats]}", markup=False),
                console=console,
                auto_refresh=False,  # redrawn here, every `interval` at most: no thread
            )
            self._task = self._bar.add_task("", total=self.total, stats="")
        self._bar.extra = self._extra()  # plain text: fields may hold "[...]"
        self._bar.update(self._task, completed=min(self.done, self.total), stats=self._stats())
        if not self._bar.live.is_started:
            self._bar.start()  # draws
        else:
            self._bar.refresh()

    def close(self) -> None:
        """Finish the display (the bar stays on screen with its last values)."""
        if self._bar is not None:
            self._draw()
            self._bar.stop()
            self._bar = None
