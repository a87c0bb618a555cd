"""`htlm launch {train,evaluate,deploy}`: run a team over ROS 2, its agents one OS process each or several per process
on a large team (htlm_agent.ros.launch)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from htlm_agent.cli.common import TEAM_HELP
from htlm_world.scenario import Scenario, ScenarioError, builtin, load

if TYPE_CHECKING:
    from htlm_agent.ros.launch import LaunchConfig


def _kv(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=VALUE")
    k, v = text.split("=", 1)
    try:
        val = json.loads(v)
    except ValueError:
        val = v
    return k.strip(), val


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm launch`."""
    from htlm_agent.learning.learners import DEFAULT_LEARNER, DEFAULT_Q_LEARNER, LEARNERS
    from htlm_agent.learning.settings import Settings
    from htlm_agent.ros.launch import (
        ALONE_UP_TO,
        EXIT_CODES,
        FREE_PERIOD,
        MAX_RESTARTS,
        PAGE_PORT,
        PEOPLE_PERIOD,
        RESPAWN_DELAY,
        RESPAWN_DELAY_MAX,
        RESPAWN_STABLE,
    )
    from htlm_agent.session.builtin import BUILTIN_POLICIES

    p.add_argument("mode", choices=("train", "evaluate", "deploy"), help="what the team does")
    p.add_argument(
        "--team",
        default=None,
        help=TEAM_HELP,
    )
    p.add_argument("--scenario", default="", help="scenario YAML file (default: the built-in 'paper')")
    budget = Settings.for_learner(learner=DEFAULT_LEARNER).episodes
    p.add_argument(
        "--episodes",
        type=int,
        default=None,
        help=f"episodes to run (default: train the learner's budget, {budget} for the {DEFAULT_LEARNER} learner, "
        "unless --set episodes=N; evaluate 500; deploy 0 = until Ctrl-C)",
    )
    p.add_argument("--first-episode", type=int, default=0, help="index of the first episode (seeds derive from it)")
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        help="B, episodes run at once through the same processes (default: train the learner's envs, evaluate 128, "
        "deploy 1)",
    )
    p.add_argument("--seed", type=int, default=0, help="master seed")
    p.add_argument(
        "--policy",
        choices=("auto", "checkpoint", *BUILTIN_POLICIES),
        default="auto",
        help="agents' policy (auto: the trainer's in train mode, else --checkpoint)",
    )
    p.add_argument("--checkpoint", default="", help="checkpoint directory of `htlm train` (evaluate, deploy)")
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        help="train: evaluate the trained checkpoint over ROS for this many episodes afterwards "
        "(default 5; 0: no evaluation)",
    )
    p.add_argument("--run-dir", default="", help="run directory (default: runs/launch-MODE__SEED__TIMESTAMP)")
    p.add_argument(
        "--only",
        default="",
        help="comma-separated processes to start on this host: world, trainer, agent names (default: all)",
    )
    p.add_argument(
        "--agents-per-process",
        type=int,
        default=0,
        metavar="N",
        help=f"most agents one process hosts, each still its own node (1: a process per agent; default 0 = auto: 1 "
        f"up to {ALONE_UP_TO} agents on this host, else the agents spread over as many processes as cores); a "
        "process that dies takes its agents with it, and they rejoin when it is restarted",
    )
    p.add_argument("--domain-id", type=int, default=42, help="ROS_DOMAIN_ID of every process (default 42)")
    p.add_argument(
        "--discovery",
        choices=("localhost", "subnet", "system_default", "off"),
        default="localhost",
        help="ROS_AUTOMATIC_DISCOVERY_RANGE (default localhost: nothing leaves this machine)",
    )
    p.add_argument("--peers", default="", help="ROS_STATIC_PEERS: 'host1;host2' for unicast discovery of other hosts")
    p.add_argument("--key-file", default="", help="team key file: sign every message, reject unsigned ones")
    p.add_argument(
        "--set",
        dest="learner",
        type=_kv,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="learner setting (htlm_agent.learning.settings.Settings), e.g. --set learning_starts=500; train: the "
        f"{DEFAULT_LEARNER} learner unless --set learner=NAME ({', '.join(LEARNERS)}) or a setting it does not read "
        f"is given (then the {DEFAULT_Q_LEARNER} learner, as htlm train)",
    )
    p.add_argument(
        "--world-param",
        type=_kv,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="world_node parameter, e.g. --world-param act_deadline=1.0",
    )
    p.add_argument(
        "--agent-param",
        type=_kv,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="agent_node parameter for every agent",
    )
    p.add_argument(
        "--trainer-param", type=_kv, action="append", default=[], metavar="NAME=VALUE", help="trainer_node parameter"
    )
    p.add_argument(
        "--operation",
        choices=("simulated", "external"),
        default="simulated",
        help="external: the world simulates nothing, the robots publish the observations (free clock, batch 1)",
    )
    p.add_argument(
        "--robots",
        choices=("none", "sim"),
        default="none",
        help="sim: a simulated robot per agent (follows goal_pose, publishes odometry and observations) and their "
        "stand-in operation; implies --operation external",
    )
    p.add_argument(
        "--period",
        type=float,
        default=None,
        help="step period of the free clock, seconds (external operation; default with --robots sim: long enough for "
        f"a robot to drive between the two farthest sites within a step, docs/ros.md Arrival; else {FREE_PERIOD:g})",
    )
    p.add_argument(
        "--person",
        action="append",
        default=[],
        metavar="AGENT",
        help="deploy: a person plays this agent (repeat, or comma-separate, for several): no robot; the agent serves "
        "the person's page, whose reports are its observations; the address with its token is printed and the token "
        f"kept in RUN/people/AGENT.token; the step period defaults to {PEOPLE_PERIOD:g} s (docs/usage.md)",
    )
    p.add_argument(
        "--page-address",
        default="127.0.0.1",
        help="address the people's pages listen on (default 127.0.0.1: this machine only; 0.0.0.0: every interface)",
    )
    p.add_argument(
        "--page-port",
        type=int,
        default=PAGE_PORT,
        help=f"port of the first person's page, the next people's after it (default {PAGE_PORT}; 0: any free port)",
    )
    p.add_argument(
        "--robot-param",
        type=_kv,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="robot_node parameter for every simulated robot, e.g. --robot-param speed=10.0",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="record every topic of the team into a ROS 2 bag (MCAP storage) in RUN/recording, for `ros2 bag "
        "info/play` and Foxglove (a process of its own, `recorder`; with --only, on the host that names it)",
    )
    p.add_argument(
        "--respawn-delay",
        type=float,
        default=RESPAWN_DELAY,
        help=f"seconds before a process that died starts again, doubled at each restart in a row up to "
        f"{RESPAWN_DELAY_MAX:g} s (default {RESPAWN_DELAY:g}); deploy restarts any process that exits with an error "
        "or is killed, train and evaluate a process killed by a signal",
    )
    p.add_argument(
        "--max-restarts",
        type=int,
        default=MAX_RESTARTS,
        help=f"restarts in a row of one process before the launch gives up and stops the team (default "
        f"{MAX_RESTARTS}; a process up for {RESPAWN_STABLE:g} s counts from 0 again; 0: a process that dies stops "
        "the team)",
    )
    p.add_argument("--timeout", type=float, default=0.0, help="stop the team after this many seconds (exit 124)")
    p.add_argument("--quiet", action="store_true", help="do not echo the episode lines")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the summary as JSON, the only output on stdout (the episode lines and messages go to stderr)",
    )
    p.epilog = "exit codes: " + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items())


