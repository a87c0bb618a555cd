"""The expert-iteration learner (`htlm train --learner expert`; docs/model.md, The expert-iteration learner):
rounds of imitation of the lookahead on the team's own play (DAgger), or approximate policy iteration, with the
lookahead as the teacher and a token policy network as the student.

Every round:

1. **Play.** The team plays its policy (the auction in the first round, then the last round's policy network, every
   agent ε-greedily with `eps_end` on its own knowledge state) for `episodes / rounds` training episodes; the run
   records every agent's knowledge state, Â and action, and the true levels.
2. **Evaluate.** The teacher's value network (`BaseValue`, the one-hot levels of every task to steps to go) is the
   lookahead's value of the auction on simulated episodes, fitted once before round 1. By default it stays so
   (`value_updates` 0): every round the same lookahead relabels the states the team's own policy visits (DAgger).
   With `value_updates` > 0 it is fitted, from round 2 on, to the steps the played policy took to finish from every
   true state it visited (the horizon's remaining steps plus the last value where an episode did not finish),
   continuing from the last round's network (approximate policy iteration).
3. **Improve.** The `Teacher` improves every recorded joint action with that value: each agent, from its own belief,
   takes the action that finishes soonest, its own load-management reward weighed second.
4. **Learn.** The policy network (the token network of `learning.tokens`, one set of weights for the team) learns to
   choose the teacher's action from the agent's own knowledge state (cross-entropy over Â, Adam), on this round's
   and the last round's improved choices; it is validated on the run's validation episodes.

Training stops at the first round that does not help (or after `rounds`): whose policy validates no sooner than the
soonest so far and is not the one `select_round` would keep. The run's policy is the network of the round
`select_round` keeps: the soonest, unless a round within one standard error
of it leaves materially more capability unused (mission first, load management second). Acting with it is
one forward pass of the token network per agent and step, whatever the size of the team. The run writes rounds.csv
(one row per round) and rounds.png beside the usual files.
"""

from __future__ import annotations

import csv
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy
from htlm_agent.learning.checkpoint import save_checkpoint
from htlm_agent.learning.lookahead import LOAD_CAP, BaseValue, Teacher, ValueSettings, load_rates
from htlm_agent.learning.qnet import init_params
from htlm_agent.learning.qpolicy import QPolicy
from htlm_agent.learning.run import (
    RunLog,
    TrainResult,
    evaluate_checkpoint,
    fresh_run_dir,
    result_json,
    write_run_files,
)
from htlm_agent.learning.settings import Settings
from htlm_agent.learning.tokens import TokenQ
from htlm_agent.mind.context import Policy
from htlm_agent.mind.policies import knowledge_context, team_epsilon_greedy
from htlm_agent.mind.reward import RewardTables
from htlm_agent.progress import Progress
from htlm_agent.runtime.evaluate import evaluate
from htlm_agent.runtime.team import Team
from htlm_world import seeds
from htlm_world.metrics import completion_step
from htlm_world.scenario import Scenario
from htlm_world.types import BoolArray, FloatArray, IntArray

LABELED_AGENTS = 8
"""The agents whose choices the teacher works out at every kept team step (all of a team this size or smaller; a
random set of this many in a larger one, new for every chunk of team steps): agent k's choice costs the lookahead's
sequence of the k agents before it."""


LABEL_WORK = 131_072
"""The teacher's work a round, in agent-heads: agent k's choice is worked out by the lookahead's sequence of the k + 1
agents up to it, so a team step costs the sum of k + 1 over the agents judged (`labeled_heads`). The round's play
keeps a random share of its team steps for the teacher within this budget (the paper's operation: 8,738 team steps,
about 5 s; every visited state feeds the value)."""


def labeled_heads(n: int) -> float:
    """The expected agent-heads of the teacher's work at one team step of a team of n (`LABEL_WORK`)."""
    return n * (n + 1) / 2 if n <= LABELED_AGENTS else LABELED_AGENTS * (n + 1) / 2


@dataclass
class RoundRow:
    """One round of rounds.csv."""

    round: int
    episodes: int
    """Training episodes played so far."""
    wall_s: float
    value_rmse: float
    """The value network's last minibatch error (steps)."""
    changed: float
    """The share of played agent-steps whose action the teacher changed."""
    policy_loss: float
    agreement: float
    """The share of the round's improved choices the new policy makes."""
    val_completion: float
    val_se: float
    val_failure_rate: float
    val_unused_fraction: float
    reassignments: float
    """Moves to another site per episode before completion in validation, the team's."""
    value_s: float = float("nan")
    """Seconds of the round's learning spent fitting the value to the play."""
    teacher_s: float = float("nan")
    """... working out the teacher's choices."""
    policy_s: float = float("nan")
    """... training the policy network."""
    validate_s: float = float("nan")
    """... validating it."""


