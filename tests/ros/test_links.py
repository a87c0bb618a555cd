"""The link emulator of tests/ros/links.py on its own, without ROS: UDP sockets in its namespaces show the delay
(every datagram arrives no earlier than the delay after it was sent, in order), the loss (over 2,000 datagrams the
lost count is within a binomial bound, and the same seed drops the same datagrams) and a partition (blocked, then
healed). Skipped, with the reason, where namespaces or TAP devices cannot be made."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Callable

import pytest

from .links import LinkEmulator, in_netns

pytestmark = [pytest.mark.timeout(120)]

PORT = 47001


@pytest.fixture
def emu(links: Callable[..., LinkEmulator]) -> LinkEmulator:
    return links(["a", "b", "c"], seed=11)


def _udp(e: LinkEmulator, host: str, bind: bool) -> socket.socket:
    def make() -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        if bind:
            s.bind((e.addr[host], PORT))
        return s

    return in_netns(e.ns[host], make)


def _wait(what: Callable[[], bool], timeout: float, why: str) -> None:
    end = time.monotonic() + timeout
    while not what():
        assert time.monotonic() < end, f"timed out after {timeout} s waiting for {why}"
        time.sleep(0.005)


def _recv(s: socket.socket, timeout: float) -> bytes | None:
    s.settimeout(timeout)
    try:
        return s.recv(65536)
    except (TimeoutError, BlockingIOError):  # timeout 0 raises the latter
        return None


def _prime(e: LinkEmulator, src: str, dst: str, rx: socket.socket | None = None) -> tuple[socket.socket, socket.socket]:
    """A sender in src and a receiver in dst (`rx`, or a new one) that have exchanged one datagram over a clean link
    (so the ARP resolution is done)."""
    tx, rx = _udp(e, src, False), rx or _udp(e, dst, True)
    tx.sendto(b"hello", (e.addr[dst], PORT))
    assert _recv(rx, 10.0) == b"hello", f"no datagram from {src} to {dst} over a clean link within 10 s"
    return tx, rx


def test_delay_holds_every_datagram_back_at_least_the_delay_and_keeps_their_order(emu: LinkEmulator) -> None:
    tx, rx = _prime(emu, "a", "b")
    emu.set_link("a", delay=0.1)
    sent: list[float] = []
    for i in range(50):
        sent.append(time.monotonic())
        tx.sendto(struct.pack("!I", i), (emu.addr["b"], PORT))
        if i % 10 == 9:
            time.sleep(0.03)  # spread the datagrams over more than one delay
    got: list[tuple[int, float]] = []
    while len(got) < 50:
        d = _recv(rx, 10.0)
        assert d is not None, f"only {len(got)} of 50 datagrams arrived within 10 s of the last"
        got.append((struct.unpack("!I", d)[0], time.monotonic()))
    assert [i for i, _ in got] == list(range(50)), "the delayed datagrams came out of order"
    early = [(i, t - sent[i]) for i, t in got if t - sent[i] < 0.1]
    assert not early, f"datagrams delivered before the 0.1 s delay: {early[:5]}"
    assert emu.counters()["a"].lost == 0


def _lost(e: LinkEmulator, n: int) -> tuple[set[int], dict[str, int]]:
    """Send n datagrams a -> b over a link with 5 % loss (in paced bursts, so no socket queue overflows): the
    sequence numbers lost and b's and a's counters."""
    tx, rx = _prime(e, "a", "b")
    e.set_link("a", loss=0.05)
    base = e.counters()["a"].sent
    got: set[int] = set()
    for start in range(0, n, 100):
        for i in range(start, min(n, start + 100)):
            tx.sendto(struct.pack("!I", i), (e.addr["b"], PORT))
        done = min(n, start + 100)
        _wait(lambda d=done: e.counters()["a"].sent - base >= d, 10.0, f"the switch to read datagram {done - 1}")
        arrive = done - e.counters()["a"].lost  # what the switch has let through so far
        while len(got) < arrive:
            d = _recv(rx, 10.0)
            assert d is not None, f"{arrive - len(got)} datagrams let through did not arrive within 10 s"
            got.add(struct.unpack("!I", d)[0])
    c = e.counters()
    return set(range(n)) - got, {"lost": c["a"].lost, "sent": c["a"].sent - base, "overflow": c["b"].overflow}


def test_loss_drops_a_binomial_share_and_the_same_seed_drops_the_same_datagrams(
    links: Callable[..., LinkEmulator],
) -> None:
    n, p = 2000, 0.05
    lost, c = _lost(links(["a", "b"], seed=7), n)
    sd = math.sqrt(n * p * (1 - p))
    assert c["sent"] == n and c["overflow"] == 0, c
    assert len(lost) == c["lost"], f"{len(lost)} datagrams missing, the switch dropped {c['lost']}"
    assert abs(len(lost) - n * p) < 5 * sd, f"{len(lost)} of {n} lost at p = {p} (5 sd: {5 * sd:.0f})"
    again, _ = _lost(links(["a", "b"], seed=7), n)
    assert again == lost, "the same seed dropped other datagrams"
    other, _ = _lost(links(["a", "b"], seed=8), n)
    assert other != lost, "another seed dropped the same datagrams"


def test_partition_blocks_across_the_cut_and_heal_restores(emu: LinkEmulator) -> None:
    ab_tx, b_rx = _prime(emu, "a", "b")
    cb_tx, _ = _prime(emu, "c", "b", b_rx)
    emu.partition([["a"], ["b", "c"]])
    before = emu.counters()["a"]
    ab_tx.sendto(b"across", (emu.addr["b"], PORT))
    _wait(lambda: emu.counters()["a"].blocked > before.blocked, 10.0, "the switch to block a's datagram to b")
    cb_tx.sendto(b"inside", (emu.addr["b"], PORT))
    assert _recv(b_rx, 10.0) == b"inside", "c's datagram to b (same side of the cut) did not arrive within 10 s"
    assert _recv(b_rx, 0.0) is None, "a's datagram crossed the partition"
    emu.heal()
    ab_tx.sendto(b"healed", (emu.addr["b"], PORT))
    assert _recv(b_rx, 10.0) == b"healed", "a's datagram to b did not arrive within 10 s of the heal"
    with pytest.raises(ValueError, match="two groups"):
        emu.partition([["a"], ["a", "b"]])
