"""Bad links on one machine: a switch in user space between network namespaces, with per-host loss, delay and
partitions set at run time.

This kernel has no netem (`tc qdisc add ... netem` answers "Specified qdisc kind is unknown"), and tbf, which it has,
only shapes the rate. So every host gets a network namespace with a TAP device in it instead of a veth: the TAP's file
descriptor stays in this process (the netdev is moved into the namespace, the descriptor stays attached), and a
thread reads every frame a host sends and writes it to the TAP of the hosts it goes to, as a MAC-learning switch
does (broadcast, multicast and unknown destinations to every other host). On the way it applies the sender's link:

- loss: each frame the host sends is dropped with that probability (one seeded generator per host);
- delay: each frame the host sends is delivered no earlier than `delay` seconds after it was read, in the order sent;
- partition: while the team is split into groups, a frame reaches only the hosts of its sender's group (a frame
  delivered during the split is checked when it is delivered, so one in flight across the cut is lost too).

These are the properties of the host's egress, what netem on the host's interface would do; the frames a host
receives cross only their sender's link. The TAPs' MTU is 65,000 by default, so a UDP datagram of DDS (at most 64 KiB)
is one frame and the loss rate is the datagram loss rate (with the usual 1,500 a large sample is cut in IP fragments
and losing any one of them loses the datagram). Each host's address is 10.232.<tag>.<10 + index>/24 with the multicast
route on its TAP, as tests/ros/test_netns.py's bridge has it. Needs Linux, root, /dev/net/tun and iproute2's `ip`.

    emu = LinkEmulator(["world", "agent1"], tag=7)
    emu.up()
    try:
        emu.set_link("agent1", loss=0.05, delay=0.1)
        subprocess.run(["ip", "netns", "exec", emu.ns["agent1"], ...])
        emu.partition([["world"], ["agent1"]]); ...; emu.heal()
        print(emu.counters())
    finally:
        emu.down()

`python tests/ros/bench_links.py` measures its forwarding rate.
"""

from __future__ import annotations

import ctypes
import fcntl
import math
import os
import random
import select
import shutil
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

T = TypeVar("T")

_TUNSETIFF = 0x400454CA
_IFF_TAP = 0x0002
_IFF_NO_PI = 0x1000
_CLONE_NEWNET = 0x40000000
_BURST = 64
"""Most frames read from one TAP before the others get their turn."""


def ip(*args: str) -> None:
    """Run `ip ARGS`; OSError with its message when it fails."""
    r = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {r.stderr.strip()}")


def in_netns(ns: str, fn: Callable[[], T]) -> T:
    """fn() called on a thread that has entered network namespace `ns` (/run/netns/NS): a socket made there stays in
    that namespace. The caller's namespace is not touched."""
    libc = ctypes.CDLL(None, use_errno=True)
    out: list[T] = []
    err: list[BaseException] = []

    def run() -> None:
        try:
            fd = os.open(f"/run/netns/{ns}", os.O_RDONLY | os.O_CLOEXEC)
            try:
                if libc.setns(fd, _CLONE_NEWNET) != 0:
                    e = ctypes.get_errno()
                    raise OSError(e, f"setns into {ns}: {os.strerror(e)}")
            finally:
                os.close(fd)
            out.append(fn())
        except BaseException as e:  # handed to the caller
            err.append(e)

    t = threading.Thread(target=run, name=f"netns-{ns}")  # the thread ends, and its namespace with it
    t.start()
    t.join()
    if err:
        raise err[0]
    return out[0]


@dataclass(frozen=True)
class Link:
    """The egress properties of one host's link."""

    loss: float = 0.0
    """Probability that a frame the host sends is dropped."""
    delay: float = 0.0
    """Seconds between reading a frame the host sent and delivering it (order kept)."""


@dataclass
class HostCounters:
    """Frames of one host, counted by the switch."""

    sent: int = 0
    """Frames the host sent (read from its TAP)."""
    lost: int = 0
    """Of those, dropped by its link's loss."""
    blocked: int = 0
    """Copies of its frames not delivered to a host across a partition."""
    received: int = 0
    """Frames written to its TAP (sent by the others)."""
    overflow: int = 0
    """Frames that could not be written to its TAP (the kernel refused them)."""


