"""The packaging and toolchain scaffold: package manifests, the colcon workspace, setup.sh."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

PACKAGES = ("htlm_msgs_py", "htlm_world", "htlm_agent")
EXECUTABLES = {
    "htlm_msgs_py": (),
    "htlm_world": ("world_node",),
    "htlm_agent": ("agent_node", "trainer_node", "record_node", "htlm"),
}


def _colcon() -> str | None:
    """The colcon of the running interpreter's environment (the venv), else one on PATH."""
    beside = Path(sys.executable).parent / "colcon"
    return str(beside) if beside.is_file() else shutil.which("colcon")


@pytest.mark.parametrize("package", PACKAGES)
def test_package_xml_declares_ament_python(repo_root: Path, package: str) -> None:
    pkg_dir = repo_root / "src" / package
    root = ET.parse(pkg_dir / "package.xml").getroot()
    assert root.tag == "package"
    assert root.get("format") == "3"
    assert root.findtext("name") == package == pkg_dir.name
    assert root.findtext("export/build_type") == "ament_python"
    assert (pkg_dir / "resource" / package).is_file(), "ament index marker missing"
    assert (pkg_dir / "setup.py").is_file()
    assert f"$base/lib/{package}" in (pkg_dir / "setup.cfg").read_text()


def test_setup_sh_parses(repo_root: Path) -> None:
    result = subprocess.run(["bash", "-n", str(repo_root / "setup.sh")], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr


@pytest.mark.colcon
@pytest.mark.timeout(120)
def test_colcon_build(repo_root: Path, tmp_path: Path) -> None:
    """`colcon build` of ros_ws installs every package, its manifest and its `ros2 run` executables.

    Build, install and log bases go to a temporary directory so the work tree stays clean.
    """
    colcon = _colcon()
    if colcon is None:
        pytest.skip("colcon is not installed (it comes with requirements-dev.txt: run ./setup.sh)")
    install = tmp_path / "install"
    env = {**os.environ, "COLCON_HOME": str(tmp_path / "colcon_home")}
    env.pop("COLCON_DEFAULTS_FILE", None)
    result = subprocess.run(
        [
            colcon,
            "--log-base",
            str(tmp_path / "log"),
            "build",
            "--build-base",
            str(tmp_path / "build"),
            "--install-base",
            str(install),
            "--event-handlers",
            "console_direct-",
            "console_cohesion+",
        ],
        cwd=repo_root / "ros_ws",
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=110,
    )
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout}\n{result.stderr}"
    for package in PACKAGES:
        assert (install / package / "share" / package / "package.xml").is_file(), package
        marker = install / package / "share" / "ament_index" / "resource_index" / "packages" / package
        assert marker.is_file(), package
        for executable in EXECUTABLES[package]:
            path = install / package / "lib" / package / executable
            assert path.is_file() and os.access(path, os.X_OK), f"{package}: {executable} not installed"
    launch_file = install / "htlm_agent" / "share" / "htlm_agent" / "launch" / "team.launch.py"
    assert launch_file.is_file(), "`ros2 launch htlm_agent team.launch.py` would not find the launch file"
    shipped = sorted(p.name for p in (repo_root / "src" / "htlm_world" / "htlm_world" / "scenarios").glob("*.yaml"))
    installed = sorted(p.name for p in (install / "htlm_world" / "share" / "htlm_world" / "scenarios").glob("*.yaml"))
    assert shipped and installed == shipped


def _setup_sh_lists(repo_root: Path) -> dict[str, list[str]]:
    """TORCH, ROS_WHEELS and PACKAGES exactly as setup.sh defines them (a word list each)."""
    text = (repo_root / "setup.sh").read_text()
    found: dict[str, list[str]] = {}
    for name in ("TORCH", "ROS_WHEELS", "PACKAGES"):
        m = re.search(rf"^{name}=(\(.*\)|\S.*)$", text, re.MULTILINE)
        assert m is not None, f"setup.sh no longer defines {name}"
        found[name] = shlex.split(m.group(1).strip("()"))
    return found


