"""`htlm bench ros`: episode-steps per second of the batched lockstep over ROS 2 (world + 5 agent processes +
trainer = 7 processes on real DDS) at B = 1, 16, 64, 128 and 256, each beside the in-process runtime at the same B with
the same per-agent policies, and the wall time of a training run over ROS beside `htlm train` with the same budget,
all measured in one run. Also `python -m htlm_agent.ros.bench [--json]`.
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

TARGET_EPISODE_STEPS_PER_S = 10_000.0
"""Target of the batched lockstep at B = 64 with 7 processes on a 2-core machine (episode-steps per second)."""

TARGET_TRAIN_RATIO = 3.0
"""Target: a training run over ROS takes at most this many times the wall time of `htlm train` with its budget."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the ROS benchmark (added to `htlm bench`)."""
    from htlm_agent.session.builtin import BUILTIN_POLICIES

    p.add_argument(
        "--ros-batches",
        default="1,16,64,128,256",
        help="ros: batch sizes B to time, comma-separated (default 1,16,64,128,256)",
    )
    p.add_argument(
        "--ros-batches-timed", type=int, default=3, help="ros: batches timed per B after the first (default 3)"
    )
    p.add_argument(
        "--ros-policy",
        choices=BUILTIN_POLICIES,
        default="greedy",
        help="ros: the agents' built-in policy of the timed evaluations (default greedy)",
    )
    p.add_argument(
        "--ros-train-episodes",
        type=int,
        default=None,
        help="ros: episodes of the timed training runs, over ROS and in process (default: htlm train's budget, "
        "12288; 0: none)",
    )
    p.add_argument("--domain-id", type=int, default=99, help="ros, scale: ROS_DOMAIN_ID of the teams (default 99)")
    p.add_argument("--keep", default="", metavar="DIR", help="ros: keep the run directories here")


def inprocess_rate(policy: str, batch: int, batches: int, seed: int = 0) -> float:
    """Episode-steps per second of the in-process runtime at batch B with the same per-agent policies."""
    from htlm_agent.mind.policies import DecentralizedPolicy
    from htlm_agent.runtime.team import Team, rollout
    from htlm_agent.session.builtin import builtin_policy
    from htlm_world.scenario import builtin

    sc = builtin()
    pols = [builtin_policy(sc, policy, i) for i in range(sc.n_agents)]
    dp = DecentralizedPolicy([p for p, _ in pols], seed, pols[0][1])
    dp.begin(0)
    rollout(Team(sc, batch, seed, episode=0), dp)  # warm-up
    t0 = time.perf_counter()
    for b in range(1, batches + 1):
        dp.begin(b)
        rollout(Team(sc, batch, seed, episode=b), dp)
    return batches * batch * sc.horizon / (time.perf_counter() - t0)


def _batch_seconds(run_dir: Path, batch: int) -> list[float]:
    """Seconds of every finished batch of a run (world.jsonl: the episodes of a batch share its seconds)."""
    f = run_dir / "world.jsonl"
    eps = [json.loads(x)["metrics"] for x in f.read_text().splitlines()] if f.exists() else []
    return [eps[i]["seconds"] for i in range(0, len(eps), batch)]


def ros_rate(batch: int, batches: int, policy: str, domain: int, run_dir: Path) -> tuple[float, int]:
    """Episode-steps per second over ROS at batch B (the first batch, with the start-up, is not timed), and the
    absent agent-steps of the run."""
    from htlm_agent.ros.launch import LaunchConfig, run_team, summarize
    from htlm_world.scenario import builtin

    sc = builtin()
    cfg = LaunchConfig(
        mode="evaluate",
        scenario=sc,
        episodes=batch * (batches + 1),
        batch=batch,
        seed=0,
        run_dir=run_dir,
        policy=policy,
        domain_id=domain,
        echo=False,
    )
    code = run_team(cfg)
    secs = _batch_seconds(run_dir, batch)
    if code != 0 or len(secs) < batches + 1:
        raise SystemExit(f"htlm bench ros: the team failed at B={batch} (exit {code}); logs in {run_dir / 'logs'}")
    timed = secs[1:]
    return batch * sc.horizon * len(timed) / sum(timed), int(summarize(run_dir).get("absent_agent_steps", 0))


