"""Scenario events the tests share."""

from __future__ import annotations

MIXED: list[dict[str, object]] = [
    {"event": "surge", "site": "site1", "task": "fire", "level": 4, "at": 6},
    {"event": "dropout", "agent": "agent2", "at": 3},
    {"event": "return", "agent": "agent2", "at": 9, "probability": 0.5},
    {"event": "surge", "site": "site2", "task": "rescue", "level": 3, "at": 2, "probability": 0.3},
    {"event": "surge", "site": "site1", "task": "rescue", "level": 2, "once_done": "site1"},
]
"""Surges (at a step, by chance, once a site is done), a dropout and a chance return, for the paper's scenario."""
