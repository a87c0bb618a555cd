"""Every random stream of a run, named once and derived from the run's master seed.

A stream is `numpy.random.SeedSequence([seed, tag, first, second])`: the master seed, the stream's tag and always
exactly two more keys (agent, episode, batch, ...; 0 where a stream has fewer). Because every key list of a seed has
the same length and the tags differ, no two streams can share an entropy key, so no two streams of a run ever draw
the same numbers (tests/test_seeds.py checks it on generated states). The fixed length matters: a SeedSequence pads
a short key with zeros, so a three-key [s, t, i] would equal the four-key [s, t, i, 0].

Both runtimes take their generators from here: the in-process Team and the ROS world process draw the world from
`world(seed, episode)`, every agent (in process or its own process) its channel from `channel(seed, agent, episode)`
and its ε-greedy exploration from `explore(seed, agent, episode)`.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

_WORD = 2**32


class Stream(IntEnum):
    """The tag of every stream; a tag is never reused for another purpose."""

    WORLD = 0
    """Transitions and observations of one episode (or one batch of evaluation episodes): keys (episode, 0)."""
    CHANNEL = 1
    """One agent's simulated channel in one episode: keys (agent, episode)."""
    EXPLORE = 2
    """One agent's ε-greedy choices in one episode of batch 1 (the agents' processes, `DecentralizedPolicy`)."""
    TRAIN_EXPLORE = 3
    """One agent's ε-greedy choices in one batch of in-process training episodes: keys (agent, batch)."""
    REPLAY = 4
    """One agent's replay-memory sampling: keys (agent, 0)."""
    RANDOM_POLICY = 5
    """One agent's draws in the random baseline: keys (agent, 0)."""
    VALIDATION = 6
    """The master seed of the validation episodes of a training run: keys (0, 0)."""
    NETWORK_INIT = 7
    """One agent's initial network weights: keys (agent, 0). (Tag 2 until the EXPLORE collision was fixed.)"""
    TRAIN_WORLD = 10
    """The world of one batch of in-process training episodes: keys (batch, 0)."""
    TRAIN_CHANNEL = 11
    """One agent's channel in one batch of in-process training episodes: keys (agent, batch)."""
    TRAIN_DROPOUT = 12
    """Which teammate drops out of which episode of one batch of training episodes (`Settings.dropout`): keys
    (batch, 0)."""
    ROBOT_OPERATION = 13
    """The stand-in operation of the simulated robots (external world): task transitions of one episode: keys
    (episode, 0)."""
    ROBOT_SENSING = 14
    """One simulated robot's observations in one episode: keys (agent, episode)."""
    EVENTS = 15
    """The scenario's events of one episode (or one batch of evaluation episodes): keys (episode, 0)."""
    TRAIN_EVENTS = 16
    """The scenario's events of one batch of in-process training episodes: keys (batch, 0)."""
    IMITATION = 17
    """The warm start's draws of stored expert choices (`Settings.imitate_updates`): keys (0, 0)."""
    BASE_ROLLOUTS = 18
    """The simulated episodes the lookahead baseline learns its value from, and its network's initial weights:
    keys (0, 0) and (1, 0)."""
    LOOKAHEAD = 19
    """The lookahead baseline's draws of states from the agents' beliefs: keys (0, 0)."""
    EXPERT_KEEP = 20
    """Which team steps of one batch of the expert-iteration learner's play its teacher judges: keys (batch, 0)."""
    EXPERT_ROUND = 21
    """One round of the expert-iteration learner: the agents its teacher judges (keys (round, 0)), the value's
    minibatches (round, 1) and the policy's (round, 2)."""


def sequence(seed: int, stream: Stream, first: int = 0, second: int = 0) -> np.random.SeedSequence:
    """The SeedSequence of `stream` with keys (first, second) under master seed `seed`.

    Raises:
        ValueError: a negative seed, or a key outside 0..2**32-1 (a key must stay one 32-bit word).
    """
    if int(seed) < 0:
        raise ValueError(f"seed {seed!r} must be >= 0")
    for name, key in (("first", first), ("second", second)):
        if not 0 <= int(key) < _WORD:
            raise ValueError(f"{stream.name} stream key {name} = {key!r} must be in 0..{_WORD - 1}")
    return np.random.SeedSequence([int(seed), int(stream), int(first), int(second)])


def generator(seed: int, stream: Stream, first: int = 0, second: int = 0) -> np.random.Generator:
    """A numpy Generator on `sequence(seed, stream, first, second)`."""
    return np.random.default_rng(sequence(seed, stream, first, second))


def derived_seed(seed: int, stream: Stream, first: int = 0, second: int = 0) -> int:
    """A 63-bit integer seed from `sequence(seed, stream, first, second)`, for consumers that take an integer
    (torch's generator, a nested master seed, a generator whose state is checkpointed)."""
    state = sequence(seed, stream, first, second).generate_state(2, np.uint64)
    return int(state[0] >> np.uint64(1))


