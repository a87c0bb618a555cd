"""Fixtures of the ROS integration tests: a team of real processes over real DDS (Fast DDS from the PyPI wheels),
on a ROS domain of its own per test and with localhost-only discovery, always cleaned up. What the tests share
beside fixtures is in tests/support/ros.py."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.ros.launch import LaunchConfig
from htlm_world.scenario import builtin
from support.ros import Launcher, RosTeam, next_domain

from .links import LinkEmulator, unavailable


@pytest.fixture
def ros_team(tmp_path: Path) -> Iterator[Callable[..., RosTeam]]:
    """Factory: ros_team(mode=..., episodes=..., ...) -> RosTeam (not started), cleaned up after the test."""
    teams: list[RosTeam] = []

    def make(**kw: Any) -> RosTeam:
        kw.setdefault("scenario", builtin())
        kw.setdefault("mode", "evaluate")
        kw.setdefault("policy", "greedy")
        kw.setdefault("run_dir", tmp_path / f"run{len(teams)}")
        kw.setdefault("domain_id", next_domain())
        kw.setdefault("echo", False)
        # generous deadlines: on a loaded machine a slow step must not turn into an absent agent (which would change
        # the run); when every agent answers, no deadline is ever waited for, so this costs nothing
        kw["world_params"] = {"act_deadline": 10.0, "update_deadline": 10.0, **kw.get("world_params", {})}
        kw["agent_params"] = {"broadcast_timeout": 5.0, **kw.get("agent_params", {})}
        team = RosTeam(tmp_path, LaunchConfig(**kw))
        teams.append(team)
        return team

    yield make
    for t in teams:
        t.cleanup()


@pytest.fixture
def launcher(tmp_path: Path) -> Iterator[Callable[..., Launcher]]:
    """Factory: launcher(*args of htlm launch, where=tmp_path) -> a started Launcher, stopped after the test."""
    made: list[Launcher] = []

    def make(*args: str, where: Path | None = None) -> Launcher:
        made.append(Launcher(where or tmp_path, *args))
        return made[-1]

    yield make
    for x in made:
        x.stop()


@pytest.fixture
def links() -> Iterator[Callable[..., LinkEmulator]]:
    """Factory: links(hosts, seed=0, mtu=65000) -> a started LinkEmulator (tests/ros/links.py: a namespace per host
    joined by a user-space switch with loss, delay and partitions set at run time), its tag a fresh domain id; torn
    down after the test, whatever happened. Skips the test, with the reason, where it cannot be made."""
    made: list[LinkEmulator] = []

    def make(hosts: list[str], seed: int = 0, mtu: int = 65000) -> LinkEmulator:
        why = unavailable()
        if why:
            pytest.skip(why)
        e = LinkEmulator(hosts, tag=next_domain(), seed=seed, mtu=mtu)
        made.append(e)
        try:
            e.up()
        except OSError as err:
            pytest.skip(f"cannot make the link emulator here: {err}")
        return e

    yield make
    for e in made:
        e.down()
