"""`htlm bench`: speed of the in-process runtime, all measured in one run so that ratios are meaningful.

- simulator agent-steps/s (`htlm_world.simulator.BatchSim`) at B = 1 and B = 1024;
- team agent-steps/s (simulator + every agent's belief filter and reward, `team.Team`) at B = 1 and B = 1024;
- learner gradient updates/s of the default settings (every agent's network, one update each);
- the wire's cost of the transitions an agent sends the trainer (`htlm/transition`) at B = 128 and B = 1024: encode,
  and decode with validation, in µs per transition (per episode row of a record), of the record in binary (v3) and
  of the same transitions as the JSON lists of v2, the ratio of the two;
- the wall time of a default training run (`htlm train` defaults, heterogeneous team, R_II on, medium T_RP) and
  whether it reached the quality targets.

With `--scenario` (and `--team`) every figure is of that scenario, the training run's targets are left out (they are
the paper's), and the team's agent-steps/s of the paper's team are measured in the same run beside it, with the cost
of an agent-step as a ratio to the paper's.

`htlm bench ros` measures the ROS 2 runtime: it calls `ros_bench(args) -> dict` of the module named in ROS_BENCH,
which the ROS runtime provides; this module does not depend on it. `htlm bench scale` measures what a team costs as
it grows, over ROS 2 (a process per agent and composed) and in process: `scale_bench(args) -> dict` of SCALE_BENCH.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import tempfile
from typing import Any

import numpy as np

from htlm_agent.experiments.speed import rate as _rate
from htlm_agent.experiments.speed import sim_rate, team_rate
from htlm_world.scenario import Scenario, ScenarioError, builtin, load

ROS_BENCH = "htlm_agent.ros.bench"
"""Module providing `ros_bench(args: argparse.Namespace) -> dict` and optionally `add_arguments(parser)`."""
SCALE_BENCH = "htlm_agent.ros.scale"
"""Module providing `scale_bench(args: argparse.Namespace) -> dict` and optionally `add_arguments(parser)`."""

OPTIMUM = {"heterogeneous": 7.09, "semi-heterogeneous": 6.70, "homogeneous": 7.61}
"""Expected completion step of the centralized optimum (docs/model.md, Reference figures)."""

TARGETS = {"completion_ratio": 1.25, "failure_rate": 0.01, "unused_fraction": 0.71}
"""Quality targets of a default run: completion <= 1.25 x optimum, failures <= 1 %, unused capability >= 71 %."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm bench`."""
    p.add_argument(
        "what",
        nargs="?",
        choices=["inproc", "ros", "scale"],
        default="inproc",
        help="inproc (default): simulator, team and learner in this process; ros: the ROS 2 runtime; scale: time to "
        "join, memory, CPU and agent-steps/s of teams of 5 to 100 agents over ROS 2, a process per agent and "
        "composed, and their team step and evaluations in process",
    )
    p.add_argument("--json", action="store_true", help="print the figures as JSON on stdout")
    p.add_argument("--seconds", type=float, default=2.0, help="measuring time per speed figure (default: 2)")
    p.add_argument("--no-train", action="store_true", help="skip the default training run")
    p.add_argument("--episodes", type=int, default=None, help="episodes of the training run (default: Settings)")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="keep the training run here (default: a temp dir); scale: write the results and runs here (default: "
        "runs/bench-scale-TIME)",
    )
    p.add_argument("--scenario", default=None, metavar="FILE", help="measure this scenario (a file or a shipped name)")
    p.add_argument("--team", default=None, help="a team of the scenario's `teams`")
    for name in (ROS_BENCH, SCALE_BENCH):
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:
                raise
        else:
            if hasattr(mod, "add_arguments"):
                mod.add_arguments(p)


def learner_rate(seconds: float, sc: Scenario | None = None) -> float:
    """Gradient updates/s of the default learner (each update trains every agent's network once)."""
    import torch

    from htlm_agent.learning.dqn import Learner
    from htlm_agent.learning.dqn_run import train_batch
    from htlm_agent.learning.run import keep_freed_memory
    from htlm_agent.learning.settings import Settings
    from htlm_agent.runtime.team import Team

    s = Settings()
    torch.set_num_threads(s.threads)
    keep_freed_memory()  # as train() does
    sc = sc or builtin()
    lr = Learner(sc, s.replace(learning_starts=1, updates_per_step=1))
    team = Team(sc, s.envs, 0)
    while int(lr.replay.size.min()) < s.batch_size:
        train_batch(lr, team, 0)
    r, _ = _rate(lambda: lr.train_step(), seconds)
    return r


