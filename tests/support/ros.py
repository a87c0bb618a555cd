"""What the ROS integration tests share beside their fixtures (tests/ros/conftest.py): a team of real processes
over real DDS started from a LaunchConfig (`RosTeam`) or from the `htlm launch` command (`Launcher`), a ROS domain
per test, and the comparison of a team's logs with the in-process runtime (`assert_same_as_in_process`)."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.ros.launch import LaunchConfig, Proc, start, stop
from htlm_world.scenario import Scenario, builtin
from support.team import builtin_team, reference

TOOLS = Path(__file__).resolve().parents[1] / "ros" / "ros_tools.py"
"""The helper script the ROS tests run beside a team (tests/ros/ros_tools.py)."""
# one domain per test, away from the launcher's default 42 and from other test sessions
_DOMAINS = itertools.count(random.Random(os.getpid()).randrange(0, 50))


def next_domain() -> int:
    """A ROS_DOMAIN_ID for one test (120..229)."""
    return 120 + next(_DOMAINS) % 110


def _jsonl(f: Path) -> list[dict[str, Any]]:
    """The complete lines of a JSON-lines log a process may be writing: a last line without its newline is still
    being written and is left for the next read."""
    text = f.read_text() if f.exists() else ""
    return [json.loads(x) for x in text[: text.rfind("\n") + 1].splitlines()]


class RosTeam:
    """The world, the agents and the trainer as processes (via htlm_agent.ros.launch), plus helper processes."""

    def __init__(self, tmp: Path, cfg: LaunchConfig) -> None:
        self.tmp = tmp
        self.cfg = cfg
        self.procs: dict[str, Proc] = {}
        self.helpers: list[subprocess.Popen[bytes]] = []

    @property
    def run_dir(self) -> Path:
        return self.cfg.run_dir

    def env(self) -> dict[str, str]:
        from htlm_agent.ros.launch import ros_env

        return ros_env(self.cfg)

    def start(self, *names: str) -> None:
        """Start these processes (all of the launch when none is named)."""
        only = names or self.cfg.only or ()
        cfg = LaunchConfig(**{**self.cfg.__dict__, "only": tuple(only)})
        for p in start(cfg):
            self.procs[p.name] = p

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        p = self.procs[name].popen
        p.send_signal(sig)
        p.wait(timeout=10)

    def helper(self, *args: str) -> subprocess.Popen[bytes]:
        """Start tests/ros/ros_tools.py with these arguments on the team's domain."""
        log = open(self.tmp / f"helper-{len(self.helpers)}.log", "wb")  # noqa: SIM115
        p = subprocess.Popen([sys.executable, str(TOOLS), *args], env=self.env(), stdout=log, stderr=subprocess.STDOUT)
        self.helpers.append(p)
        return p

    def wait(self, name: str, timeout: float) -> int:
        """Exit code of a process, waiting for it at most `timeout` seconds (fails the test after that)."""
        popen = self.procs[name].popen
        try:
            return popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            popen.send_signal(signal.SIGUSR1)  # every node dumps its threads' stacks to its log (run_node)
            with contextlib.suppress(subprocess.TimeoutExpired):
                popen.wait(timeout=1.0)
            pytest.fail(f"{name} still running after {timeout} s; log and stacks:\n{self.log(name)[-6000:]}")

    def wait_all(self, timeout: float) -> dict[str, int]:
        end = time.monotonic() + timeout
        return {n: self.wait(n, max(0.1, end - time.monotonic())) for n in self.procs}

    def log(self, name: str) -> str:
        return self.procs[name].log.read_text(errors="replace")

    def world_episodes(self) -> list[dict[str, Any]]:
        return _jsonl(self.run_dir / "world.jsonl")

    def agent_episodes(self, name: str) -> list[dict[str, Any]]:
        return _jsonl(self.run_dir / f"{name}.jsonl")

    def wait_for(self, what: Callable[[], bool], timeout: float, why: str) -> None:
        end = time.monotonic() + timeout
        while not what():
            if time.monotonic() > end:
                pytest.fail(
                    f"timed out after {timeout} s waiting for {why}; world log:\n"
                    f"{self.log('world')[-3000:] if 'world' in self.procs else ''}"
                )
            time.sleep(0.05)

    def cleanup(self) -> None:
        stop(list(self.procs.values()), signal.SIGKILL, wait=2.0)
        for h in self.helpers:
            if h.poll() is None:
                h.kill()
            h.wait()