def _run(cmd: list[str | Path], cwd: Path, env: dict[str, str], timeout: float) -> str:
    """Run a command, fail the test with its output when it fails; returns its stdout."""
    result = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, check=False, timeout=timeout
    )
    output = f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    assert result.returncode == 0, f"{shlex.join(map(str, cmd))} failed:\n{output}"
    return result.stdout


@pytest.mark.slow  # a fresh venv with torch and the ROS wheels: about a minute (make test-slow; CI runs it)
@pytest.mark.timeout(420)
def test_packages_alone_install_and_run(repo_root: Path, tmp_path: Path) -> None:
    """The three packages declare every run-time dependency they import.

    A fresh venv (`python -m venv`, no system site-packages, none of the dev tools of requirements-dev.txt) gets what
    setup.sh installs before and besides them (the pinned torch, the ROS 2 wheels) and then the three packages from
    src/, non-editable, as a user installs them. From that venv `htlm optimal` and `htlm evaluate --baseline greedy`
    (which writes its reports and histogram) must run, every runtime and ROS module must import, and `pip check`
    must find every declared requirement satisfied. Part of the default test run: about a minute on an idle 2-core
    machine, most of it unpacking torch and fetching the ROS 2 wheels.
    """
    lists = _setup_sh_lists(repo_root)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    # pip builds a local package inside its source directory: build copies, so the work tree stays untouched
    src = tmp_path / "src"
    for package in lists["PACKAGES"]:
        shutil.copytree(
            repo_root / package,
            src / Path(package).name,
            ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"),
        )
    venv = tmp_path / "venv"
    python = venv / "bin" / "python"
    started = time.monotonic()
    _run([sys.executable, "-m", "venv", venv], tmp_path, env, 120)
    # --no-compile: byte-compiling torch's thousands of modules would be most of the install time and proves nothing
    pip = [python, "-m", "pip", "install", "-q", "--no-compile"]
    _run([*pip, "--upgrade", "pip"], tmp_path, env, 300)
    _run([*pip, *lists["TORCH"]], tmp_path, env, 300)
    _run([*pip, *lists["ROS_WHEELS"]], tmp_path, env, 300)
    _run([*pip, *[src / Path(p).name for p in lists["PACKAGES"]]], tmp_path, env, 300)
    installed = time.monotonic() - started
    _run([python, "-m", "pip", "check"], tmp_path, env, 60)

    # the installed copies are the ones that run, and every module that imports a third-party package loads
    where = _run(
        [
            python,
            "-c",
            "import htlm_msgs_py, htlm_world, htlm_agent;"
            "import htlm_agent.learning.dqn, htlm_agent.runtime.pz_env, htlm_agent.runtime.evaluate;"
            "import htlm_world.ros.world_node, htlm_agent.ros.agent_node, htlm_agent.ros.trainer_node;"
            "from torch.utils.tensorboard import SummaryWriter;"
            "print(htlm_msgs_py.__file__, htlm_world.__file__, htlm_agent.__file__)",
        ],
        tmp_path,
        env,
        120,
    )
    for path in where.split():
        assert Path(path).resolve().is_relative_to(venv.resolve()), f"{path} is not the copy installed in the venv"

    htlm = venv / "bin" / "htlm"
    optimum = json.loads(_run([htlm, "optimal", "--team", "heterogeneous", "--json"], tmp_path, env, 120))
    assert round(optimum["expected_completion_step"], 2) == 7.09

    out = tmp_path / "evaluation"
    cmd = [htlm, "evaluate", "--baseline", "greedy", "--episodes", "20", "--json", "--out", out]
    report = json.loads(_run(cmd, tmp_path, env, 120))
    assert report["policy"] == "greedy" and report["episodes"] == 20
    completion = report["completion"]
    assert 1.0 <= completion["mean"] <= 30.0 and 0.0 <= completion["failure_rate"] <= 1.0
    for name in ("metrics.json", "summary.csv", "episodes.csv", "scenario.yaml", "completion_hist.png"):
        assert (out / name).is_file(), f"htlm evaluate wrote no {name}"
    print(f"fresh venv: packages installed in {installed:.1f} s, whole test {time.monotonic() - started:.1f} s")
