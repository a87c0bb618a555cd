"""`htlm train` in process: Algorithm 1 with B parallel episodes, validation and selection of the best networks,
checkpoints, progress.csv / TensorBoard logs and the final greedy evaluation; and the lookahead learner
(`train_lookahead`: its value network fitted in one go, the same run files); and the expert-iteration learner
(`train_expert_run`: its rounds, rounds.csv and rounds.png besides the same run files).

A run directory holds: settings.json, scenario.yaml, progress.csv (one row per batch of episodes), tb/ (TensorBoard),
checkpoint/ (periodic and final; with select_best its networks are the best validated ones, the latest are in its
training state), eval/ (final evaluation: metrics.json, CSVs, histogram PNG), result.json.

Training episodes draw from their own streams of the run's seed (`seeds.train_world`, `seeds.train_channel`,
`seeds.train_explore` per batch), validation episodes from the world and channels of `seeds.validation(seed)`, and
the final evaluation from those of the seed itself.
"""

from __future__ import annotations

import csv
import ctypes
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy
from htlm_agent.baselines.optimal import ProblemTooLarge, QmdpPolicy
from htlm_agent.experiments.expert import train_expert, write_rounds
from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.learners import team_policy
from htlm_agent.learning.lookahead import BaseValue, ValueSettings, own_rewards
from htlm_agent.learning.loop import LaggedNets, Selection, episode_epsilons
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.context import Policy
from htlm_agent.mind.policies import knowledge_context, team_epsilon_greedy
from htlm_agent.progress import Progress
from htlm_agent.runtime.evaluate import evaluate, evaluate_run, write_reports
from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.metrics import episode_metrics
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray


@dataclass
class TrainResult:
    """What `train` produced."""

    out_dir: Path
    scenario: Scenario
    settings: Settings
    episodes: int
    wall_time: float
    """Seconds of the whole call, final evaluation included."""
    train_time: float
    """Seconds of training only (no final evaluation, no checkpoint writing)."""
    metrics: dict[str, Any]
    """Final greedy evaluation (`evaluate.evaluate`)."""
    history: list[dict[str, float]] = field(default_factory=list)


LOG_FIELDS = (
    "episodes",
    "wall_s",
    "episodes_per_s",
    "epsilon",
    "updates",
    "loss",
    "reward",
    "completion",
    "failure_rate",
    "unused_fraction",
    "val_completion",
    "val_failure_rate",
    "val_unused_fraction",
)
"""Columns of progress.csv."""

RESUMABLE_CHANGES = (
    "episodes",
    "eval_episodes",
    "validate_every",
    "validate_episodes",
    "checkpoint_every",
    "keep_replay",
    "threads",
)
"""Settings that may differ when a run is resumed; every other field must match the checkpoint's."""


def keep_freed_memory() -> None:
    """Have glibc's allocator keep freed memory for reuse instead of handing it back to the system at once.

    Every gradient update allocates activations of several hundred kB; with glibc's defaults such blocks are mapped
    afresh (or the heap top trimmed) again and again, and every first touch of a new page is a page fault: about 80
    faults per environment step, a tenth of the learner's time. Other C libraries: nothing to do.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # glibc's <malloc.h>
    mallopt(m_mmap_threshold, 64 << 20)  # blocks below 64 MB come from the heap ...
    mallopt(m_trim_threshold, 256 << 20)  # ... which is trimmed only when 256 MB are free at its top
    mallopt(m_top_pad, 16 << 20)


def deterministic_torch() -> None:
    """`torch.use_deterministic_algorithms(True)` without the import of torch._inductor it makes (a second or more at
    start-up) only to set the compiler's own flag: training compiles nothing."""
    torch._C._set_deterministic_algorithms(True)


# ----- one batch of training episodes -----------------------------------------------------------------------------


def dropouts(share: float, batch: int, n_agents: int, rng: np.random.Generator) -> BoolArray | None:
    """(B, N) mask of the teammates that sit out each of B training episodes: in a `share` of the episodes one agent,
    drawn uniformly, sits out (Settings.dropout); None when share is 0 (no draw, so other streams are untouched)."""
    if share <= 0.0:
        return None
    u = rng.random(batch)
    who = rng.integers(0, n_agents, size=batch)
    mask = np.zeros((batch, n_agents), dtype=bool)
    mask[np.flatnonzero(u < share), who[u < share]] = True
    return mask


