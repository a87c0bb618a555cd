"""The packaging and toolchain scaffold: package manifests, the colcon workspace, setup.sh."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

PACKAGES = ("htlm_msgs_py", "htlm_world", "htlm_agent")
EXECUTABLES = {
    "htlm_msgs_py": (),
    "htlm_world": ("world_node",),
    "htlm_agent": ("agent_node", "trainer_node", "htlm"),
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
    shipped = sorted(p.name for p in (repo_root / "src" / "htlm_world" / "htlm_world" / "scenarios").glob("*.yaml"))
    installed = sorted(p.name for p in (install / "htlm_world" / "share" / "htlm_world" / "scenarios").glob("*.yaml"))
    assert shipped and installed == shipped
