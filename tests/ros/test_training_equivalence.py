"""Training over ROS equals `htlm train` bit for bit: with the same settings and seed, the trainer process of a
launched team (world, five agents, trainer over real DDS; the world paces steps by the trainer's progress and the
agents act with the trainer's weights on the cadence) ends with exactly the Q-networks of the in-process
htlm_agent.learning.run.train(), 96 episodes in batches of 32, at trainer lag 0 (Algorithm 1 as written) and at the
learner's default lag (the agents act with networks k steps older while the trainer's updates overlap their work),
for the token networks with a warm start on the auction; and the expert-iteration learner's rounds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.settings import Settings
from htlm_world.scenario import builtin

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

LEARNER = {"envs": 32, "learning_starts": 300, "batch_size": 32, "validate_every": 0, "select_best": False}
EPISODES, SEED = 96, 0


WARM_START = {"learner": "tokens", "hidden": [16, 16], "imitate": "auction", "imitate_episodes": 32}
"""Token networks whose first batch is a warm start: the agents act with the auction on their own belief and the
trainer's networks learn to rank its choices first."""


@pytest.mark.parametrize(
    ("lag", "changes"),
    [  # the default run keeps the default lag; lag 0 and the warm start with -m slow (CI budget)
        pytest.param(0, {}, marks=pytest.mark.slow),
        *([(Settings().trainer_lag, {})] if Settings().trainer_lag else []),
        pytest.param(Settings().trainer_lag, WARM_START, marks=pytest.mark.slow),
    ],
    ids=lambda v: "warm-start" if v == WARM_START else str(v) if not isinstance(v, dict) else "paper",
)
def test_training_over_ros_equals_htlm_train(ros_team: Any, tmp_path: Path, lag: int, changes: dict[str, Any]) -> None:
    from htlm_agent.learning.run import train

    sc = builtin()
    learner = {**LEARNER, "trainer_lag": lag, **changes}
    settings = Settings.from_dict(
        Settings.with_preset({**learner, "episodes": EPISODES, "seed": SEED, "eval_episodes": 0})
    )
    train(sc, settings, tmp_path / "inproc", progress=False, tensorboard=False, evaluate_at_end=False)
    ref = load_checkpoint(tmp_path / "inproc" / "checkpoint")

    team = ros_team(
        scenario=sc, mode="train", policy="auto", episodes=EPISODES, batch=LEARNER["envs"], seed=SEED, learner=learner
    )
    team.start()
    assert team.wait("world", 150) == 0
    codes = team.wait_all(60)
    assert codes == dict.fromkeys(codes, 0), codes
    eps = team.world_episodes()
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(EPISODES))
    assert all(sum(w["metrics"]["absent"]) == 0 for w in eps), "every agent acted in every step"
    got = load_checkpoint(team.run_dir / "trainer" / "checkpoint")
    assert got.episodes_done == ref.episodes_done == EPISODES
    assert len(got.weights) == len(ref.weights) == sc.n_agents
    for i, (a, b) in enumerate(zip(ref.weights, got.weights, strict=True)):
        assert len(a) == len(b)
        for j, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"agent {i} tensor {j} differs"


EXPERT = {"learner": "expert", "episodes": 64, "envs": 16, "rounds": 2, "policy_updates": 100, "value_updates": 100}
"""Two rounds of two batches of 16 episodes: the auction plays the first, the first round's policy the second."""


def test_expert_iteration_over_ros_equals_htlm_train(tmp_path: Path) -> None:
    """`htlm launch train --set learner=expert` (the world shares the true levels with the trainer, the trainer learns
    each round while the world waits, the agents play each round's policy) ends with exactly the policy network and
    the rounds of `htlm train --learner expert`."""
    _expert_over_ros_equals_in_process(tmp_path, builtin(), [])


@pytest.mark.slow
def test_expert_iteration_with_travel_over_ros_equals_htlm_train(tmp_path: Path) -> None:
    """The same with drives (docs/model.md, Travel): every agent process follows its teammates' drives, the trainer's
    teacher counts them, and the networks and rounds are exactly `htlm train`'s."""
    import yaml

    from htlm_world.scenario import from_dict

    base = builtin()
    spec = [{"name": a.name, **a.capabilities} for a in base.agents]
    spec[0]["speed"] = 50.0
    sc = from_dict({"step_seconds": 2.0, "speed": 10.0, "agents": spec}, "<travel>")
    (path := tmp_path / "travel.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    _expert_over_ros_equals_in_process(tmp_path, sc, ["--scenario", str(path)])


def _expert_over_ros_equals_in_process(tmp_path: Path, sc: Any, scenario_args: list[str]) -> None:
    import subprocess
    import sys

    from htlm_agent.learning.run import train

    settings = Settings.for_learner(**EXPERT, validate_episodes=40, eval_episodes=0, seed=SEED)
    train(sc, settings, tmp_path / "inproc", progress=False, tensorboard=False, evaluate_at_end=False)
    ref = load_checkpoint(tmp_path / "inproc" / "checkpoint")

    sets = [x for k, v in {**EXPERT, "validate_episodes": 40}.items() for x in ("--set", f"{k}={v}")]
    cmd = [sys.executable, "-m", "htlm_agent.cli", "launch", "train", *scenario_args, *sets, "--eval-episodes", "0"]
    r = subprocess.run(
        [*cmd, "--quiet", "--run-dir", str(tmp_path / "ros")], capture_output=True, text=True, timeout=200
    )
    assert r.returncode == 0, r.stderr[-2000:]
    got = load_checkpoint(tmp_path / "ros" / "trainer" / "checkpoint")
    assert got.episodes_done == ref.episodes_done == EXPERT["episodes"]

    def rounds(info: dict[str, Any]) -> list[dict[str, Any]]:
        return [{k: v for k, v in row.items() if not k.endswith("_s")} for row in info["rounds"]]  # not the times

    assert len(rounds(got.info)) == 3 and str(rounds(got.info)) == str(rounds(ref.info))  # nan == nan as text
    assert (tmp_path / "ros" / "trainer" / "rounds.png").exists()
    for i, (a, b) in enumerate(zip(ref.weights, got.weights, strict=True)):
        for j, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"agent {i} tensor {j} differs"
