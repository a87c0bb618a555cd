"""The launcher supervises the team: kills through `htlm launch` itself, the entry point users run (real processes over
real DDS, no fixture starting them). Each kind of process the launcher started is SIGKILLed in turn; the launcher
must say so with the exit code, start it again, and the others must not notice: in a deployed team (`--robots sim
--record`) the agents never killed act at every step; in a training launch the killed world, agent and trainer
resume and the run ends with exit code 0. The launcher's choices per exit are tested without ROS in
tests/test_supervise.py."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from typing import Any

import pytest

from htlm_world.clock import StepClock
from support.ros import Launcher, alive_with

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PERIOD = 0.5
STAMP = re.compile(r"\[(?:INFO|WARN|ERROR)\] \[(\d+\.\d+)\]")


def _after(team: Launcher, name: str, start: int, pattern: str, timeout: float, why: str) -> re.Match[str]:
    """The first match of `pattern` in `name`'s log after byte `start`, waited for."""
    found: re.Match[str] | None = team.wait_for(
        lambda: re.search(pattern, team.log(name)[start:]), timeout, f"{name} to log {why} ({pattern!r})"
    )
    assert found is not None
    return found


@pytest.mark.timeout(420)
def test_a_deployed_team_restarts_whatever_is_killed_and_the_others_miss_no_step(launcher: Any) -> None:
    team = launcher(
        *("deploy", "--robots", "sim", "--policy", "greedy", "--record", "--episodes", "0", "--period", str(PERIOD)),
        *("--respawn-delay", "0.5", "--agent-param", "broadcast_timeout=0.2", "--world-param", "begin_deadline=5.0"),
    )
    run = team.run
    f = run / "agent1.run.json"
    team.wait_for(lambda: f.exists() and json.loads(f.read_text())["epoch"] > 0, 120, "the team's epoch (agent1)")
    rec = json.loads(f.read_text())
    horizon = rec["scenario"]["horizon"]
    clock = StepClock(rec["epoch"], PERIOD, horizon, 0, 0)
    now = lambda: clock.last(time.time())  # noqa: E731  # the step index in progress on the team's clock
    # what each process logs once it is back; with the step it rejoined at (episode, step) where it says it
    back = {
        "world": r"observing the agents' clock from episode (\d+) step (\d+)",
        "agent3": r"joined the team's clock at episode (\d+) step (\d+)",
        "operation": r"joined the team's clock at episode (\d+) step (\d+)",
        "robot_agent2": r"run \S+: robot of agent2 at",
        "recorder": r"recording \d+ topics into \S+recording_1",
        "trainer": r"run \S+: mode deploy",
    }
    report: dict[str, dict[str, Any]] = {}
    i = now() + 2
    for name, pattern in back.items():
        team.wait_for(lambda i=i: now() >= i, 60 + i * PERIOD, f"step index {i} (before killing {name})")
        pid, start, said = team.pid(name), len(team.log(name)), len(team.said())
        os.kill(pid, signal.SIGKILL)
        killed_at, t_kill = now(), time.time()
        restarted = team.wait_for(
            lambda said=said, name=name: re.search(rf"{name} restarted \(pid (\d+)", team.said()[said:]),
            30,
            f"the launcher to restart {name}",
        )
        assert f"{name} exited with -9; restarting it" in team.said()[said:]
        assert int(restarted.group(1)) != pid
        m = _after(team, name, start, pattern, 60, "that it is back")
        text = team.log(name)[start:]
        stamp = STAMP.search(text[text.rfind("\n", 0, m.start()) + 1 : m.start()])  # the ROS time of that line
        assert stamp is not None, text[-2000:]
        t_back = float(stamp.group(1))
        joined = clock.index(int(m.group(1)), int(m.group(2))) if m.groups() else clock.last(t_back)
        report[name] = {"killed": killed_at, "rejoined": joined, "seconds": round(t_back - t_kill, 2)}
        i = max(now(), joined) + 2
    # every agent logs the episode after the last rejoin: the steps they took around every kill are in their logs
    last = max(r["rejoined"] for r in report.values()) // horizon
    agents = [f"agent{k}" for k in range(1, 6)]
    for a in agents:
        team.wait_for(
            lambda a=a: any(x["episode"] > last for x in team.agent_episodes(a)),
            60 + 2 * horizon * PERIOD,
            f"{a} to log episode {last + 1}",
        )
    os.kill(team.popen.pid, signal.SIGINT)  # Ctrl-C: the team stops cleanly
    assert team.popen.wait(timeout=60) == 130, team.said()[-3000:]
    assert alive_with(str(run)) == [], "orphaned processes"
    said = team.said()
    assert "restarts: " in said and all(f"{n} 1" in said.rsplit("restarts: ", 1)[1] for n in back), said[-2000:]
    # the agents never killed acted at every step of every episode, whoever was down
    missed = {}
    for a in agents:
        acted = {
            clock.index(x["episode"], t + 1)
            for x in team.agent_episodes(a)
            for t, yes in enumerate(x["acted"])
            if yes and x["episode"] <= last + 1
        }
        missed[a] = sorted(set(range((last + 2) * horizon)) - acted)  # an episode it did not log: every step
    assert all(not missed[a] for a in agents if a != "agent3"), missed
    # the killed agent acted at every step from its rejoin on (its log counts the steps of the episode before its
    # rejoin as missed, also those its first process took before the kill)
    k3, gap = report["agent3"], missed["agent3"]
    assert gap and max(gap) < k3["rejoined"], (k3, gap)
    # the restarted recorder recorded into the next recording; the first one holds what came before the kill
    assert (run / "recording_1" / "metadata.yaml").exists() and (run / "recording").is_dir()
    print(
        "killed (step index at the kill), rejoined (step index), seconds from the kill to the rejoin line: "
        + json.dumps(report)
    )
    print(
        f"agents never killed missed 0 steps in {last + 2} episodes; agent3 was down for "
        f"{k3['rejoined'] - k3['killed']} steps and acted at every step from its rejoin on"
    )