class LaunchError(ValueError):
    """The input of a launch has problems (one per line, each naming the option or file, the field and the value)."""


def config(argv: list[str]) -> LaunchConfig:
    """The launch of an `htlm launch` command line (the words after `htlm launch`), checked as `htlm launch` checks
    it before it starts anything: the one reading of a launch's options, which team.launch.py uses too.

    Raises:
        LaunchError: every problem of the input (argparse's own errors exit as usual).
    """
    parser = argparse.ArgumentParser(prog="htlm launch")
    add_arguments(parser)
    cfg, bad = make_config(parser.parse_args(argv))
    if bad:
        raise LaunchError("\n".join(bad))
    return cfg


def make_config(args: argparse.Namespace) -> tuple[LaunchConfig, list[str]]:
    """The launch of parsed `htlm launch` options and every problem of its input (empty: it can start)."""
    from htlm_agent.learning.learners import learner
    from htlm_agent.learning.settings import Settings
    from htlm_agent.ros.launch import PEOPLE_PERIOD, LaunchConfig
    from htlm_agent.ros.launch_check import check_launch

    bad: list[str] = []  # every problem of the input, reported together
    sc = builtin(args.team or "heterogeneous")  # a stand-in when the scenario file does not load
    if args.scenario and args.team:
        bad.append(f"--scenario {args.scenario}, --team {args.team}: give one, not both")
    if args.scenario:
        with contextlib.suppress(ScenarioError):  # check_launch reports every problem of the file
            sc = load(args.scenario)
    if args.mode in ("evaluate", "deploy") and args.policy in ("auto", "checkpoint") and not args.checkpoint:
        bad.append(f"{args.mode}: needs --checkpoint DIR (or --policy greedy / auction / random)")
    try:
        settings = Settings.from_dict(Settings.for_users(dict(args.learner)), "--set")  # for the defaults
    except ValueError:  # check_launch reports every bad key
        settings = Settings()
    kind = learner(settings.learner)
    if args.mode == "train" and kind.in_process_only is not None:
        bad.append(f"train: --set learner={settings.learner} {kind.in_process_only}")
    if args.mode == "train" and settings.dropout > 0:
        bad.append(f"train: --set dropout={settings.dropout!r}: training for resilience runs in process only")
    default_episodes = {"train": settings.episodes, "evaluate": 500, "deploy": 0}[args.mode]
    if args.mode == "train" and kind.rounds:  # every round whole, as `htlm train` plays them
        default_episodes = settings.rounds * settings.round_batches * settings.envs
    episodes = args.episodes if args.episodes is not None else default_episodes
    batch = args.batch if args.batch is not None else {"train": settings.envs, "evaluate": 128, "deploy": 1}[args.mode]
    people = tuple(x.strip() for item in args.person for x in item.split(",") if x.strip())
    names = [a.name for a in sc.agents]
    for name in people:
        if name not in names:
            bad.append(f"--person {name}: not an agent of the team ({', '.join(names)})")
    if len(set(people)) != len(people):
        bad.append(f"--person {','.join(people)}: an agent is named twice")
    if people and args.mode != "deploy":
        bad.append(f"--person: people play agents of a deployed team (htlm launch deploy), not {args.mode}")
    if not 0 <= args.page_port <= 65535 - len(people):
        bad.append(f"--page-port {args.page_port!r}: must be a port (0 to 65535, 0: any free port)")
    deployed = args.operation == "external" or args.robots == "sim" or bool(people)
    if deployed and (args.mode == "train" or batch != 1):
        bad.append(f"{args.mode}: an external operation runs evaluate or deploy with --batch 1 (got {batch})")
    period, notes = step_period(sc, args)
    if people and args.period is None and not sc.travel:  # the step is theirs to keep: minutes, not seconds
        # (an operation with travel has its own step, which its people walk and report in too)
        period, notes = PEOPLE_PERIOD, (f"--period {PEOPLE_PERIOD:g} s: a step a person can keep (people in the team)",)
    if period <= 0:
        bad.append(f"--period {period!r}: must be > 0")
    if not args.respawn_delay >= 0:
        bad.append(f"--respawn-delay {args.respawn_delay!r}: must be >= 0")
    if args.agents_per_process < 0:
        bad.append(f"--agents-per-process {args.agents_per_process!r}: must be >= 1 (or 0: auto)")
    if args.max_restarts < 0:
        bad.append(f"--max-restarts {args.max_restarts!r}: must be >= 0")
    if batch < 1 or args.first_episode % batch:
        bad.append(f"--batch {batch}: must be >= 1 and divide --first-episode {args.first_episode}")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dir = Path(args.run_dir or f"runs/launch-{args.mode}__{args.seed}__{stamp}")
    only = tuple(x.strip() for x in args.only.split(",") if x.strip())
    known = {"world", "trainer", *(a.name for a in sc.agents)}
    if args.robots == "sim":
        known |= {"operation", *(f"robot_{a.name}" for a in sc.agents)}
    if args.record:
        known.add("recorder")
    if args.person:
        known.add("commander")
    if set(only) - known:
        bad.append(f"--only {sorted(set(only) - known)}: unknown; choose from {sorted(known)}")
    cfg = LaunchConfig(
        mode=args.mode,
        scenario=sc,
        scenario_file=args.scenario,
        episodes=episodes,
        first_episode=args.first_episode,
        batch=batch,
        seed=args.seed,
        run_dir=run_dir,
        policy=args.policy,
        checkpoint=args.checkpoint,
        only=only,
        domain_id=args.domain_id,
        discovery=args.discovery,
        peers=args.peers,
        key_file=args.key_file,
        learner={"learner": settings.learner, **dict(args.learner)} if args.mode == "train" else dict(args.learner),
        world_params=dict(args.world_param),
        agent_params=dict(args.agent_param),
        trainer_params=dict(args.trainer_param),
        timeout=args.timeout,
        echo=not args.quiet,
        echo_to_stderr=args.json,  # --json: stdout holds the summary only
        operation="external" if people else args.operation,
        robots="" if args.robots == "none" else args.robots,
        period=period,
        notes=notes,
        robot_params=dict(args.robot_param),
        record=args.record,
        respawn_delay=args.respawn_delay,
        max_restarts=args.max_restarts,
        agents_per_process=args.agents_per_process,
        people=people,
        page_address=args.page_address,
        page_port=args.page_port,
    )
    return cfg, bad + check_launch(cfg)