def train_batch(
    learner: Learner,
    team: Team,
    batch_index: int,
    lagged: LaggedNets | None = None,
    expert: Policy | None = None,
) -> dict[str, float]:
    """Algorithm 1, lines 3-10, for B episodes at once: run one batch of episodes ε-greedily, storing every agent's
    transitions in its own memory and training every agent `updates_per_step` times per step; under a trainer lag
    the agents act with the networks of `lagged` (kept across the run's batches; default: new ones, this batch being
    the run's first). With an `expert` (the warm start, `Settings.imitate`), the team acts with the expert's
    choices, each agent's made from its own knowledge state as an agent process makes them (`knowledge_context`),
    ε-greedily with the final ε, and the networks also learn to rank them first (`imitate_step`).
    Returns the batch's row of progress.csv (the metrics of `htlm_world.metrics` over its episodes)."""
    sc, s, seed = learner.scenario, learner.settings, learner.seed
    if lagged is None:
        lagged = LaggedNets(learner, batch_index * sc.horizon)
    team.sim.rng = seeds.train_world(seed, batch_index)
    team.sim.channel_rngs = [seeds.train_channel(seed, i, batch_index) for i in range(sc.n_agents)]
    team.event_rng = seeds.train_events(seed, batch_index)
    rngs = [seeds.train_explore(seed, i, batch_index) for i in range(sc.n_agents)]
    eps, eps_env = episode_epsilons(s, learner.episodes_done, team.batch)
    team.dropped = dropouts(s.dropout, team.batch, sc.n_agents, seeds.train_dropout(seed, batch_index))
    k = team.reset()
    m = team.mask()
    levels, actions = [team.sim.levels.copy()], []
    rsum = 0.0
    losses: list[float] = []
    for t in range(sc.horizon):
        net = lagged.at(batch_index * sc.horizon + t)
        if expert is not None:  # each agent acts around the expert's choice from its own K, as a process does
            a_exp = expert.act(knowledge_context(sc, k, m))
            a = team.force_inactive(team_epsilon_greedy(a_exp, m, eps_env, rngs))
            losses.append(imitate_step(learner, expert, k))
        else:  # a dropped agent's stored action: its idling
            a = team.force_inactive(learner.act(k, m, eps_env, rngs, net))
        k2, r, info = team.step(a)
        m2 = team.mask()
        learner.store_batch(k, a, r, k2, m2, t == sc.horizon - 1)
        losses += learner.train_steps(s.td_updates(learner.episodes_done))
        levels.append(info.levels)
        actions.append(a)
        rsum += float(r.mean())
        k, m = k2, m2
    learner.episodes_done += team.batch
    em = episode_metrics(sc, np.stack(levels), np.stack(actions))
    return {
        "epsilon": eps,
        "loss": float(np.mean(losses)) if losses else float("nan"),
        "reward": rsum / sc.horizon,
        "completion": float(em.completion.mean()),
        "failure_rate": float(em.failed.mean()),
        "unused_fraction": float(em.unused_fraction.mean()),
    }


def imitate_step(learner: Learner, expert: Policy, k: FloatArray) -> float:
    """The warm start's update of one step for the whole team, in process and in the trainer over ROS alike: the
    networks learn to rank first the expert's choices made from every agent's own knowledge state (B, N, K) and its
    Â(a_o) (`Learner.imitate`), the knowledge as the trainer receives it (float32, the precision of the wire and of
    the replay memories); with `Settings.imitate_updates` > 1, also on minibatches of the expert choices stored so
    far. Returns the last update's loss."""
    k32 = np.asarray(k, dtype=np.float32).astype(np.float64)  # the values of float32, as the trainer has them
    m = learner.knowledge_mask(k32).numpy()
    a = np.asarray(expert.act(knowledge_context(learner.scenario, k32, m)), dtype=np.int64)
    loss = learner.imitate(k32, m, a)
    s = learner.settings
    if s.imitate_updates > 1:  # more updates on every expert choice of the warm start so far
        memory = learner.expert_memory()
        memory.add(k32, m, a)
        for _ in range(s.imitate_updates - 1):
            loss = learner.imitate(*memory.sample(s.batch_size))
    return loss