def train_walls(episodes: int, domain: int, run_dir: Path) -> dict[str, float]:
    """Wall seconds of a training run over ROS (7 processes, start-up included) and of `htlm train` in process,
    both with `episodes` episodes of the default settings and no validation or final evaluation."""
    from htlm_agent.learning.run import train
    from htlm_agent.learning.settings import Settings
    from htlm_agent.ros.launch import LaunchConfig, run_team
    from htlm_world.scenario import builtin

    sc = builtin()
    learner = {"episodes": episodes, "validate_every": 0, "eval_episodes": 0}
    s = Settings.from_dict(learner, "bench")
    cfg = LaunchConfig(
        mode="train",
        scenario=sc,
        episodes=episodes,
        batch=s.envs,
        seed=0,
        run_dir=run_dir / "ros-train",
        learner=learner,
        domain_id=domain,
        echo=False,
    )
    t0 = time.monotonic()
    code = run_team(cfg)
    ros_wall = time.monotonic() - t0
    if code != 0:
        raise SystemExit(f"htlm bench ros: the training run failed (exit {code}); logs in {cfg.run_dir / 'logs'}")
    t0 = time.monotonic()
    train(sc, s, run_dir / "inprocess-train", progress=False, tensorboard=False, evaluate_at_end=False)
    return {"ros": ros_wall, "inprocess": time.monotonic() - t0}


def ros_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Time the batched lockstep over ROS at every B (and the in-process runtime at the same B right after), then a
    training run over ROS beside `htlm train`; every ratio is of two numbers measured in this run."""
    from htlm_agent.learning.settings import Settings

    batches = [int(x) for x in str(getattr(args, "ros_batches", "1,16,64,128,256")).split(",") if x.strip()]
    timed = max(1, int(getattr(args, "ros_batches_timed", 3)))
    policy = getattr(args, "ros_policy", "greedy")
    domain = int(getattr(args, "domain_id", 99))
    train_episodes = getattr(args, "ros_train_episodes", None)
    train_episodes = Settings().episodes if train_episodes is None else int(train_episodes)
    keep = getattr(args, "keep", "")
    tmp = None
    if keep:
        root = Path(keep)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="htlm-bench-ros-")
        root = Path(tmp.name)
    rows = []
    for b in batches:
        n = timed if b > 1 else max(timed, 20)
        rate, absent = ros_rate(b, n, policy, domain, root / f"B{b}")
        inproc = inprocess_rate(policy, b, max(n, 3))
        rows.append(
            {
                "batch": b,
                "ros_episode_steps_per_s": round(rate, 1),
                "inprocess_episode_steps_per_s": round(inproc, 1),
                "ratio_ros_to_inprocess": round(rate / inproc, 3),
                "absent_agent_steps": absent,
            }
        )
        print(
            f"B={b:4d}: {rate:9.1f} episode-steps/s over ROS, {inproc:10.1f} in process (ratio {rate / inproc:.3f})",
            file=sys.stderr,
            flush=True,
        )
    out: dict[str, Any] = {
        "processes": 7,
        "policy": policy,
        "batches": rows,
        "target_episode_steps_per_s_at_B64": TARGET_EPISODE_STEPS_PER_S,
    }
    at64 = [r for r in rows if r["batch"] == 64]
    if at64:
        out["target_met_at_B64"] = at64[0]["ros_episode_steps_per_s"] >= TARGET_EPISODE_STEPS_PER_S
    if train_episodes > 0:
        walls = train_walls(train_episodes, domain, root)
        out["training"] = {
            "episodes": train_episodes,
            "ros_wall_s": round(walls["ros"], 1),
            "inprocess_wall_s": round(walls["inprocess"], 1),
            "ratio_ros_to_inprocess": round(walls["ros"] / walls["inprocess"], 2),
            "target_ratio": TARGET_TRAIN_RATIO,
            "target_met": walls["ros"] <= TARGET_TRAIN_RATIO * walls["inprocess"],
        }
    out["cpu_count"] = os.cpu_count()
    if tmp is not None:
        tmp.cleanup()
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m htlm_agent.ros.bench [--json] ...`."""
    p = argparse.ArgumentParser(prog="python -m htlm_agent.ros.bench", description=__doc__)
    p.add_argument("--json", action="store_true", help="print JSON")
    add_arguments(p)
    args = p.parse_args(argv)
    res = ros_bench(args)
    print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
