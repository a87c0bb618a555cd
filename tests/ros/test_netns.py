"""Agents on separate hosts: the world, the trainer and every agent in a network namespace of its own (ip netns +
veth pairs on a bridge, made here), each started the way the README documents for several hosts:
`launch_scripts/team.sh MODE --only <its processes> --discovery subnet` on the same domain id. DDS is forced onto
UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4): on one machine Fast DDS would otherwise use shared memory across the
namespaces and the network would not be tested. Skipped, with the reason, where namespaces cannot be made."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from htlm_agent.ros.launch import LaunchConfig
from htlm_world.scenario import builtin

from .conftest import RosTeam, assert_same_as_in_process, next_domain

pytestmark = [pytest.mark.ros, pytest.mark.timeout(150)]

NAMES = ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {r.stderr.strip()}")


class Net:
    """A bridge and one namespace per process, each with a veth pair and an address on 10.231.<n>.0/24."""

    def __init__(self, tag: int) -> None:
        self.tag = tag
        self.bridge = f"hbr{tag}"
        self.ns = {name: f"htlm{tag}n{i}" for i, name in enumerate(NAMES)}
        self.addr = {name: f"10.231.{tag % 250}.{10 + i}" for i, name in enumerate(NAMES)}

    def up(self) -> None:
        _ip("link", "add", self.bridge, "type", "bridge")
        _ip("link", "set", self.bridge, "type", "bridge", "mcast_snooping", "0")
        _ip("link", "set", self.bridge, "up")
        for i, name in enumerate(NAMES):
            ns, host, inner = self.ns[name], f"hv{self.tag}h{i}", f"hv{self.tag}n{i}"
            _ip("netns", "add", ns)
            _ip("link", "add", host, "type", "veth", "peer", "name", inner)
            _ip("link", "set", inner, "netns", ns)
            _ip("link", "set", host, "master", self.bridge)
            _ip("link", "set", host, "up")
            _ip("-n", ns, "addr", "add", f"{self.addr[name]}/24", "dev", inner)
            _ip("-n", ns, "link", "set", inner, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", inner)  # multicast discovery over the veth

    def down(self) -> None:
        for ns in self.ns.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
        subprocess.run(["ip", "link", "del", self.bridge], capture_output=True, check=False)


@pytest.fixture
def net() -> Iterator[Net]:
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need Linux, root and iproute2's `ip`")
    n = Net(next_domain())
    try:
        n.up()
    except OSError as e:
        n.down()
        pytest.skip(f"cannot make network namespaces here: {e}")
    yield n
    n.down()


def test_world_trainer_and_agents_in_separate_network_namespaces(net: Net, repo_root: Path, tmp_path: Path) -> None:
    domain, seed, episodes = net.tag, 3, 4  # two batches of 2: time for every process to discover the world
    run = tmp_path / "run"
    script = str(repo_root / "launch_scripts" / "team.sh")
    env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}

    def bridged() -> int:  # bytes the namespaces sent through the bridge
        return sum(int(Path(f"/sys/class/net/hv{net.tag}h{i}/statistics/rx_bytes").read_text()) for i in range(7))

    before = bridged()
    procs = {}
    for name in NAMES:
        cmd = [
            "ip",
            "netns",
            "exec",
            net.ns[name],
            script,
            "evaluate",
            "--policy",
            "greedy",
            "--seed",
            str(seed),
            "--episodes",
            str(episodes),
            "--batch",
            "2",
            "--only",
            name,
            "--discovery",
            "subnet",
            "--domain-id",
            str(domain),
            "--run-dir",
            str(run),
            "--quiet",
            "--timeout",
            "100",
        ]
        procs[name] = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        codes = {name: p.wait(timeout=120) for name, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    outs = {name: p.stdout.read().decode() if p.stdout else "" for name, p in procs.items()}
    world_log = (run / "logs" / "world.log").read_text() if (run / "logs" / "world.log").exists() else ""
    assert codes == dict.fromkeys(NAMES, 0), (codes, outs["world"], world_log[-2000:])
    team = RosTeam(tmp_path, LaunchConfig(mode="evaluate", scenario=builtin(), run_dir=run, seed=seed, batch=2))
    assert assert_same_as_in_process(team, seed, "greedy") == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    sent = bridged() - before
    assert sent > 200_000, f"only {sent} bytes crossed the bridge: the processes did not talk over the network"
    print(f"{sent} bytes crossed the bridge between the 7 namespaces")
