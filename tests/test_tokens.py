"""The token learner (docs/model.md, The token learner) and the difference reward: the network scores every action
from that action's own features, the same weights serve other teams and operations, one agent's copy acts as the
team's network does, the warm start learns the auction's choices, and checkpoints carry it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from htlm_agent.baselines.heuristics import AuctionPolicy
from htlm_agent.baselines.optimal import QmdpPolicy
from htlm_agent.experiments.market import changed_operations
from htlm_agent.learning.checkpoint import load_checkpoint
from htlm_agent.learning.dqn import Learner
from htlm_agent.learning.loop import imitate_step
from htlm_agent.learning.qnet import AgentQ, build_network, init_params, network_shapes
from htlm_agent.learning.qpolicy import QPolicy, greedy_actions
from htlm_agent.learning.run import train
from htlm_agent.learning.settings import Settings
from htlm_agent.mind import knowledge
from htlm_agent.mind.reward import RewardTables, reward
from htlm_agent.runtime.team import Team
from htlm_world.model import Model
from htlm_world.scenario import builtin, load

TOKENS = Settings(learner="tokens", hidden=(16, 16), learning_starts=64, batch_size=32, envs=16, episodes=64)


def _certain(levels: list[int], sc_levels: int) -> np.ndarray:
    marg = np.zeros((len(levels), sc_levels))
    marg[np.arange(len(levels)), levels] = 1.0
    return marg


def test_swapping_two_alike_sites_swaps_their_q_values() -> None:
    sc = builtin()  # two sites with a fire and a rescue each: site 2 is site 1 renamed
    net = build_network(sc, TOKENS, [init_params(sc, TOKENS, 3)])
    marg = _certain([4, 4, 2, 3], sc.levels)  # fire@1, rescue@1, fire@2, rescue@2
    swapped = marg[[2, 3, 0, 1]]
    k = knowledge.build(np.stack([marg, swapped])[None], np.array([[4, 5]]), sc.n_actions)  # idle@1, idle@2
    x = torch.from_numpy(np.repeat(k, sc.n_agents, axis=0).astype(np.float32))  # (N, 2, K)
    with torch.no_grad():
        q = net(x).numpy()
    assert np.allclose(q[:, 1], q[:, 0][:, [2, 3, 0, 1, 5, 4]], atol=1e-5)


def test_the_same_weights_act_on_another_team_and_operation() -> None:
    paper, warehouse = builtin(), load("warehouse")
    assert network_shapes(paper, TOKENS) == network_shapes(warehouse, TOKENS)  # nothing sized by the operation
    params = [t.numpy() for t in init_params(paper, TOKENS, 1)]
    team = Team(warehouse, 4, 0)
    net = build_network(warehouse, TOKENS, [params])
    a = greedy_actions(net, team.knowledge(), team.mask())
    assert a.shape == (4, warehouse.n_agents)
    assert np.take_along_axis(team.mask(), a[..., None], axis=-1).all()


def test_one_agents_copy_chooses_what_the_team_network_chooses() -> None:
    sc = load("warehouse")
    lr = Learner(sc, TOKENS)
    team = Team(sc, 8, 2)
    for _ in range(3):
        team.step(AuctionPolicy(sc).act(team.context()))
    k, m = team.knowledge(), team.mask()
    together = greedy_actions(lr.net, k, m)
    for i in range(sc.n_agents):
        alone = AgentQ.for_agent(sc, TOKENS, i, lr.net.agent_params(i))
        assert (alone.act(k[:, i], m[:, i]) == together[:, i]).all()
        assert alone.get_weights() == lr.agent_weights(i)


def test_the_warm_start_learns_the_auctions_choices() -> None:
    sc = builtin()
    lr = Learner(sc, TOKENS.replace(lr=3e-3))
    expert = AuctionPolicy(sc)
    team = Team(sc, 32, 0)
    agree = []
    for _ in range(4):
        team.reset()
        for _ in range(sc.horizon):
            ctx = team.context()
            a = expert.act(ctx)
            agree.append(float((greedy_actions(lr.net, ctx.knowledge, ctx.mask) == a).mean()))
            lr.imitate(ctx.knowledge, ctx.mask, a)
            team.step(a)
    assert np.mean(agree[-sc.horizon :]) > 0.97, agree[-sc.horizon :]


def test_a_warm_start_with_more_imitation_updates_draws_from_every_expert_choice_so_far() -> None:
    """`imitate_updates` > 1: the step's update, then minibatches of the expert memory; no TD updates meanwhile."""
    sc = builtin()
    s = TOKENS.replace(imitate="qmdp", imitate_episodes=32, imitate_updates=3)
    assert s.td_updates(0) == 0 and s.td_updates(32) == s.updates_per_step
    assert TOKENS.replace(imitate="auction", imitate_episodes=32).td_updates(0) == TOKENS.updates_per_step
    lr = Learner(sc, s)
    expert = QmdpPolicy(sc)
    team = Team(sc, 16, 0)
    before = lr.net.flat.detach().clone()
    for _ in range(2):
        imitate_step(lr, expert, team.knowledge())
        team.step(expert.act(team.context()))
    memory = lr.expert_memory()
    assert memory.size == 32
    k, m, a = memory.sample(s.batch_size)
    assert k.shape == (s.batch_size, sc.n_agents, sc.knowledge_size) and m.shape[:2] == a.shape
    assert np.take_along_axis(m, a[..., None], axis=-1).all()  # every stored choice lies in its Â
    assert not torch.equal(before, lr.net.flat)
    with pytest.raises(ValueError, match="imitate_updates: 0 must be >= 1"):
        TOKENS.replace(imitate_updates=0)


