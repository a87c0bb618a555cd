"""`htlm train` in process (`train`): the learner the settings name (`learning.learners`) trains into a run directory,
and what every learner's run writes there.

A run directory holds: settings.json, scenario.yaml, progress.csv (one row per batch of episodes, or per round),
tb/ (TensorBoard), checkpoint/ (periodic and final; with select_best its networks are the best validated ones, the
latest are in its training state), eval/ (final evaluation: metrics.json, CSVs, histogram PNG), result.json; the
expert-iteration learner's also rounds.csv and rounds.png.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml

from htlm_agent.learning.checkpoint import CheckpointError, load_checkpoint
from htlm_agent.learning.learners import learner, team_policy
from htlm_agent.learning.settings import Settings
from htlm_agent.runtime.evaluate import evaluate_run, write_reports
from htlm_world.scenario import Scenario


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


def evaluate_checkpoint(ckpt_dir: Path, out: Path, name: str) -> dict[str, Any]:
    """Greedy evaluation of a run's checkpoint, as its agents act (settings.eval_episodes episodes, seed
    settings.seed) into out/eval; returns its metrics."""
    ck = load_checkpoint(ckpt_dir)
    s = ck.settings
    evaluation = evaluate_run(team_policy(ck), ck.scenario, s.eval_episodes, seed=s.seed, policy_name=name)
    write_reports(evaluation, out / "eval")
    return evaluation.metrics


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


# ----- the run ----------------------------------------------------------------------------------------------------


def train(
    scenario: Scenario,
    settings: Settings,
    out_dir: str | Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """Train a team in process with the learner of `settings` (`LearnerKind.train`) and evaluate it greedily at the
    end, as its agents act; writes the run directory of the module docstring.

    Args:
        scenario: operation and team (ignored when resuming: the checkpoint's is used).
        settings: learning settings (when resuming, only the fields in RESUMABLE_CHANGES may differ).
        out_dir: the run directory.
        progress: show a progress line on stderr.
        resume: continue the run in out_dir from its checkpoint.
        tensorboard: also write TensorBoard logs.
        evaluate_at_end: run the final greedy evaluation (settings.eval_episodes episodes, seed settings.seed).
    """
    out = Path(out_dir)
    return learner(settings.learner).train(scenario, settings, out, progress, resume, tensorboard, evaluate_at_end)