def step_period(sc: Scenario, args: argparse.Namespace) -> tuple[float, tuple[str, ...]]:
    """The free clock's step period of a launch and what to say about it: --period when given, else the operation's
    `step_seconds` when it has travel, else with simulated robots `robots.arrival_period` at their speed
    (--robot-param speed, else the robot's default), else FREE_PERIOD. Without travel and with simulated robots, a
    period too short for a robot to reach every site within its step is warned about: a move then takes several
    steps, which that operation's model does not count (docs/ros.md, Arrival)."""
    from htlm_agent.ros.launch import FREE_PERIOD
    from htlm_world.robots import arrival_period, longest_drive
    from htlm_world.ros.robot_settings import RobotSettings

    given = None if args.period is None else float(args.period)
    if sc.travel:  # the operation's own step: drives take the steps the model gives them
        if given is None:
            return sc.step_seconds, (
                f"--period {sc.step_seconds:g} s: the operation's step (step_seconds); a drive takes the steps its "
                "distance over the robot's speed gives (docs/model.md, Travel)",
            )
        if given != sc.step_seconds:
            return given, (
                f"warning: --period {given:g} s is not the operation's step of {sc.step_seconds:g} s: drives take "
                "another number of steps than the model and every policy trained on it count (docs/model.md, Travel)",
            )
        return given, ()
    speed = dict(args.robot_param).get("speed", RobotSettings().speed)
    if args.robots != "sim" or not isinstance(speed, int | float) or isinstance(speed, bool):
        return (FREE_PERIOD if given is None else given), ()  # a bad speed: check_launch names it
    need = arrival_period(sc, float(speed))
    metres, a, b = longest_drive(sc)
    drive = f"{metres:.0f} m from {sc.sites[a].name} to {sc.sites[b].name} at {float(speed):g} m/s"
    if given is None:
        return need, (f"--period {need:g} s: a robot drives the farthest way within a step ({drive})",)
    if given < need:
        return given, (
            f"warning: --period {given:g} s is shorter than the {need:g} s a robot needs to drive the "
            f"farthest way within a step ({drive}): a move to a far site takes several steps, which the model and "
            "every policy trained on it do not know, and teams fail episodes (docs/ros.md, Arrival)",
        )
    return given, ()


