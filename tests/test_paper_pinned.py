"""The paper's scenario pinned bit for bit: simulator, beliefs, rewards, a fixed-seed training run's networks, the
lockstep protocol's records and logs, markers. The digests in tests/data/paper_pinned.json were taken from the code
before task kinds became data; the scenario file `paper` must keep reproducing them exactly.

To take the digests anew after a change that is meant to change the numbers: `python tests/test_paper_pinned.py`
(prints the JSON to store), and say why in the commit.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.baselines.heuristics import GreedyPolicy, RandomPolicy
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.run import train
from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.runtime.evaluate import _log_lines, evaluate_run
from htlm_agent.runtime.team import Team, rollout
from htlm_agent.session.builtin import builtin_policy
from htlm_world.scenario import Scenario, builtin, load
from support.learning import TINY  # the learner tests' run of a few seconds

PINNED = Path(__file__).parent / "data" / "paper_pinned.json"
PINNED_WEIGHTS = Path(__file__).parent / "data" / "paper_pinned_weights.npz"
"""The training run's networks (`python tests/test_paper_pinned.py` writes them beside the digests)."""


def _digest(*parts: Any) -> str:
    h = hashlib.sha256()
    for x in parts:
        if isinstance(x, np.ndarray):
            h.update(str(x.dtype).encode() + str(x.shape).encode())
            h.update(np.ascontiguousarray(x).tobytes())
        else:
            h.update(json.dumps(x, sort_keys=True).encode())
    return h.hexdigest()[:24]


def _rollout_digest(sc: Scenario, policy: Any, batch: int, seed: int) -> str:
    team = Team(sc, batch, seed)
    tr = rollout(team, policy)
    parts = [tr.levels, tr.actions, tr.observations, tr.messages, tr.rewards, team.sites, team.marg]
    parts += [tr.extra[k] for k in sorted(tr.extra)]
    return _digest(*parts)


def _scenarios() -> dict[str, Scenario]:
    return {
        "heterogeneous": builtin(),
        "semi": builtin("semi-heterogeneous", reassign="high"),
        "homogeneous-ht": builtin("homogeneous", idle_incentive=0.0, mode="ht"),
        "first-calibration": load("first-calibration"),
    }


def digests(tmp: Path) -> dict[str, str]:
    """Every pinned digest (a few seconds)."""
    torch.set_num_threads(1)
    out: dict[str, str] = {}
    for name, sc in _scenarios().items():
        out[f"rollout/random/{name}"] = _rollout_digest(sc, RandomPolicy(sc, seed=5), 16, 3)
        out[f"rollout/greedy/{name}"] = _rollout_digest(sc, GreedyPolicy(sc), 16, 4)
    sc = builtin()
    pols = [builtin_policy(sc, "random", i)[0] for i in range(sc.n_agents)]
    dp = DecentralizedPolicy(pols, 7, 1.0)
    dp.begin(0)
    out["rollout/epsilon/batch1"] = _rollout_digest(sc, dp, 1, 7)
    ev = evaluate_run(GreedyPolicy(sc), sc, episodes=12, seed=1, policy_name="greedy")
    lines = [json.loads(line) for line in _log_lines(ev, "pinned", 0)]
    for line in lines:
        line["metrics"].pop("seconds")  # wall time
    out["evaluate/log"] = _digest(lines)
    run = train(sc, TINY, tmp / "train", progress=False, tensorboard=False)
    ck = load_checkpoint(tmp / "train")
    out["train/weights"] = _digest(*[w for ws in ck.weights for w in ws])
    np.savez(tmp / "weights.npz", *[np.asarray(w) for ws in ck.weights for w in ws])
    metrics = json.loads(json.dumps(run.metrics))
    for a in metrics.get("agents", []):  # how capabilities are named changed with task kinds as data
        for key in ("fire", "rescue", "capabilities"):
            a.pop(key, None)
    for key in ("events", "unused_fraction_open"):  # added with events: new keys, the others unchanged
        metrics.pop(key, None)
    out["train/metrics"] = _digest(metrics)
    return out


def test_the_paper_scenario_is_pinned_bit_for_bit(tmp_path: Path) -> None:
    """Every digest equal; the training run's networks equal to float rounding: their last bits follow the CPU's
    vector kernels (the same run on two x86-64 machines differs there, and in nothing the run reports)."""
    want = json.loads(PINNED.read_text())
    want.pop("protocol/logs")
    got = digests(tmp_path)
    assert got.keys() == want.keys()
    differ = {k: (got[k], want[k]) for k in want if got[k] != want[k] and k != "train/weights"}
    assert not differ, f"digests that changed (got, pinned): {differ}"
    with np.load(tmp_path / "weights.npz") as run, np.load(PINNED_WEIGHTS) as pinned:
        assert run.files == pinned.files
        for name in pinned.files:
            np.testing.assert_allclose(run[name], pinned[name], rtol=1e-4, atol=1e-6, err_msg=name)


def _protocol_digest() -> str:
    from support.team import loopback_run  # the one-process protocol with one AgentMind per agent

    sc = builtin()
    pols = [builtin_policy(sc, "random", i)[0] for i in range(sc.n_agents)]
    world_log, agent_logs = loopback_run(sc, 3, 0, 3, pols, 1.0, batch=2)
    return _digest(world_log, {str(k): v for k, v in agent_logs.items()})


def test_the_lockstep_records_are_pinned() -> None:
    want = json.loads(PINNED.read_text())
    assert _protocol_digest() == want["protocol/logs"]


if __name__ == "__main__":  # print the digests to pin
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        found = digests(Path(d))
        (Path(d) / "weights.npz").replace(PINNED_WEIGHTS)
    found["protocol/logs"] = _protocol_digest()
    json.dump(found, sys.stdout, indent=1, sort_keys=True)
    print()