def warm_start_expert(scenario: Scenario, settings: Settings) -> Policy | None:
    """The baseline the warm start imitates (`Settings.imitate`), None without a warm start."""
    if settings.imitate == "none" or settings.imitate_episodes == 0:
        return None
    if settings.imitate == "qmdp":
        try:
            return QmdpPolicy(scenario)
        except ProblemTooLarge as e:
            raise ValueError(f"settings.imitate: 'qmdp' needs the centralized optimum, and {e}") from None
    return AuctionPolicy(scenario) if settings.imitate == "auction" else GreedyPolicy(scenario)


# ----- validation and selection -----------------------------------------------------------------------------------


def validate(learner: Learner, episodes: int) -> dict[str, Any]:
    """Greedy validation of the current networks on episodes of the run's validation stream."""
    return evaluate(learner.policy(), learner.scenario, episodes, seed=seeds.validation(learner.seed))


# ----- the run's files --------------------------------------------------------------------------------------------


def write_run_files(out_dir: Path, scenario: Scenario, settings: Settings) -> None:
    """settings.json and scenario.yaml beside the run's results."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "settings.json").write_text(json.dumps(settings.to_dict(), indent=2) + "\n")
    (out_dir / "scenario.yaml").write_text(yaml.safe_dump(scenario.to_dict(), sort_keys=False))


class RunLog:
    """progress.csv (one row per batch of episodes) and, optionally, TensorBoard scalars of a training run."""

    def __init__(self, out: Path, episodes_done: int, resume: bool, tensorboard: bool) -> None:
        """Open the logs; a resumed run keeps its rows up to the checkpoint (drops those of an interrupted tail)."""
        self.writer: Any = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter  # heavy and optional: only when asked for

            self.writer = SummaryWriter(str(out / "tb"), purge_step=episodes_done if resume else None)
        path = out / "progress.csv"
        rows_before: list[dict[str, str]] = []
        if resume and path.exists():
            with path.open() as f:
                rows_before = [r for r in csv.DictReader(f) if int(r["episodes"]) <= episodes_done]
        self.file = path.open("w", newline="")
        self.csv = csv.DictWriter(self.file, LOG_FIELDS, extrasaction="ignore")
        self.csv.writeheader()
        self.csv.writerows(rows_before)

    def row(self, row: dict[str, float], episodes: int) -> None:
        """Write one batch's row (and its scalars to TensorBoard)."""
        self.csv.writerow(row)
        self.file.flush()
        if self.writer is not None:
            for key, val in row.items():
                if key not in ("episodes", "wall_s") and not math.isnan(val):
                    self.writer.add_scalar(f"train/{key}", val, episodes)

    def evaluation(self, metrics: dict[str, Any], episodes: int) -> None:
        """The final evaluation's scalars (TensorBoard only)."""
        if self.writer is not None:
            self.writer.add_scalar("eval/completion", metrics["completion"]["mean"], episodes)
            self.writer.add_scalar("eval/failure_rate", metrics["completion"]["failure_rate"], episodes)
            self.writer.add_scalar("eval/unused_fraction", metrics["unused_fraction"]["mean"], episodes)

    def close_progress(self) -> None:
        """Close progress.csv (training is over)."""
        self.file.close()

    def close(self) -> None:
        """Close everything."""
        if not self.file.closed:
            self.file.close()
        if self.writer is not None:
            self.writer.close()


# ----- the training loop ------------------------------------------------------------------------------------------


def start_learner(
    scenario: Scenario, settings: Settings, ckpt_dir: Path, resume: bool
) -> tuple[Learner, dict[str, Any]]:
    """A fresh learner, or the one of the checkpoint to resume (only RESUMABLE_CHANGES may differ in `settings`),
    and the checkpoint's info (empty for a fresh run)."""
    if not resume:
        if (ckpt_dir / "meta.json").exists():
            raise FileExistsError(
                f"{ckpt_dir.parent}: already holds a run; resume it or choose another output directory"
            )
        return Learner(scenario, settings), {}
    ck = load_checkpoint(ckpt_dir)
    fixed = {k: v for k, v in ck.settings.to_dict().items() if k not in RESUMABLE_CHANGES}
    mine = {k: v for k, v in settings.to_dict().items() if k in fixed}
    if fixed != mine:
        diff = sorted(k for k in fixed if fixed[k] != mine[k])
        raise CheckpointError(
            f"{ck.path}: cannot resume with changed settings {diff}; only {list(RESUMABLE_CHANGES)} may change"
        )
    return Learner.load(ckpt_dir, settings), ck.info


