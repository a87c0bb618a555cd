"""How far each teammate's wall clock is from ours, without ROS (`ClockOffsets`), measured from the send times of
their broadcasts; a deployed team steps on its wall clocks, which must agree within `CLOCK_TOLERANCE` periods."""

from __future__ import annotations

from collections import deque

CLOCK_SAMPLES = 20
"""Broadcasts per teammate from which its clock offset is measured (the least of them)."""

CLOCK_TOLERANCE = 0.25
"""The clock offset between two agents tolerated under a deployed team's step clock, in periods."""


class ClockOffsets:
    """Per teammate, the arrival minus send time of its latest broadcasts on the two wall clocks: the delivery's
    latency plus how far our clock is ahead of its. The least of the last CLOCK_SAMPLES is the offset (latency on a
    local network is milliseconds, queueing only adds)."""

    def __init__(self) -> None:
        """No broadcast heard yet."""
        self.samples: dict[int, deque[float]] = {}

    def sample(self, k: int, seconds: float) -> None:
        """A broadcast of teammate k arrived `seconds` after its send time (on the two wall clocks)."""
        self.samples.setdefault(k, deque(maxlen=CLOCK_SAMPLES)).append(seconds)

    def offsets(self) -> dict[int, float]:
        """Per teammate heard, how far our wall clock is ahead of its (negative: behind), seconds; /diagnostics
        shows the opposite, `clock_offset/<teammate>`: how far the teammate's clock is ahead of ours."""
        return {k: min(q) for k, q in sorted(self.samples.items()) if q}

    def warning(self, names: list[str], period: float) -> str | None:
        """Which teammates (`names` by index) have clocks off ours by more than CLOCK_TOLERANCE periods of
        `period` seconds (docs/ros.md, Connecting your robots), or None."""
        limit = CLOCK_TOLERANCE * period
        far = {k: x for k, x in self.offsets().items() if abs(x) > limit}
        if not far:
            return None
        said = ", ".join(f"{names[k]} {-x:+.3f} s" for k, x in far.items())
        return f"teammates' clocks off ours by more than {limit:g} s (a quarter of the period): {said}"

    def values(self, names: list[str], period: float | None) -> dict[str, str]:
        """The offsets for the node's /diagnostics (teammates by `names`); the tolerance too when the team steps on
        its own clock of `period` seconds (None: it does not)."""
        offsets = self.offsets()
        if not offsets:
            return {}
        vals = {f"clock_offset/{names[k]}": f"{-x:+.3f}" for k, x in offsets.items()}
        vals["clock_offset_max"] = f"{max(abs(x) for x in offsets.values()):.3f}"
        if period is not None:
            vals["clock_tolerance"] = f"{CLOCK_TOLERANCE * period:g}"
        return vals