HTLM = str(Path(sys.executable).parent / "htlm")


def alive_with(marker: str) -> list[int]:
    """PIDs of live processes whose command line mentions `marker`."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (d / "stat").read_text().split()[2]
        except OSError:
            continue
        if marker in cmd and state != "Z":
            out.append(int(d.name))
    return out


class Launcher:
    """`htlm launch ...` as a user runs it, into `where`/run (its stderr in where/launcher.err, its --json summary in
    where/launcher.out), on a ROS domain of its own; helper processes (tests/ros/ros_tools.py) join that domain."""

    def __init__(self, where: Path, *args: str) -> None:
        where.mkdir(parents=True, exist_ok=True)
        self.tmp = where
        self.run = where / "run"
        self.out = where / "launcher.err"
        self.summary = where / "launcher.out"
        self.domain = next_domain()
        self.helpers: list[subprocess.Popen[bytes]] = []
        with open(self.out, "wb") as err, open(self.summary, "wb") as out:
            self.popen = subprocess.Popen(
                [HTLM, "launch", *args, "--domain-id", str(self.domain), "--run-dir", str(self.run), "--json"],
                stdout=out,
                stderr=err,
                start_new_session=True,
            )

    def said(self) -> str:
        return self.out.read_text(errors="replace")

    def log(self, name: str) -> str:
        f = self.run / "logs" / f"{name}.log"
        return f.read_text(errors="replace") if f.exists() else ""

    def pid(self, name: str) -> int:
        """The live process of `name` (its parameters file is on its command line; one at a time)."""
        pids = alive_with(str(self.run / "parameters" / f"{name}.yaml"))
        assert len(pids) == 1, f"{name}: processes {pids}"
        return pids[0]

    def run_id(self) -> str:
        """The run id the launch keeps in RUN/run_id (waited for)."""
        f = self.run / "run_id"
        self.wait_for(lambda: f.exists() and f.read_text().strip(), 60, "the launch's run id (RUN/run_id)")
        return f.read_text().strip()

    def wait_for(self, what: Callable[[], Any], timeout: float, why: str) -> Any:
        """Wait for `what()` to be truthy; fail naming `why` (and what the launcher said) after `timeout` seconds."""
        end = time.monotonic() + timeout
        while True:
            got = what()
            if got:
                return got
            assert self.popen.poll() is None, (
                f"the launcher exited ({self.popen.returncode}) before {why}:\n" + (self.said()[-3000:])
            )
            assert time.monotonic() < end, (
                f"timed out after {timeout} s waiting for {why}; the launcher said:\n" + (self.said()[-3000:])
            )
            time.sleep(0.05)

    def helper(self, *args: str) -> subprocess.Popen[bytes]:
        """Start tests/ros/ros_tools.py with these arguments on the launch's domain (its output in where/)."""
        from htlm_agent.ros.launch import LaunchConfig, ros_env

        env = ros_env(LaunchConfig(mode="deploy", scenario=builtin(), domain_id=self.domain))
        log = open(self.tmp / f"helper-{len(self.helpers)}-{args[0]}.log", "wb")  # noqa: SIM115
        p = subprocess.Popen([sys.executable, str(TOOLS), *args], env=env, stdout=log, stderr=subprocess.STDOUT)
        self.helpers.append(p)
        return p

    def jsonl(self, name: str) -> list[dict[str, Any]]:
        """The complete lines of RUN/<name>.jsonl (world, agent1, ...)."""
        return _jsonl(self.run / f"{name}.jsonl")

    def agent_episodes(self, name: str) -> list[dict[str, Any]]:
        return self.jsonl(name)

    def stop(self) -> None:
        if self.popen.poll() is None:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait()
        for pid in alive_with(str(self.run)):
            os.kill(pid, signal.SIGKILL)
        for h in self.helpers:
            if h.poll() is None:
                h.kill()
            h.wait()


