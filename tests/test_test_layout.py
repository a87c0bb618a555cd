"""The test suite's own layout: a test module imports its helpers from the support package (tests/support/), never
from another test module or from a conftest, whose fixtures pytest hands over by name."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def _imported(path: Path) -> list[str]:
    """The modules a file imports, relative ones with their leading dots."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            names += [base] if node.module else [f"{base}{a.name}" for a in node.names]
    return names


def test_no_test_module_imports_another_or_a_conftest() -> None:
    files = [p for p in TESTS.rglob("*.py") if p.name.startswith("test_") or p.name == "conftest.py"]
    files += list((TESTS / "support").glob("*.py"))
    wrong = [
        f"{p.relative_to(TESTS)}: {name}"
        for p in sorted(files)
        for name in _imported(p)
        if name.rsplit(".", 1)[-1].startswith("test_") or name.rsplit(".", 1)[-1] == "conftest"
    ]
    assert not wrong, "import helpers from tests/support instead:\n" + "\n".join(wrong)