def unread_settings(sc: Scenario, settings: Settings) -> list[str]:
    """What of the scenario's reward this learner does not read or may not act on, one sentence each (warned about
    at the start of a run): the teacher counts steps to finish, then R_II and T_RP; `credit`, γ and the level rewards
    between R_0 and R_4 do not enter; an agent's own reassignment cost or idle bonus beyond `LOAD_CAP` acts as the
    cap, and one that differs from the team's by less than `TEMPERATURE` steps may change little."""
    out: list[str] = []
    tables = RewardTables.build(sc)
    if tables.difference.any():
        out.append("reward.credit 'difference' is not read: the teacher counts the team's steps to finish")
    levels = tables.level_rewards
    if not np.allclose(levels, levels[:1]) or not np.allclose(levels[0], (10.0, 5.0, 2.0, 1.0, 0.0)[: levels.shape[1]]):
        out.append(
            "reward.level_rewards: only R_0 − R_4 is read (the exchange rate of the load terms), the levels between "
            "do not enter"
        )
    if not math.isclose(sc.gamma, 0.95):
        out.append(f"gamma {sc.gamma!r} is not read: the teacher counts undiscounted steps to finish")
    own = [i for i in range(sc.n_agents) if sc.has_own_reward(i)]
    if own and (settings.load_weight <= 0 or not tables.load_management):
        names = ", ".join(sc.agents[i].name for i in own)
        why = f"load_weight {settings.load_weight!r}" if settings.load_weight <= 0 else "this mode"
        out.append(f"with {why} the teacher counts completion alone: the own rewards of {names} are not read")
    if settings.load_weight > 0 and tables.load_management:
        rates = load_rates(sc, settings.load_weight)
        for i, gaps in small_own_gaps(sc, settings).items():
            name = sc.agents[i].name
            for field, gap in gaps:
                out.append(
                    f"agents[{i}] ({name}): {field} differs from the team's by {gap:.3f} steps a choice in the "
                    f"teacher's eyes (a unit of reward is worth {rates[i]:.4f} steps with {sc.n_agents} agents), "
                    f"less than the {TEMPERATURE} steps the policy's targets tell apart: it may change little of "
                    f"what {name} learns (a larger load_weight weighs every load term more, and can leave "
                    "missions unfinished: docs/model.md, The expert-iteration learner)"
                )
        for i in range(sc.n_agents):
            r = sc.agent_reward(i)
            worth = abs(r.reassign_cost) * rates[i]
            if worth > LOAD_CAP:
                out.append(
                    f"agents[{i}] ({sc.agents[i].name}): reassign_cost {r.reassign_cost!r} is worth {worth:.2f} "
                    f"steps a move, more than the {LOAD_CAP} a choice's load terms may count for (mission first): it "
                    f"acts as {-LOAD_CAP / rates[i]:.2f}"
                )
            bonus = r.idle_bonus * r.idle_incentive * rates[i]
            if bonus > LOAD_CAP:
                out.append(
                    f"agents[{i}] ({sc.agents[i].name}): idle_bonus {r.idle_bonus!r} is worth {bonus:.2f} steps, more "
                    f"than the {LOAD_CAP} a choice's load terms may count for: it acts as {LOAD_CAP / rates[i]:.2f}"
                )
    return out


def small_own_gaps(sc: Scenario, settings: Settings) -> dict[int, list[tuple[str, float]]]:
    """{agent: [(field, steps)]}: every agent's own reassignment cost or idle bonus that the teacher tells apart from
    the team's by less than the policy's targets do (`TEMPERATURE`), in steps a choice (`unread_settings`)."""
    rates = load_rates(sc, settings.load_weight)
    shared, out = sc.reward, {}
    for i in range(sc.n_agents):
        r = sc.agent_reward(i)
        gaps = [
            (field, abs(mine - team) * rates[i])
            for field, mine, team in (
                ("reassign_cost", r.reassign_cost, shared.reassign_cost),
                ("idle_bonus", r.idle_bonus * r.idle_incentive, shared.idle_bonus * shared.idle_incentive),
            )
        ]
        small = [(f, g) for f, g in gaps if 0 < g < TEMPERATURE]
        if small:
            out[i] = small
    return out


