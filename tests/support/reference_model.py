"""The reference model of docs/model.md, re-derived from its text in plain Python, independently of
htlm_world.model's tables: the transition T of the paper's fire and rescue, O and I (test_model.py checks the tables
against it, test_belief.py's brute-force Bayes filter is built from it)."""

from __future__ import annotations

L = 5
"""Severity levels 0..4."""


def ref_p_drop(c: int, level: int) -> float:
    """p_drop(c, l): 0 if c = 0 or l = 0; else by margin m = c - l: >=0 0.90, -1 0.60, -2 0.35, -3 0.15, <=-4 0.05."""
    if c == 0 or level == 0:
        return 0.0
    m = c - level
    if m >= 0:
        return 0.90
    return {-1: 0.60, -2: 0.35, -3: 0.15}.get(m, 0.05)


def ref_fire(c: int, f: int) -> list[float]:
    """Distribution of the next fire level from level f under joint fire capability c."""
    out = [0.0] * L
    if f == 0:
        out[0] = 1.0
    elif c == 0:
        out[min(L - 1, f + 1)] += 0.10
        out[f] += 0.90
    else:
        p = ref_p_drop(c, f)
        out[f - 1] += p
        out[f] += 1.0 - p
    return out


def ref_rescue(c: int, f: int, r: int) -> list[float]:
    """Distribution of the next rescue level from level r under capability c, the site's fire at level f."""
    out = [0.0] * L
    if r == 0:
        out[0] = 1.0
    elif f > 2 or c == 0:
        out[r] = 1.0
    elif f <= 1 and c >= r and r >= 2:
        p = ref_p_drop(c, r)
        out[r - 2] += 0.5 * p
        out[r - 1] += 0.5 * p
        out[r] += 1.0 - p
    else:
        p = ref_p_drop(c, r)
        out[r - 1] += p
        out[r] += 1.0 - p
    return out


SENSING_BASE, CHANNEL_BASE = 0.65, 0.2
"""docs/model.md's defaults: accuracy 0.95 at sensing 3, tau 0.8 at comm 3 (the first calibration: 0.5 and 0)."""


def ref_obs(s: int, level: int, base: float = SENSING_BASE) -> list[float]:
    """O(z | l) for sensing s: acc = min(1, base + 0.1 s) on the truth, the rest split over existing neighbours."""
    acc = min(1.0, base + 0.1 * s)
    out = [0.0] * L
    out[level] = acc
    nbrs = [n for n in (level - 1, level + 1) if 0 <= n < L]
    for n in nbrs:
        out[n] += (1.0 - acc) / len(nbrs)
    return out


def ref_info(
    s: int, comm: int, level: int, channel: bool = True, base: float = SENSING_BASE, channel_base: float = CHANNEL_BASE
) -> list[float]:
    """I(m | l) = tau O(m | l) + (1 - tau) / L with tau = min(1, channel_base + comm / 5) (1 without the channel)."""
    tau = min(1.0, channel_base + comm / 5) if channel else 1.0
    return [tau * o + (1.0 - tau) / L for o in ref_obs(s, level, base)]
