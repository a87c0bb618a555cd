"""Benchmark: how a flood of rejected records on /htlm/action slows the lockstep, by flood rate (a team of real
processes over real DDS, as in test_flood.py). Not collected by the default run; run it by name:

    .venv/bin/python -m pytest tests/ros/bench_flood.py -s -p no:cacheprovider

It prints one line per rate and writes docs/results/flood.csv and docs/images/flood.png (slowdown against flood
rate, measured in one run per rate: mean batch duration flooded / not flooded; for the flood as fast as the process
can publish, the batches finished during the flood against those the same time holds unflooded).

test_step_rate_under_a_full_speed_flood measures a team's step rate (episodes of batch 1) without and with a flood as
fast as one process can send on /htlm/broadcast, which every agent reads: malformed records against an unsigned team,
well-formed records signed with a wrong key against a signed one; it writes docs/results/flood_step_rate.csv.
test_the_readers_queue_losses_are_not_reported shows what a reader's message_lost QoS event says of the records it
lost (nodes do not take that event: under a flood, taking it blocked an agent for good in rmw's take_event). Run
them by name (-k step_rate, -k queue_losses) on an otherwise idle machine."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from htlm_msgs_py import topics
from support.ros import read_json

from .test_flood import OPEN, run_flood

pytestmark = [pytest.mark.ros, pytest.mark.timeout(1800)]

RATES = [1000, 2000, 4000, 8000, 16000]
ROOT = Path(__file__).resolve().parents[2]


def test_flood_sweep(ros_team: Any) -> None:
    rows = []
    for rate in [*RATES, 0]:
        args = ["--rate", str(rate)] if rate else ["--seconds", "10"]
        f = run_flood(ros_team, args, flooded=3)
        # at full speed: the batches the flood's time holds unflooded / those finished; none finished: at least that
        finished = f.progress * f.expected
        slowdown = f.slowdown if rate else f.expected / max(finished, 1.0)
        rows.append(
            {
                "rate_set": rate or "max",
                "rate_sent": f.sent["rate"],
                "rejected_counted": sum(f.rejected.values()),
                "sent": f.sent["sent"],
                "slowdown": round(slowdown, 2),
                "slowdown_is_lower_bound": bool(not rate and finished < 1.0),
                "progress_while_flooded": round(f.progress, 3),
                "absent_agent_steps": f.absent,
                "warnings": f.warnings,
                "flood_seconds": round(f.flood_seconds, 1),
            }
        )
        print("BENCH", rows[-1], flush=True)
    out = ROOT / "docs" / "results" / "flood.csv"
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, ROOT / "docs" / "images" / "flood.png")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    timed = [r for r in rows if r["rate_set"] != "max"]
    ax.plot([r["rate_sent"] for r in timed], [r["slowdown"] for r in timed], "o-", label="flood at a set rate")
    full = [r for r in rows if r["rate_set"] == "max"]
    ax.plot(
        [r["rate_sent"] for r in full],
        [r["slowdown"] for r in full],
        "s",
        color="tab:red",
        label="as fast as one process can (no batch finished: a lower bound)",
    )
    ax.axhline(2.0, color="grey", ls="--", lw=1, label="2x")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("rejected records/s sent to /htlm/action")
    ax.set_ylabel("lockstep slowdown (flooded / unflooded)")
    ax.set_title("A flood of bad records vs the lockstep (greedy team, B = 8, 2-core machine)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


STEP = re.compile(r"episode (\d+) step (\d+)")
WINDOW = 10.0
"""Seconds of each window the step rate is measured over (unflooded, then flooded)."""
TEAM_KEY = "a-team-key-only-the-team-knows-0123"


def _step_index(diag: Path) -> int:
    """The world's step index (episode x h + step) from the message of its last /diagnostics status."""
    got = read_json(diag) if diag.exists() else {}
    m = STEP.search(got.get("htlm: world", {}).get("message", ""))
    return int(m.group(1)) * 30 + int(m.group(2)) if m else -1


def _counters(diag: Path, prefix: str) -> dict[str, int]:
    """Per node, the sum of its counters starting with `prefix`."""
    got = read_json(diag) if diag.exists() else {}
    return {
        n.removeprefix("htlm: "): sum(int(v) for k, v in st.items() if k.startswith(prefix)) for n, st in got.items()
    }


