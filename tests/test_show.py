"""`htlm show` and the episode log of `htlm evaluate` (no ROS processes).

The episode log `htlm evaluate` writes is checked against the world's own (htlm_world.protocol.WorldEpisode fed the
logged actions); the picture against the log it was drawn from.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.cli import main
from htlm_agent.experiments.episode_plot import (
    EpisodeLogError,
    decision_rows,
    episode_figure,
    read_episode,
    save_episode_figure,
    shown_steps,
)
from htlm_agent.ros.launch import write_params
from htlm_world.episode import WorldEpisode
from htlm_world.model import Model
from htlm_world.scenario import builtin

EPISODES = 5


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The output directory of a real in-process evaluation of the greedy baseline."""
    out = tmp_path_factory.mktemp("show") / "greedy"
    code = main(["evaluate", "--baseline", "greedy", "--episodes", str(EPISODES), "--seed", "3", "--out", str(out)])
    assert code == 0
    return out


def log_lines(f: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in f.read_text().splitlines()]


def htlm_show(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["show", *argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_evaluate_logs_what_the_world_would_log(evaluated: Path) -> None:
    """The lines of OUT/world.jsonl are the world's: the world, fed the logged actions with the same seed, makes the
    same levels, observations and metrics."""
    lines = log_lines(evaluated / "world.jsonl")
    assert [x["metrics"]["episode"] for x in lines] == list(range(EPISODES))
    sc = builtin("heterogeneous")
    world = WorldEpisode(sc, Model.build(sc), seed=3, episode=0, size=EPISODES, b=0, mode="evaluate")
    actions = np.array([x["actions"] for x in lines]).transpose(1, 0, 2)  # (h, E, N)
    assert actions.shape == (sc.horizon, EPISODES, sc.n_agents)
    for t in range(sc.horizon):
        world.step({k: actions[t, :, k] for k in range(sc.n_agents)})
    for e, (line, metrics) in enumerate(zip(lines, world.metrics(), strict=True)):
        assert set(line) == {"run", "metrics", *world.trajectory(e)}
        assert line["run"] == "greedy"
        assert {k: v for k, v in line.items() if k not in ("run", "metrics")} == world.trajectory(e)
        assert set(line["metrics"]) == set(metrics)
        for k in ("episode", "completion", "failed", "idle_before", "reassign_before", "absent"):
            assert line["metrics"][k] == metrics[k], k
        assert line["metrics"]["unused_capability"] == pytest.approx(metrics["unused_capability"])
    with (evaluated / "episodes.csv").open() as f:
        completions = [int(row.split(",")[1]) for row in f.read().splitlines()[1:]]
    assert completions == [x["metrics"]["completion"] for x in lines]


def test_show_draws_the_logged_episode(evaluated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = htlm_show(capsys, str(evaluated), "--episode", "3")
    assert code == 0, err
    png = Path(out.strip())
    assert png == evaluated / "episode-3.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"episode 3 of {evaluated / 'world.jsonl'} (line 4)" in err
    assert str(evaluated / "scenario.yaml") in err

    line = log_lines(evaluated / "world.jsonl")[3]
    ep = read_episode(evaluated, 3)
    assert ep.levels.tolist() == line["levels"] and ep.actions.tolist() == line["actions"]
    steps = shown_steps(ep)
    assert steps == min(ep.actions.shape[0], line["metrics"]["completion"] + 3)

    # what the figure holds is the log: the bands' colours are the levels, the lines the decisions
    fig = episode_figure(ep)
    ax = fig.axes[0]
    bands = np.asarray(ax.collections[0].get_array()).reshape(ep.scenario.n_tasks, steps + 1)
    assert bands.tolist() == np.array(line["levels"])[: steps + 1].T.tolist()
    markers = [x for x in ax.lines if x.get_linestyle() == "None"]
    assert [x.get_label().split()[0] for x in markers] == [a.name for a in ep.scenario.agents]
    for i, m in enumerate(markers):
        rows = np.rint(np.asarray(m.get_ydata(), dtype=float)).astype(int)  # the offsets of agents are < 0.5
        assert rows.tolist() == np.array(line["actions"])[:steps, i].tolist()
        assert np.asarray(m.get_xdata()).tolist() == [t + 0.5 for t in range(steps)]
    assert f"complete at step {line['metrics']['completion']}" in ax.get_title()

    # the same episode gives the same bytes; one logged level changed gives another picture
    first = save_episode_figure(ep, tmp_path / "a.png").read_bytes()
    assert save_episode_figure(read_episode(evaluated, 3), tmp_path / "b.png").read_bytes() == first
    altered = tmp_path / "altered"
    altered.mkdir()
    (altered / "scenario.yaml").write_bytes((evaluated / "scenario.yaml").read_bytes())
    line["levels"][1][0] = (line["levels"][1][0] + 1) % ep.scenario.levels
    (altered / "world.jsonl").write_text(json.dumps(line) + "\n")
    ep2 = read_episode(altered, 3)
    assert ep2.levels[1, 0] != ep.levels[1, 0]
    assert save_episode_figure(ep2, tmp_path / "c.png").read_bytes() != first


def test_decision_rows_put_idling_below_the_tasks() -> None:
    """Task j on row j, idle at site s on row p + s, no action (HT) as a gap."""
    sc = builtin("heterogeneous")
    p = sc.n_tasks
    levels = np.array([sc.initial_levels, [0] * p])
    ep_actions = np.array([[0, 3, p, p + 1, -1]])
    from htlm_agent.experiments.episode_plot import LoggedEpisode

    ep = LoggedEpisode(Path("x"), 1, "r", 0, sc, "builtin", levels, ep_actions, {})
    rows = decision_rows(ep)
    assert rows[0, :4].tolist() == [0, 3, p, p + 1] and np.isnan(rows[0, 4])
    assert [sc.action_names[int(r)] for r in rows[0, :4]] == ["fire@site1", "rescue@site2", "idle@site1", "idle@site2"]
    fig = episode_figure(ep)  # a gap draws
    assert "complete at step 1" in fig.axes[0].get_title()


def launch_dir(root: Path) -> Path:
    """A run directory laid out as `htlm launch train` leaves it: the training episodes' world.jsonl, the evaluation
    in evaluate/, and the world's parameters files; the logs written from the world's own records."""
    sc = builtin("heterogeneous")
    model = Model.build(sc)
    rng = np.random.default_rng(0)
    for sub, mode, run_id in (("", "train", "launchrun"), ("evaluate", "evaluate", "evaluate")):
        d = root / sub if sub else root
        write_params(d / "parameters" / "world.yaml", {"team": "heterogeneous", "mode": mode, "run_id": run_id})
        world = WorldEpisode(sc, model, seed=0, episode=0, size=2, b=0, mode=mode)
        for _ in range(sc.horizon):
            world.step({k: rng.integers(0, sc.n_actions, size=2) for k in range(sc.n_agents)})
        with (d / "world.jsonl").open("w") as f:
            for i, m in enumerate(world.metrics()):
                f.write(json.dumps({"run": run_id, "metrics": m, **world.trajectory(i)}) + "\n")
    return root


def test_show_reads_a_launch_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The run directory `htlm launch train` prints: the evaluation's episodes first, the training ones by file."""
    run = launch_dir(tmp_path / "launch-train__0__x")
    code, out, err = htlm_show(capsys, str(run), "--episode", "1", "--out", str(tmp_path / "pic" / "e1.png"))
    assert code == 0, err
    assert out.strip() == str(tmp_path / "pic" / "e1.png") and (tmp_path / "pic" / "e1.png").stat().st_size > 10_000
    assert f"of {run / 'evaluate' / 'world.jsonl'} (line 2)" in err
    assert "built-in scenario, team heterogeneous" in err
    ep = read_episode(run / "world.jsonl", 1)
    assert ep.run == "launchrun"
    assert ep.levels.tolist() == log_lines(run / "world.jsonl")[1]["levels"]
    assert ep.levels.tolist() != read_episode(run, 1).levels.tolist()  # training and evaluation streams differ
    assert shown_steps(ep, all_steps=True) == ep.scenario.horizon


def test_show_errors_name_the_bad_value(evaluated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = htlm_show(capsys, str(evaluated), "--episode", "99")
    assert code == 2 and out == ""
    assert "episode 99 is not in" in err and f"episodes 0-{EPISODES - 1}" in err

    missing = tmp_path / "nowhere"
    code, _, err = htlm_show(capsys, str(missing))
    assert code == 2 and repr(str(missing)) in err

    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = htlm_show(capsys, str(empty))
    assert code == 2
    for f in ("evaluate/world.jsonl", "eval/world.jsonl", "empty/world.jsonl"):
        assert f in err

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "scenario.yaml").write_bytes((evaluated / "scenario.yaml").read_bytes())
    lines = (evaluated / "world.jsonl").read_text().splitlines()
    (bad / "world.jsonl").write_text("\n".join([lines[0], lines[1], '{"run": "x", "metrics": {"episo', lines[3]]))
    code, _, err = htlm_show(capsys, str(bad), "--episode", "3")
    assert code == 2 and f"{bad / 'world.jsonl'}:3: malformed episode record" in err

    rec = json.loads(lines[0])
    rec["levels"][2][1] = 7
    (bad / "world.jsonl").write_text(json.dumps(rec) + "\n")
    code, _, err = htlm_show(capsys, str(bad), "--episode", "0")
    assert code == 2 and f"{bad / 'world.jsonl'}:1: levels[2][1] = 7 is outside 0..4" in err

    code, _, err = htlm_show(capsys, str(evaluated), "--episode", "-1")
    assert code == 2 and "--episode -1" in err
    code, _, err = htlm_show(capsys, str(evaluated), "--out", str(tmp_path / "x.jpg"))
    assert code == 2 and "x.jpg" in err

    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "world.jsonl").write_text(lines[0] + "\n")
    with pytest.raises(EpisodeLogError, match=r"no scenario for .*looked for .*scenario\.yaml"):
        read_episode(alone, 0)


def test_unreported_levels_show_grey(evaluated: Path, tmp_path: Path) -> None:
    """An external operation's log holds null rows where no level was reported: read as -1, drawn masked (grey)."""
    rec = json.loads((evaluated / "world.jsonl").read_text().splitlines()[0])
    rec["levels"][2] = None
    rec["metrics"].update(severity="unknown", completion=-1)
    d = tmp_path / "external"
    d.mkdir()
    (d / "scenario.yaml").write_bytes((evaluated / "scenario.yaml").read_bytes())
    (d / "world.jsonl").write_text(json.dumps(rec) + "\n")
    ep = read_episode(d, 0)
    assert ep.levels[2].tolist() == [-1] * ep.scenario.n_tasks
    fig = episode_figure(ep)
    bands = fig.axes[0].collections[0].get_array()
    assert np.ma.getmaskarray(bands).reshape(ep.scenario.n_tasks, -1)[:, 2].all()
    assert np.ma.getmaskarray(bands).sum() == ep.scenario.n_tasks
    assert "grey: level not reported" in fig.axes[0].get_xlabel()
