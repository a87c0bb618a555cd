"""The auction baseline (docs/model.md, Baselines): the sequential single-item auction on small hand-made contexts,
its decentralization (agent i reads only row i of the Context, as the agent processes over ROS run it), and that it
completes the default operation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from htlm_agent.baselines.heuristics import AuctionPolicy, GreedyPolicy, RandomPolicy
from htlm_agent.experiments.baselines import make_baseline
from htlm_agent.mind import knowledge
from htlm_agent.mind.auction import allocate, own_assignment
from htlm_agent.mind.context import Context
from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.mind.reward import confident_levels
from htlm_agent.runtime.evaluate import evaluate
from htlm_agent.runtime.team import Team, rollout
from htlm_agent.session.builtin import builtin_policy
from htlm_world.model import Model
from htlm_world.scenario import AgentSpec, EventSpec, Scenario, builtin, load


def _team(*caps: tuple[int, int], mode: str = "htlm") -> Scenario:
    """The default operation with a hand-made team: (capability on the first task of a site, on the second)."""
    agents = tuple(
        AgentSpec(name=f"agent{i + 1}", capabilities={"fire": a, "rescue": b}) for i, (a, b) in enumerate(caps)
    )
    # not validated: a team without anyone for a kind is refused from a file, but is what some cases here need
    return dataclasses.replace(builtin(mode=mode), agents=agents)


def _context(sc: Scenario, levels: list[list[int]], prev: list[int] | None = None) -> Context:
    """One episode in which agent i is certain of levels[i] (one list per agent, or one list for all)."""
    n, L = sc.n_agents, sc.levels
    lv = np.array(levels if len(levels) == n else levels * n, dtype=np.int64)[None]  # (1, N, p)
    marg = np.eye(L)[lv]  # (1, N, p, L)
    pv = np.array([prev if prev is not None else [sc.start_assignment] * n], dtype=np.int64)
    return Context(
        knowledge=knowledge.build(marg, pv, sc.n_actions),
        mask=Model.build(sc).action_mask(pv),
        marginals=marg,
        prev=pv,
        t=0,
        true_levels=np.zeros((1, sc.n_tasks), dtype=np.int64),
    )


def pol_levels(pol: AuctionPolicy, ctx: Context) -> np.ndarray:
    """Every agent's confident levels (B, N, p) under its own threshold b_th."""
    return confident_levels(ctx.marginals, pol.threshold)


def _act(sc: Scenario, levels: list[list[int]], prev: list[int] | None = None) -> list[int]:
    out: list[int] = AuctionPolicy(sc).act(_context(sc, levels, prev))[0].tolist()
    return out


def test_blocked_is_the_dependency_between_the_tasks_of_a_site() -> None:
    model = Model.build(builtin())
    lv = np.array([[4, 4, 2, 3], [3, 0, 0, 1]])
    assert model.blocked(lv).tolist() == [[False, True, False, False], [False, True, False, False]]


def test_a_single_agent_takes_the_task_where_its_bid_is_highest() -> None:
    sc = _team((3, 2))
    assert _act(sc, [[1, 0, 4, 4]]) == [2]  # bids 1 (task 0) and 3 (task 2); task 3 is blocked
    assert _act(sc, [[2, 2, 0, 3]]) == [3]  # bids 2, 2, -, 2: the larger need (3) wins the tie
    assert _act(sc, [[4, 4, 4, 4]]) == [0]  # equal bids and needs: the lower task
    assert _act(_team((0, 2)), [[4, 2, 1, 1]]) == [3]  # only the second tasks; task 1 is blocked


def test_two_agents_do_not_both_take_a_task_that_one_covers() -> None:
    sc = _team((3, 1), (3, 2))
    idle = sc.n_tasks  # the idle location of site 1 (their previous assignment)
    assert _act(sc, [[2, 0, 0, 0]]) == [0, idle]  # agent1 covers level 2 alone
    assert _act(sc, [[2, 0, 3, 0]]) == [2, 0]  # the larger need first: agent1 covers task 2, agent2 task 0
    assert _act(sc, [[4, 0, 0, 0]]) == [0, 0]  # 3 < 4: the task stays open for agent2
    assert _act(_team((2, 0), (3, 0)), [[2, 0, 0, 0]]) == [idle, 0]  # equal bids: the larger capability wins


def test_a_level_of_disagreement_does_not_change_who_takes_a_task() -> None:
    """Agent1 believes the task at level 2, agent2 at level 1: both auctions give it to agent2 (the larger
    capability among equal bids), so it is neither left undone nor doubled."""
    sc = _team((1, 0), (2, 0))
    assert _act(sc, [[2, 0, 0, 0], [1, 0, 0, 0]]) == [sc.n_tasks, 0]
    assert _act(sc, [[1, 0, 0, 0], [2, 0, 0, 0]]) == [sc.n_tasks, 0]


def test_an_agent_without_capability_on_any_open_task_idles_at_its_site() -> None:
    sc = _team((0, 1), (3, 0))
    model = Model.build(sc)
    prev = [2, 0]  # agent1 last worked at site 2
    assert _act(sc, [[4, 4, 4, 4]], prev) == [int(model.idle_action(np.array(2))), 0]
    assert _act(sc, [[0, 0, 0, 0]], prev) == [sc.n_tasks + 1, sc.n_tasks]  # nothing open: both idle
    ht = _team((0, 1), (3, 0), mode="ht")
    assert _act(ht, [[4, 4, 4, 4]], [3, 0]) == [3, 0]  # HT mode: it stays on its previous task
    assert _act(ht, [[4, 4, 4, 4]], [-1, -1]) == [0, 0]


