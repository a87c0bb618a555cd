"""`htlm optimal`: the centralized, fully observed optimum reproduces docs/model.md's reference figures, and a
problem too large for the machine is refused from its estimate, before anything is built."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from htlm_agent.baselines.heuristics import AuctionPolicy
from htlm_agent.baselines.optimal import (
    QMDP_LOAD_COST,
    Limits,
    ProblemSize,
    ProblemTooLarge,
    QmdpPolicy,
    action_values,
    estimate,
    solve,
    state_index,
)
from htlm_agent.runtime.evaluate import evaluate
from htlm_agent.runtime.team import Team
from htlm_world.model import Model
from htlm_world.scenario import Scenario, builtin, from_dict

REFERENCE = {"heterogeneous": 7.09, "semi-heterogeneous": 6.70, "homogeneous": 7.61}
SRC = Path(__file__).resolve().parent.parent / "src"


def _env() -> dict[str, str]:
    """The current environment, with the source packages importable even without an install."""
    paths = [str(SRC / pkg) for pkg in ("htlm_world", "htlm_agent", "htlm_msgs_py")]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def test_cli_reproduces_reference_figures() -> None:
    procs = {
        team: subprocess.Popen(
            [sys.executable, "-m", "htlm_agent.cli", "optimal", "--team", team, "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        for team in REFERENCE
    }  # the three solves run side by side
    for team, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        result = json.loads(out)
        assert result["team"] == team and result["horizon"] == 30
        assert round(result["expected_completion_step"], 2) == REFERENCE[team], result
        est = result["estimate"]  # an upper bound of the problem's size
        assert est["states"] == 625 and est["joint_actions"] == 5**5
        assert result["capability_vectors"] <= est["capability_vectors_max"] <= 6**4
        assert est["seconds"] < 2 and est["memory_bytes"] < 2**26


def test_optimum_is_a_floor_for_the_horizon() -> None:
    sol = solve(builtin("homogeneous").replace(horizon=3))
    # nothing completes 4 tasks at level 4 in 3 steps (fire drops at most one level a step): every episode fails
    assert sol.expected_completion == pytest.approx(3.0)


SEVEN_ON_THREE = {
    "sites": ["a", "b", "c"],
    "site_positions": [[0.0, 0.0], [50.0, 0.0], [100.0, 0.0]],
    "initial_levels": [4, 4, 4, 4, 4, 4],
    "agents": [
        {"name": f"agent{i + 1}", "fire": f, "rescue": r}
        for i, (f, r) in enumerate([(3, 1), (3, 2), (2, 0), (0, 1), (1, 1), (2, 2), (1, 3)])
    ],
}
"""3 sites and 7 agents of distinct capabilities: 5^6 states, 7^7 joint actions to enumerate, up to 6^6 capability
vectors; about 15 minutes and 17 GiB by the estimate."""

REFUSAL = (
    "3 sites x 2 tasks, 5 levels, 7 agents, horizon 30: 15,625 states x at most 46,656 capability vectors "
    "(from 823,543 joint actions) = 21,870,000,000 state-action evaluations; estimated 15 min and 17.0 GiB, over the "
    "limits of 10 min and 4.0 GiB"
)


def test_too_large_a_problem_is_refused_from_its_estimate() -> None:
    sc = from_dict(SEVEN_ON_THREE)
    with pytest.raises(ProblemTooLarge) as e:
        solve(sc)
    assert isinstance(e.value, ValueError)
    assert REFUSAL in str(e.value), str(e.value)
    assert e.value.estimate.states == 5**6 and e.value.limits == Limits()
    assert e.value.estimate.memory_bytes > e.value.limits.memory_bytes


def test_cli_refuses_too_large_a_problem_with_exit_2(tmp_path: Path) -> None:
    f = tmp_path / "seven.yaml"
    f.write_text(yaml.safe_dump(SEVEN_ON_THREE))
    r = subprocess.run(
        [sys.executable, "-m", "htlm_agent.cli", "optimal", "--scenario", str(f), "--json"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=60,
        check=False,
    )
    assert r.returncode == 2 and r.stdout == "", r.stdout + r.stderr
    assert r.stderr.startswith("htlm optimal: the optimum of this scenario is too large to compute here: ")
    assert REFUSAL in r.stderr and "--max-minutes and --max-memory-gb raise the limits" in r.stderr


def test_limits_and_progress(capsys: pytest.CaptureFixture[str]) -> None:
    sc = builtin()
    with pytest.raises(ProblemTooLarge, match=r"over the limits of 0\.1 s and 4\.0 GiB \(time 0\.7 s > 0\.1 s\)"):
        solve(sc, Limits(seconds=0.1))
    assert capsys.readouterr().err == ""  # refused before the enumeration started
    assert round(solve(sc, progress=True).expected_completion, 2) == REFERENCE["heterogeneous"]
    err = capsys.readouterr().err  # the final line of each phase (not a terminal: plain lines)
    assert "3125/3125 100%" in err and "joint actions/s" in err and "30/30 100%" in err and "steps/s" in err
    assert "ETA 0:00" in err


@pytest.mark.parametrize("team", sorted(REFERENCE))
def test_estimate_bounds_the_problem(team: str) -> None:
    sc: Scenario = builtin(team)
    model = Model.build(sc)
    est = estimate(ProblemSize.of(model))
    sol = solve(sc)
    assert sol.cap_vectors.shape[0] <= est.capability_vectors
    assert sol.values.size == (sc.horizon + 1) * est.states
    assert est.evaluations == sc.horizon * est.states * est.capability_vectors


def test_qmdp_agents_act_on_their_own_belief_with_the_optimums_values() -> None:
    """Each agent's QMDP choice is its part of the joint action the optimum takes in a state its belief is certain
    of, idles once it believes every task done, and does not read the true levels."""
    sc = builtin()
    pol = QmdpPolicy(sc)
    sol = pol.sol
    team = Team(sc, 4, 3)
    ctx = team.context()
    certain = np.zeros_like(ctx.marginals)
    levels = np.array([[4, 4, 4, 4], [0, 3, 0, 3], [0, 1, 0, 1], [0, 0, 0, 0]])
    for e, lv in enumerate(levels):
        certain[e, :, np.arange(sc.n_tasks), lv] = 1.0
    ctx.marginals = certain
    a = pol.act(ctx)
    caps = Model.build(sc).agent_caps[:, : sc.n_tasks]
    for e, lv in enumerate(levels[:3]):
        work = a[e] < sc.n_tasks
        joint = np.zeros(sc.n_tasks, dtype=np.int64)
        np.add.at(joint, a[e][work], caps[np.flatnonzero(work), a[e][work]])
        q = action_values(sol, sc.horizon)[:, state_index(sc, lv)]
        best = q.min()
        mine = int(np.flatnonzero((sol.cap_vectors == np.minimum(joint, sc.capability_max)).all(axis=1))[0])
        assert q[mine] <= best + QMDP_LOAD_COST * caps.sum(), (lv, a[e])  # the optimum's step, up to the load cost
    assert (a[3] >= sc.n_tasks).all()  # believed complete: everyone idles
    ctx.true_levels = np.full_like(ctx.true_levels, 4)
    assert (pol.act(ctx) == a).all()


def test_qmdp_beats_the_auction_on_the_paper_operation() -> None:
    """The reference docs/model.md gives (Baselines, qmdp): on the same episodes, sooner than the auction."""
    sc = builtin()
    qmdp = evaluate(QmdpPolicy(sc), sc, 200, 0)["completion"]["mean"]
    auction = evaluate(AuctionPolicy(sc), sc, 200, 0)["completion"]["mean"]
    assert qmdp < auction - 0.5, (qmdp, auction)
