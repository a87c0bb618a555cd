"""Learner settings the tests share."""

from __future__ import annotations

from htlm_agent.learning.settings import Settings

TINY = Settings(
    episodes=64,
    envs=16,
    learning_starts=64,
    batch_size=32,
    memory=2_000,
    hidden=(16, 16),
    validate_every=32,
    validate_episodes=8,
    eval_episodes=16,
    checkpoint_every=0,
    updates_per_step=2,
    trainer_lag=0,
)
"""A run of a few seconds (the learner's defaults before 2026-11-26 where they are not set here: the paper's digests
in tests/data/paper_pinned.json come from it)."""
