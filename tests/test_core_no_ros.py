"""The core imports without ROS (STYLE.md 1): every module of htlm_world and htlm_agent except the *_node.py
adapters, and the htlm_msgs_py modules that do not need rclpy, import in a process where rclpy is unavailable."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent / "src"
CORE_PACKAGES = ("htlm_world", "htlm_agent")
RCLPY_IMPORT = re.compile(r"^\s*(import\s+rclpy\b|from\s+rclpy\b)", re.MULTILINE)


def _module_name(pkg: str, path: Path) -> str:
    rel = path.relative_to(SRC / pkg).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def core_files() -> list[tuple[str, Path]]:
    """(package, source file) of the ROS-free core: htlm_world and htlm_agent without the *_node.py adapters."""
    return [
        (pkg, p)
        for pkg in CORE_PACKAGES
        for p in sorted((SRC / pkg / pkg).rglob("*.py"))
        if not p.name.endswith("_node.py")
    ]


def importable_without_ros() -> list[str]:
    """Modules that must import without rclpy: the core, and htlm_msgs_py modules whose source has no rclpy."""
    names = [_module_name(pkg, p) for pkg, p in core_files()]
    for p in sorted((SRC / "htlm_msgs_py" / "htlm_msgs_py").rglob("*.py")):
        if not RCLPY_IMPORT.search(p.read_text()):
            names.append(_module_name("htlm_msgs_py", p))
    return names


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
    assert "htlm_world.model" in modules and "htlm_agent.team" in modules and "htlm_agent.pz_env" in modules
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(SRC / pkg) for pkg in (*CORE_PACKAGES, "htlm_msgs_py")] + [p for p in [env.get("PYTHONPATH")] if p]
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