@dataclass
class _Run:
    """The state of a training run between batches."""

    learner: Learner
    team: Team
    selection: Selection
    log: RunLog
    bar: Progress
    ckpt_dir: Path
    t_start: float
    lagged: LaggedNets
    expert: Policy | None = None
    """The baseline of the warm start (`Settings.imitate`), None without one."""
    history: list[dict[str, float]] = field(default_factory=list)
    train_time: float = 0.0
    last_ckpt: int = 0
    last_val: int = 0

    def save(self) -> None:
        """Write the checkpoint: the selected networks (with select_best) and the training state."""
        s = self.learner.settings
        policy = self.selection.flat if s.select_best else None
        self.learner.save(self.ckpt_dir, replay=s.keep_replay, extra=self.selection.info(), policy_flat=policy)

    def batch(self) -> None:
        """Train one batch, validate when due, log, and write a periodic checkpoint when due."""
        learner, s = self.learner, self.learner.settings
        t0 = time.perf_counter()
        expert = self.expert if s.warm_start(learner.episodes_done) else None
        row = train_batch(learner, self.team, learner.episodes_done // s.envs, self.lagged, expert)
        self.train_time += time.perf_counter() - t0
        done = learner.episodes_done
        row["episodes"] = done
        row["updates"] = int(learner.updates.max())
        row["wall_s"] = round(time.perf_counter() - self.t_start, 3)
        row["episodes_per_s"] = self.bar.rate
        final = done >= s.episodes
        if s.validate_every and s.validate_episodes and (done - self.last_val >= s.validate_every or final):
            self.validate(row)
        self.history.append(row)
        self.log.row(row, done)
        self.bar.update(
            done,
            completion=f"{row['completion']:.2f}",
            unused=f"{row['unused_fraction']:.2f}",
            eps=f"{row['epsilon']:.2f}",
        )
        if s.checkpoint_every and done - self.last_ckpt >= s.checkpoint_every and not final:
            self.last_ckpt = done
            self.save()

    def validate(self, row: dict[str, float]) -> None:
        """Validate the current networks into `row`; once ε has decayed, offer them to the selection."""
        s = self.learner.settings
        self.last_val = self.learner.episodes_done
        vm = validate(self.learner, s.validate_episodes)
        row["val_completion"] = vm["completion"]["mean"]
        row["val_failure_rate"] = vm["completion"]["failure_rate"]
        row["val_unused_fraction"] = vm["unused_fraction"]["mean"]
        if self.learner.episodes_done >= s.selection_from:
            self.selection.offer(vm["completion"]["mean"])


def final_evaluation(run: _Run, out: Path) -> dict[str, Any]:
    """Greedy evaluation of the checkpoint's networks (settings.eval_episodes episodes, seed settings.seed) into
    out/eval; returns its metrics."""
    metrics = evaluate_checkpoint(run.ckpt_dir, out, "htlm-dqn")
    run.log.evaluation(metrics, run.learner.episodes_done)
    return metrics


def evaluate_checkpoint(ckpt_dir: Path, out: Path, name: str) -> dict[str, Any]:
    """Greedy evaluation of a run's checkpoint, as its agents act (settings.eval_episodes episodes, seed
    settings.seed) into out/eval; returns its metrics."""
    ck = load_checkpoint(ckpt_dir)
    s = ck.settings
    evaluation = evaluate_run(team_policy(ck), ck.scenario, s.eval_episodes, seed=s.seed, policy_name=name)
    write_reports(evaluation, out / "eval")
    return evaluation.metrics


def write_result(run: _Run, out: Path, metrics: dict[str, Any], progress: bool) -> float:
    """result.json (and the final line on stderr with `progress`); returns the wall time of the run."""
    s = run.learner.settings
    selected = run.selection.episode if s.select_best else None
    return result_json(out, run.learner.episodes_done, run.t_start, run.train_time, selected, metrics, progress)


def result_json(
    out: Path,
    episodes: int,
    t_start: float,
    train_time: float,
    selected: int | None,
    metrics: dict[str, Any],
    progress: bool,
) -> float:
    """Write result.json (and the final line on stderr with `progress`) for a run that began at `t_start`
    (`time.perf_counter`); returns its wall time."""
    wall = time.perf_counter() - t_start
    summary = {
        "episodes": episodes,
        "wall_time_s": round(wall, 2),
        "train_time_s": round(train_time, 2),
        "selected_episode": selected,
        "metrics": metrics,
    }
    (out / "result.json").write_text(json.dumps(summary, indent=2) + "\n")
    if progress and metrics:
        c = metrics["completion"]
        print(
            f"final evaluation ({metrics['episodes']} episodes): completion {c['mean']:.2f} ± {c['se']:.2f}"
            f", failures {c['failure_rate']:.1%}, unused capability {metrics['unused_fraction']['mean']:.1%}"
            f" ({wall:.0f} s)",
            file=sys.stderr,
        )
    return wall


def train(
    scenario: Scenario,
    settings: Settings,
    out_dir: str | Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """Train a team in process (Algorithm 1 with B parallel episodes) and evaluate it greedily at the end; writes the
    run directory of the module docstring.

    Args:
        scenario: operation and team (ignored when resuming: the checkpoint's is used).
        settings: learning settings (when resuming, only the fields in RESUMABLE_CHANGES may differ).
        out_dir: the run directory.
        progress: show a progress line on stderr.
        resume: continue the run in out_dir from its checkpoint.
        tensorboard: also write TensorBoard logs.
        evaluate_at_end: run the final greedy evaluation (settings.eval_episodes episodes, seed settings.seed).
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    if settings.learner == "lookahead":
        return train_lookahead(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)
    if settings.learner == "expert":
        return train_expert_run(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)
    torch.set_num_threads(settings.threads)
    deterministic_torch()
    keep_freed_memory()
    ckpt_dir = out / "checkpoint"
    learner, info = start_learner(scenario, settings, ckpt_dir, resume)
    scenario, s = learner.scenario, settings
    write_run_files(out, scenario, s)
    selection = Selection(learner, info)
    if resume:
        selection.restore(ckpt_dir)
    done = learner.episodes_done
    run = _Run(
        learner=learner,
        team=Team(scenario, s.envs, s.seed),
        selection=selection,
        log=RunLog(out, done, resume, tensorboard),
        bar=Progress(s.episodes, initial=done, unit="ep", enabled=progress),
        ckpt_dir=ckpt_dir,
        t_start=t_start,
        lagged=LaggedNets(learner, done // s.envs * scenario.horizon),
        expert=warm_start_expert(scenario, s),
        last_ckpt=done,
        last_val=done,
    )
    metrics: dict[str, Any] = {}
    try:
        try:
            while learner.episodes_done < s.episodes:
                run.batch()
        finally:
            run.bar.close()
            run.log.close_progress()
        run.save()
        if evaluate_at_end and s.eval_episodes > 0:
            metrics = final_evaluation(run, out)
    finally:
        run.log.close()
    wall = write_result(run, out, metrics, progress)
    return TrainResult(out, scenario, s, learner.episodes_done, wall, run.train_time, metrics, run.history)


def train_lookahead(
    scenario: Scenario,
    settings: Settings,
    out: Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """`train` for the lookahead learner (docs/model.md, The lookahead learner): its value network learns from
    `settings.episodes` simulated episodes in one go; the checkpoint gives every agent a copy, and the final
    evaluation acts as the agents do, each improving on the auction from its own belief with it."""
    t_start = time.perf_counter()
    ckpt_dir = fresh_run_dir(out, resume, "lookahead", "it learns in one go, in seconds")
    mine = own_rewards(scenario)
    if mine:  # it weighs load by load_price alone: say so rather than ignore them silently
        print(
            f"warning: the lookahead learner does not read the scenario's reward: the own rewards of {mine} change "
            "nothing it does; `--learner expert` weighs every agent's own R_II and T_RP",
            file=sys.stderr,
            flush=True,
        )
    write_run_files(out, scenario, settings)
    value = BaseValue(scenario, ValueSettings.of(settings), settings.seed)
    bars: list[Progress] = []  # the regression's, from its first update on (after the simulation)

    def show(done: int, loss: float) -> None:
        if not bars:
            bars.append(Progress(settings.value_updates, unit="upd", enabled=progress))
        bars[0].update(done, rmse=f"{math.sqrt(loss):.2f}")

    if progress:
        print(f"lookahead: simulating {settings.episodes:,} episodes of the auction", file=sys.stderr, flush=True)
    try:
        rmse = value.fit(on_update=show)
    finally:
        for bar in bars:
            bar.close()
    train_time = time.perf_counter() - t_start
    row = {
        "episodes": settings.episodes,
        "wall_s": round(train_time, 3),
        "episodes_per_s": settings.episodes / max(train_time, 1e-9),
        "updates": settings.value_updates,
        "loss": rmse**2,
    }
    save_checkpoint(
        ckpt_dir,
        scenario,
        settings,
        settings.seed,
        settings.episodes,
        [value.params()] * scenario.n_agents,
        info={"value_rmse": rmse},
    )
    log = RunLog(out, 0, False, tensorboard)
    metrics: dict[str, Any] = {}
    try:
        log.row(row, settings.episodes)
        log.close_progress()
        if evaluate_at_end and settings.eval_episodes > 0:
            metrics = evaluate_checkpoint(ckpt_dir, out, "htlm-lookahead")
            log.evaluation(metrics, settings.episodes)
    finally:
        log.close()
    wall = result_json(out, settings.episodes, t_start, train_time, None, metrics, progress)
    return TrainResult(out, scenario, settings, settings.episodes, wall, train_time, metrics, [row])


def fresh_run_dir(out: Path, resume: bool, learner: str, why: str) -> Path:
    """The checkpoint directory of a new run of a learner that cannot resume (`why`: what it does instead);
    raises when asked to resume or when `out` already holds a run."""
    ckpt_dir = out / "checkpoint"
    if resume:
        raise CheckpointError(
            f"{out}: a run of the {learner} learner has nothing to resume ({why}); train again "
            "into another output directory"
        )
    if (ckpt_dir / "meta.json").exists():
        raise FileExistsError(f"{out}: already holds a run; choose another output directory")
    return ckpt_dir


def train_expert_run(
    scenario: Scenario,
    settings: Settings,
    out: Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """`train` for the expert-iteration learner (docs/model.md, The expert-iteration learner): its rounds
    (`experiments.expert`), the best round's policy network as the checkpoint (every agent a copy), rounds.csv and
    rounds.png, one progress.csv row a round, and the final evaluation as the agents act."""
    t_start = time.perf_counter()
    ckpt_dir = fresh_run_dir(out, resume, "expert-iteration", "its rounds are quick to run again")
    write_run_files(out, scenario, settings)
    run = train_expert(scenario, settings, progress)
    train_time = time.perf_counter() - t_start
    write_rounds(out, run.rows, scenario.name, run.best_round)
    info = {"best_round": run.best_round, "rounds": [asdict(r) for r in run.rows]}
    save_checkpoint(ckpt_dir, scenario, settings, settings.seed, run.episodes, run.best_weights, info=info)
    log = RunLog(out, 0, False, tensorboard)
    history: list[dict[str, float]] = []
    metrics: dict[str, Any] = {}
    try:
        for r in run.rows[1:]:
            row = {
                "episodes": r.episodes,
                "wall_s": r.wall_s,
                "episodes_per_s": r.episodes / max(r.wall_s, 1e-9),
                "loss": r.policy_loss,
                "val_completion": r.val_completion,
                "val_failure_rate": r.val_failure_rate,
                "val_unused_fraction": r.val_unused_fraction,
            }
            log.row(row, r.episodes)
            history.append(row)
        log.close_progress()
        if evaluate_at_end and settings.eval_episodes > 0:
            metrics = evaluate_checkpoint(ckpt_dir, out, "htlm-expert")
            log.evaluation(metrics, run.episodes)
    finally:
        log.close()
    selected = run.rows[run.best_round].episodes
    wall = result_json(out, run.episodes, t_start, train_time, selected, metrics, progress)
    return TrainResult(out, scenario, settings, run.episodes, wall, train_time, metrics, history)
