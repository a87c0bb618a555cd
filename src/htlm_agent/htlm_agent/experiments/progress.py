"""A small progress display on stderr with rate and ETA, no dependency.

On a terminal it redraws one line (``\\r``) at most every `interval` seconds; elsewhere (logs, pipes, CI) it prints a
plain line every `log_interval` seconds, so captured output stays short.
"""

from __future__ import annotations

import sys
import time
from typing import IO


def format_duration(seconds: float) -> str:
    """Seconds as m:ss or h:mm:ss."""
    if seconds != seconds or seconds == float("inf"):  # NaN or infinite
        return "?"
    s = round(seconds)
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


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
        self._drawn = False

    @property
    def elapsed(self) -> float:
        """Seconds since start."""
        return time.perf_counter() - self.t0

    @property
    def rate(self) -> float:
        """Units per second since start."""
        el = self.elapsed
        return (self.done - self.initial) / el if el > 0 else 0.0

    @property
    def eta(self) -> float:
        """Estimated seconds left."""
        r = self.rate
        return (self.total - self.done) / r if r > 0 else float("inf")

    def line(self) -> str:
        """The current status line."""
        frac = min(self.done / self.total, 1.0)
        fill = round(frac * self.width)
        bar = "#" * fill + "-" * (self.width - fill)
        extra = " ".join(f"{k} {v}" for k, v in self.fields.items())
        return (
            f"[{bar}] {self.done}/{self.total} {frac:4.0%} {self.rate:.0f} {self.unit}/s "
            f"elapsed {format_duration(self.elapsed)} ETA {format_duration(self.eta)}"
            + (f" | {extra}" if extra else "")
        )

    def update(self, done: int, **fields: object) -> None:
        """Record progress `done` (absolute) and the fields to show, redrawing when due."""
        self.done = done
        self.fields.update({k: str(v) for k, v in fields.items()})
        now = time.perf_counter()
        if self.enabled and (now - self.last_draw >= self.interval or done >= self.total):
            self.last_draw = now
            self._draw()

    def _draw(self) -> None:
        if self.tty:
            self.stream.write("\r" + self.line() + "\x1b[K")
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """Finish the line."""
        if self.enabled and self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
