"""docs/architecture.md's file map is true: every file and folder it names exists, and every module under src/ is
in it.

The map is the code block that begins with `src/htlm_msgs_py/htlm_msgs_py/`. A line that starts in the first column
names a folder (ending in `/`) or a file, relative to the repository; a line indented by two spaces names a file, a
folder or a glob relative to the last such folder; deeper lines continue a description. A package's `__init__.py`
is in the map when its folder is.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def map_entries(text: str) -> list[str]:
    """The paths the file map names, relative to the repository, in the order it names them.

    Args:
        text: the text of docs/architecture.md.

    Returns:
        One path (or glob) per entry of the map; folders end in `/`.
    """
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("src/htlm_msgs_py/htlm_msgs_py/ "))
    entries: list[str] = []
    base = ""
    for line in lines[start:]:
        if line == "```":
            break
        if not line.strip():
            continue
        if not line.startswith(" "):
            name = line.split()[0]
            entries.append(name)
            base = name if name.endswith("/") else ""
        elif line.startswith("  ") and not line.startswith("   "):
            assert base, f"docs/architecture.md: {line.strip()!r} is indented under no folder"
            entries.append(base + line.split()[0])
    return entries


def test_the_map_is_found() -> None:
    entries = map_entries(ARCHITECTURE.read_text())
    assert "src/htlm_world/htlm_world/scenario.py" in entries
    assert "src/htlm_agent/htlm_agent/mind/belief.py" in entries


def test_every_file_the_map_names_exists() -> None:
    missing = [e for e in map_entries(ARCHITECTURE.read_text()) if not any(ROOT.glob(e.rstrip("/")))]
    assert not missing, f"docs/architecture.md names what does not exist: {missing}"


def test_every_module_under_src_is_in_the_map() -> None:
    entries = map_entries(ARCHITECTURE.read_text())
    named: set[Path] = set()
    for e in entries:
        named.update(ROOT.glob(e.rstrip("/")))
    modules = sorted(p for p in (ROOT / "src").glob("*/**/*.py") if p.name != "setup.py")
    missing = [
        str(p.relative_to(ROOT))
        for p in modules
        if p not in named and not (p.name == "__init__.py" and p.parent in named)
    ]
    assert not missing, f"docs/architecture.md's file map lacks: {missing}"