def test_a_token_run_checkpoints_and_loads_as_a_policy(tmp_path: Path) -> None:
    sc = builtin()
    s = TOKENS.replace(
        imitate="auction", imitate_episodes=32, validate_every=32, validate_episodes=16, eval_episodes=16
    )
    train(sc, s, tmp_path / "run", progress=False, tensorboard=False)
    ck = load_checkpoint(tmp_path / "run")
    assert ck.settings.learner == "tokens" and len(ck.weights) == sc.n_agents
    pol = QPolicy.from_checkpoint(ck)
    team = Team(sc, 4, 9)
    a = pol.act(team.context())
    assert np.take_along_axis(team.mask(), a[..., None], axis=-1).all()
    again = Learner.load(tmp_path / "run" / "checkpoint")
    assert torch.equal(again.net.flat, Learner.load(tmp_path / "run" / "checkpoint").net.flat)


def test_difference_credit_pays_an_agent_only_for_what_its_own_work_adds() -> None:
    sc = builtin().with_credit("difference")
    model, tables = Model.build(sc), RewardTables.build(sc)
    prior = np.broadcast_to(_certain([4, 4, 2, 3], sc.levels), (1, sc.n_agents, 4, sc.levels)).copy()
    prev = np.full((1, sc.n_agents), 4)
    # agent1 (fire 3) alone on fire@2 at level 2; agent2 and agent3 together on fire@1 at 4 (3 + 2, capped at 5);
    # agent4 (rescue 1) on rescue@1, blocked by its fire at 4; agent5 idle
    actions = np.array([[2, 0, 0, 1, 4]])
    _, parts = reward(model, tables, prev, prior, actions, prior)
    comp = parts["comp"][0]
    assert comp[0] > 0 and comp[1] > 0 and comp[2] > 0
    assert comp[3] == 0.0  # a blocked task makes no progress, whoever works on it
    assert comp[4] == 0.0  # idle
    alone = reward(model, tables, prev, prior, np.array([[2, 0, 4, 1, 4]]), prior)[1]["comp"][0]
    assert alone[1] > comp[1]  # agent2 adds more to fire@1 alone than beside agent3
    team = reward(model, RewardTables.build(builtin()), prev, prior, actions)[1]["comp"][0]
    assert np.allclose(team, team[0])  # the paper's credit: the same completion reward for every agent


def test_a_trained_network_acts_on_a_changed_team_and_operation() -> None:
    """The transfer of docs/results/CHANGELOG.md (2026-11-27): one agent lost, one added, capabilities changed, a site
    added; the shared network built for each from the same weights acts within Â."""
    sc = builtin().replace(roster=True)
    params = [t.numpy() for t in init_params(sc, TOKENS, 5)]
    changed = changed_operations(sc)
    assert [c.n_agents for c in changed.values()] == [4, 6, 5, 5]
    assert changed["site added"].n_sites == sc.n_sites + 1
    for c in changed.values():
        net = build_network(c, TOKENS, [params])
        team = Team(c, 4, 1)
        a = greedy_actions(net, team.knowledge(), team.mask())
        assert np.take_along_axis(team.mask(), a[..., None], axis=-1).all()


class _Recording:
    """An agent policy that keeps every knowledge state it acts on."""

    def __init__(self, inner: object) -> None:
        self.inner = inner
        self.seen: list[np.ndarray] = []

    def act(self, k: np.ndarray, mask: np.ndarray) -> np.ndarray:
        self.seen.append(k.copy())
        return self.inner.act(k, mask)  # type: ignore[attr-defined, no-any-return]


def test_every_agent_knows_where_its_teammates_were_as_the_in_process_team_does() -> None:
    """With `teammates` (and the roster), K ends with where the teammates were at the last step: an agent's mind
    builds it from the broadcasts it heard, the in-process Team from the joint assignment, and the two agree
    step for step; a teammate's capability on a task, or its presence at an idle location, shows there."""
    from htlm_agent.mind.policies import DecentralizedPolicy
    from htlm_agent.runtime.team import rollout
    from htlm_agent.session.builtin import builtin_policy
    from support.team import loopback_episode

    sc = builtin().replace(roster=True, teammates=True)
    assert sc.knowledge_size == builtin().knowledge_size + sc.n_agents + sc.n_actions
    inner = [builtin_policy(sc, "greedy", i)[0] for i in range(sc.n_agents)]
    in_team = [_Recording(p) for p in inner]
    dp = DecentralizedPolicy(in_team, 3, 0.2)  # type: ignore[arg-type]
    dp.begin(2)
    tr = rollout(Team(sc, 1, 3, episode=2), dp)
    in_minds = [_Recording(p) for p in inner]
    lb = loopback_episode(sc, 3, 2, in_minds, epsilon=0.2)  # type: ignore[arg-type]
    assert np.array_equal(tr.actions[:, 0], lb["actions"])
    model = Model.build(sc)
    for i in range(sc.n_agents):
        assert len(in_team[i].seen) == len(in_minds[i].seen) == sc.horizon
        for t, (a, b) in enumerate(zip(in_team[i].seen, in_minds[i].seen, strict=True)):
            assert np.array_equal(a, b), (i, t)
            mates = knowledge.teammates(b, sc)[0]
            if t == 0:  # everyone starts at idle@site1
                assert mates[sc.n_tasks] == 1.0 and mates.sum() == 1.0
                continue
            joint = tr.actions[t - 1, 0]
            want = knowledge.teammates_of(model, joint)[i]
            assert np.allclose(mates, want)
            for j in range(sc.n_tasks):  # a task a teammate worked on shows its capability there
                others = [n for n in range(sc.n_agents) if n != i and joint[n] == j]
                assert (mates[j] > 0) == any(model.agent_caps[n, j] > 0 for n in others)
