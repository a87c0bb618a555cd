"""The random streams of a run (htlm_world.seeds): every stream is named once, no two streams of a run draw the same
numbers, and the streams the two runtimes share kept their draws."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from htlm_world import seeds

SRC = Path(__file__).resolve().parent.parent / "src"


def _state(g: np.random.Generator) -> tuple[int, ...]:
    """What a generator will draw: its first four 64-bit words (equal streams draw equal words)."""
    return tuple(int(x) for x in g.integers(0, 2**63, size=4))


def run_streams(seed: int, n_agents: int, episodes: int, batches: int, chunks: int) -> dict[str, tuple[int, ...]]:
    """Every stream of one run, by name: an evaluation or ROS run of `episodes` episodes, an in-process training run
    of `batches` batches with validation over `chunks` evaluation batches, the random baseline."""
    out: dict[str, tuple[int, ...]] = {}
    val = seeds.validation(seed)
    for e in range(episodes):
        out[f"world/{e}"] = _state(seeds.world(seed, e))
        out[f"validation_world/{e}"] = _state(seeds.world(val, e)) if e < chunks else ()
        for i in range(n_agents):
            out[f"channel/{i}/{e}"] = _state(seeds.channel(seed, i, e))
            out[f"explore/{i}/{e}"] = _state(seeds.explore(seed, i, e))
            if e < chunks:
                out[f"validation_channel/{i}/{e}"] = _state(seeds.channel(val, i, e))
    for b in range(batches):
        out[f"train_world/{b}"] = _state(seeds.train_world(seed, b))
        out[f"train_dropout/{b}"] = _state(seeds.train_dropout(seed, b))
        for i in range(n_agents):
            out[f"train_channel/{i}/{b}"] = _state(seeds.train_channel(seed, i, b))
            out[f"train_explore/{i}/{b}"] = _state(seeds.train_explore(seed, i, b))
    for i in range(n_agents):
        out[f"network_init/{i}"] = _state(np.random.default_rng(seeds.network_init(seed, i)))
        out[f"replay/{i}"] = _state(np.random.default_rng(seeds.replay(seed, i)))
        out[f"random_policy/{i}"] = _state(seeds.random_policy(seed, i))
    out["validation"] = _state(np.random.default_rng(val))
    return {k: v for k, v in out.items() if v}


@pytest.mark.parametrize("seed", [0, 1, 7, 2**32 + 1, 2**63 - 1])
def test_no_two_streams_of_a_run_coincide(seed: int) -> None:
    streams = run_streams(seed, n_agents=5, episodes=12, batches=12, chunks=3)
    assert len(streams) == 12 + 3 + 5 * (12 + 12 + 3) + 12 + 12 + 5 * 2 * 12 + 5 * 3 + 1  # train_dropout: 12
    by_state: dict[tuple[int, ...], str] = {}
    for name, state in streams.items():
        assert state not in by_state, f"streams {by_state[state]} and {name} draw the same numbers (seed {seed})"
        by_state[state] = name


def test_network_initialisation_and_episode_0_exploration_are_different_streams() -> None:
    """A collision once found: SeedSequence([s, 2, i]) (weights) equalled SeedSequence([s, 2, i, 0]) (exploration
    of episode 0)."""
    for i in range(5):
        init = seeds.sequence(3, seeds.Stream.NETWORK_INIT, i).generate_state(4).tolist()
        explore = seeds.explore(3, i, 0).bit_generator.seed_seq.generate_state(4).tolist()  # type: ignore[attr-defined]
        assert init != explore
        old_init = np.random.SeedSequence([3, 2, i]).generate_state(4).tolist()
        assert old_init == explore  # what it was


def test_tags_are_distinct_and_keys_have_a_fixed_length() -> None:
    tags = [s.value for s in seeds.Stream]
    assert len(set(tags)) == len(tags)
    for stream in seeds.Stream:
        assert len(seeds.sequence(11, stream).entropy) == 4  # type: ignore[arg-type]
        assert len(seeds.sequence(11, stream, 2, 3).entropy) == 4  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="seed -1"):
        seeds.sequence(-1, seeds.Stream.WORLD)
    with pytest.raises(ValueError, match="CHANNEL stream key second"):
        seeds.sequence(0, seeds.Stream.CHANNEL, 0, 2**32)


@pytest.mark.parametrize(
    ("name", "args", "key"),
    [
        ("world", (5, 3), [5, 0, 3]),
        ("channel", (5, 2, 3), [5, 1, 2, 3]),
        ("explore", (5, 2, 3), [5, 2, 2, 3]),
        ("train_world", (5, 4), [5, 10, 4]),
        ("train_channel", (5, 1, 4), [5, 11, 1, 4]),
        ("train_explore", (5, 1, 4), [5, 3, 1, 4]),
        ("random_policy", (5, 1), [5, 5, 1]),
    ],
)
def test_streams_other_than_network_init_kept_their_draws(name: str, args: tuple[int, ...], key: list[int]) -> None:
    """Only the network initialisation moved (it shared tag 2 with exploration); every other stream draws what it
    drew before the streams were named here, so evaluations and the ROS equivalence reference are unchanged."""
    before = np.random.default_rng(np.random.SeedSequence(key))
    assert _state(getattr(seeds, name)(*args)) == _state(before)


def test_only_the_seeds_module_builds_seed_sequences() -> None:
    """Every stream is named in htlm_world.seeds: no other source of the packages derives a SeedSequence itself."""
    pattern = re.compile(r"SeedSequence\(")
    offenders = [
        str(p.relative_to(SRC))
        for p in SRC.rglob("*.py")
        if "build" not in p.parts and p.name != "seeds.py" and pattern.search(p.read_text())
    ]
    assert offenders == []
