"""The launcher's supervision (`htlm_agent.ros.launch.run_team`) with stand-in processes: small Python programs that
stand in for the nodes (they exit with a code, kill themselves or run until told to end), so that what the launcher
does with each kind of exit is checked in a second, without ROS. The kills of real nodes through `htlm launch` are in
tests/ros/test_supervise.py."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from htlm_agent.ros import launch
from htlm_agent.ros.launch import LaunchConfig, ProcessSpec, killed, last_error, restarts, run_team, write_params
from htlm_world.scenario import builtin

pytestmark = pytest.mark.timeout(60)

CHILD = """
import json, os, signal, sys, time
params = {}
path = sys.argv[sys.argv.index("--params-file") + 1]
for line in open(path).read().splitlines()[2:]:
    k, v = line.strip().split(": ", 1)
    params[k] = json.loads(v)
run = params["run"]
count = os.path.join(run, params["name"] + ".count")
n = int(open(count).read()) + 1 if os.path.exists(count) else 1
open(count, "w").write(str(n))
stopped = []
signal.signal(signal.SIGINT, lambda s, f: stopped.append(s))
signal.signal(signal.SIGTERM, lambda s, f: stopped.append(s))
fail = params.get("fail", [])  # what incarnation i does: an exit code, "kill" or "raise"; past the list: run
how = fail[n - 1] if n <= len(fail) else "run"
if how == "kill":
    os.kill(os.getpid(), signal.SIGKILL)
if how == "raise":
    raise RuntimeError(f"{params['name']} cannot go on")
if how != "run":
    sys.exit(how)
while not stopped and not os.path.exists(os.path.join(run, "end")):
    time.sleep(0.02)