def in_process(scenario: Scenario, seed: int, b: int, policy: str, batch: int = 1) -> Any:
    """The in-process Team's trajectory of batch b (B = `batch` episodes b*B..b*B+B-1; with batch 1, episode b) with
    per-agent built-in policies: Team(scenario, B, seed, episode=b) and DecentralizedPolicy.begin(b)."""
    pols, eps = builtin_team(scenario, policy)
    return reference(scenario, pols, seed, eps, b, batch)


def assert_same_as_in_process(team: RosTeam, seed: int, policy: str | Callable[[int], Any]) -> int:
    """Every episode the world logged equals the in-process rollout of its batch (B = the launch's batch; episode
    e is entry e % B of batch e // B): levels, assignments and observations (world log), and each agent's
    assignments, broadcast levels and rewards (agent logs; in train mode agents log only the first episode of each
    batch). `policy` is a built-in policy's name or a function of the batch index b returning the trajectory of
    Team(scenario, B, seed, b). Returns the episodes compared."""
    sc = team.cfg.scenario
    B = max(1, team.cfg.batch)
    agents = {a.name: {x["episode"]: x for x in team.agent_episodes(a.name)} for a in sc.agents}
    episodes = team.world_episodes()
    assert episodes, "no episode finished"
    assert len({w["metrics"]["episode"] for w in episodes}) == len(episodes), "an episode logged twice"
    cache: dict[int, Any] = {}
    sizes: dict[int, int] = {}  # a run's last batch is shorter when its episodes are not a multiple of B
    for w in episodes:
        sizes[w["metrics"]["episode"] // B] = sizes.get(w["metrics"]["episode"] // B, 0) + 1
    for w in episodes:
        e = w["metrics"]["episode"]
        b, i = divmod(e, B)
        if b not in cache:
            cache[b] = policy(b) if callable(policy) else in_process(sc, seed, b, policy, sizes[b])
        tr = cache[b]
        assert np.array_equal(tr.levels[:, i], w["levels"]), f"episode {e}: levels differ"
        assert np.array_equal(tr.actions[:, i], w["actions"]), f"episode {e}: assignments differ"
        assert np.array_equal(tr.observations[:, i], w["observations"]), f"episode {e}: observations differ"
        for k, a in enumerate(sc.agents):
            rec = agents[a.name].get(e)
            if rec is None and team.cfg.mode == "train" and i > 0:
                continue
            assert rec is not None, f"episode {e}: {a.name} logged no record"
            assert rec["actions"] == tr.actions[:, i, k].tolist(), f"episode {e} {a.name}: actions differ"
            assert rec["messages"] == tr.messages[:, i, k].tolist(), f"episode {e} {a.name}: broadcasts differ"
            assert rec["rewards"] == tr.rewards[:, i, k].tolist(), f"episode {e} {a.name}: rewards differ"
    return len(episodes)


def read_json(path: Path, timeout: float = 10.0) -> Any:
    end = time.monotonic() + timeout
    while True:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            if time.monotonic() > end:
                raise
            time.sleep(0.1)


def wait_team(procs: dict[str, subprocess.Popen[bytes]], run: Path, timeout: float) -> dict[str, int]:
    """Every process's exit code (all must be 0: the failure message holds the world's output and log tail)."""
    end = time.monotonic() + timeout
    try:
        codes = {name: p.wait(timeout=max(0.1, end - time.monotonic())) for name, p in procs.items()}
    except subprocess.TimeoutExpired:
        codes = {name: p.poll() if p.poll() is not None else -999 for name, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    outs = {name: p.stdout.read().decode() if p.stdout else "" for name, p in procs.items()}
    logs = run / "logs"
    tails = {n: (logs / f"{n}.log").read_text()[-1500:] for n in procs if (logs / f"{n}.log").exists()}
    assert codes == dict.fromkeys(procs, 0), (codes, outs["world"], tails)
    return codes
