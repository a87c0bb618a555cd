"""The expert-iteration learner in the trainer node (`ExpertTrainer`): the rounds of `htlm train --learner expert`
(`htlm_agent.learning.expert.ExpertRounds`) fed from what the trainer receives over ROS.

Every step of the run, `TrainerCore` hands over the agents' transitions of the step (their knowledge states, the
actions they played and Â of the next step); the world's /htlm/ground_truth records give the true levels of every
step (centralized training: the world shares them with the trainer only). After the last batch of a round the
round's work (fitting the value, the teacher's judgement, the policy's updates, the validation) runs in a worker
thread while the node goes on acknowledging and telling the world it is alive; the world holds the next step until
the trainer announces it, and the agents act with the new weights from the next round's first step (the weights'
cadence is a round). Round 1 is played by the baseline (`Settings.warm_baseline`), which the agents run themselves
from the learner settings of the first weights record, as in process. With every agent's transitions of every step
the learner sees exactly the steps `htlm train --learner expert` sees, in the same order, and learns the same
networks; a step some agent's transitions missed is left out of the teacher's steps (counted).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from htlm_agent.learning.checkpoint import save_checkpoint
from htlm_agent.learning.expert import ExpertRounds, RoundRow, write_rounds
from htlm_agent.learning.qnet import pack_weights
from htlm_agent.learning.settings import Settings
from htlm_world.episode import batch_index
from htlm_world.model import Model
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, IntArray


class ExpertTrainer:
    """The expert-iteration learner of one training run over ROS, fed step by step by `TrainerCore`."""

    def __init__(self, sc: Scenario, settings: Settings, batch: int) -> None:
        """The learner of a run played in batches of `batch` (the learner's `envs`); its round 0
        (`ExpertRounds.prepare`) starts at once in the worker, while round 1 is played.

        Raises:
            ValueError: a batch other than the learner's envs.
        """
        if batch != settings.envs:
            raise ValueError(
                f"the world plays batches of {batch}, the expert-iteration learner's rounds batches of envs "
                f"{settings.envs}: start the world with batch {settings.envs}"
            )
        self.scenario, self.settings = sc, settings
        self.n_agents = sc.n_agents
        self.batch = batch
        self.rounds = ExpertRounds(sc, settings, progress=False)  # the trainer logs each round itself
        self.start_mask = Model.build(sc).action_mask(np.full((batch, sc.n_agents), sc.start_assignment))
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="expert")
        self.job: Future[Any] | None = self.pool.submit(self.rounds.prepare)
        """The worker's work in progress: round 0 at first, then each round's learning."""
        self.mask: BoolArray | None = None
        """Â of every agent at the next step of the batch in progress (B, N, |Ḡ|); None after a missing step."""
        self.truth: dict[int, dict[int, IntArray]] = {}
        """First episode of a batch -> step -> the true levels after it (B, p), from /htlm/ground_truth."""
        self.ended: list[int] = []
        """The first episodes of the round's batches whose steps are all in, in order."""
        self.ended_at = 0.0
        self.episodes_done = 0
        self.updates = 0
        self.skipped = 0
        """Team steps left out of the teacher's steps (some agent's transitions missed)."""
        self.untrue = 0
        """Batches left out of the value's data (their true levels did not all come)."""

    @property
    def busy(self) -> bool:
        """Whether the round's learning (or round 0) is running in the worker."""
        return self.job is not None and not self.job.done()

    def step(self, episode: int, t: int, recs: list[dict[str, Any]] | None) -> None:
        """The transitions of step t of the batch from `episode` on: every agent's record in agent order, or None
        when some agent's did not come (the step is left out of the teacher's steps, its draw kept in line)."""
        if t == 1:
            self.rounds.begin_batch(batch_index(episode, self.batch))
            self.mask = self.start_mask
        if recs is None or self.mask is None:
            self.rounds.skip_step(self.batch)
            self.skipped += 1
            self.mask = None  # the next Â is unknown without every agent's: the rest of the batch is left out
            return
        k = np.stack([r["k"] for r in recs], axis=1)
        a = np.stack([r["a"] for r in recs], axis=1)
        self.rounds.add_step(k, self.mask, a)
        self.mask = np.stack([r["mask2"] for r in recs], axis=1)

    def on_truth(self, episode: int, t: int, levels: Any) -> None:
        """A /htlm/ground_truth record: the true levels (B, p) after step t of the batch from `episode` on."""
        if episode in self.ended and episode not in self.truth:
            return  # a batch already handed over (a repeat)
        self.truth.setdefault(episode, {})[t] = np.asarray(levels, dtype=np.int64)

    def end_batch(self, episode: int, size: int, now: float) -> bool:
        """The last step of the batch from `episode` on is in; returns whether that ends a round (then `learn`)."""
        self.ended.append(episode)
        self.episodes_done += size
        self.ended_at = now
        return len(self.ended) >= self.rounds.per_round

    def truth_ready(self, now: float, deadline: float) -> bool:
        """Whether the round's true levels are all in, or `deadline` seconds have passed since its last batch."""
        h = self.scenario.horizon
        whole = all(len(self.truth.get(e, {})) >= h for e in self.ended)
        return whole or now - self.ended_at > deadline

    def learn(self) -> Future[Any]:
        """Hand the round's true levels to the learner (batches in order; those missing a step are left out,
        counted) and start the round's learning in the worker."""
        h = self.scenario.horizon
        init = np.asarray(self.scenario.initial_levels, dtype=np.int64)
        for e in self.ended:
            got = self.truth.pop(e, {})
            if len(got) < h:
                self.untrue += 1
                continue
            first = np.broadcast_to(init, got[1].shape)
            self.rounds.add_batch(np.stack([first, *(got[t] for t in range(1, h + 1))]))
        self.ended = []
        assert not self.busy
        self.job = self.pool.submit(self._learn)
        return self.job

    def _learn(self) -> RoundRow:
        row = self.rounds.learn()
        self.updates += self.settings.policy_updates
        return row

    def result(self) -> RoundRow | None:
        """The round's row once the worker is done (None for round 0); raises what the worker raised."""
        assert self.job is not None and self.job.done()
        job, self.job = self.job, None
        out = job.result()
        return out if isinstance(out, RoundRow) else None

    @property
    def finished(self) -> bool:
        """Whether the rounds are over (`ExpertRounds.finished`)."""
        return self.rounds.finished

    def agent_weights(self, agent: int) -> bytes:
        """Agent `agent`'s copy of the policy network the team plays next: the best round's once the rounds are
        over (the format of `qnet.AgentQ.get_weights`)."""
        if self.finished:
            return pack_weights(self.rounds.best[2][agent])
        return pack_weights(self.rounds.student.net.agent_params(agent))

    def save(self, directory: Path, extra: dict[str, Any]) -> Path:
        """The checkpoint of the best round so far (the format of `htlm train --learner expert`), with rounds.csv
        and rounds.png beside it in the run directory."""
        ex = self.rounds
        info = {**extra, **ex.info()}
        if len(ex.rows) > 1:
            write_rounds(directory.parent, ex.rows, self.scenario.name, ex.best[1])
        return save_checkpoint(
            directory, self.scenario, self.settings, self.settings.seed, ex.done, ex.best[2], info=info
        )

    def finish(self) -> None:
        """The end of the run: wait for the worker, and learn the round whose play is in but not learned yet (a
        run that ended within a round)."""
        if self.job is not None:
            self.job.result()
            self.job = None
        if self.ended and not self.finished:
            self.learn().result()
            self.job = None

    def close(self) -> None:
        """Stop the worker (after the work in progress)."""
        self.pool.shutdown(wait=True)
