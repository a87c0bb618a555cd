"""A deployed team keeps its own step clock: real processes over real DDS (`--robots sim`, greedy
agents, a 0.5 s period). One process at a time is SIGKILLed and started again: the observing world, an agent, the
robots' stand-in operation, the trainer (in deployment it only records). The others miss no step (every agent that
was not killed acted at every step of every episode, by its own log) and the restarted one rejoins at the step in
progress (by its log: the step it joined at, and its episode log idle before it and acting from it on)."""

from __future__ import annotations

import json
import re
import time
from typing import Any

import pytest

from htlm_world.clock import StepClock

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240), pytest.mark.slow]  # 14 processes for a minute

PERIOD = 0.5
EPISODES = 4
GAP = 4
"""Instants a killed process stays dead."""


def _clock(team: Any) -> StepClock:
    f = team.run_dir / "agent1.run.json"
    team.wait_for(lambda: f.exists(), 90, "agent1 to keep the run announcement with the epoch (RUN/agent1.run.json)")
    rec = json.loads(f.read_text())
    assert rec["epoch"] > 0.0 and rec["period"] == PERIOD, rec
    return StepClock(rec["epoch"], PERIOD, team.cfg.scenario.horizon, 0, EPISODES)


def _at(team: Any, clock: StepClock, i: int, why: str) -> None:
    """Wait until the instant of step index i has passed on the team's clock."""
    team.wait_for(lambda: clock.last(time.time()) >= i, 60 + i * PERIOD, f"the instant of step index {i} ({why})")


def _log_after(team: Any, name: str, start: int, pattern: str, why: str) -> re.Match[str]:
    found: list[re.Match[str]] = []

    def seen() -> bool:
        m = re.search(pattern, team.log(name)[start:])
        if m is not None:
            found.append(m)
        return m is not None

    team.wait_for(seen, 60, f"{name} to log {why} ({pattern!r})")
    return found[0]


def test_any_one_process_killed_costs_the_others_no_step_and_rejoins_at_the_current_step(ros_team: Any) -> None:
    team = ros_team(
        mode="deploy",
        policy="greedy",
        episodes=EPISODES,
        seed=4,
        robots="sim",
        period=PERIOD,
        world_params={"begin_deadline": 5.0},
        agent_params={"broadcast_timeout": 0.2},
    )
    sc = team.cfg.scenario
    agents = [a.name for a in sc.agents]
    robots = [f"robot_{a}" for a in agents]
    team.start("world", "operation", "trainer", *agents, *robots)
    clock = _clock(team)
    victim = "agent3"
    rejoined: dict[str, tuple[int, int]] = {}
    killed_at: dict[str, int] = {}
    restarted_at: dict[str, int] = {}
    """The step index in progress when the process was started again: it cannot join before it."""
    i = 6
    patterns = {
        "world": r"observing the agents' clock from episode (\d+) step (\d+)",
        victim: r"joined the team's clock at episode (\d+) step (\d+)",
        "operation": r"joined the team's clock at episode (\d+) step (\d+)",
        "trainer": r"run \S+",
    }
    for name in ("world", victim, "operation", "trainer"):
        _at(team, clock, i, f"before killing {name}")
        team.kill(name)
        killed_at[name] = clock.last(time.time())
        _at(team, clock, killed_at[name] + GAP, f"{name} dead for {GAP} steps")
        start = len(team.log(name))
        restarted_at[name] = clock.last(time.time())
        team.start(name)
        m = _log_after(team, name, start, patterns[name], "that it is back")
        if name != "trainer":
            rejoined[name] = (int(m.group(1)), int(m.group(2)))
        i = clock.last(time.time()) + 2
    assert team.wait("world", 150) == 0
    codes = team.wait_all(40)
    assert codes == dict.fromkeys(codes, 0), codes

    h = sc.horizon
    # the agents never killed took every step of every episode on their own clock, whoever was away
    for a in agents:
        if a == victim:
            continue
        eps = team.agent_episodes(a)
        assert [x["episode"] for x in eps] == list(range(EPISODES)), a
        gaps = [(x["episode"], t + 1) for x in eps for t, acted in enumerate(x["acted"]) if not acted]
        assert gaps == [], f"{a} missed steps {gaps}"
    # the restarted agent rejoined at the step in progress: idle before it, acting from it on
    e, t = rejoined[victim]
    join = clock.index(e, t)
    assert restarted_at[victim] <= join <= restarted_at[victim] + 40, (restarted_at, rejoined)
    eps = {x["episode"]: x for x in team.agent_episodes(victim)}
    assert eps[e]["acted"] == [False] * (t - 1) + [True] * (h - t + 1), eps[e]["acted"]
    assert all(all(eps[x]["acted"]) for x in range(e + 1, EPISODES)), "missed a step after rejoining"
    # the operation rejoined at the step in progress too; the observer logged every episode it saw to its end
    e_op, t_op = rejoined["operation"]
    assert restarted_at["operation"] <= clock.index(e_op, t_op) <= restarted_at["operation"] + 40, restarted_at
    e_w, t_w = rejoined["world"]
    assert restarted_at["world"] <= clock.index(e_w, t_w) <= restarted_at["world"] + 40, restarted_at
    world_eps = team.world_episodes()
    logged = [w["metrics"]["episode"] for w in world_eps]
    assert logged == list(range(EPISODES)), logged
    # the observer rebuilt the steps it missed while down from the agents' records: its joint assignments of
    # those steps are the ones the agents logged
    mine = {a: {x["episode"]: x["actions"] for x in team.agent_episodes(a)} for a in agents if a != victim}
    seen = world_eps[e_w]["actions"]
    for k, a in enumerate(agents):
        if a != victim:
            assert [row[k] for row in seen[: t_w - 1]] == mine[a][e_w][: t_w - 1], f"{a}: steps 1..{t_w - 1}"
    print(
        f"killed at step index {killed_at}; {victim} rejoined at episode {e} step {t} (index {join}), "
        f"the operation at episode {e_op} step {t_op}, the world at episode {e_w} step {t_w}; "
        f"the world logged episodes {logged}; "
        "the agents never killed missed 0 steps"
    )
