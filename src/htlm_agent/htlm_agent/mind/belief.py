"""The belief filter of docs/model.md (Eq. 2 of the paper): per-site joint belief over (fire, rescue) levels.

Vectorized over a batch of episodes and the agents of a team: beliefs have shape (B, N, S, L, L).
"""

from __future__ import annotations

import numpy as np

from htlm_world.model import Model
from htlm_world.types import Belief, BoolArray, FloatArray, IntArray, Marginals


def initial_belief(model: Model, batch: int) -> Belief:
    """b0: certain of the initial levels, for every agent of every episode."""
    sc = model.scenario
    L = sc.levels
    b = np.zeros((batch, sc.n_agents, sc.n_sites, L, L))
    for s in range(sc.n_sites):
        b[:, :, s, sc.initial_levels[2 * s], sc.initial_levels[2 * s + 1]] = 1.0
    return b


def predict(model: Model, belief: Belief, caps: IntArray) -> Belief:
    """Predict every site's belief with T (Eq. 2, sum over s of T(s, a, s') b(s)).

    Args:
        belief: (..., S, L, L) over (fire, rescue).
        caps: (..., p) joint capabilities each belief assumes for the step.
    """
    cf = caps[..., 0::2]  # (..., S)
    cr = caps[..., 1::2]
    rescue = model.rescue[cr]  # (..., S, f, r, r')
    fire = model.fire[cf]  # (..., S, f, f')
    tmp = np.einsum("...fr,...frs->...fs", belief, rescue)
    out: Belief = np.einsum("...fg,...fs->...gs", fire, tmp)
    return out


def agent_evidence(
    model: Model,
    agent: int,
    actions: IntArray,
    own_observation: IntArray,
    messages: IntArray,
    heard: BoolArray | None = None,
) -> FloatArray:
    """Likelihood of agent `agent`'s evidence of one step for every task level: (B, p, L).

    Its own observation is weighed with O, teammate k's message with I_k (docs/model.md, Information I).

    Args:
        actions: (B, N) the joint assignment of the step (as the agent knows it).
        own_observation: (B,) the agent's own observation, -1 when idle.
        messages: (B, N) levels received from each teammate after its channel, -1 when idle or not sent.
        heard: optional (B, N) mask of teammates whose message arrived; all when None.
    """
    sc = model.scenario
    b, n = actions.shape
    p = sc.n_tasks
    lik = np.ones((b, p, sc.levels))
    rows = np.arange(b)
    for k in range(n):
        works = (actions[:, k] >= 0) & (actions[:, k] < p)
        task = np.where(works, actions[:, k], 0)
        if k == agent:
            level = own_observation
            table = model.obs[model.sensing[k]]
        else:
            level = messages[:, k]
            table = model.info[model.sensing[k], model.comm[k]]
            if heard is not None:
                works = works & heard[:, k]
        ok = works & (level >= 0)
        if ok.any():
            lik[rows[ok], task[ok]] *= table[:, level[ok]].T
    return lik


def evidence(model: Model, actions: IntArray, observations: IntArray, messages: IntArray) -> FloatArray:
    """Likelihood of every agent's evidence, all messages delivered: (B, N, p, L) (see `agent_evidence`)."""
    n = actions.shape[1]
    return np.stack([agent_evidence(model, i, actions, observations[:, i], messages) for i in range(n)], axis=1)


def update(model: Model, belief: Belief, caps: IntArray, likelihood: FloatArray) -> tuple[Belief, np.ndarray]:
    """One step of Eq. 2: predict with T, multiply by the evidence, normalise.

    Args:
        belief: (..., S, L, L), e.g. (B, N, S, L, L) for a team or (B, S, L, L) for one agent.
        caps: (..., p) joint capabilities each belief assumes for the step.
        likelihood: (..., p, L) from `evidence` or `agent_evidence`.

    Returns:
        The new belief and a (...) mask of agents whose evidence had zero probability: they keep the prediction
        (docs/model.md), and the caller counts the event.
    """
    pred = predict(model, belief, caps)
    post = pred * likelihood[..., 0::2, :, None] * likelihood[..., 1::2, None, :]
    z = post.sum(axis=(-1, -2))  # (B, N, S)
    bad_site = z <= 0.0
    post = np.where(bad_site[..., None, None], pred, post / np.where(bad_site, 1.0, z)[..., None, None])
    return post, bad_site.any(axis=-1)


def marginals(belief: Belief) -> Marginals:
    """Per-task marginals (..., p, L) in task order fire@site1, rescue@site1, fire@site2, ..."""
    fire = belief.sum(axis=-1)  # (..., S, L)
    rescue = belief.sum(axis=-2)
    out = np.stack([fire, rescue], axis=-2)  # (..., S, 2, L)
    return out.reshape(belief.shape[:-3] + (2 * belief.shape[-3], belief.shape[-1]))