def run(args: argparse.Namespace) -> int:
    """Check the launch's input (every problem on stderr, exit 2, nothing started), launch the team, print a summary."""
    from htlm_agent.ros.launch import LaunchConfig, page_addresses, run_team, summarize

    cfg, bad = make_config(args)
    sc, run_dir, only, episodes = cfg.scenario, cfg.run_dir, cfg.only, cfg.episodes
    if bad:
        for line in bad:
            print(f"htlm launch: {line}", file=sys.stderr)
        return 2
    for line in cfg.notes:
        print(f"htlm launch: {line}", file=sys.stderr, flush=True)
    for name, address in page_addresses(cfg).items():
        if not only or name in only:
            whose = "the commander's page" if name == "commander" else f"{name}'s page (a person plays {name})"
            print(f"htlm launch: {whose}: {address}", file=sys.stderr, flush=True)
    code = run_team(cfg)
    out: dict[str, Any] = {"mode": args.mode, "run_dir": str(run_dir), "exit_code": code, **summarize(run_dir)}
    if cfg.operation == "external" or cfg.robots:
        out["period"] = cfg.period  # the free clock's, chosen or given
    ckpt = run_dir / "trainer" / "checkpoint"
    eval_episodes = 500 if args.eval_episodes is None else args.eval_episodes
    if args.mode == "train" and code == 0 and (ckpt / "meta.json").exists():
        out["checkpoint"] = str(ckpt)
        if eval_episodes > 0 and (not only or "world" in only):
            print(f"htlm launch: evaluating {ckpt} over ROS for {eval_episodes} episodes", flush=True, file=sys.stderr)
            ecfg = LaunchConfig(
                **{
                    **cfg.__dict__,
                    "mode": "evaluate",
                    "episodes": eval_episodes,
                    "first_episode": 0,  # evaluation streams (seeds.world), apart from the training ones
                    "batch": min(128, eval_episodes),
                    "run_dir": run_dir / "evaluate",
                    "policy": "checkpoint",
                    "checkpoint": str(ckpt),
                    "echo": False,
                }
            )
            code = run_team(ecfg)
            out["evaluation"] = {"exit_code": code, **summarize(ecfg.run_dir)}
            if code == 0:
                trained = int(json.loads((ckpt / "meta.json").read_text()).get("episodes_done", episodes))
                out["result"] = _report(sc, args.seed, trained, eval_episodes, run_dir, ecfg.run_dir, ecfg.batch)
    if args.json:
        print(json.dumps(out))
    else:
        _print_summary(out)
    return code