sys.exit(128 + stopped[0] if stopped else 0)
"""


class Launch:
    """run_team on stand-in processes, in a thread; `stderr` holds what the launcher said."""

    def __init__(self, tmp: Path, monkeypatch: pytest.MonkeyPatch, mode: str, fail: dict[str, list[Any]], **kw: Any):
        (tmp / "child").mkdir()
        (tmp / "child" / "stand_in.py").write_text(CHILD)
        monkeypatch.setenv("PYTHONPATH", str(tmp / "child"))
        self.run = tmp / "run"
        self.cfg = LaunchConfig(mode=mode, scenario=builtin(), run_dir=self.run, echo=False, **kw)
        respawn = mode == "deploy"

        def prepare(cfg: LaunchConfig) -> list[tuple[ProcessSpec, Path]]:
            (cfg.run_dir / "logs").mkdir(parents=True, exist_ok=True)
            out = []
            for name in ("world", "trainer", "agent1"):
                params = {"name": name, "run": str(cfg.run_dir), "fail": fail.get(name, [])}
                spec = ProcessSpec(name, "stand_in", params, respawn, cfg.respawn_delay, cfg.max_restarts)
                out.append((spec, write_params(cfg.run_dir / "parameters" / f"{name}.yaml", params)))
            return out

        monkeypatch.setattr(launch, "prepare", prepare)
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run)
        self.stderr: list[str] = []
        self.monkeypatch = monkeypatch

    def _run(self) -> None:
        self.code = run_team(self.cfg)

    def start(self, capsys: pytest.CaptureFixture[str]) -> Launch:
        self.capsys = capsys
        self.thread.start()
        return self

    def said(self) -> str:
        self.stderr.append(self.capsys.readouterr().err)
        return "".join(self.stderr)

    def incarnations(self, name: str) -> int:
        f = self.run / f"{name}.count"
        return int(f.read_text() or 0) if f.exists() else 0

    def wait_for(self, what: Any, why: str, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while not what():
            assert time.monotonic() < end, f"timed out waiting for {why}; the launcher said:\n{self.said()}"
            time.sleep(0.02)

    def end(self) -> int:
        """The run's end (every stand-in exits 0), then the launcher's exit code."""
        (self.run / "end").touch()
        return self.finish()

    def finish(self) -> int:
        self.thread.join(timeout=30)
        assert not self.thread.is_alive(), f"the launcher did not return; it said:\n{self.said()}"
        assert self.code is not None
        return self.code


@pytest.fixture
def launched(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> Any:
    monkeypatch.setattr(signal, "signal", lambda *a: signal.SIG_DFL)  # run_team runs in a thread here
    return lambda mode, fail, **kw: Launch(tmp_path, monkeypatch, mode, fail, **kw).start(capsys)


def test_which_exits_are_restarted() -> None:
    spec = ProcessSpec("agent1", "m", {}, respawn=False)
    deployed = ProcessSpec("agent1", "m", {}, respawn=True)
    assert killed(-9) and killed(-15) and killed(130) and killed(143) and not killed(1) and not killed(0)
    assert [restarts(spec, rc) for rc in (0, 1, 2, -9, 130, 143)] == [False, False, False, True, True, True]
    assert [restarts(deployed, rc) for rc in (0, 1, 2, -9, 130, 143)] == [False, True, False, True, True, True]


def test_the_line_that_says_why(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    log.write_text(
        '[INFO] [1.0] [htlm_trainer]: run r\nTraceback (most recent call last):\n  File "x.py", line 1, in <module>\n'
        "    return f()\nValueError: bad row\n[INFO] [2.0] [htlm_trainer]: counters at exit: a 1\n"
    )
    assert last_error(log) == "ValueError: bad row"
    log.write_text("[ERROR] [1.0] [htlm_trainer]: the store is broken\n[INFO] [2.0] [htlm_trainer]: counters\n")
    assert last_error(log) == "the store is broken"
    assert last_error(tmp_path / "none.log") == ""


def test_deploy_restarts_a_process_that_fails_with_a_back_off_and_the_others_go_on(launched: Any) -> None:
    team = launched("deploy", {"agent1": [1, "kill"]}, respawn_delay=0.05)
    team.wait_for(lambda: team.incarnations("agent1") == 3, "agent1's third start")
    assert team.incarnations("world") == team.incarnations("trainer") == 1, "another process was restarted"
    assert team.end() == 0
    said = team.said()
    assert "agent1 exited with 1; restarting it in 0.05 s (restart 1 in a row of at most 5)" in said, said
    assert "agent1 exited with -9; restarting it in 0.1 s (restart 2 in a row of at most 5)" in said, said
    assert "restarts: agent1 2" in said, said
    log = (team.run / "logs" / "agent1.log").read_text()
    assert "--- htlm launch: restart 1 after exit 1 ---" in log and "restart 2 after exit -9" in log, log


def test_deploy_gives_up_after_max_restarts_in_a_row(launched: Any) -> None:
    team = launched("deploy", {"world": [3, 3, 3, 3]}, respawn_delay=0.01, max_restarts=2)
    assert team.finish() == 1
    said = team.said()
    assert "world exited with 3 after 2 restarts in a row (--max-restarts 2): stopping the team" in said, said
    assert team.incarnations("world") == 3


def test_a_killed_process_is_restarted_in_lockstep(launched: Any) -> None:
    team = launched("train", {"trainer": ["kill"], "world": [143]}, respawn_delay=0.01)
    team.wait_for(lambda: team.incarnations("trainer") == 2 and team.incarnations("world") == 2, "the restarts")
    assert team.end() == 0
    said = team.said()
    assert "trainer exited with -9; restarting it" in said and "world exited with 143; restarting it" in said, said


def test_in_lockstep_a_process_that_fails_by_itself_stops_the_launch_at_once_with_its_message(launched: Any) -> None:
    team = launched("train", {"trainer": ["raise"]})
    assert team.finish() == 1  # without the run's end: the launcher stops the team itself
    said = team.said()
    assert "trainer exited with 1: RuntimeError: trainer cannot go on; in train a process that fails by itself" in said
    assert team.incarnations("trainer") == 1 and team.incarnations("world") == 1


def test_exit_2_stops_every_mode(launched: Any) -> None:
    team = launched("deploy", {"agent1": [2]})
    assert team.finish() == 2
    assert "agent1 exited with 2 (bad parameters or store)" in team.said()


def test_no_restart_after_the_world_finished(launched: Any) -> None:
    team = launched("deploy", {}, respawn_delay=0.01)
    team.wait_for(lambda: team.incarnations("agent1") == 1, "agent1 to start")
    assert team.end() == 0
    assert team.incarnations("agent1") == 1 and "restarting" not in team.said()