class PolicyNet:
    """The student: the shared token network, scoring every action of Ḡ from the agent's own knowledge state."""

    def __init__(self, sc: Scenario, settings: Settings) -> None:
        """Fresh weights from the run's seed."""
        self.sc, self.settings = sc, settings
        params = init_params(sc, settings, seeds.network_init(settings.seed, 0))
        self.net = TokenQ(sc, settings.hidden, [params], shared=True)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=settings.lr)

    def policy(self) -> Policy:
        """The team policy of the current weights (every agent the masked argmax of its own scores)."""
        return QPolicy(self.sc, self.net)

    def weights(self) -> list[list[Any]]:
        """Every agent's copy of the weights, for a checkpoint."""
        return [self.net.agent_params(i) for i in range(self.sc.n_agents)]

    def tokens(
        self, k: FloatArray, m: BoolArray, worth: FloatArray, chunk: int = 512
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The tokens (X, |Ḡ|, F), Â (X, |Ḡ|) and the teacher's worth (X, |Ḡ|) of every agent-step the teacher
        judged, from knowledge states (S, N, K), masks (S, N, |Ḡ|) and worth (S, N, |Ḡ|): the tokens depend on the
        knowledge state alone, so they are made once for all of a round's updates."""
        toks, ms, ws = [], [], []
        judged = np.asarray(np.isfinite(worth).any(axis=-1), dtype=bool)  # (S, N)
        with torch.no_grad():
            for i in range(0, k.shape[0], chunk):
                x = torch.from_numpy(np.ascontiguousarray(k[i : i + chunk].transpose(1, 0, 2), dtype=np.float32))
                tok = self.net.spec.features(x)  # (N, C, |Ḡ|, F)
                on = torch.from_numpy(np.ascontiguousarray(judged[i : i + chunk].T))
                toks.append(tok[on])
                ms.append(torch.from_numpy(np.ascontiguousarray(m[i : i + chunk].transpose(1, 0, 2)))[on])
                ws.append(torch.from_numpy(np.ascontiguousarray(worth[i : i + chunk].transpose(1, 0, 2)))[on])
        return torch.cat(toks), torch.cat(ms), torch.cat(ws)

    def learn(
        self, tok: torch.Tensor, allowed: torch.Tensor, worth: torch.Tensor, updates: int, seed: int
    ) -> tuple[float, float]:
        """`updates` Adam updates of the cross-entropy between the network's choice over Â and the teacher's
        `soft_targets`, from the tokens (X, |Ḡ|, F), Â and worth (X, |Ḡ|; inf where not judged) of `tokens`,
        minibatches of `batch_size` agent-steps; returns the mean loss of the last tenth of the updates and
        the share of the teacher's best choices the network then makes."""
        gen = torch.Generator().manual_seed(seed)
        batch = min(self.settings.batch_size, tok.shape[0])
        losses: list[float] = []
        for _ in range(updates):
            idx = torch.randint(0, tok.shape[0], (batch,), generator=gen)
            logits = self.net.score(tok[idx][None])[0]
            logp = torch.log_softmax(logits.masked_fill(~allowed[idx], -1e9), dim=-1)
            loss = -(soft_targets(worth[idx]) * logp.clamp(min=-1e4)).sum(dim=-1).mean()
            self.opt.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            self.opt.step()
            losses.append(float(loss.detach()))
        with torch.no_grad():
            agree = sum(
                int(
                    (
                        self.net.score(tok[i : i + 4096][None])[0]
                        .masked_fill(~allowed[i : i + 4096], -torch.inf)
                        .argmax(-1)
                        == worth[i : i + 4096].argmin(-1)
                    ).sum()
                )
                for i in range(0, tok.shape[0], 4096)
            )
        tail = losses[-max(1, updates // 10) :]
        return float(np.mean(tail)) if tail else float("nan"), agree / max(1, tok.shape[0])


@dataclass
class Played:
    """One round of play: what the teacher improves and what the value learns from."""

    knowledge: FloatArray  # (S, N, K) float32 values, the team steps kept
    mask: BoolArray  # (S, N, |Ḡ|)
    actions: IntArray  # (S, N) what the team played
    levels: IntArray  # (X, p) every open true state visited
    to_go: FloatArray  # (X,) the steps the played policy took from it (bootstrapped past the horizon)


class ExpertRounds:
    """The learner between its rounds, fed the team's play a step at a time: in process by `play`, over ROS by the
    trainer node (`htlm_agent.trainer.core`) from the agents' transitions and the world's true levels (centralized
    training: the levels reach the trainer only). Both feed it the same steps in the same order, so both learn the
    same networks.

    `prepare` is round 0 (the value of the baseline on simulated episodes, the baseline's validation row); then, a
    round at a time, `begin_batch` / `add_step` for every step of every batch the team plays with `acting()`,
    `add_batch` with the batch's true levels, and `learn` at the end of the round's `Settings.round_batches` batches.
    `finished` says when the rounds are over; `best` holds the best round's weights."""

    def __init__(self, sc: Scenario, settings: Settings, progress: bool = True) -> None:
        """The learner of `sc` with fresh networks; prints its warnings (`unread_settings`)."""
        self.sc, self.s, self.progress = sc, settings, progress
        self.t0 = time.perf_counter()
        for warning in unread_settings(sc, settings):
            print(f"warning: expert learner: {warning}", file=sys.stderr, flush=True)
        self.per_round = settings.round_batches
        h = sc.horizon
        self.keep_share = min(1.0, LABEL_WORK / labeled_heads(sc.n_agents) / max(1, self.per_round * settings.envs * h))
        """The share of played team steps the teacher judges (`LABEL_WORK`)."""
        self.value = BaseValue(sc, ValueSettings(), settings.seed)
        self.student = PolicyNet(sc, settings)
        self.round = 1
        """The round being played (1-based)."""
        self.rows: list[RoundRow] = []
        self.best: tuple[float, int, list[list[Any]]] = (math.inf, 0, self.student.weights())
        """(validation completion, round, weights) of the round the run keeps so far (`select_round`; round 0: the
        fresh network)."""
        self.weights: dict[int, list[list[Any]]] = {}
        """Every round's weights until the rounds are over (`select_round` may choose any of them)."""
        self.done = 0
        """Training episodes played."""
        self.finished = False
        self.data: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self.own_effect: list[OwnEffect] = []
        """Every round's `OwnEffect`."""
        self.own_total = OwnEffect.zero(sc.n_agents)
        warned = small_own_gaps(sc, settings) if settings.load_weight > 0 else {}
        self.own_untold = {i for i in range(sc.n_agents) if sc.has_own_reward(i) and i not in warned}
        """The agents with their own reward whose effect is still to be told (`OWN_JUDGED`; not those whose own
        reward `unread_settings` warned about already)."""
        self._clear()

    def _clear(self) -> None:
        self.ks: list[FloatArray] = []
        self.ms: list[BoolArray] = []
        self.acts: list[IntArray] = []
        self.lvs: list[IntArray] = []
        self.keep_rng: np.random.Generator | None = None

    def info(self) -> dict[str, Any]:
        """What a checkpoint records of the rounds: the best round, every round's row, and what the agents' own
        rewards did to each round's teacher (`OwnEffect.summary`)."""
        return {
            "best_round": self.best[1],
            "rounds": [asdict(r) for r in self.rows],
            "own_rewards": [e.summary(self.sc) for e in self.own_effect],
        }

    def baseline(self) -> Policy:
        """The team policy of round 1 (`Settings.warm_baseline`)."""
        return AuctionPolicy(self.sc) if self.s.warm_baseline == "auction" else GreedyPolicy(self.sc)

    def acting(self) -> Policy:
        """The policy the team plays in the current round: the baseline in round 1, then the last round's network."""
        return self.baseline() if self.round == 1 else self.student.policy()

    def prepare(self) -> None:
        """Round 0: the lookahead's value of the auction on simulated episodes (round 1's teacher) and the
        baseline's validation row."""
        if self.progress:
            print("expert: the value of the auction on simulated episodes (round 0's teacher)", file=sys.stderr)
        self.value.fit()
        base = evaluate(self.baseline(), self.sc, self.s.validate_episodes, seed=seeds.validation(self.s.seed))
        self.rows = [
            RoundRow(
                0, 0, round(time.perf_counter() - self.t0, 2), float("nan"), float("nan"), float("nan"),
                float("nan"), base["completion"]["mean"], base["completion"]["se"],
                base["completion"]["failure_rate"], base["unused_fraction"]["mean"], reassignments(base),
            )
        ]  # fmt: skip

    def begin_batch(self, bi: int) -> None:
        """Training batch `bi` (its index in the run) begins: its draws of the team steps the teacher keeps."""
        self.keep_rng = seeds.expert_keep(self.s.seed, bi)

    def add_step(self, k32: FloatArray, m: BoolArray, a: IntArray) -> None:
        """One team step of the batch: every agent's knowledge state (B, N, K) as sent (float32 values), Â (B, N,
        |Ḡ|) and the actions played (B, N); a random share (`keep_share`) of the B rows is kept for the teacher."""
        assert self.keep_rng is not None, "begin_batch first"
        keep = self.keep_rng.random(len(a)) < self.keep_share
        self.ks.append(np.asarray(k32[keep], dtype=np.float32))
        self.ms.append(np.asarray(m[keep], dtype=bool))
        self.acts.append(np.asarray(a[keep], dtype=np.int64))

    def skip_step(self, rows: int) -> None:
        """A team step of the batch left out (over ROS: some agent's transitions did not come): its draw is
        made, so that the batch's other steps keep theirs."""
        assert self.keep_rng is not None, "begin_batch first"
        self.keep_rng.random(rows)

    def add_batch(self, lv: IntArray) -> None:
        """The batch's true levels, (h + 1, B, p) from the initial ones; counts its episodes."""
        self.lvs.append(np.asarray(lv, dtype=np.int64))
        self.done += lv.shape[1]

    def played(self) -> Played:
        """The round's play: the kept steps, and (for a value fitted on the play, `value_updates` > 0) every open true
        state with the steps the play took from it to finish (the value's prediction past the horizon where an
        episode did not finish)."""
        h = self.sc.horizon
        xs, ys = [], []
        for lv in self.lvs if self.s.value_updates > 0 else []:
            comp, failed = completion_step(lv)
            open_ = lv[:h].any(axis=-1)  # (h, B)
            t = np.arange(h)[:, None]
            finished = np.where(failed, h + self.value(lv[h]), comp)[None, :]  # the step it finished (or would)
            xs.append(lv[:h][open_])
            ys.append(np.broadcast_to(finished - t, (h, lv.shape[1]))[open_])
        n, p, na = self.sc.n_agents, self.sc.n_tasks, self.sc.n_actions
        ks = self.ks or [np.zeros((0, n, self.sc.knowledge_size), np.float32)]
        ms = self.ms or [np.zeros((0, n, na), bool)]
        acts = self.acts or [np.zeros((0, n), np.int64)]
        return Played(
            np.concatenate(ks),
            np.concatenate(ms),
            np.concatenate(acts),
            np.concatenate(xs) if xs else np.zeros((0, p), np.int64),
            np.concatenate(ys).astype(np.float64) if ys else np.zeros(0),
        )

    def learn(self) -> RoundRow:
        """The end of a round: evaluate (the value on the play, from round 2), improve (the teacher), learn (the
        policy network) and validate; decides whether the rounds are over (`finished`)."""
        s, r = self.s, self.round
        played = self.played()
        self._clear()
        rmse = float("nan")  # the first round's value: the auction's on simulated true levels (the lookahead's)
        t0 = time.perf_counter()
        if r > 1 and s.value_updates > 0 and len(played.to_go):
            rmse = self.value.regress(played.levels, played.to_go, s.value_updates, seeds.expert_round(s.seed, r, 1))
        t1 = time.perf_counter()
        teacher = Teacher(self.sc, self.value, s.seed, s.load_weight)
        better, worth, effect = improve(teacher, self.sc, played, seeds.expert_round(s.seed, r, 0))
        t2 = time.perf_counter()
        self.own_effect.append(effect)
        self.own_total.merge(effect)
        told = [i for i in self.own_untold if self.own_total.judged[i] >= OWN_JUDGED]
        self.own_untold -= set(told)
        for warning in self.own_total.warnings(self.sc, sorted(told)):
            print(f"warning: expert learner: {warning}", file=sys.stderr, flush=True)
        labeled = better >= 0
        changed = float((better != played.actions)[labeled].mean()) if labeled.any() else float("nan")
        self.data = [*self.data[-1:], self.student.tokens(played.knowledge, played.mask, worth)]
        tok, allowed, w = (torch.cat([d[j] for d in self.data]) for j in range(3))
        loss, agree = float("nan"), float("nan")
        if len(tok):
            loss, agree = self.student.learn(tok, allowed, w, s.policy_updates, seeds.expert_round(s.seed, r, 2))
        t3 = time.perf_counter()
        val = evaluate(self.student.policy(), self.sc, s.validate_episodes, seed=seeds.validation(s.seed))
        t4 = time.perf_counter()
        c = val["completion"]
        row = RoundRow(
            r, self.done, round(t4 - self.t0, 2), rmse, changed, loss, agree, c["mean"], c["se"],
            c["failure_rate"], val["unused_fraction"]["mean"], reassignments(val),
            round(t1 - t0, 2), round(t2 - t1, 2), round(t3 - t2, 2), round(t4 - t3, 2),
        )  # fmt: skip
        self.rows.append(row)
        if self.progress:
            print(
                f"expert: round {r}: validation {c['mean']:.2f} ± {c['se']:.2f} steps, failures "
                f"{c['failure_rate']:.1%} (teacher changed {changed:.1%} of the play, policy agrees with "
                f"{agree:.1%}; value rmse {rmse:.2f}; learning took {t4 - t0:.0f} s: value {t1 - t0:.0f}, teacher "
                f"{t2 - t1:.0f}, policy {t3 - t2:.0f}, validation {t4 - t3:.0f})",
                file=sys.stderr,
                flush=True,
            )
            own = effect.summary(self.sc)
            if own:
                each = ", ".join(
                    f"{k} {v['moved']:.1%} ({v['changed']:.1%} of choices)" if v["judged"] else f"{k} not judged"
                    for k, v in own.items()
                )
                print(
                    f"expert: round {r}: the agents' own rewards moved the teacher's targets: {each}", file=sys.stderr
                )
        self.finished = r >= s.rounds or not helps(self.rows)
        self.weights[r] = self.student.weights()
        keep = select_round(self.rows)
        self.best = (self.rows[keep].val_completion, keep, self.weights[keep])
        if self.finished:
            self.weights.clear()
        base = self.rows[0].val_completion
        if self.finished and self.best[0] >= base:  # said, not hidden: the checkpoint is a network, not the auction
            print(
                f"warning: expert learner: no round validated sooner than the {s.warm_baseline} it started from "
                f"({base:.2f} steps); the run's policy, round {self.best[1]}, validates at {self.best[0]:.2f}",
                file=sys.stderr,
                flush=True,
            )
        self.round += 1
        return row


RESERVE_GAIN = 0.05
"""`select_round`: the share of the team's capability a round as soon as the soonest must leave unused beyond it."""


def select_round(rows: list[RoundRow]) -> int:
    """The round whose network the run keeps, from the validation rows of rounds 1.. (`rows[0]` is the baseline's):
    mission first, load management second. The soonest round, unless a round whose validation completion is within
    one standard error of it (they validate on the same episodes) leaves at least `RESERVE_GAIN` more of the team's
    capability unused: then the one of those that leaves the most."""
    rounds = rows[1:]
    best = min(rounds, key=lambda x: x.val_completion)
    close = [x for x in rounds if x.val_completion <= best.val_completion + best.val_se]
    most = max(close, key=lambda x: (x.val_unused_fraction, -x.val_completion))
    return most.round if most.val_unused_fraction >= best.val_unused_fraction + RESERVE_GAIN else best.round


def helps(rows: list[RoundRow]) -> bool:
    """Whether the last of the validation rows `rows` (`rows[0]` the baseline's) helps, so that another round may: it
    validates sooner than every round before it (a failed episode counts as the horizon), or it is the round
    `select_round` keeps (as soon within a standard error and leaving more capability unused)."""
    last = rows[-1]
    soonest = min((x.val_completion for x in rows[1:-1]), default=math.inf)
    return last.val_completion < soonest or select_round(rows) == last.round


def play(ex: ExpertRounds, first_batch: int, batches: int, on_batch: Callable[[], None] | None = None) -> None:
    """`batches` batches of `envs` training episodes from training batch `first_batch` on (the training streams of
    `seeds`, as the world and the agents draw them over ROS), every agent ε-greedily (`eps_end`) around the round's
    policy (`ExpertRounds.acting`) from its own knowledge state, fed to `ex` step by step; `on_batch()` after every
    batch."""
    sc, s = ex.sc, ex.s
    n, h = sc.n_agents, sc.horizon
    policy = ex.acting()
    team = Team(sc, s.envs, s.seed)
    for bi in range(first_batch, first_batch + batches):
        team.sim.rng = seeds.train_world(s.seed, bi)
        team.sim.channel_rngs = [seeds.train_channel(s.seed, i, bi) for i in range(n)]
        team.event_rng = seeds.train_events(s.seed, bi)
        rngs = [seeds.train_explore(s.seed, i, bi) for i in range(n)]
        ex.begin_batch(bi)
        k = team.reset()
        levels = [team.sim.levels.copy()]
        for _ in range(h):
            m = team.mask()
            # every agent acts on its own knowledge; the learner keeps it as the trainer receives it (float32)
            a = team.force_inactive(team_epsilon_greedy(policy.act(knowledge_context(sc, k, m)), m, s.eps_end, rngs))
            ex.add_step(k.astype(np.float32).astype(np.float64), m, a)
            k, _, info = team.step(a)
            levels.append(info.levels)
        ex.add_batch(np.stack(levels))
        if on_batch is not None:
            on_batch()


@dataclass
class OwnEffect:
    """What every agent's own reward did to the teacher's choices in a round (zero for an agent without one): at
    each of its judged steps where the teacher weighed more than one action, whether its choice differs from the
    one it would make with the team's reward, and how far the policy's targets move (total variation)."""

    judged: IntArray  # (N,) such steps
    flips: IntArray  # (N,) of them where the choice differs
    shift: FloatArray  # (N,) the sum of their targets' total variation

    @staticmethod
    def zero(n: int) -> OwnEffect:
        return OwnEffect(np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n))

    def add(self, who: IntArray, worth: FloatArray, shared: FloatArray) -> None:
        """The steps of one chunk: what the teacher judged every action worth to the agents `who` (B, R, |Ḡ|), with
        their own reward and with the team's."""
        several = np.isfinite(worth).sum(axis=-1) > 1  # (B, R)
        flips = worth.argmin(axis=-1) != shared.argmin(axis=-1)
        with torch.no_grad():
            pa, pb = (soft_targets(torch.from_numpy(np.asarray(w, dtype=np.float64))) for w in (worth, shared))
            tv = 0.5 * (pa - pb).abs().sum(dim=-1).numpy()
        self.judged[who] += several.sum(axis=0)
        self.flips[who] += (flips & several).sum(axis=0)
        self.shift[who] += np.where(several, tv, 0.0).sum(axis=0)

    def summary(self, sc: Scenario) -> dict[str, dict[str, float]]:
        """{agent name: {judged, changed (share of its choices), moved (mean share of its targets)}} of every agent
        with its own reward."""
        out = {}
        for i in range(sc.n_agents):
            if sc.has_own_reward(i):
                n = max(1, int(self.judged[i]))
                out[sc.agents[i].name] = {
                    "judged": int(self.judged[i]),
                    "changed": round(float(self.flips[i]) / n, 5),
                    "moved": round(float(self.shift[i]) / n, 5),
                }
        return out

    def merge(self, other: OwnEffect) -> None:
        """Add `other`'s steps to these."""
        self.judged += other.judged
        self.flips += other.flips
        self.shift += other.shift

    def warnings(self, sc: Scenario, agents: list[int]) -> list[str]:
        """One sentence for every agent of `agents` whose own reward moved less than `OWN_EFFECT` of its targets."""
        out = []
        for i in agents:
            n = max(1, int(self.judged[i]))
            moved = self.shift[i] / n
            if moved < OWN_EFFECT:
                out.append(
                    f"agents[{i}] ({sc.agents[i].name}): its own reward moved {moved:.2%} of the teacher's targets "
                    f"and changed its choice in {self.flips[i] / n:.2%} of its {int(self.judged[i]):,} judged steps "
                    f"against the team's reward: it changes little of what {sc.agents[i].name} learns (docs/model.md, "
                    "The expert-iteration learner)"
                )
        return out


OWN_EFFECT = 0.01
"""An agent's own reward that moves less than this share of the policy's targets at its judged steps (the mean total
variation against the team's reward) is warned about: it changes too little of what the agent learns to see."""

OWN_JUDGED = 200
"""The judged steps of an agent (over the rounds so far) on which its own reward's effect is told (`OwnEffect`)."""


def improve(
    teacher: Teacher, sc: Scenario, played: Played, seed: int, chunk: int = 1024
) -> tuple[IntArray, FloatArray, OwnEffect]:
    """The teacher's choices (S, N) at every kept team step of `played`, -1 for the agents not labeled there, what
    every action is worth to them (S, N, |Ḡ|, float32 steps; inf where not judged), and what the agents' own rewards
    did to it."""
    n = sc.n_agents
    out = np.full_like(played.actions, -1)
    worth = np.full((*out.shape, sc.n_actions), np.inf, dtype=np.float32)
    effect = OwnEffect.zero(n)
    rng = np.random.default_rng(seed)
    for i in range(0, len(out), chunk):
        who = np.arange(n) if n <= LABELED_AGENTS else np.sort(rng.choice(n, LABELED_AGENTS, replace=False))
        k = played.knowledge[i : i + chunk].astype(np.float64)
        ctx = knowledge_context(sc, k, played.mask[i : i + chunk])
        mine = teacher.own[who]
        if mine.any():
            a, q, shared = teacher.improve_shared(ctx, who)
            effect.add(who[mine], q[:, mine], shared[:, mine])
        else:
            a, q = teacher.improve(ctx, who)
        out[i : i + chunk, who] = a
        worth[i : i + chunk, who] = q
    return out, worth, effect


def soft_targets(worth: torch.Tensor) -> torch.Tensor:
    """The policy's targets from what the teacher judged every action worth (..., |Ḡ|) steps: a softmax of minus the
    steps over `TEMPERATURE` (0 where not judged), so that near-ties, which the teacher's 64 draws decide by chance,
    teach the network both actions."""
    z = -(worth - worth.amin(dim=-1, keepdim=True)) / TEMPERATURE
    return torch.softmax(torch.nan_to_num(z, nan=-torch.inf), dim=-1)


TEMPERATURE = 0.02
"""Steps: the temperature of `soft_targets` (an action a fiftieth of a step worse than the best gets e⁻¹ of its
weight: soft enough to share near-ties, sharp enough that the network ranks as the teacher does)."""


def reassignments(metrics: dict[str, Any]) -> float:
    """Moves to another site per episode before completion, the team's (`reassign_before_completion`)."""
    return float(metrics["reassign_before_completion"]["mean"])


def write_rounds(out: Path, rows: list[RoundRow], name: str, best: int) -> None:
    """rounds.csv and rounds.png of a run on operation `name`: every round's validation completion (± se), the
    chosen round `best` ringed; its failures, how much of the play the teacher changed, how much the network
    learned and how much of the team's capability it leaves unused."""
    with (out / "rounds.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 4.0))
    x = [r.round for r in rows]
    ax1.errorbar(x, [r.val_completion for r in rows], yerr=[r.val_se for r in rows], marker="o", capsize=3)
    ax1.plot([best], [rows[best].val_completion], "o", ms=14, mfc="none", mec="C3", label="the run's policy")
    ax1.set_xlabel("round (0: the auction)")
    ax1.set_ylabel("validation completion step")
    ax1.set_xticks(x)
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2.plot(x, [100 * r.val_failure_rate for r in rows], marker="o", label="failed episodes")
    ax2.plot(x, [100 * r.changed for r in rows], marker="s", label="played choices the teacher changed")
    ax2.plot(x, [100 * r.agreement for r in rows], marker="^", label="teacher's best choices the policy makes")
    ax2.plot(x, [100 * r.val_unused_fraction for r in rows], marker="D", label="capability unused")
    ax2.set_xlabel("round")
    ax2.set_ylabel("%")
    ax2.set_xticks(x)
    ax2.set_ylim(-3, 103)
    ax2.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2)
    ax2.grid(alpha=0.3)
    fig.suptitle(f"expert iteration on {name}: one point per round", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "rounds.png", dpi=110)
    plt.close(fig)


@dataclass
class ExpertRun:
    """What `train_expert` learned: the best round's network and every round's row."""

    best_weights: list[list[Any]]
    best_round: int
    rows: list[RoundRow]
    episodes: int
    info: dict[str, Any]
    """`ExpertRounds.info`."""


def train_expert(sc: Scenario, settings: Settings, progress: bool = True) -> ExpertRun:
    """The rounds of the module docstring, in process; returns the best round's weights and every round's row."""
    s = settings
    threads = torch.get_num_threads()
    torch.set_num_threads(s.threads)
    ex = ExpertRounds(sc, s, progress)
    bar = Progress(s.rounds * ex.per_round * s.envs, unit="ep", enabled=progress)
    try:
        ex.prepare()
        while not ex.finished:
            play(ex, (ex.round - 1) * ex.per_round, ex.per_round, lambda: bar.update(ex.done, round=ex.round))
            ex.learn()
    finally:
        bar.close()
        torch.set_num_threads(threads)
    return ExpertRun(ex.best[2], ex.best[1], ex.rows, ex.done, ex.info())


def train_expert_run(
    scenario: Scenario,
    settings: Settings,
    out: Path,
    progress: bool = True,
    resume: bool = False,
    tensorboard: bool = True,
    evaluate_at_end: bool = True,
) -> TrainResult:
    """`learning.run.train` for the expert-iteration learner (docs/model.md, The expert-iteration learner): its rounds
    (the module docstring), the best round's policy network as the checkpoint (every agent a copy), rounds.csv and
    rounds.png, one progress.csv row a round, and the final evaluation as the agents act."""
    t_start = time.perf_counter()
    ckpt_dir = fresh_run_dir(out, resume, "expert-iteration", "its rounds are quick to run again")
    write_run_files(out, scenario, settings)
    run = train_expert(scenario, settings, progress)
    train_time = time.perf_counter() - t_start
    write_rounds(out, run.rows, scenario.name, run.best_round)
    save_checkpoint(ckpt_dir, scenario, settings, settings.seed, run.episodes, run.best_weights, info=run.info)
    log = RunLog(out, 0, False, tensorboard)
    history: list[dict[str, float]] = []
    metrics: dict[str, Any] = {}
    try:
        for r in run.rows[1:]:
            row = {
                "episodes": r.episodes,
                "wall_s": r.wall_s,
                "episodes_per_s": r.episodes / max(r.wall_s, 1e-9),
                "loss": r.policy_loss,
                "val_completion": r.val_completion,
                "val_failure_rate": r.val_failure_rate,
                "val_unused_fraction": r.val_unused_fraction,
            }
            log.row(row, r.episodes)
            history.append(row)
        log.close_progress()
        if evaluate_at_end and settings.eval_episodes > 0:
            metrics = evaluate_checkpoint(ckpt_dir, out, "htlm-expert")
            log.evaluation(metrics, run.episodes)
    finally:
        log.close()
    selected = run.rows[run.best_round].episodes
    wall = result_json(out, run.episodes, t_start, train_time, selected, metrics, progress)
    return TrainResult(out, scenario, settings, run.episodes, wall, train_time, metrics, history)
