"""Soak run: the ROS test sets again and again with CPU hogs beside them, to find the tests that fail under load.
Not collected by pytest; run it by name, with nothing else heavy running:

    .venv/bin/python tests/ros/soak.py --runs 20 --hogs 2 --set default --set slow [--json]

Each run is `pytest -q -m "ros and not slow" tests/ros` (default) or `pytest -q -m slow tests/ros` (slow) in a fresh
process while `--hogs` processes spin on the CPU. Prints one line per run (set, result, passed, failed, seconds, the
failed tests) and at the end a table per set; --out writes them as CSV. A failure's output is kept in
--keep-dir/<set>-<run>.log for its cause to be found (the rule: fix the cause, never rerun)."""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SETS = {"default": ["-m", "ros and not slow"], "slow": ["-m", "slow"]}


def _hog() -> None:
    while True:
        pass


def run_once(name: str, keep: Path, i: int) -> dict[str, object]:
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *SETS[name], "tests/ros"]
    t0 = time.monotonic()
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    seconds = time.monotonic() - t0
    out = p.stdout + p.stderr
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|errors?)", out.splitlines()[-1] if out else "")}
    failed = sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", out, flags=re.M)))
    if p.returncode != 0:
        keep.mkdir(parents=True, exist_ok=True)
        (keep / f"{name}-{i}.log").write_text(out)
    return {
        "set": name,
        "run": i,
        "ok": p.returncode == 0,
        "passed": counts.get("passed", 0),
        "failed": counts.get("failed", 0) + counts.get("error", 0) + counts.get("errors", 0),
        "seconds": round(seconds, 1),
        "failures": " ".join(failed),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--hogs", type=int, default=2, help="processes spinning on the CPU meanwhile")
    ap.add_argument("--set", dest="sets", action="append", choices=sorted(SETS), help="default, slow (repeatable)")
    ap.add_argument("--out", default="", help="CSV of every run")
    ap.add_argument("--keep-dir", default="soak-failures", help="where a failed run's output goes")
    ap.add_argument("--json", action="store_true", help="print the runs as JSON on stdout (lines go to stderr)")
    args = ap.parse_args()
    hogs = [multiprocessing.Process(target=_hog, daemon=True) for _ in range(args.hogs)]
    for h in hogs:
        h.start()
    rows = []
    try:
        for name in args.sets or ["default"]:
            for i in range(1, args.runs + 1):
                row = run_once(name, Path(args.keep_dir), i)
                rows.append(row)
                print(
                    f"{name} run {i}/{args.runs}: {'ok' if row['ok'] else 'FAILED'} {row['passed']} passed "
                    f"{row['failed']} failed in {row['seconds']} s {row['failures']}",
                    file=sys.stderr,
                    flush=True,
                )
    finally:
        for h in hogs:
            h.terminate()
    if args.out:
        with open(args.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    for name in dict.fromkeys(r["set"] for r in rows):
        mine = [r for r in rows if r["set"] == name]
        ok = sum(bool(r["ok"]) for r in mine)
        secs = [float(str(r["seconds"])) for r in mine]
        print(
            f"{name}: {ok}/{len(mine)} runs passed with {args.hogs} CPU hogs; {min(secs):.0f}-{max(secs):.0f} s a run",
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps(rows))
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