def step_rate(ros_team: Any, kind: str, topic: str = topics.BROADCAST) -> dict[str, Any]:
    """A greedy team evaluating one episode at a time (lockstep), its step rate over WINDOW s unflooded, then over
    the WINDOW s of a flood as fast as one process can publish on `topic`: malformed records (`kind` malformed, the
    team unsigned) or well-formed records signed with a wrong key (`wrong_key`, the team signed). The counters of the
    readers of `topic` after the flood, and the agent-steps the world counted absent."""
    team = ros_team(
        policy="greedy",
        seed=11,
        episodes=OPEN,
        batch=1,
        world_params={"diagnostics_period": 0.1},
        agent_params={"diagnostics_period": 0.2},
    )
    if kind == "wrong_key":
        kf = team.tmp / "team.key"
        kf.write_text(TEAM_KEY + "\n")
        kf.chmod(0o600)
        team.cfg.key_file = str(kf)
    here = team.tmp / f"{team.cfg.run_dir.name}-{kind}"
    here.mkdir(exist_ok=True)
    diag, go, out = here / "diag.json", here / "go", here / "flood.json"
    team.helper("diag", "--out", str(diag))
    wrong = ["--wrong-key", "a-guessed-wrong-key-0000"] if kind == "wrong_key" else []
    readers = 5 if topic == topics.BROADCAST else 1
    flooder = team.helper(
        "flood", "--out", str(out), "--topic", topic, "--go", str(go), "--seconds", str(WINDOW),
        "--subscribers", str(readers), *wrong,
    )  # fmt: skip
    load = os.getloadavg()[0]
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= 2, 120, "the first two episodes")
    tag = topic.rsplit("/", 1)[-1]
    i0, t0 = _step_index(diag), time.monotonic()
    time.sleep(WINDOW)
    i1, t1 = _step_index(diag), time.monotonic()
    go.touch()
    team.wait_for(
        lambda: sum(_counters(diag, f"rejected/{tag}/").values()) > 0, 60, f"the flood to reach the {tag} readers"
    )
    f0, s0 = _step_index(diag), time.monotonic()
    team.wait_for(lambda: flooder.poll() is not None, 3 * WINDOW, "the flooder to end")
    f1, s1 = _step_index(diag), time.monotonic()
    sent = read_json(out)
    seen = [sum(_counters(diag, f"rejected/{tag}/").values()), time.monotonic()]

    def still() -> bool:
        now = sum(_counters(diag, f"rejected/{tag}/").values())
        if now != seen[0]:
            seen[:] = [now, time.monotonic()]
        return time.monotonic() - seen[1] >= 2.0

    team.wait_for(still, 60, "the readers' counts of rejected records to stand still")
    counted = dict(sorted((n, c) for n, c in _counters(diag, f"rejected/{tag}/").items() if n.startswith("agent")))
    # the team steps again once its deadlines passed (a broadcast lost in the flood is waited for until the agents'
    # broadcast_timeout, an action until the world's act_deadline)
    stalled = _step_index(diag)
    team.wait_for(lambda: _step_index(diag) > stalled, 90, "the team to step again after the flood")
    recovered = round(time.monotonic() - s1, 1)
    a0, ta = _step_index(diag), time.monotonic()
    time.sleep(WINDOW)
    a1, tb = _step_index(diag), time.monotonic()
    logged = len(team.world_episodes())
    team.wait_for(lambda: len(team.world_episodes()) > logged, 90, "an episode begun after the flood to be logged")
    absent = sum(sum(w["metrics"]["absent"]) for w in team.world_episodes())
    team.cleanup()
    shares = (min(counted.values(), default=0), max(counted.values(), default=0))
    row = {
        "kind": kind,
        "topic": topic,
        "sent": sent["sent"],
        "rate_sent": sent["rate"],
        "steps_per_s_unflooded": round((i1 - i0) / (t1 - t0), 2),
        "steps_per_s_flooded": round((f1 - f0) / (s1 - s0), 2),
        "steps_per_s_after": round((a1 - a0) / (tb - ta), 2),
        "flooded_seconds": round(s1 - s0, 1),
        "seconds_to_step_again": recovered,
        "counted_per_reader": counted,
        "counted_share": [round(c / max(sent["sent"], 1), 3) for c in shares],
        "absent_agent_steps": absent,
        "load_before": round(load, 2),
    }
    print("STEP_RATE", json.dumps(row), flush=True)
    return row


def test_step_rate_under_a_full_speed_flood(ros_team: Any) -> None:
    """Malformed records (an unsigned team) and wrongly signed ones (a signed team) on /htlm/broadcast, which every
    agent reads, as fast as one process can send them: the step rate flooded and unflooded, and what the agents
    counted; written to docs/results/flood_step_rate.csv."""
    rows = []
    for kind in ("malformed", "wrong_key"):
        while os.getloadavg()[0] >= 2.0:  # the machine to itself (the flood before leaves load behind)
            time.sleep(5)
        rows.append(step_rate(ros_team, kind))
    out = ROOT / "docs" / "results" / "flood_step_rate.csv"
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows({**r, "counted_per_reader": json.dumps(r["counted_per_reader"])} for r in rows)


def test_the_readers_queue_losses_are_not_reported(ros_team: Any) -> None:
    """A reader of /htlm/broadcast with the team's QoS that spends 1 ms per record, under a full-speed flood for
    5 s: how many records it got, and what its message_lost QoS event reported (Fast DDS of the wheels)."""
    team = ros_team(policy="greedy", seed=11, episodes=1, batch=1)
    out, go, fl = team.tmp / "listen.json", team.tmp / "go", team.tmp / "flood.json"
    listener = team.helper("listen", "--out", str(out), "--cost", "0.001")
    flooder = team.helper("flood", "--out", str(fl), "--topic", topics.BROADCAST, "--go", str(go), "--seconds", "5")
    time.sleep(3.0)
    go.touch()
    assert flooder.wait(timeout=60) == 0
    time.sleep(3.0)
    listener.send_signal(signal.SIGTERM)
    listener.wait(timeout=10)
    got, sent = read_json(out), read_json(fl)
    print("QUEUE_LOSS", json.dumps({"sent": sent["sent"], "rate": sent["rate"], **got}), flush=True)