def _report(
    sc: Any, seed: int, train_episodes: int, episodes: int, run_dir: Path, eval_dir: Path, batch: int
) -> dict[str, Any]:
    """The learned team (evaluated over ROS in batches of `batch`) beside the baselines (`ros_report.BASELINES`) on
    the same episodes: run_dir/result.{csv,json,png}."""
    from htlm_agent.experiments.ros_report import baseline_rows, learned_row, write_report

    print(f"htlm launch: evaluating the baselines in process on {episodes} episodes (seed {seed})", file=sys.stderr)
    skipped: dict[str, str] = {}
    try:  # the learner the trainer trained, for the row's name
        learner = json.loads((run_dir / "trainer" / "settings.json").read_text())["learner"]
    except (OSError, ValueError, KeyError):
        learner = "?"
    rows = [
        learned_row(eval_dir / "world.jsonl", f"learned ({learner})"),
        *baseline_rows(sc, episodes, seed, skipped, batch),
    ]
    info = {
        "team": sc.team or sc.name,
        "seed": seed,
        "train_episodes": train_episodes,
        "eval_episodes": episodes,
        "not_computed": skipped,
    }
    doc = write_report(run_dir, rows, info)
    doc["files"] = [str(run_dir / f"result.{x}") for x in ("csv", "json", "png")]
    return doc


def _print_summary(out: dict[str, Any]) -> None:
    def line(tag: str, s: dict[str, Any]) -> str:
        if not s.get("episodes"):
            return f"{tag}: no episode finished"
        if s.get("severity_unknown"):
            return f"{tag}: {s['episodes']} episodes, completion unknown (no outside source reported the severities)"
        return (
            f"{tag}: {s['episodes']} episodes, completion step {s['completion_mean']:.2f} "
            f"(failure rate {s['failure_rate']:.2f}), unused capability {s['unused_fraction_mean']:.3f}, "
            f"absent agent-steps {s['absent_agent_steps']}, {s['seconds']:.1f} s"
        )

    print(line(out["mode"], out))
    if "evaluation" in out:
        print(line("evaluation of the trained team over ROS", out["evaluation"]))
    if "result" in out:
        from htlm_agent.experiments.ros_report import table

        r = out["result"]
        print(
            f"\nthe team trained over ROS 2 beside the baselines "
            f"({r['eval_episodes']} episodes each, seed {r['seed']}):"
        )
        print(table(r["rows"]))
        for name, why in r.get("not_computed", {}).items():
            print(f"{name}: {why}")
        print("result: " + ", ".join(r["files"]))
    if "checkpoint" in out:
        print(f"checkpoint: {out['checkpoint']}")
    print(f"run directory: {out['run_dir']} (exit code {out['exit_code']})")
