"""The domain of an example lives in its scenario file: no module but the scenario loader (which still reads the first
file format's paper keys) names a kind of the shipped scenarios."""

from __future__ import annotations

import re
from pathlib import Path

from htlm_world.scenario import load, named_scenarios

SRC = Path(__file__).resolve().parent.parent / "src"
LOADER = SRC / "htlm_world" / "htlm_world" / "scenario.py"


def test_no_module_names_a_kind_of_the_paper() -> None:
    kinds = {k.name for k in load("paper").kinds} | {k.uses for k in load("paper").kinds}
    pattern = re.compile(r"\b(" + "|".join(sorted(kinds)) + r")s?\b", re.IGNORECASE)
    found = [
        f"{path.relative_to(SRC)}:{n}: {line.strip()}"
        for path in sorted(SRC.rglob("*.py"))
        if path != LOADER
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not found, "\n".join(found)


def test_every_shipped_scenario_loads_with_kinds_of_its_own() -> None:
    for name in named_scenarios():
        sc = load(name)
        assert sc.kinds and sc.n_tasks >= 1 and sc.n_agents >= 1, name
