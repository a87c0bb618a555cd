"""The core imports without ROS: every module outside a `ros/` folder, in all three packages, imports in a process
where rclpy is unavailable, and no source outside a `ros/` folder mentions an rclpy import."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent / "src"
PACKAGES = ("htlm_msgs_py", "htlm_world", "htlm_agent")
RCLPY_IMPORT = re.compile(r"^\s*(import\s+rclpy\b|from\s+rclpy\b)", re.MULTILINE)


def _module_name(pkg: str, path: Path) -> str:
    rel = path.relative_to(SRC / pkg).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def core_files() -> list[tuple[str, Path]]:
    """(package, source file) of the ROS-free core: every module of the three packages outside a `ros/` folder."""
    return [
        (pkg, p)
        for pkg in PACKAGES
        for p in sorted((SRC / pkg / pkg).rglob("*.py"))
        if "ros" not in p.relative_to(SRC / pkg / pkg).parts[:-1]
    ]


def importable_without_ros() -> list[str]:
    """Modules that must import without rclpy: the whole core (a `__main__` runs its command when imported)."""
    return [_module_name(pkg, p) for pkg, p in core_files() if p.name != "__main__.py"]


PROBE = """
import importlib, json, sys, traceback
sys.modules["rclpy"] = None  # `import rclpy` (and rclpy.*) now raises ImportError
failed = {}
for name in json.loads(sys.argv[1]):
    try:
        importlib.import_module(name)
    except Exception:
        failed[name] = traceback.format_exc(limit=-3)
loaded = sorted(m for m, v in sys.modules.items() if v is not None and (m == "rclpy" or m.startswith("rclpy.")))
print(json.dumps({"failed": failed, "rclpy_loaded": loaded}))
"""


def test_core_modules_import_without_rclpy() -> None:
    modules = importable_without_ros()
    assert {"htlm_world.model", "htlm_agent.runtime.team", "htlm_agent.cli", "htlm_msgs_py.schema"} <= set(modules)
    assert not any("ros" in m.split(".") for m in modules)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(SRC / pkg) for pkg in PACKAGES] + [p for p in [env.get("PYTHONPATH")] if p]
    )
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(modules)], capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["failed"] == {}, "\n".join(f"{k}:\n{v}" for k, v in result["failed"].items())
    assert result["rclpy_loaded"] == []


def test_core_sources_do_not_import_rclpy() -> None:
    offenders = [str(p.relative_to(SRC)) for _, p in core_files() if RCLPY_IMPORT.search(p.read_text())]
    assert offenders == [], f"core modules importing rclpy: {offenders}"