def json_transition() -> Any:
    """`htlm/transition` v2, every array as JSON lists: what v3's binary arrays replaced, the yardstick of
    `wire_costs`."""
    from htlm_msgs_py import schema as S

    knowledge = S.Rows(S.FloatList(-1e6, 1e6, length="knowledge"))
    lists = {"k": knowledge, "a": S.Rows(S.Int(0, "action")), "r": S.Rows(S.Float(-1e6, 1e6)), "k2": knowledge}
    fields = {**S.TRANSITION.fields, **lists, "mask2": S.Rows(S.BoolList("actions"))}
    return S.Schema(S.TRANSITION.name, 2, fields, S.TRANSITION.max_bytes)


def wire_costs(batch: int, seconds: float, sc: Scenario | None = None) -> dict[str, float]:
    """µs per transition of encoding one agent's transition record of a step of B episodes (the sender's whole
    job: from the arrays to the text) and of decoding it with every check (the trainer's), in binary and as JSON
    lists; the transitions are a random team's fifth step, so the beliefs are as sparse as in a run."""
    from htlm_agent.baselines.heuristics import RandomPolicy
    from htlm_agent.runtime.team import Team
    from htlm_msgs_py import schema as S

    sc = sc or builtin()
    team = Team(sc, batch, 0)
    pol = RandomPolicy(sc, 0)
    team.reset()
    for _ in range(4):
        team.step(pol.act(team.context()))
    k = team.knowledge()
    a = pol.act(team.context())
    k2, r, _ = team.step(a)
    arrays = {"k": k[:, 0], "a": a[:, 0], "r": r[:, 0], "k2": k2[:, 0], "mask2": team.mask()[:, 0]}
    head = {"run": "bench", "agent": 0, "session": "0123456789abcdef", "seq": 4, "episode": 0, "step": 5}
    lim = S.limits(sc.n_agents, sc.n_tasks, sc.n_actions, sc.levels, sc.horizon, batch, sc.knowledge_size)
    old = json_transition()

    def binary() -> str:
        return S.encode(S.TRANSITION, {**head, **arrays, "done": False})

    def lists() -> str:
        return S.encode(old, {**head, **{key: v.tolist() for key, v in arrays.items()}, "done": False})

    new_text, old_text = binary(), lists()
    got = S.decode(new_text, S.TRANSITION, lim)
    assert all(np.array_equal(got[key], v.astype(got[key].dtype)) for key, v in arrays.items())
    out: dict[str, float] = {}
    for name, fn in (
        ("binary_encode", binary),
        ("binary_decode", lambda: S.decode(new_text, S.TRANSITION, lim)),
        ("json_encode", lists),
        ("json_decode", lambda: S.decode(old_text, old, lim)),
    ):
        rate, _ = _rate(fn, seconds / 4)
        out[f"{name}_us"] = round(1e6 / rate / batch, 3)
    out["encode_ratio"] = round(out["json_encode_us"] / out["binary_encode_us"], 1)
    out["decode_ratio"] = round(out["json_decode_us"] / out["binary_decode_us"], 1)
    out["binary_chars"], out["json_chars"] = len(new_text), len(old_text)
    return out


def training_run(episodes: int | None, out: str | None, sc: Scenario | None = None) -> dict[str, Any]:
    """A default `htlm train` run (no TensorBoard, no progress) and its final evaluation against the targets (the
    paper's teams only)."""
    from htlm_agent.learning.run import train
    from htlm_agent.learning.settings import Settings

    s = Settings() if episodes is None else Settings(episodes=episodes)
    paper = sc is None
    sc = sc or builtin()
    with tempfile.TemporaryDirectory(prefix="htlm-bench-") as tmp:
        res = train(sc, s, out or os.path.join(tmp, "run"), progress=False, tensorboard=False)
    m = res.metrics
    comp, fail, unused = m["completion"]["mean"], m["completion"]["failure_rate"], m["unused_fraction"]["mean"]
    result: dict[str, Any] = {
        "episodes": res.episodes,
        "wall_time_s": round(res.wall_time, 2),
        "train_time_s": round(res.train_time, 2),
        "agent_steps_per_s": round(res.episodes * sc.n_agents * sc.horizon / res.train_time),
        "completion_mean": round(comp, 3),
        "completion_se": round(m["completion"]["se"], 3),
        "failure_rate": round(fail, 4),
        "unused_fraction": round(unused, 4),
    }
    if not paper or sc.team not in OPTIMUM:
        return result
    opt = OPTIMUM[sc.team]
    return {
        **result,
        "optimum": opt,
        "completion_ratio": round(comp / opt, 3),
        "targets": TARGETS,
        "targets_met": {
            "completion": comp <= TARGETS["completion_ratio"] * opt,
            "failure_rate": fail <= TARGETS["failure_rate"],
            "unused_fraction": unused >= TARGETS["unused_fraction"],
        },
    }