@pytest.mark.timeout(420)
def test_a_training_launch_restarts_a_killed_world_agent_and_trainer_and_finishes(launcher: Any) -> None:
    episodes, batch = 48, 4
    team = launcher(
        *("train", "--episodes", str(episodes), "--eval-episodes", "0", "--seed", "4", "--respawn-delay", "0.5"),
        *("--set", f"envs={batch}", "--set", "learning_starts=60", "--set", "batch_size=32", "--set", "memory=5000"),
        *("--trainer-param", "checkpoint_every=4", "--agent-param", "resend_period=0.5"),
        *("--agent-param", "stop_timeout=20.0", "--agent-param", "broadcast_timeout=0.5"),
        *("--world-param", "act_deadline=2.0", "--world-param", "begin_deadline=2.0"),
        *("--world-param", "update_deadline=2.0"),
    )
    run = team.run

    def logged() -> list[dict[str, Any]]:
        f = run / "world.jsonl"
        text = f.read_text() if f.exists() else ""
        return [json.loads(x)["metrics"] for x in text[: text.rfind("\n") + 1].splitlines()]

    back = {
        "world": r"continuing at episode (\d+)",
        "agent3": r"run \S+",
        "trainer": r"resumed from",
    }
    at: dict[str, int] = {}
    came: dict[str, re.Match[str]] = {}
    for name, pattern in back.items():
        n = len(logged()) + batch
        team.wait_for(lambda n=n: len(logged()) >= n, 120, f"episode {n} (before killing {name})")
        if name == "trainer":
            meta = run / "trainer" / "checkpoint" / "meta.json"
            team.wait_for(meta.exists, 60, "the trainer's first checkpoint")
        pid, start, said = team.pid(name), len(team.log(name)), len(team.said())
        os.kill(pid, signal.SIGKILL)
        at[name] = len(logged())
        team.wait_for(
            lambda said=said, name=name: f"{name} restarted (pid" in team.said()[said:],
            30,
            f"the launcher to restart {name}",
        )
        assert f"{name} exited with -9; restarting it" in team.said()[said:]
        came[name] = _after(team, name, start, pattern, 60, "that it is back")
    assert team.popen.wait(timeout=300) == 0, team.said()[-3000:]
    assert alive_with(str(run)) == [], "orphaned processes"
    summary = json.loads(team.summary.read_text())
    assert summary["exit_code"] == 0 and summary["episodes"] == episodes, summary
    said = team.said()
    assert all(f"{n} 1" in said.rsplit("restarts: ", 1)[1] for n in back), said[-2000:]
    eps = logged()
    assert sorted(e["episode"] for e in eps) == list(range(episodes)), "every episode logged once"
    assert int(came["world"].group(1)) == at["world"], "the restarted world continued at its first batch not logged"
    # the restarted agent rejoins at the begin of a later batch: absent in the batch of its kill, then not
    absent = {e["episode"]: e["absent"] for e in eps}
    rejoined = next(e for e in sorted(absent) if e >= at["agent3"] and absent[e][2] == 0 and e % batch == 0)
    assert all(absent[e][2] == 0 for e in absent if e >= rejoined), absent
    # the others play on: a teammate waiting for the killed agent's last broadcast may miss a step, no more
    others = {e: a[:2] + a[3:] for e, a in absent.items() if sum(a[:2] + a[3:])}
    assert all(max(a) <= 2 for a in others.values()), others
    meta = json.loads((run / "trainer" / "checkpoint" / "meta.json").read_text())
    assert meta["episodes_done"] == episodes, meta
    print(
        f"killed after episodes {at}; the world continued at its first batch not logged, agent3 rejoined at episode "
        f"{rejoined}; absences of the agents never killed (episode: absences) {others}; checkpoint after "
        f"{meta['episodes_done']} episodes"
    )
