"""Agents on separate hosts: the world, the trainer and every agent in a network namespace of its own (ip netns +
veth pairs on a bridge, made here), each started the way docs/ros.md documents for several hosts:
`launch_scripts/team.sh MODE --only <its processes> --discovery subnet` on the same domain id. DDS is forced onto
UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4): on one machine Fast DDS would otherwise use shared memory across the
namespaces and the network would not be tested. Skipped, with the reason, where namespaces cannot be made."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from htlm_agent.learning.transition_store import read_store
from htlm_agent.ros.launch import LaunchConfig
from htlm_world.scenario import builtin
from support.ros import RosTeam, assert_same_as_in_process, next_domain, wait_team

pytestmark = [pytest.mark.ros, pytest.mark.timeout(150)]

NAMES = ["world", "trainer", "agent1", "agent2", "agent3", "agent4", "agent5"]


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {r.stderr.strip()}")


class Net:
    """A bridge and one namespace per host (by default one per process of NAMES), each with a veth pair and an
    address on 10.231.<n>.0/24."""

    def __init__(self, tag: int, hosts: list[str] = NAMES) -> None:
        self.tag = tag
        self.hosts = hosts
        self.bridge = f"hbr{tag}"
        self.ns = {name: f"htlm{tag}n{i}" for i, name in enumerate(hosts)}
        self.addr = {name: f"10.231.{tag % 250}.{10 + i}" for i, name in enumerate(hosts)}
        self.dev = {name: f"hv{tag}n{i}" for i, name in enumerate(hosts)}
        """The host's end of its veth pair, inside its namespace."""

    def up(self) -> None:
        _ip("link", "add", self.bridge, "type", "bridge")
        _ip("link", "set", self.bridge, "type", "bridge", "mcast_snooping", "0")
        _ip("link", "set", self.bridge, "up")
        for i, name in enumerate(self.hosts):
            ns, host, inner = self.ns[name], f"hv{self.tag}h{i}", self.dev[name]
            _ip("netns", "add", ns)
            _ip("link", "add", host, "type", "veth", "peer", "name", inner)
            _ip("link", "set", inner, "netns", ns)
            _ip("link", "set", host, "master", self.bridge)
            _ip("link", "set", host, "up")
            _ip("-n", ns, "addr", "add", f"{self.addr[name]}/24", "dev", inner)
            _ip("-n", ns, "link", "set", inner, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", inner)  # multicast discovery over the veth

    def cut(self, host: str) -> None:
        """Take the host off the network: its link down."""
        _ip("-n", self.ns[host], "link", "set", self.dev[host], "down")

    def heal(self, host: str) -> None:
        """Bring the host's link back up, with the multicast route that went down with it."""
        _ip("-n", self.ns[host], "link", "set", self.dev[host], "up")
        _ip("-n", self.ns[host], "route", "replace", "224.0.0.0/4", "dev", self.dev[host])

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


def _launch(net: Net, script: str, name: str, args: list[str], run: Path) -> subprocess.Popen[bytes]:
    """`team.sh ARGS --only NAME` inside NAME's namespace, discovering the others over the bridge (DDS on UDP)."""
    cmd = ["ip", "netns", "exec", net.ns[name], script, *args]
    cmd += ["--only", name, "--discovery", "subnet", "--domain-id", str(net.tag), "--run-dir", str(run), "--quiet"]
    env = {**os.environ, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.mark.slow  # CI budget: every network test (root, 20-45 s each) runs with -m slow
def test_world_trainer_and_agents_in_separate_network_namespaces(net: Net, repo_root: Path, tmp_path: Path) -> None:
    seed, episodes = 3, 4  # two batches of 2: time for every process to discover the world
    run = tmp_path / "run"
    script = str(repo_root / "launch_scripts" / "team.sh")

    def bridged() -> int:  # bytes the namespaces sent through the bridge
        return sum(int(Path(f"/sys/class/net/hv{net.tag}h{i}/statistics/rx_bytes").read_text()) for i in range(7))

    before = bridged()
    args = ["evaluate", "--policy", "greedy", "--seed", str(seed), "--episodes", str(episodes), "--batch", "2"]
    procs = {name: _launch(net, script, name, [*args, "--timeout", "100"], run) for name in NAMES}
    wait_team(procs, run, 120)
    team = RosTeam(tmp_path, LaunchConfig(mode="evaluate", scenario=builtin(), run_dir=run, seed=seed, batch=2))
    assert assert_same_as_in_process(team, seed, "greedy") == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    sent = bridged() - before
    assert sent > 200_000, f"only {sent} bytes crossed the bridge: the processes did not talk over the network"
    print(f"{sent} bytes crossed the bridge between the 7 namespaces")


CUT = "agent3"
CUT_SECONDS = 4.0


@pytest.mark.slow  # CI budget (43 s)
def test_agent_cut_off_the_network_mid_training_is_idle_then_rejoins_and_loses_no_transition(
    net: Net, repo_root: Path, tmp_path: Path
) -> None:
    """A training run (B = 4) where agent3's link goes down for 4 s mid-run and comes back: the world counts it
    absent in the batches of the cut and present again later, every process exits 0, and the trainer's store keeps
    everything it had acknowledged and ends up with every transition of every agent, once."""
    B, batches, seed = 4, 12, 5
    run = tmp_path / "run"
    script = str(repo_root / "launch_scripts" / "team.sh")
    learner = {"envs": B, "learning_starts": 60, "batch_size": 32, "memory": 20000}
    # deadlines: short enough that the cut costs seconds, not the run (a silent agent is waited for once per step
    # phase and begin, then no longer until heard), long enough that a slow step on a loaded machine is no absence
    world = {"act_deadline": 1.5, "update_deadline": 1.5, "begin_deadline": 1.5}
    args = ["train", "--seed", str(seed), "--episodes", str(B * batches), "--batch", str(B), "--eval-episodes", "0"]
    args += [x for k, v in learner.items() for x in ("--set", f"{k}={v}")]
    args += [x for k, v in world.items() for x in ("--world-param", f"{k}={v}")]
    args += ["--trainer-param", "round_deadline=1.5", "--agent-param", "resend_period=0.5"]
    args += ["--agent-param", "stop_timeout=20.0", "--agent-param", "broadcast_timeout=1.0", "--timeout", "100"]
    procs = {name: _launch(net, script, name, args, run) for name in NAMES}
    world_log = run / "world.jsonl"
    store = run / "trainer" / "transitions.bin"

    def logged() -> int:
        return len(world_log.read_text().splitlines()) if world_log.exists() else 0

    end = time.monotonic() + 60
    while logged() < 2 * B:  # two batches trained: past the learner's start, every process matched
        assert time.monotonic() < end and procs["world"].poll() is None, f"no two batches: {logged()} episodes"
        time.sleep(0.05)
    before = read_store(store).copy()  # whatever the trainer may have acknowledged so far: acks follow the fsync
    cut_at = logged()
    net.cut(CUT)
    time.sleep(CUT_SECONDS)
    net.heal(CUT)
    up_at = logged()
    wait_team(procs, run, 100)

    eps = {w["metrics"]["episode"]: w for w in (json.loads(x) for x in world_log.read_text().splitlines())}
    assert sorted(eps) == list(range(B * batches)), "every episode ran once"
    k = NAMES.index(CUT) - 2  # agent index in the scenario
    absent = [eps[b * B]["metrics"]["absent"] for b in range(batches)]  # one count for all B episodes of a batch
    during = range(cut_at // B, up_at // B + 1)  # the batches in progress while the link was down
    missed = sum(absent[b][k] for b in during)
    assert missed > 0, f"{CUT} never absent during the cut (batches {list(during)}): {absent}"
    assert all(absent[b][k] == 0 for b in range(cut_at // B)), f"{CUT} absent before the cut: {absent}"
    back = [b for b in range(up_at // B + 1, batches) if absent[b][k] == 0]
    assert back, f"{CUT} never rejoined after the cut: {absent}"
    assert all(absent[b][k] == 0 for b in range(back[0], batches)), f"{CUT} left again after rejoining: {absent}"
    others = [a for b in range(batches) for i, a in enumerate(absent[b]) if i != k]
    assert max(others) <= 2, f"a teammate missed steps: {absent}"

    after = read_store(store)
    key = ["agent", "session", "seq", "row"]
    keys = {tuple(r[f].item() for f in key) for r in after}
    assert len(keys) == len(after), "a transition stored twice"
    acked = {tuple(r[f].item() for f in key) for r in before}
    assert acked <= keys, f"{len(acked - keys)} acknowledged transitions lost"
    h = builtin().horizon
    for i in range(5):
        mine = after[after["agent"] == i]
        assert len(set(mine["session"].tolist())) == 1, f"agent {i}: one process, one session"
        seqs = sorted(set(mine["seq"].tolist()))
        assert seqs == list(range(len(seqs))), f"agent {i}: a record missing between 0 and {seqs[-1]}"
        steps = {(int(e), int(t)) for e, t in zip(mine["episode"].tolist(), mine["step"].tolist(), strict=True)}
        played = {
            (e, t)
            for b in range(batches)
            if absent[b][i] == 0
            for e in range(b * B, b * B + B)
            for t in range(1, h + 1)
        }
        assert played <= steps, f"agent {i}: {len(played - steps)} transitions of steps it played are missing"
    print(
        f"{CUT} cut for {CUT_SECONDS:g} s during batches {list(during)}: absent steps per batch "
        f"{[absent[b][k] for b in range(batches)]}; back from batch {back[0]}; store: {len(before)} rows at the cut "
        f"(all kept), {len(after)} at the end, {len(after[after['agent'] == k])} of them {CUT}'s"
    )
