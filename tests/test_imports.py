"""The import structure of the three packages: every module imports, the module-level imports between first-party
modules form no cycle, and a first-party import inside a function appears only where loading lazily is the point
(the command line, the ROS nodes)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"
PACKAGES = ("htlm_msgs_py", "htlm_world", "htlm_agent")

LAZY_FOLDERS = ("cli", "ros", "learners")
"""Folders whose modules import first-party modules inside functions on purpose: the command line loads a
subcommand's module only when it runs (`htlm optimal` never loads torch), a ROS node loads the learner only in the
mode that needs it, a learner of the registry (`learning.learners`, which every `Settings` reads) loads its
training code and networks only when it trains or acts."""

LAZY_MODULES = {
    "htlm_agent.trainer.core": "the ROS trainer's core: loads the learner (torch) only once a run starts",
    "htlm_agent.session.policy": "an agent's choice of policy: loads torch only for a checkpoint",
    "htlm_agent.session.weights": "an agent's client of the trainer's weights: loads torch only to train on them",
    "htlm_agent.learning.transition_store": "read by the trainer node: loads the learner settings only on demand",
    "htlm_agent.session.builtin": "the built-in policies by name: loads torch only for the lookahead, the optimum's "
    "code only for QMDP",
}
"""Other modules allowed first-party imports inside functions, with the reason."""


def modules() -> dict[str, Path]:
    """Every module of the three packages (dotted name -> source file)."""
    out = {}
    for pkg in PACKAGES:
        root = SRC / pkg
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _is_package(name: str, mods: dict[str, Path]) -> bool:
    return mods[name].name == "__init__.py"


def _targets(node: ast.Import | ast.ImportFrom, name: str, mods: dict[str, Path]) -> set[str]:
    """First-party modules an import statement of module `name` loads (the deepest module each name reaches)."""
    if isinstance(node, ast.Import):
        found = set()
        for alias in node.names:
            parts = alias.name.split(".")
            while parts and ".".join(parts) not in mods:
                parts.pop()
            if parts:
                found.add(".".join(parts))
        return found
    base = node.module or ""
    if node.level:
        here = name.split(".") if _is_package(name, mods) else name.split(".")[:-1]
        anchor = here[: len(here) - (node.level - 1)]
        base = ".".join(anchor + ([base] if base else []))
    if base not in mods:
        return set()
    found = set()
    for alias in node.names:
        sub = f"{base}.{alias.name}"
        found.add(sub if sub in mods else base)
    return found


def _module_level(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Import statements that run when the module is imported: outside functions and `if TYPE_CHECKING:` blocks."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(body: list[ast.stmt]) -> None:
        for st in body:
            if isinstance(st, ast.Import | ast.ImportFrom):
                found.append(st)
            elif isinstance(st, ast.If):
                if not (isinstance(st.test, ast.Name) and st.test.id == "TYPE_CHECKING"):
                    visit(st.body)
                visit(st.orelse)
            elif isinstance(st, ast.Try):
                for part in (st.body, st.orelse, st.finalbody, *[h.body for h in st.handlers]):
                    visit(part)
            elif isinstance(st, ast.With | ast.ClassDef):
                visit(st.body)

    visit(tree.body)
    return found


def _in_functions(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Import statements inside function bodies."""
    out: list[ast.Import | ast.ImportFrom] = []
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            out += [n for n in ast.walk(fn) if isinstance(n, ast.Import | ast.ImportFrom)]
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the first-party modules its module-level imports load."""
    mods = modules()
    graph = {}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        graph[name] = {t for node in _module_level(tree) for t in _targets(node, name, mods)} - {name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of the graph as a list of modules (first = last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def dfs(u: str) -> list[str] | None:
        state[u] = 1
        path.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return path[path.index(v) :] + [v]
            if v not in state and (c := dfs(v)) is not None:
                return c
        path.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (c := dfs(u)) is not None:
            return c
    return None


def test_the_import_graph_has_no_cycle() -> None:
    graph = import_graph()
    assert {"htlm_agent.learning.dqn", "htlm_agent.learning.checkpoint", "htlm_world.seeds"} <= set(graph)
    assert "htlm_agent.learning.checkpoint" in graph["htlm_agent.learning.dqn"]
    assert "htlm_agent.learning.dqn" not in graph["htlm_agent.learning.checkpoint"]
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_first_party_imports_inside_functions_only_where_lazy_on_purpose() -> None:
    mods = modules()
    offenders = []
    for name, path in mods.items():
        if any(part in LAZY_FOLDERS for part in name.split(".")[1:]) or name in LAZY_MODULES:
            continue
        tree = ast.parse(path.read_text(), str(path))
        for node in _in_functions(tree):
            if _targets(node, name, mods):
                offenders.append(f"{path.relative_to(SRC)}:{node.lineno}")
    assert offenders == [], f"first-party imports inside functions: {offenders}"


@pytest.mark.parametrize(
    "name", sorted(n for n in modules() if "ros" not in n.split(".") and not n.endswith("__main__"))
)
def test_every_module_imports(name: str) -> None:
    importlib.import_module(name)