class LinkEmulator:
    """A namespace and a TAP per host, a switch thread between them (the module's docstring says how).

    Args:
        hosts: the hosts' names (each becomes namespace `htlm<tag>l<index>`).
        tag: a number that keeps this emulator's names and subnet apart from another's (0..249).
        seed: seed of the loss generators (host i draws from Random(f"{seed}:{i}")).
        mtu: the TAPs' MTU.
    """

    def __init__(self, hosts: Sequence[str], tag: int, seed: int = 0, mtu: int = 65000) -> None:
        assert len(set(hosts)) == len(hosts) and 0 < len(hosts) <= 200, hosts
        assert 0 <= tag < 250 and 68 <= mtu <= 65521, (tag, mtu)
        self.hosts = list(hosts)
        self.tag = tag
        self.mtu = mtu
        self.ns = {h: f"htlm{tag}l{i}" for i, h in enumerate(hosts)}
        """Each host's namespace (run a process there with `ip netns exec NS ...`)."""
        self.dev = {h: f"hl{tag}t{i}" for i, h in enumerate(hosts)}
        """Each host's TAP device (inside its namespace)."""
        self.addr = {h: f"10.232.{tag}.{10 + i}" for i, h in enumerate(hosts)}
        """Each host's IPv4 address."""
        self._fd: dict[str, int] = {}
        self._host_of: dict[int, str] = {}
        self._made: list[str] = []
        self._rng = {h: random.Random(f"{seed}:{i}") for i, h in enumerate(hosts)}
        self._link = dict.fromkeys(hosts, Link())
        self._group: dict[str, int] | None = None
        self._shared: frozenset[str] = frozenset()
        self._queue: dict[str, deque[tuple[float, bytes]]] = {h: deque() for h in hosts}
        self._last_due = dict.fromkeys(hosts, 0.0)
        self._mac: dict[bytes, str] = {}
        self._count = {h: HostCounters() for h in hosts}
        self._wake_r = self._wake_w = -1
        self._stop = False
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    # set-up and teardown

    def up(self) -> None:
        """Make the namespaces and TAPs and start the switch; OSError (after undoing what was made) when it cannot."""
        assert self._thread is None and not self._made, "up() twice"
        try:
            for h in self.hosts:
                self._add(h)
        except BaseException:
            self.down()
            raise
        self._stop = False
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name=f"links-{self.tag}", daemon=True)
        self._thread.start()

    def _add(self, h: str) -> None:
        ns, dev = self.ns[h], self.dev[h]
        ip("netns", "add", ns)
        self._made.append(ns)
        in_netns(ns, _no_ipv6)  # no router solicitations and MLD reports: the frames are the test's
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
        try:
            fcntl.ioctl(fd, _TUNSETIFF, struct.pack("16sH", dev.encode(), _IFF_TAP | _IFF_NO_PI))
        except OSError:
            os.close(fd)
            raise
        self._fd[h] = fd
        self._host_of[fd] = h
        ip("link", "set", dev, "netns", ns)  # the device moves, the descriptor stays attached to it
        ip("-n", ns, "link", "set", dev, "mtu", str(self.mtu))
        ip("-n", ns, "addr", "add", f"{self.addr[h]}/24", "dev", dev)
        ip("-n", ns, "link", "set", dev, "up")
        ip("-n", ns, "link", "set", "lo", "up")
        ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", dev)  # DDS discovers its peers by multicast

    def down(self) -> None:
        """Stop the switch, close the TAPs (which removes them) and delete the namespaces. Safe to call again."""
        if self._thread is not None:
            self._stop = True
            self._wake()
            self._thread.join(timeout=10)
            assert not self._thread.is_alive(), "the switch thread did not stop within 10 s"
            self._thread = None
            for fd in (self._wake_r, self._wake_w):
                os.close(fd)
            self._wake_r = self._wake_w = -1
        for fd in self._fd.values():
            os.close(fd)
        self._fd.clear()
        self._host_of.clear()
        for ns in self._made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
        self._made.clear()

    def __enter__(self) -> LinkEmulator:
        self.up()
        return self

    def __exit__(self, *exc: object) -> None:
        self.down()

    # the links, at run time

    def set_link(self, host: str, loss: float = 0.0, delay: float = 0.0) -> None:
        """Set the loss probability and one-way delay (seconds) of the frames `host` sends from now on."""
        if host not in self._link:
            raise ValueError(f"no host {host!r} (hosts: {self.hosts})")
        if not (0.0 <= loss <= 1.0 and 0.0 <= delay <= 3600.0):
            raise ValueError(f"loss must be in [0, 1] and delay in [0, 3600] s, got loss={loss} delay={delay}")
        self._link = {**self._link, host: Link(loss, delay)}
        self._wake()

    def link(self, host: str) -> Link:
        return self._link[host]

    def partition(self, groups: Iterable[Iterable[str]], shared: Iterable[str] = ()) -> None:
        """Split the hosts: a frame reaches only the hosts of its sender's group (a host in no group is alone), and
        the `shared` hosts, which reach and are reached by every group (what no split cuts: the physical world)."""
        self._shared = frozenset(shared)
        group: dict[str, int] = {}
        for g, members in enumerate(groups):
            for h in members:
                if h not in self._link or h in group:
                    raise ValueError(f"{h!r} is not a host or is in two groups (hosts: {self.hosts})")
                group[h] = g
        n = len(group)
        for h in self.hosts:
            if h not in group:
                group[h] = n
                n += 1
        self._group = group
        self._wake()

    def heal(self) -> None:
        """End the partition: every host reaches every other again."""
        self._group = None
        self._wake()

    def counters(self) -> dict[str, HostCounters]:
        """A copy of every host's counters (raises what stopped the switch, if it failed)."""
        if self._error is not None:
            raise RuntimeError("the switch thread failed") from self._error
        return {h: HostCounters(**vars(c)) for h, c in self._count.items()}

    def _wake(self) -> None:
        """Make the switch thread look at its settings again (a new delay changes when it must wake up)."""
        if self._wake_w >= 0:
            os.write(self._wake_w, b"x")

    # the switch

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as e:  # seen by counters(); the test's wait then fails naming it
            self._error = e

    def _loop(self) -> None:
        poll = select.poll()
        for fd in self._fd.values():
            poll.register(fd, select.POLLIN)
        poll.register(self._wake_r, select.POLLIN)
        size = self.mtu + 64
        while not self._stop:
            due = [q[0][0] for q in self._queue.values() if q]
            timeout = None if not due else max(0, math.ceil((min(due) - time.monotonic()) * 1000.0))
            for fd, _ in poll.poll(timeout):
                if fd == self._wake_r:
                    os.read(fd, 4096)
                    continue
                h = self._host_of[fd]
                for _ in range(_BURST):
                    try:
                        frame = os.read(fd, size)
                    except BlockingIOError:
                        break
                    self._ingress(h, frame)
            self._release(time.monotonic())

    def _ingress(self, h: str, frame: bytes) -> None:
        c = self._count[h]
        c.sent += 1
        self._mac[frame[6:12]] = h
        link = self._link[h]
        if link.loss > 0.0 and self._rng[h].random() < link.loss:
            c.lost += 1
            return
        q = self._queue[h]
        if link.delay > 0.0 or q:
            due = max(time.monotonic() + link.delay, self._last_due[h])
            self._last_due[h] = due
            q.append((due, frame))
        else:
            self._deliver(h, frame)

    def _release(self, now: float) -> None:
        for h, q in self._queue.items():
            while q and q[0][0] <= now:
                self._deliver(h, q.popleft()[1])

    def _deliver(self, h: str, frame: bytes) -> None:
        dst = frame[0:6]
        to = self._mac.get(dst) if not dst[0] & 1 else None
        targets = [x for x in self.hosts if x != h] if to is None else [to] if to != h else []
        group = self._group
        for x in targets:
            if group is not None and group[x] != group[h] and x not in self._shared and h not in self._shared:
                self._count[h].blocked += 1
                continue
            try:
                os.write(self._fd[x], frame)
                self._count[x].received += 1
            except OSError:
                self._count[x].overflow += 1


def _no_ipv6() -> None:
    for conf in ("all", "default"):
        with open(f"/proc/sys/net/ipv6/conf/{conf}/disable_ipv6", "w") as f:
            f.write("1")


def unavailable() -> str | None:
    """Why a LinkEmulator cannot be made here (None when it can be tried)."""
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("ip") is None:
        return "the link emulator needs Linux, root and iproute2's `ip`"
    if not os.path.exists("/dev/net/tun"):
        return "the link emulator needs /dev/net/tun (TAP devices)"
    return None
