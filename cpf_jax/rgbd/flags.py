"""Per-cell occlusion flags (paper 2.5, eq. 6) and their exact marginalisation.

Each particle carries ``C`` flags as an ``int32`` bit mask (bit ``i``: cell ``i``
occluded). Transitions: a full ``2^C x 2^C`` matrix (``flag_transition = "full"``, by
default the Kronecker product of the per-cell chains, or ``occlusion.transition``) or the
factorised per-cell chains ``P(0 -> 1) = p_occlude``, ``P(1 -> 0) = p_reveal``. Instead
of drawing the flags blindly from the transition and weighting, each particle draws them
from the locally optimal proposal ``p(z_t | z_{t-1}, B_t, y_t) ∝ T[z_{t-1}, z_t] p(y_t |
B_t, z_t)`` and is weighted by ``sum_z T[z_{t-1}, z] p(y_t | B_t, z)``: the model of eq.
6 with the flags' Monte Carlo noise integrated out (2^C terms per particle for the full
matrix, 2 per cell for the factorised form).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.kernels.cells import side_cells
from cpf_jax.rgbd.beta import box_log_density
from cpf_jax.rgbd.cells import CellTerms
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.params import BetaParams, OcclusionParams

__all__ = [
    "flag_bits",
    "kronecker_transition",
    "log_clip",
    "FlagPosterior",
    "flag_posterior",
    "state_terms",
    "marginal_likelihood",
]


def flag_bits(n_cells: int) -> Array:
    """``[2^C, C] float32``: bit ``i`` of every flag state (state index = bit mask)."""
    s = np.arange(1 << n_cells)[:, None]
    return jnp.asarray(((s >> np.arange(n_cells)[None]) & 1).astype(np.float32))


def kronecker_transition(p_occlude: Array, p_reveal: Array, n_cells: int) -> Array:
    """Full ``[2^C, 2^C]`` matrix (rows: from, columns: to) of independent per-cell chains,
    ``T[s, z] = prod_i P(z_i | s_i)``; ``p_occlude`` / ``p_reveal`` scalars or ``[C]``."""
    bits = flag_bits(n_cells)  # [S, C]
    po = jnp.broadcast_to(jnp.asarray(p_occlude, jnp.float32), (n_cells,))
    pr = jnp.broadcast_to(jnp.asarray(p_reveal, jnp.float32), (n_cells,))
    s = bits[:, None, :]
    z = bits[None, :, :]
    p1 = jnp.where(s > 0, 1.0 - pr, po)  # P(z_i = 1 | s_i)
    return jnp.prod(jnp.where(z > 0, p1, 1.0 - p1), axis=-1)


def log_clip(p: Array) -> Array:
    """``log p`` with ``log 0 = -inf`` (an impossible transition) and no NaN gradient at 0."""
    pos = p > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, jnp.minimum(p, 1.0), 1.0)), -jnp.inf)


class FlagPosterior(NamedTuple):
    log_likelihood: Array  # [N] the flags marginalised out
    flags: Array  # [N] int32 bit masks drawn from the locally optimal proposal
    p_cell: Array  # [N, C] posterior probability that each cell is occluded


def flag_posterior(
    config: RGBDConfig,
    params: OcclusionParams,
    key: Array,
    prev: Array,
    l_vis: Array,
    l_occ: Array,
    l_state: Array | None = None,
) -> FlagPosterior:
    """Marginal likelihood, new flags and per-cell posteriors of ``N`` particles with
    previous flags ``prev [N]`` and per-cell log-likelihoods ``[N, C]`` if visible /
    occluded; ``l_state [N, 2^C]`` (full form only) adds terms over several cells."""
    n, c = l_vis.shape
    if config.full_transition:
        bits = flag_bits(c)  # [S, C]
        if params.transition is None:
            trans = kronecker_transition(params.p_occlude, params.p_reveal, c)
        else:
            trans = jnp.asarray(params.transition, jnp.float32)
        log_t = log_clip(trans)[prev]  # [N, S]
        joint = log_t + jnp.sum(l_vis, -1, keepdims=True) + (l_occ - l_vis) @ bits.T
        if l_state is not None:
            joint = joint + l_state
        log_lik = jax.nn.logsumexp(joint, axis=-1)
        post = jnp.exp(joint - log_lik[:, None])  # [N, S]
        new = jax.random.categorical(key, joint, axis=-1).astype(jnp.int32)
        return FlagPosterior(log_lik, new, post @ bits)
    prev_bits = ((prev[:, None] >> jnp.arange(c)) & 1).astype(bool)  # [N, C]
    po = jnp.broadcast_to(jnp.asarray(params.p_occlude, jnp.float32), (c,))
    pr = jnp.broadcast_to(jnp.asarray(params.p_reveal, jnp.float32), (c,))
    p1 = jnp.where(prev_bits, 1.0 - pr, po)
    a0 = log_clip(1.0 - p1) + l_vis
    a1 = log_clip(p1) + l_occ
    lse = jnp.logaddexp(a0, a1)
    p_cell = jnp.exp(a1 - lse)
    draw = jax.random.uniform(key, (n, c)) < p_cell
    new = jnp.sum(draw.astype(jnp.int32) << jnp.arange(c), axis=-1).astype(jnp.int32)
    return FlagPosterior(jnp.sum(lse, axis=-1), new, p_cell)


def state_terms(config: RGBDConfig, beta: BetaParams, terms: CellTerms) -> Array:
    """Log-likelihood ``[N, 2^C]`` of the terms over several cells in every flag state: the
    border strips of the sides whose cells are all visible, the body colour of the visible
    cells and (``box_term``) the pooled foreground ratio of the visible cells."""
    c = config.n_cells
    vis = 1.0 - flag_bits(c)  # [S, C]: 1 where the cell is visible
    sides = jnp.asarray(side_cells(config.k), jnp.float32)  # [4, C]
    side_on = (vis @ sides.T) >= jnp.sum(sides, axis=-1)  # [S, 4]
    side_sum = terms.l_border[:, :4] + terms.l_border[:, 4:]  # [N, 4] per side
    l_state = side_sum @ side_on.astype(jnp.float32).T + terms.l_body  # [N, S]
    if config.box_term and c > 1:
        l_state = l_state + box_log_density(beta, terms.fg_count @ vis.T, terms.area @ vis.T)
    return l_state


def _all_visible_terms(
    config: RGBDConfig, beta: BetaParams, terms: CellTerms, log_lik: Array | None = None
) -> Array:
    """Log-likelihood ``[N]`` of the terms over several cells with every cell visible,
    added to ``log_lik [N]`` when given."""
    side_sum = terms.l_border[:, :4] + terms.l_border[:, 4:]
    extra = jnp.sum(side_sum, axis=-1)
    if log_lik is not None:
        extra = log_lik + extra
    extra = extra + terms.l_body[:, 0]
    if config.box_term and config.n_cells > 1:
        extra = extra + box_log_density(
            beta, jnp.sum(terms.fg_count, axis=-1), jnp.sum(terms.area, axis=-1)
        )
    return extra


def marginal_likelihood(
    config: RGBDConfig,
    params: OcclusionParams,
    beta: BetaParams,
    key: Array,
    prev: Array,
    terms: CellTerms,
) -> FlagPosterior:
    """The particles' log-likelihood with their flags marginalised (``grid-occlusion``), or
    with every cell visible (the other variants, whose flags stay as they are)."""
    if not config.occlusion:
        n, c = terms.l_vis.shape
        log_lik = _all_visible_terms(config, beta, terms, jnp.sum(terms.l_vis, axis=-1))
        return FlagPosterior(log_lik, prev, jnp.zeros((n, c), jnp.float32))
    if config.full_transition:
        l_state = state_terms(config, beta, terms)
        return flag_posterior(config, params, key, prev, terms.l_vis, terms.l_occ, l_state)
    # Factorised flags: the multi-cell terms cannot be split per cell; they are scored as
    # if every cell were visible.
    post = flag_posterior(config, params, key, prev, terms.l_vis, terms.l_occ)
    extra = _all_visible_terms(config, beta, terms)
    return post._replace(log_likelihood=post.log_likelihood + extra)
