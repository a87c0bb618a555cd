"""Settings of the deep Q-learner (`htlm train`, the trainer node): one frozen dataclass, one docstring per field.

The command line (`htlm train --help`), the settings files of the trainer node and every run's `settings.yaml` are
generated from or checked against `Settings`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from htlm_agent.learning import learners
from htlm_agent.mind.reward import LOAD_PRICE
from htlm_msgs_py.validation import ConversionError, convert_value
from htlm_world.episode import TRAINER_LAG

IMITATE = ("none", "auction", "greedy", "qmdp")
"""The baselines a warm start can imitate (`Settings.imitate`)."""


@dataclass(frozen=True)
class Settings:
    """Everything that decides a training run besides the scenario. Saved with every run (settings.json)."""

    learner: str = "paper"
    """The learner (`learning.learners`): `paper`, one MLP per agent from K to one Q-value per element of Ḡ (the
    paper's learner); `tokens`, one network scoring every action from its own features, shared across tasks
    (docs/model.md, The token learner); `lookahead`, a value network of the auction learned from simulated episodes,
    with which every agent improves on the auction from its own belief (docs/model.md, The lookahead learner; it
    learns in process only, `htlm train`); `expert`, rounds of the team's own play improved by that lookahead with
    every agent's own reward and learned into a token policy network (docs/model.md, The expert-iteration
    learner)."""
    shared: bool = True
    """tokens: the agents share one network (their capabilities and preferences are inputs); False: each agent
    trains its own."""
    imitate: str = "none"
    """Warm start: `auction`, `greedy` or `qmdp` (where the optimum can be computed) trains the networks first to
    rank that baseline's choice, made from each agent's own belief, above the other actions (with its episodes stored
    as experience); `none`: no warm start."""
    imitate_episodes: int = 0
    """Episodes of the warm start (part of `episodes`), run by the baseline the networks imitate."""
    imitate_updates: int = 1
    """Imitation updates per step of the warm start: one on the step's expert choices, the others on minibatches
    (`batch_size` team steps) drawn from every expert choice of the warm start so far. A baseline whose choices the
    token features do not carry (`qmdp`) needs many; the auction's advice is one of the features."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer sizes of every agent's Q-network MLP (ReLU); tokens: the token encoder's and the head's."""
    lr: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 128
    """Minibatch size per agent and gradient update."""
    memory: int = 50_000
    """Replay memory capacity per agent, in transitions (oldest overwritten first)."""
    learning_starts: int = 2_000
    """Transitions an agent must have stored before its network is trained."""
    target_sync: int = 200
    """Gradient updates of an agent between copies of its network into its target network."""
    horizon_terminal: bool = False
    """Treat the last step (the horizon h) as terminal in the Bellman target. Episodes end only by the time limit and
    the knowledge state holds no time, so by default the last step bootstraps like any other (a terminal there would
    give the same knowledge state targets from 1 to 1/(1-γ) times the reward, depending only on the hidden time)."""
    n_step: int = 1
    """n of n-step returns: a stored transition sums n discounted rewards and bootstraps from the knowledge state n
    steps later (shorter at the end of an episode)."""
    advantage_learning: float = 0.9
    """α of advantage learning (Bellemare et al. 2016): the target is lowered by α (max_b Q̂(K, b) − Q̂(K, a)), which
    widens the gaps between actions without changing the greedy policy; 0 is plain Q-learning."""
    double_dqn: bool = True
    """Double DQN targets (online network picks a', target network values it); False: plain max over the target."""
    huber_delta: float = 1.0
    """Huber loss threshold on the TD error (in scaled reward units)."""
    reward_scale: float = 0.1
    """Rewards are multiplied by this before learning (a positive scale leaves the greedy policy unchanged)."""
    grad_clip: float = 10.0
    """Clip each agent's gradient norm to this (0: no clipping)."""
    eps_start: float = 1.0
    """ε of ε-greedy exploration at the first episode."""
    eps_end: float = 0.05
    """ε after the decay."""
    eps_fraction: float = 0.5
    """Fraction of `episodes` over which ε decays linearly from eps_start to eps_end."""
    eps_spread: bool = False
    """Spread ε over the B parallel episodes, linearly from 0 to 2ε (mean ε), so some run the greedy team."""
    episodes: int = 12_288
    """Training episodes in total (lookahead: the simulated episodes its value network learns from)."""
    value_updates: int = 600
    """lookahead: Adam updates of the value network (minibatches of `batch_size` states). expert: Adam updates a round,
    from round 2 on, of the teacher's value on the team's own play (approximate policy iteration); 0, its default,
    keeps round 0's value, so every round relabels the team's own play with the same lookahead (DAgger)."""
    rounds: int = 4
    """expert: the most rounds of play, evaluation and improvement (`episodes` / `rounds` episodes each); training
    stops at the first round whose policy validates no sooner than the soonest so far, unless it is the round the run
    keeps (one as soon within a standard error that leaves more capability unused: `expert.select_round`)."""
    policy_updates: int = 750
    """expert: Adam updates of the policy network per round (minibatches of `batch_size` agent-steps)."""
    load_weight: float = 1.0
    """expert: the weight of the load-management reward R_II + T_RP against completion in the teacher's choice (1: the
    reward's own exchange rate, a unit of reward worth 1 / (R_0 − R_4) steps; 0: completion alone)."""
    load_price: float = LOAD_PRICE
    """lookahead: the steps of completion a unit of committed capability is worth (load management second: the
    default, QMDP's, only breaks near ties; more keeps more capability in reserve at some cost in steps)."""
    dropout: float = 0.0
    """Training for resilience: the share of training episodes in which one teammate, drawn uniformly, sits out
    the whole episode (idles at its site, as a robot that drops out); 0 trains every episode with the full team."""
    envs: int = 256
    """B, episodes simulated in parallel; one batch of B episodes runs the whole horizon together."""
    updates_per_step: int = 8
    """Gradient updates of every agent per batched environment step (B transitions per agent)."""
    trainer_lag: int = TRAINER_LAG
    """k of the trainer lag: the agents act at step t + 1 with the networks updated through step t − k (0: through
    step t, Algorithm 1 as written). Over ROS the trainer's updates of the last k steps then overlap the agents' work
    instead of holding it up; `htlm train` acts with the same networks, so both runtimes stay equal bit for bit."""
    seed: int = 0
    """Master seed of the run."""
    threads: int = 1
    """torch intra-op threads; results are reproducible for a fixed value."""
    eval_episodes: int = 500
    """Episodes of the greedy evaluation at the end of training."""
    validate_every: int = 1024
    """Episodes between greedy validation runs during training (0: none), logged as val_* columns."""
    validate_episodes: int = 500
    """Episodes of every validation run (their own random streams, never those of the final evaluation)."""
    select_best: bool = True
    """Make the networks with the best validation completion step, among validations after ε has decayed and at the
    end, the run's policy (the latest networks are kept for resuming)."""
    checkpoint_every: int = 4_096
    """Episodes between checkpoints (always one at the end)."""
    keep_replay: bool = True
    """Save the replay memories in checkpoints (about 60 MB with the defaults), so that a resumed run continues exactly;
    without them a resumed run refills its memories first."""

    def __post_init__(self) -> None:
        """Validate every field: a bad value raises ValueError naming it."""
        positive = (
            "n_step",
            "lr",
            "batch_size",
            "memory",
            "target_sync",
            "episodes",
            "envs",
            "updates_per_step",
            "threads",
            "rounds",
            "policy_updates",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"settings.{name}: {getattr(self, name)!r} must be > 0")
        if not (self.value_updates > 0 or (self.value_updates == 0 and self.learner == "expert")):
            raise ValueError(
                f"settings.value_updates: {self.value_updates!r} must be > 0 (0 only for the expert learner: keep "
                "round 0's value)"
            )
        for name in (
            "learning_starts",
            "grad_clip",
            "eval_episodes",
            "validate_every",
            "validate_episodes",
            "checkpoint_every",
            "trainer_lag",
            "seed",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"settings.{name}: {getattr(self, name)!r} must be >= 0")
        if not self.load_weight >= 0.0:
            raise ValueError(f"settings.load_weight: {self.load_weight!r} must be >= 0")
        if not self.load_price >= 0.0:
            raise ValueError(f"settings.load_price: {self.load_price!r} must be >= 0")
        for name in ("eps_start", "eps_end", "eps_fraction", "advantage_learning", "dropout"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"settings.{name}: {getattr(self, name)!r} must be in [0, 1]")
        if not self.hidden or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"settings.hidden: {self.hidden!r} needs at least one layer, every size >= 1")
        if not self.reward_scale > 0 or not self.huber_delta > 0:
            raise ValueError(
                f"settings: reward_scale {self.reward_scale!r} and huber_delta {self.huber_delta!r} must be > 0"
            )
        learners.learner(self.learner)  # one of them, else the error names the value and the choices
        if self.imitate not in IMITATE:
            raise ValueError(f"settings.imitate: {self.imitate!r} is not one of {', '.join(IMITATE)}")
        if self.imitate_episodes < 0 or self.imitate_episodes > self.episodes:
            raise ValueError(
                f"settings.imitate_episodes: {self.imitate_episodes!r} must be in 0..episodes ({self.episodes})"
            )
        if self.imitate_updates < 1:
            raise ValueError(f"settings.imitate_updates: {self.imitate_updates!r} must be >= 1")
        learners.check(self)
        if self.envs > self.memory:
            raise ValueError(f"settings.envs: {self.envs!r} must not exceed settings.memory {self.memory!r}")

    @property
    def network(self) -> str:
        """The network of this learner's checkpoints (`LearnerKind.network`): `mlp`, `tokens` or `value`."""
        return learners.learner(self.learner).network

    def epsilon(self, episode: float) -> float:
        """ε of ε-greedy at training episode `episode`: linear decay from eps_start to eps_end over the first
        eps_fraction · episodes, then constant (an agent process computes its own ε with this)."""
        span = self.eps_fraction * self.episodes
        frac = 1.0 if span <= 0 else min(max(float(episode) / span, 0.0), 1.0)
        return self.eps_start + frac * (self.eps_end - self.eps_start)

    def td_updates(self, episodes_done: int) -> int:
        """TD updates of every agent at a step: `updates_per_step`, none in a warm start with more than one imitation
        update a step (`imitate_updates`), where the imitation alone shapes the networks (TD targets from the
        belief-based reward pull them away from a baseline they cannot read off their features)."""
        if self.imitate_updates > 1 and self.warm_start(episodes_done):
            return 0
        return self.updates_per_step

    def warm_start(self, episodes_done: int) -> bool:
        """Whether the batch after `episodes_done` training episodes is one of the warm start: the baseline of
        `imitate` acts (ε-greedily with eps_end) and the networks learn to rank its choices first; the
        expert-iteration learner's first round (`round_batches`), which the baseline plays (`LearnerKind`)."""
        return learners.learner(self.learner).warm_start(self, episodes_done)

    @property
    def warm_baseline(self) -> str:
        """The baseline that acts in the warm start (`warm_start`): `imitate`; the expert-iteration learner's first
        round is the auction's unless `imitate` names greedy (`LearnerKind.warm_baseline`)."""
        return learners.learner(self.learner).warm_baseline(self)

    @property
    def round_batches(self) -> int:
        """expert: the batches of `envs` episodes a round plays (`episodes` / `rounds`, rounded up)."""
        return max(1, -(-self.episodes // (self.rounds * self.envs)))

    @property
    def selection_from(self) -> float:
        """The episode from which validated networks compete for selection (`select_best`): once ε has decayed, or
        once the warm start is over (its networks act as the baseline they imitated) when that comes first."""
        decayed = self.eps_fraction * self.episodes
        if self.imitate != "none" and self.imitate_episodes > 0:
            return min(decayed, self.imitate_episodes)
        return decayed

    @staticmethod
    def with_preset(changes: dict[str, Any]) -> dict[str, Any]:
        """Settings changes as plain data, after the preset of the learner they choose (`LearnerKind.with_preset`:
        what `htlm train --learner tokens` and `htlm launch train --set learner=tokens` start from); unchanged when
        they choose none."""
        name = changes.get("learner")
        return learners.LEARNERS[name].with_preset(changes) if name in learners.LEARNERS else dict(changes)

    @staticmethod
    def for_users(changes: dict[str, Any]) -> dict[str, Any]:
        """The changes of a user's command (`htlm train`, `htlm launch train`), after the preset of their learner
        (`with_preset`): the one they choose, else the default (`learners.default_learner`)."""
        return Settings.with_preset({"learner": learners.default_learner(changes), **changes})

    @staticmethod
    def for_learner(**changes: Any) -> Settings:
        """Settings with `changes`, starting from the preset of the learner they choose (`with_preset`)."""
        return Settings(**Settings.with_preset(changes))

    def replace(self, **changes: Any) -> Settings:
        """A copy with fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain data for settings.json."""
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @staticmethod
    def from_dict(data: Any, src: str = "<settings>") -> Settings:
        """Settings from plain data; unknown keys or bad values raise ValueError naming src, the field and the value.

        Types are checked by `htlm_msgs_py.validation.convert` (fields are named `settings.<field>`), ranges by
        `__post_init__`.
        """
        try:
            out: Settings = convert_value(data, Settings, "settings", src)
        except ConversionError:
            raise
        except ValueError as e:  # __post_init__
            raise ValueError(f"{src}: {e}") from None
        return out
