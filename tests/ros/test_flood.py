"""Flooding, with real processes over real DDS: a stranger publishing records that its receivers reject (cut JSON,
unknown schema, wrong version, a value out of range, bytes that are not UTF-8) on /htlm/action, the topic every step
of the lockstep waits on, while a team runs. The lockstep is timed per batch without and with the flood in one run (a
ratio, never a time).

- At 2,000 records/s, a flood the world reads as it comes: the lockstep slows by at most 2x where the machine has
  CPU to spare (0.95x measured; beside two CPU hogs on two cores 2.0x, printed then, not bounded) and loses no step
  (every episode equals the in-process one, no agent absent), the world's /diagnostics counts every record sent, by
  reason (where the machine has CPU to spare; beside two CPU hogs the world reads slower than the flood comes, its
  queue overflows and what DDS drops goes uncounted: the count is then bounded by what was sent, and printed), and its
  warning about them is rate-limited (one every 5 s at most).
- As fast as one Python process can publish (about 35,000 records/s here): every node stays up, the rejections it
  read are counted, the warning is rate-limited and the team finishes its run once the flood stops; the slowdown is
  printed, not bounded. On this 2-core machine such a flood stops the lockstep while it lasts: a receiving rclpy
  process spends about 45 us of CPU per record in DDS and the executor before any HTLM code runs (HTLM's validation
  and counting add about 12 us), the flooder about 30 us per record sent, so the flood asks more CPU of the
  receiving host than the machine has (docs/ros.md, Flooding, with the measured curve).

Slow (each run floods several batches)."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_msgs_py import qos, topics
from htlm_world.scenario import builtin
from support.ros import in_process, read_json

pytestmark = [pytest.mark.ros, pytest.mark.timeout(400), pytest.mark.slow]

B = 8
QUIET = 5
"""Batches timed without the flood (after the first, which holds the start-up)."""


@dataclass
class Flood:
    """What one flooded run measured."""

    sent: dict[str, Any]
    """The flooder's count: sent, seconds, rate."""
    rejected: dict[str, int]
    """The world's rejected/action/<reason> counters at the end."""
    warnings: int
    """The world's warnings about rejected action records."""
    flood_seconds: float
    slowdown: float
    """Mean batch duration flooded / not flooded."""
    foreign: float
    """The share of the machine's CPU that other processes than the test's took while the batches without the
    flood ran."""
    flood_foreign: float
    """The same share while the flood ran (from the go to the flooder's end)."""

    @property
    def alone(self) -> bool:
        """The team had the machine to itself, flooded and not (see FOREIGN)."""
        return _alone(self.foreign, self.flood_foreign)

    progress: float
    """Batches finished while flooded / the batches the same time holds unflooded."""
    expected: float
    """The batches the time of the flood holds unflooded."""
    absent: int
    """Agent-steps the world counted absent, over the run."""
    episodes: list[dict[str, Any]]
    """world.jsonl's episodes."""
    seed: int


FOREIGN = 0.1
"""Largest share of the machine's CPU that processes other than the test's may take, unflooded and flooded, for the 2x
bound and the exact count to be asserted (measured: 0-3 % alone; beside two CPU hogs 9-19 % unflooded, which the
scheduler mostly keeps off while the whole team runs, but 42-45 % flooded)."""


def _alone(*shares: float) -> bool:
    return max(shares) <= FOREIGN


def _cpu(pids: list[int]) -> tuple[int, int, int]:
    """CPU jiffies so far: of these processes (with their children they reaped: the flooder of a timed flood ends
    and is reaped by pytest before the flooded share is read), busy on the whole machine, and all of the machine
    (/proc; zeros where there is none)."""
    try:
        f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return 0, 0, 0
    ours = 0
    for pid in pids:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            ours += sum(int(x) for x in stat[11:15])  # utime, stime, cutime, cstime
        except (OSError, ValueError, IndexError):
            pass
    return ours, sum(f) - f[3] - f[4], sum(f)


def _foreign_share(a: tuple[int, int, int], b: tuple[int, int, int]) -> float:
    """The share of the machine's CPU that processes other than ours used between two `_cpu()` readings (0 where
    unknown)."""
    ours, busy, total = (y - x for x, y in zip(a, b, strict=True))
    return max(0, busy - ours) / total if total > 0 else 0.0


OPEN = 100_000
"""Episodes of a flooded run until the test gives it its end (the world's `episodes`, tunable while running)."""