def test_each_agent_acts_on_its_own_row_only() -> None:
    """Agent i's action depends only on row i of the Context: changing every other row changes nothing of it, and
    each agent's action is its own result of the auction on its own belief (here the beliefs disagree)."""
    sc = builtin()
    n, p, L = sc.n_agents, sc.n_tasks, sc.levels
    rng = np.random.default_rng(0)
    pol = AuctionPolicy(sc)
    model = Model.build(sc)

    def random_context(b: int) -> Context:
        marg = rng.dirichlet(np.full(L, 0.3), size=(b, n, p))
        prev = rng.integers(0, sc.n_actions, size=(b, n))
        return Context(
            knowledge.build(marg, prev, sc.n_actions),
            model.action_mask(prev),
            marg,
            prev,
            0,
            rng.integers(0, L, (b, p)),
        )

    ctx = random_context(256)
    base = pol.act(ctx)
    assert ctx.mask[np.arange(256)[:, None], np.arange(n)[None], base].all()
    for i in range(n):
        other = random_context(256)
        for f in ("knowledge", "mask", "marginals", "prev"):
            getattr(other, f)[:, i] = getattr(ctx, f)[:, i]
        other.true_levels = ctx.true_levels
        assert np.array_equal(pol.act(other)[:, i], base[:, i]), i
        # the agent process's rule: the auction on agent i's knowledge state alone
        row, _eps = builtin_policy(sc, "auction", i)
        assert np.array_equal(row.act(ctx.knowledge[:, i], ctx.mask[:, i]), base[:, i]), i
    # each takes its own assignment of the auction on its own belief
    own = pol.allocate(pol_levels(pol, ctx))[:, np.arange(n), np.arange(n)]
    assert np.array_equal(np.where(own >= 0, own, model.idle_action(ctx.prev)), base)


@pytest.mark.parametrize("kind", ["greedy", "auction", "qmdp"])
def test_some_agents_actions_alone_are_their_columns_of_the_team_action(kind: str) -> None:
    """`act_rows` (what an agent process asks for, its own action only) gives the agents' columns of `act`, for any
    subset of agents in any order."""
    sc = builtin()
    n, p, L = sc.n_agents, sc.n_tasks, sc.levels
    rng = np.random.default_rng(1)
    pol = make_baseline(kind, sc)[0]
    model = Model.build(sc)
    marg = rng.dirichlet(np.full(L, 0.3), size=(64, n, p))
    prev = rng.integers(-1, sc.n_actions, size=(64, n))
    ctx = Context(knowledge.build(marg, prev, sc.n_actions), model.action_mask(prev), marg, prev, 0, np.zeros((64, p)))
    team = pol.act(ctx)
    for who in ([0], [n - 1], [3, 1], list(range(n))[::-1]):
        assert np.array_equal(pol.act_rows(ctx, np.array(who)), team[:, who]), who


def test_agent_processes_run_the_team_auction() -> None:
    """The built-in policy of the agent nodes (one RowPolicy per agent, as over ROS) equals the team policy."""
    sc = builtin()
    pols = [builtin_policy(sc, "auction", i)[0] for i in range(sc.n_agents)]
    dp = DecentralizedPolicy(pols, 5, 0.0)
    dp.begin(4)
    a = rollout(Team(sc, 4, 5, episode=4), dp)
    b = rollout(Team(sc, 4, 5, episode=4), AuctionPolicy(sc))
    assert np.array_equal(a.actions, b.actions) and np.array_equal(a.levels, b.levels)


@pytest.mark.parametrize("team", ["heterogeneous", "semi-heterogeneous", "homogeneous"])
def test_the_auction_completes_the_operation(team: str) -> None:
    sc = builtin(team)
    policy, bsc = make_baseline("auction", sc)
    assert isinstance(policy, AuctionPolicy) and bsc is sc
    auction = evaluate(policy, sc, 200, seed=0)["completion"]
    rand = evaluate(RandomPolicy(sc, 0), sc, 200, seed=0)["completion"]
    assert auction["mean"] + 3 * (auction["se"] + rand["se"]) < rand["mean"], (auction, rand)
    assert auction["failure_rate"] < 0.2
    assert evaluate(GreedyPolicy(sc), sc, 200, seed=0)["completion"]["mean"] < rand["mean"]


@pytest.mark.parametrize("name", ["warehouse", "facility-20", "city-50"])
def test_the_own_assignment_is_what_the_whole_auction_gives(name: str) -> None:
    """`own_assignment` stops each auction once its own agent is settled: the same result as `allocate`, ties
    included (low levels make many equal bids), with and without a roster."""

    sc = load(name)
    model, n, p = Model.build(sc), sc.n_agents, sc.n_tasks
    rng = np.random.default_rng(3)
    for _ in range(4):
        lv = rng.integers(0, 3, size=(16, n, p))
        for present in (None, rng.random((16, n, n)) < 0.85):
            whole = allocate(model, lv, present)[:, np.arange(n), np.arange(n)]
            flat = None if present is None else present.reshape(-1, n)
            own = own_assignment(model, lv.reshape(-1, p), np.tile(np.arange(n), 16), flat).reshape(16, n)
            assert (whole == own).all()


def test_the_fair_market_leaves_a_silent_teammate_out() -> None:
    """With the roster, the auction gives a teammate's work to the others once its broadcasts stop: losing the most
    capable fire-fighter fails almost every episode without the roster, almost none with it."""

    lose = (EventSpec("dropout", agent="agent2", at=3),)
    rates = {}
    for roster in (False, True):
        sc = builtin().replace(roster=roster).with_events(lose)
        rates[roster] = evaluate(AuctionPolicy(sc), sc, 100, seed=0)["completion"]["failure_rate"]
    assert rates[False] > 0.8 and rates[True] < 0.05, rates