def fresh_seed() -> int:
    """A master seed from the operating system's entropy (when the user gives none)."""
    entropy = np.random.SeedSequence().entropy
    assert isinstance(entropy, int)
    return entropy


# ----- the named streams ------------------------------------------------------------------------------------------


def world(seed: int, episode: int) -> np.random.Generator:
    """The world of `episode` (or of evaluation batch `episode`): what the in-process Team and the world node use."""
    return generator(seed, Stream.WORLD, episode)


def channel(seed: int, agent: int, episode: int) -> np.random.Generator:
    """Agent `agent`'s simulated channel in `episode`."""
    return generator(seed, Stream.CHANNEL, agent, episode)


def explore(seed: int, agent: int, episode: int) -> np.random.Generator:
    """Agent `agent`'s ε-greedy exploration in `episode` (batch 1: the agents' processes and DecentralizedPolicy)."""
    return generator(seed, Stream.EXPLORE, agent, episode)


def train_world(seed: int, batch: int) -> np.random.Generator:
    """The world of in-process training batch `batch`."""
    return generator(seed, Stream.TRAIN_WORLD, batch)


def train_channel(seed: int, agent: int, batch: int) -> np.random.Generator:
    """Agent `agent`'s channel in in-process training batch `batch`."""
    return generator(seed, Stream.TRAIN_CHANNEL, agent, batch)


def train_explore(seed: int, agent: int, batch: int) -> np.random.Generator:
    """Agent `agent`'s ε-greedy exploration in in-process training batch `batch`."""
    return generator(seed, Stream.TRAIN_EXPLORE, agent, batch)


def train_dropout(seed: int, batch: int) -> np.random.Generator:
    """Which episodes of in-process training batch `batch` lose a teammate, and which one."""
    return generator(seed, Stream.TRAIN_DROPOUT, batch)


def robot_operation(seed: int, episode: int) -> np.random.Generator:
    """The task transitions of the simulated robots' stand-in operation in `episode`."""
    return generator(seed, Stream.ROBOT_OPERATION, episode)


def robot_sensing(seed: int, agent: int, episode: int) -> np.random.Generator:
    """Simulated robot `agent`'s observations of its task in `episode`."""
    return generator(seed, Stream.ROBOT_SENSING, agent, episode)


def events(seed: int, episode: int) -> np.random.Generator:
    """The events of `episode` (or of evaluation batch `episode`): what the in-process Team and the world node use."""
    return generator(seed, Stream.EVENTS, episode)


def train_events(seed: int, batch: int) -> np.random.Generator:
    """The events of in-process training batch `batch`."""
    return generator(seed, Stream.TRAIN_EVENTS, batch)


def random_policy(seed: int, agent: int) -> np.random.Generator:
    """Agent `agent`'s draws in the random baseline."""
    return generator(seed, Stream.RANDOM_POLICY, agent)


def network_init(seed: int, agent: int) -> int:
    """The torch seed of agent `agent`'s initial network weights."""
    return derived_seed(seed, Stream.NETWORK_INIT, agent)


def replay(seed: int, agent: int) -> int:
    """The seed of agent `agent`'s replay-memory sampling generator (an integer: its state goes into checkpoints)."""
    return derived_seed(seed, Stream.REPLAY, agent)


def imitation(seed: int) -> np.random.Generator:
    """The warm start's sampling of the expert choices stored so far (`Settings.imitate_updates`)."""
    return generator(seed, Stream.IMITATION)


def base_rollouts(seed: int) -> np.random.Generator:
    """The episodes of the auction on the true levels that the lookahead baseline learns its value from."""
    return generator(seed, Stream.BASE_ROLLOUTS)


def base_value_init(seed: int) -> int:
    """The torch seed of the lookahead baseline's value network and its minibatches."""
    return derived_seed(seed, Stream.BASE_ROLLOUTS, 1)


def lookahead(seed: int) -> int:
    """The key of the lookahead's draws of states from an agent's belief (hashed with the agent and its knowledge
    state, so that an agent draws the same in any batch and in its own process)."""
    return derived_seed(seed, Stream.LOOKAHEAD)


def validation(seed: int) -> int:
    """The master seed of a training run's validation episodes (their world and channels derive from it)."""
    return derived_seed(seed, Stream.VALIDATION)


def expert_keep(seed: int, batch: int) -> np.random.Generator:
    """Which team steps of training batch `batch` the expert-iteration learner's teacher judges."""
    return generator(seed, Stream.EXPERT_KEEP, batch)


def expert_round(seed: int, round_: int, part: int) -> int:
    """The integer seed of part `part` of round `round_` of the expert-iteration learner: 0 the agents its teacher
    judges, 1 the value's minibatches, 2 the policy's."""
    return derived_seed(seed, Stream.EXPERT_ROUND, round_, part)
