"""Benchmark of the link emulator (tests/ros/links.py): how many frames per second its switch thread forwards, and
what bad links cost a training run over ROS. Not collected by pytest; run it as root, under the heavy-job lock:

    flock /tmp/htlm-heavy.lock .venv/bin/python tests/ros/bench_links.py [--json] [--no-training]

Forwarding: a sender process in one namespace sends UDP datagrams as fast as it can for `--seconds` to a receiver
process in another (clean links), once per datagram size and TAP MTU; reported are the frames the switch forwarded
per second, the datagrams and megabytes per second that arrived, and the share the switch could not keep up with
(datagrams sent but never received: dropped in a full TAP or socket queue). Training: the run of
tests/ros/test_bad_links.py at twice its budget (the five agents on links with 5 % loss and 100 ms delay, once with
the launch's Fast DDS profile (reliable writers' heartbeat every 0.1 s) and once with Fast DDS's default 3 s, then
every link clean, in the same namespaces), with the wall time of each and its ratio to the clean run.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
PORT = 47002


def _sender(addr: str, size: int, seconds: float) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    payload = b"x" * size
    n = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for _ in range(100):
            try:
                s.sendto(payload, (addr, PORT))
                n += 1
            except OSError:  # ENOBUFS: the TAP's queue is full, the switch is behind
                pass
    print(json.dumps({"sent": n}), flush=True)


def _receiver(addr: str, seconds: float) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.bind((addr, PORT))
    print("ready", flush=True)
    s.settimeout(seconds + 10.0)  # until the first datagram; then the flood is over after a second without one
    n = nbytes = 0
    try:
        while True:
            d = s.recv(65536)
            s.settimeout(1.0)
            n += 1
            nbytes += len(d)
    except TimeoutError:
        pass
    print(json.dumps({"received": n, "bytes": nbytes}), flush=True)


def forwarding(size: int, mtu: int, seconds: float) -> dict[str, Any]:
    """One flood of `size`-byte datagrams between two namespaces over TAPs of this MTU."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from links import LinkEmulator

    me = [sys.executable, str(Path(__file__).resolve())]
    with LinkEmulator(["a", "b"], tag=240 + os.getpid() % 10, mtu=mtu) as e:
        rx = subprocess.Popen(
            [
                "ip",
                "netns",
                "exec",
                e.ns["b"],
                *me,
                "--role",
                "receive",
                "--addr",
                e.addr["b"],
                "--seconds",
                str(seconds),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert rx.stdout is not None and rx.stdout.readline().strip() == "ready"
        before = e.counters()
        t0 = time.monotonic()
        tx = subprocess.run(
            ["ip", "netns", "exec", e.ns["a"], *me, "--role", "send", "--addr", e.addr["b"], "--size", str(size)]
            + ["--seconds", str(seconds)],
            capture_output=True,
            text=True,
            check=True,
        )
        took = time.monotonic() - t0
        out, _ = rx.communicate(timeout=seconds + 10)
        after = e.counters()
    sent = json.loads(tx.stdout.strip().splitlines()[-1])["sent"]
    got = json.loads(out.strip().splitlines()[-1])
    frames = after["b"].received - before["b"].received
    return {
        "size": size,
        "mtu": mtu,
        "frames_per_s": round(frames / took),
        "datagrams_per_s": round(got["received"] / took),
        "MB_per_s": round(got["bytes"] / took / 1e6, 1),
        "not_delivered": round(1.0 - got["received"] / max(sent, 1), 3),
    }


def training(seed: int = 0) -> dict[str, Any]:
    """The bad-links training runs of tests/ros/test_bad_links.py (the launch's heartbeat period and Fast DDS's
    default) and the clean one."""
    sys.path.insert(0, str(ROOT / "tests"))
    from ros.links import LinkEmulator
    from ros.test_bad_links import HOSTS, bad_then_clean

    with tempfile.TemporaryDirectory() as tmp, LinkEmulator(HOSTS, tag=215 + os.getpid() % 10, seed=seed) as e:
        return bad_then_clean(e, Path(tmp), heartbeats=(None, 3.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of lines")
    ap.add_argument("--seconds", type=float, default=3.0, help="seconds of each flood")
    ap.add_argument("--no-training", action="store_true", help="only the forwarding rate")
    ap.add_argument("--role", choices=["send", "receive"], help=argparse.SUPPRESS)
    ap.add_argument("--addr", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, default=64, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "send":
        return _sender(args.addr, args.size, args.seconds)
    if args.role == "receive":
        return _receiver(args.addr, args.seconds)
    result: dict[str, Any] = {"forwarding": []}
    for size, mtu in [(64, 65000), (1400, 65000), (8000, 1500), (8000, 65000), (60000, 1500), (60000, 65000)]:
        r = forwarding(size, mtu, args.seconds)
        result["forwarding"].append(r)
        if not args.json:
            print("forwarding", r, flush=True)
    if not args.no_training:
        result["training"] = training()
        if not args.json:
            print("training", result["training"], flush=True)
    if args.json:
        print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
