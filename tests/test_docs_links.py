"""Every relative link of README.md and docs/ leads somewhere: the file exists and, for a Markdown file, the
heading the link's anchor names is in it (GitHub's anchors: lower case, punctuation dropped, spaces to hyphens)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading.

    Args:
        heading: the heading's text, without its leading `#`s.

    Returns:
        The anchor a link names it by.
    """
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_every_relative_link_resolves() -> None:
    broken = []
    for doc in DOCS:
        text = doc.read_text()
        for m in re.finditer(r"\]\(([^)\s]+)\)", text):
            link = m.group(1)
            if re.match(r"[a-z]+:", link):
                continue
            path, _, name = link.partition("#")
            target = (doc.parent / path).resolve() if path else doc
            where = f"{doc.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}: {link}"
            if not target.exists():
                broken.append(f"{where} (no such file)")
            elif name and target.suffix == ".md":
                headings = re.findall(r"^#+ (.*)$", target.read_text(), re.MULTILINE)
                if name not in {anchor(h) for h in headings}:
                    broken.append(f"{where} (no such heading)")
    assert not broken, "\n".join(broken)
