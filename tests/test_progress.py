"""The progress display: plain lines when not on a terminal, a rich bar on one, rate and ETA from a fake clock."""

from __future__ import annotations

import io

import pytest

from htlm_agent import progress
from htlm_agent.progress import Progress, format_duration


class FakeClock:
    """time.perf_counter of the progress module, moved by hand."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Tty(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    c = FakeClock()
    monkeypatch.setattr(progress.time, "perf_counter", c)
    return c


def test_format_duration() -> None:
    assert format_duration(0) == "0:00"
    assert format_duration(75.4) == "1:15"
    assert format_duration(3600 + 62) == "1:01:02"
    assert format_duration(float("inf")) == "?"
    assert format_duration(float("nan")) == "?"


def test_rate_and_eta_count_only_what_is_done_from_the_start(clock: FakeClock) -> None:
    bar = Progress(100, initial=40, unit="ep", enabled=False)
    assert bar.rate == 0.0
    assert bar.eta == float("inf")
    clock.t += 10.0
    bar.update(60)
    assert bar.elapsed == pytest.approx(10.0)
    assert bar.rate == pytest.approx(2.0)  # 20 episodes in 10 s; the 40 of the resumed run do not count
    assert bar.eta == pytest.approx(20.0)  # 40 left at 2 per second
    line = bar.line()
    assert "60/100" in line and "60%" in line and "2.0 ep/s" in line
    assert "elapsed 0:10" in line and "ETA 0:20" in line


def test_plain_lines_every_log_interval_when_not_a_terminal(clock: FakeClock) -> None:
    out = io.StringIO()
    bar = Progress(10, unit="ep", stream=out, log_interval=5.0, width=10)
    for k in range(1, 11):
        clock.t += 1.0
        bar.update(k, completion=f"{k / 2:.2f}")
    bar.close()
    lines = out.getvalue().splitlines()
    # the first update, then one line at least 5 s after the previous one, and always the last
    assert [ln.split()[1] for ln in lines] == ["1/10", "6/10", "10/10"]
    assert lines[-1] == "[##########] 10/10 100% 1.0 ep/s elapsed 0:10 ETA 0:00 | completion 5.00"
    assert "\x1b" not in out.getvalue() and "\r" not in out.getvalue()


def test_disabled_prints_nothing(clock: FakeClock) -> None:
    out = io.StringIO()
    bar = Progress(3, stream=out, enabled=False, log_interval=0.0)
    for k in range(4):
        clock.t += 1.0
        bar.update(k)
    bar.close()
    assert out.getvalue() == ""
    assert bar.rate == pytest.approx(0.75)


def test_a_terminal_gets_a_rich_bar_with_rate_eta_and_fields(clock: FakeClock) -> None:
    out = Tty()
    bar = Progress(8, unit="run", stream=out, interval=0.0)
    for k in range(1, 9):
        clock.t += 2.0
        bar.update(k, last=f"config [{k}]")  # square brackets are shown as they are, not taken as markup
    bar.close()
    text = out.getvalue()
    assert "\x1b[" in text  # drawn in place with terminal control sequences
    assert "8/8 100% 0.50 run/s elapsed 0:16 ETA 0:00" in text
    assert "last config [8]" in text
    assert "━" in text  # rich's bar