def run(args: argparse.Namespace) -> int:
    """Measure and print."""
    if args.what in ("ros", "scale"):
        name = ROS_BENCH if args.what == "ros" else SCALE_BENCH
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:
                raise
            raise SystemExit(
                f"htlm bench {args.what}: the ROS benchmark is not available in this build (no {name})"
            ) from None
        if args.what == "scale":
            res = mod.scale_bench(args)
            if args.json:
                print(json.dumps(res))
            return 0
        res = mod.ros_bench(args)
        print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
        return 0
    import torch

    from htlm_agent.learning.settings import Settings

    out: dict[str, Any] = {"cpu_count": os.cpu_count(), "torch_threads": Settings().threads, "torch": torch.__version__}

    def say(msg: str) -> None:
        if not args.json:
            print(msg, file=sys.stderr)

    try:
        sc = load(args.scenario, team=args.team) if args.scenario else (builtin(args.team) if args.team else None)
    except ScenarioError as e:
        raise SystemExit(f"htlm bench: {e}") from None
    if sc is not None:
        out["scenario"] = {"name": sc.name, "team": sc.team, "agents": sc.n_agents, "sites": sc.n_sites,
                           "tasks": sc.n_tasks, "kinds": sc.n_kinds}  # fmt: skip
        say(f"scenario {sc.name}: {sc.n_agents} agents, {sc.n_sites} sites, {sc.n_tasks} tasks of {sc.n_kinds} kinds")
    for b in (1, 1024):
        out[f"sim_agent_steps_per_s_B{b}"] = round(sim_rate(b, args.seconds, sc))
        say(f"simulator B={b}: {out[f'sim_agent_steps_per_s_B{b}']:,} agent-steps/s")
    for b in (1, 1024):
        out[f"team_agent_steps_per_s_B{b}"] = round(team_rate(b, args.seconds, sc))
        say(f"team (simulator + beliefs + rewards) B={b}: {out[f'team_agent_steps_per_s_B{b}']:,} agent-steps/s")
    if sc is not None:  # the paper's team in the same run: the cost of an agent-step as a ratio
        paper = round(team_rate(1024, args.seconds))
        out["paper_team_agent_steps_per_s_B1024"] = paper
        out["agent_step_cost_vs_paper_B1024"] = round(paper / max(out["team_agent_steps_per_s_B1024"], 1), 2)
        say(f"paper's team B=1024: {paper:,} agent-steps/s; an agent-step costs "
            f"{out['agent_step_cost_vs_paper_B1024']} x the paper's")  # fmt: skip
    n_agents = (sc or builtin()).n_agents
    out["learner_updates_per_s"] = round(learner_rate(args.seconds, sc), 1)
    say(
        f"learner: {out['learner_updates_per_s']} updates/s ({n_agents} agents, minibatch {Settings().batch_size} each)"
    )
    for b in (128, 1024):
        w = out[f"transition_wire_B{b}"] = wire_costs(b, args.seconds, sc)
        say(
            f"transition record B={b}, µs per transition: encode {w['binary_encode_us']} in binary, "
            f"{w['json_encode_us']} as JSON lists ({w['encode_ratio']}x); decode and validate "
            f"{w['binary_decode_us']}, {w['json_decode_us']} as JSON ({w['decode_ratio']}x); "
            f"{w['binary_chars']:,} characters against {w['json_chars']:,}"
        )
    if not args.no_train:
        say("default training run ...")
        out["train"] = training_run(args.episodes, args.out, sc)
        t = out["train"]
        quality = (
            f" ({t['completion_ratio']} x optimum), failures {t['failure_rate']:.1%}, "
            f"unused {t['unused_fraction']:.1%}; targets met: {t['targets_met']}"
            if "targets_met" in t
            else f", failures {t['failure_rate']:.1%}, unused {t['unused_fraction']:.1%}"
        )
        say(
            f"default training run: {t['wall_time_s']} s wall ({t['episodes']} episodes, {t['agent_steps_per_s']:,} "
            f"agent-steps/s), completion {t['completion_mean']} ± {t['completion_se']}{quality}"
        )
    if args.json:
        print(json.dumps(out))
    return 0
