"""`htlm bench ros`: lockstep steps per second of a team over ROS 2 (world + 5 agent processes + trainer = 7
processes on real DDS) and its ratio to the in-process runtime (batch 1, the same per-agent policies), measured in
one run. Also `python -m htlm_agent.experiments.ros_bench [--json]`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TARGET_STEPS_PER_S = 100.0
"""The ROS runtime's target on a 2-core machine (issue 4)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the ROS benchmark (added to `htlm bench`)."""
    p.add_argument("--ros-episodes", type=int, default=20, help="ros: episodes of the timed run (default 20)")
    p.add_argument(
        "--ros-mode",
        choices=("evaluate", "train"),
        default="evaluate",
        help="ros: evaluate (greedy policy per agent, default) or train (Q-networks, ε-greedy, learner)",
    )
    p.add_argument(
        "--ros-policy",
        choices=("greedy", "random"),
        default="greedy",
        help="ros, evaluate: the agents' built-in policy (default greedy)",
    )
    p.add_argument("--domain-id", type=int, default=99, help="ros: ROS_DOMAIN_ID of the timed team (default 99)")
    p.add_argument("--keep", default="", metavar="DIR", help="ros: keep the run directory here")


def inprocess_rate(policy: str, episodes: int, seed: int = 0) -> float:
    """Steps per second of the in-process runtime, batch 1, with the same decentralized per-agent policies."""
    from htlm_agent.mind.policies import DecentralizedPolicy, builtin_policy
    from htlm_agent.runtime.team import Team, rollout
    from htlm_world.scenario import builtin

    sc = builtin()
    pols = [builtin_policy(sc, policy, i) for i in range(sc.n_agents)]
    dp = DecentralizedPolicy([p for p, _ in pols], seed, pols[0][1])
    dp.begin(0)
    rollout(Team(sc, 1, seed, episode=0), dp)  # warm-up
    t0 = time.perf_counter()
    for e in range(episodes):
        dp.begin(e)
        rollout(Team(sc, 1, seed, episode=e), dp)
    return episodes * sc.horizon / (time.perf_counter() - t0)


def ros_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Run a team over ROS, time its lockstep steps, and the in-process runtime right after."""
    from htlm_agent.ros.launch import LaunchConfig, run_team
    from htlm_world.scenario import builtin

    episodes = max(3, int(getattr(args, "ros_episodes", 20)))
    mode = getattr(args, "ros_mode", "evaluate")
    policy = getattr(args, "ros_policy", "greedy")
    keep = getattr(args, "keep", "")
    tmp = None
    if keep:
        run_dir = Path(keep)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="htlm-bench-ros-")
        run_dir = Path(tmp.name)
    sc = builtin()
    cfg = LaunchConfig(
        mode=mode,
        scenario=sc,
        episodes=episodes,
        seed=0,
        run_dir=run_dir,
        policy=policy if mode == "evaluate" else "auto",
        domain_id=int(getattr(args, "domain_id", 99)),
        echo=False,
    )
    t0 = time.monotonic()
    code = run_team(cfg)
    wall = time.monotonic() - t0
    lines = (run_dir / "world.jsonl").read_text().splitlines() if (run_dir / "world.jsonl").exists() else []
    eps = [json.loads(x)["metrics"] for x in lines]
    if code != 0 or len(eps) < episodes:
        raise SystemExit(
            f"htlm bench ros: the team failed (exit {code}, {len(eps)} of {episodes} episodes); "
            f"logs in {run_dir / 'logs'}"
        )
    timed = eps[1:]  # the first episode includes the start-up of the processes
    seconds = sum(e["seconds"] for e in timed)
    steps = len(timed) * sc.horizon
    ros_rate = steps / seconds
    inproc = inprocess_rate(policy if mode == "evaluate" else "random", max(10, episodes))
    out = {
        "processes": 2 + sc.n_agents,
        "agents": sc.n_agents,
        "mode": mode,
        "policy": policy if mode == "evaluate" else "q-network (epsilon-greedy) + learner",
        "episodes_timed": len(timed),
        "ros_lockstep_steps_per_s": round(ros_rate, 1),
        "inprocess_steps_per_s_B1": round(inproc, 1),
        "ratio_ros_to_inprocess": round(ros_rate / inproc, 3),
        "target_steps_per_s": TARGET_STEPS_PER_S,
        "target_met": ros_rate >= TARGET_STEPS_PER_S,
        "absent_agent_steps": sum(sum(e["absent"]) for e in eps),
        "launch_wall_s": round(wall, 1),
        "cpu_count": os.cpu_count(),
    }
    if tmp is not None:
        tmp.cleanup()
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m htlm_agent.experiments.ros_bench [--json] ...`."""
    p = argparse.ArgumentParser(prog="python -m htlm_agent.experiments.ros_bench", description=__doc__)
    p.add_argument("--json", action="store_true", help="print JSON")
    add_arguments(p)
    args = p.parse_args(argv)
    res = ros_bench(args)
    print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