def run_flood(ros_team: Any, flood_args: list[str], flooded: int, every: bool = False) -> Flood:
    """A greedy evaluate team of batches of B: 1 + QUIET + 1 + `flooded` batches, then the flood ends (SIGTERM) and
    the run goes on until the world has read what the flood left queued (every record the flooder sent counted when
    `every`, else its count standing still for a second); then it ends after one more batch. The flood starts once the
    quiet batches are done; the batches in progress when it reaches the world and when it ends are not timed."""
    seed, batches = 11, 1 + QUIET + 1 + flooded + 1
    team = ros_team(policy="greedy", seed=seed, episodes=OPEN, batch=B, world_params={"diagnostics_period": 0.2})
    here = team.tmp / team.cfg.run_dir.name  # one directory per team of the test (bench_flood.py runs several)
    here.mkdir(exist_ok=True)
    diag = here / "diag.json"
    team.helper("diag", "--out", str(diag))
    go, out = here / "flood.go", here / "flood.json"
    flooder = team.helper("flood", "--out", str(out), "--topic", topics.ACTION, "--go", str(go), *flood_args)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= B, 90, "the first batch")
    pids = [os.getpid()] + [p.popen.pid for p in team.procs.values()] + [h.pid for h in team.helpers]  # the test's
    cpu_at = _cpu(pids)
    team.wait_for(lambda: len(team.world_episodes()) >= (1 + QUIET) * B, 90, "the batches without the flood")
    foreign = _foreign_share(cpu_at, _cpu(pids))
    go.touch()
    flood_cpu_at = _cpu(pids)

    def reached() -> bool:  # the world counted a rejected action record: the flood is on (the flooder takes a
        # second or more to start, and an unflooded batch timed as flooded would hide the slowdown)
        got = read_json(diag) if diag.exists() else {}
        return any(k.startswith("rejected/action/") and int(v) > 0 for k, v in got.get("htlm: world", {}).items())

    team.wait_for(reached, 60, "the flood to reach the world (rejected/action/* on its /diagnostics)")
    flood_from = len(team.world_episodes()) // B + 1  # the first batch that starts flooded
    flood_at = time.monotonic()
    at_go = len(team.world_episodes())
    team.wait_for(lambda: len(team.world_episodes()) >= (batches - 1) * B or flooder.poll() is not None, 300, "flood")
    during = len(team.world_episodes()) - at_go  # episodes the lockstep finished while flooded
    during_seconds = time.monotonic() - flood_at
    team.wait_for(lambda: len(team.world_episodes()) >= (batches - 1) * B, 300, "the flooded batches")
    # while flooded the world is one busy reader beside the flooder: other processes can take enough to starve it
    # although they took little while the whole team ran (the fair scheduler gives each runnable process its part;
    # soak, 2026-11-27: 14 of 17,870 records dropped with two hogs, after an unflooded share within FOREIGN)
    flood_foreign = _foreign_share(flood_cpu_at, _cpu(pids))  # (a reaped flooder counts: _cpu)
    flooder.send_signal(signal.SIGTERM)
    flooder.wait(timeout=10)
    flood_seconds = time.monotonic() - flood_at
    sent = read_json(out)

    def counted() -> int:
        got = read_json(diag) if diag.exists() else {}
        return sum(int(v) for k, v in got.get("htlm: world", {}).items() if k.startswith("rejected/action/"))

    if every and _alone(foreign, flood_foreign):  # the run goes on until the world has read the last record
        # sent (it may still be on its way); on a machine shared with other processes the world's intake can fall
        # below the flood's rate, its queue then overflows and DDS drops the oldest records uncounted (see the test),
        # so the count stops short
        team.wait_for(lambda: counted() >= sent["sent"], 60, f"the world to count the {sent['sent']} records sent")
    else:
        seen = [counted(), time.monotonic()]

        def still() -> bool:
            now = counted()
            if now != seen[0]:
                seen[:] = [now, time.monotonic()]
            return time.monotonic() - seen[1] >= 1.0

        team.wait_for(still, 60, "the world's count of rejected records to stand still (the flood's queue read)")
    end = team.tmp / f"{team.cfg.run_dir.name}-end.json"
    ends = len(team.world_episodes()) + B
    setp = team.helper("setparam", "--out", str(end), "--name", "episodes", "--value", str(ends))
    assert setp.wait(timeout=30) == 0 and read_json(end)["successful"], f"the world took no end: {read_json(end)}"
    assert team.wait("world", 60) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    time.sleep(0.6)  # the diag listener hears the world's last status
    team.helpers[0].send_signal(signal.SIGTERM)
    team.helpers[0].wait(timeout=10)

    team.cleanup()  # nothing of this team left running when the next one starts (bench_flood.py runs several)
    eps = team.world_episodes()
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(len(eps))) and len(eps) >= batches * B
    seconds = {w["metrics"]["episode"] // B: w["metrics"]["seconds"] for w in eps}  # one duration per batch
    quiet = [seconds[b] for b in range(1, 1 + QUIET)]
    flood = [seconds[b] for b in range(flood_from, batches - 1)]
    assert flood, f"no batch started and ended under the flood (flooded from batch {flood_from}): {seconds}"
    world = json.loads(diag.read_text())["htlm: world"]
    result = Flood(
        sent=sent,
        rejected={k: int(v) for k, v in world.items() if k.startswith("rejected/action/")},
        warnings=len(re.findall(r"rejected a record on action", team.log("world"))),
        flood_seconds=flood_seconds,
        slowdown=(sum(flood) / len(flood)) / (sum(quiet) / len(quiet)),
        foreign=foreign,
        flood_foreign=flood_foreign,
        progress=during / B / (during_seconds / (sum(quiet) / len(quiet))),
        expected=during_seconds / (sum(quiet) / len(quiet)),
        absent=sum(sum(w["metrics"]["absent"]) for w in eps),
        episodes=eps,
        seed=seed,
    )
    steps_per_s = [round(B * 30 / x) for x in (sum(quiet) / len(quiet), sum(flood) / len(flood))]
    print(
        f"flood: {sent['sent']} records in {sent['seconds']:.1f} s ({sent['rate']}/s) on {topics.ACTION}; world "
        f"rejected {sum(result.rejected.values())} {result.rejected}; {result.warnings} warnings in "
        f"{flood_seconds:.1f} s; episode-steps/s without/with {steps_per_s}; slowdown {result.slowdown:.2f}x "
        f"(CPU taken by other processes meanwhile {result.foreign:.0%}, while flooded {result.flood_foreign:.0%}); "
        f"progress while flooded {result.progress:.0%} of unflooded; "
        f"absent agent-steps {result.absent}"
    )
    assert sent["matched"] >= 1, sent
    # one warning about the rejections every 5 s at most
    assert 1 <= result.warnings <= flood_seconds / 5 + 2, (result.warnings, flood_seconds)
    reasons = ("json", "schema", "version", "range", "encoding")
    assert set(result.rejected) == {f"rejected/action/{r}" for r in reasons}, world
    return result


def test_a_flood_the_world_reads_as_it_comes_slows_the_lockstep_at_most_2x_and_loses_no_step(ros_team: Any) -> None:
    # the flood lasts as long as the flooded batches, which the lockstep's pace decides (four batches of 8 took 0.9 s
    # here, and a 2,000-record floor failed): 12 batches, some 2-3 s, and a floor that only says a flood happened
    f = run_flood(ros_team, ["--rate", "2000"], flooded=12, every=True)
    # every record sent reached the world and was counted, under its reason (the flooder cycles the five), where the
    # team had the machine to itself. Beside two CPU hogs the world's intake fell below 2,000 records/s: its reader's
    # queue (EVENTS, depth 1000) overflowed and DDS replaced the oldest records unread, and tells nobody (a reader
    # taking 1,000 records/s under this flood for 4 s got 2,972 of 8,000, every one acknowledged to the writer, no
    # message_lost event). The count then stopped short (soak, 2026-11-27: still short 60 s after the flood of 18,570
    # ended); it is printed, and bounded by what was sent
    if f.alone:
        assert sum(f.rejected.values()) == f.sent["sent"] > 1000, (f.rejected, f.sent)
        assert max(f.rejected.values()) - min(f.rejected.values()) <= 1, f.rejected
    else:
        assert 1000 < sum(f.rejected.values()) <= f.sent["sent"], (f.rejected, f.sent)
    # the bound is the product's on a machine the team has to itself. Beside two CPU hogs on two cores it slowed
    # 2.0-2.06x (0.93x alone) although the hogs got only 19 % of the CPU: every flood record wakes the world, and
    # under contention each wakeup waits for a core; the slowdown is then printed, not bounded
    if f.alone:
        assert f.slowdown <= 2.0, f.slowdown
    # no step lost: every episode ran all h steps with every agent, and the world's trajectories (levels,
    # assignments, observations) are exactly the in-process ones
    assert f.absent == 0, [w["metrics"]["absent"] for w in f.episodes[::B]]
    for w in f.episodes:
        b, i = divmod(w["metrics"]["episode"], B)
        tr = in_process(builtin(), f.seed, b, "greedy", B)
        assert np.array_equal(tr.levels[:, i], w["levels"]) and np.array_equal(tr.actions[:, i], w["actions"])
        assert np.array_equal(tr.observations[:, i], w["observations"]), w["metrics"]["episode"]


def test_a_flood_as_fast_as_a_process_can_publish_stops_nothing_and_is_counted(ros_team: Any) -> None:
    # 20 batches flooded: a batch of 8 takes about 0.3 s, less than the flooder takes to start; with 2 the run could
    # end before the flood reached the world (CI, 2026-11-26: flooded from batch 9 of 10)
    f = run_flood(ros_team, ["--seconds", "12"], flooded=20)
    # a flood, not a speed: the flooder's rate is the CPU share it gets (28,800-41,000 records/s alone, 7,804/s beside
    # two CPU hogs: slow soak of 2026-11-27, which failed the floor of 8,000/s this had), and it is printed; the
    # floor is on volume, twenty times the world's reader queue (depth 1000)
    assert f.sent["sent"] > 20 * qos.EVENTS.depth, f.sent
    assert 10_000 < sum(f.rejected.values()) <= f.sent["sent"], (f.rejected, f.sent)
