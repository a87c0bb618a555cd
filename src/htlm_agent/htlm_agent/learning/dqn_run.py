"""A run of the deep Q-learners in process (`htlm train --learner paper|tokens`; `learners.paper.QLearner`):
Algorithm 1 with B parallel episodes, validation and selection of the best networks, checkpoints, progress.csv /
TensorBoard logs and the final greedy evaluation (the run directory of `learning.run`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.loop import (
    LaggedNets,
    Selection,
    episode_epsilons,
    imitate_step,
    validate,
    warm_start_expert,
)
from htlm_agent.learning.run import (
    RESUMABLE_CHANGES,
    RunLog,
    TrainResult,
    deterministic_torch,
    evaluate_checkpoint,
    keep_freed_memory,
    result_json,
    write_run_files,
)
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.context import Policy
from htlm_agent.mind.policies import knowledge_context, team_epsilon_greedy
from htlm_agent.progress import Progress
from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.metrics import episode_metrics
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray

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


def write_result(run: _Run, out: Path, metrics: dict[str, Any], progress: bool) -> float:
    """result.json (and the final line on stderr with `progress`); returns the wall time of the run."""
    s = run.learner.settings
    selected = run.selection.episode if s.select_best else None
    return result_json(out, run.learner.episodes_done, run.t_start, run.train_time, selected, metrics, progress)


def train_dqn(
    scenario: Scenario,
    settings: Settings,
    out: Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """`learning.run.train` for a deep Q-learner (the module docstring)."""
    t_start = time.perf_counter()
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
