"""The per-cell observation model of the RGB-D filter (paper 2.3-2.4, eqs. 1-5).

A particle's box is cut into a ``k x k`` grid of cells. A visible cell ``i`` scores::

    log p_i = max(beta.weight * log Beta(r_i; a_i, b_i), beta.floor)          (eq. 2)
              + max(-d_i^2 / (2 colour.sigma^2), colour.floor)                 (eqs. 4-5)
              + max(-(m_i - mu_i)^2 / (2 s_i^2), depth.floor)                  (2.4)

with ``r_i`` the cell's foreground ratio, ``d_i`` the Bhattacharyya distance of its
foreground colours to the template (the paper's exponent in eq. 4 is garbled; we read it
as the thesis's Gaussian in ``d``), ``m_i`` the median depth of its foreground and
``s_i = sqrt((sigma + sigma_rel mu_i)^2 + drift^2)``. An occluded cell scores eq. 1's
constant plus the depth-ordering rule "depth decides who occludes whom"::

    log p_i = log_occluded + log(eps + (1 - eps) e_i)

where ``e_i`` is the share of the cell covered by foreground nearer than the template by
more than the occluder margin: a cell with nothing in front cannot be occluded, so a
particle on empty background cannot call its cells occluded and score like the hidden
target. The floors make one implausible statistic cost a bounded amount. Border strips
and the whole-body colour term add evidence over several cells (``flags.py`` combines
them per flag state). Every count is exact (``rect_reduce`` over ``[N, C, 4]`` rects).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.cells import (
    beta_log_density,
    border_strips,
    grid_cells,
    histogram_fraction_below,
    histogram_quantile,
    strip_counts,
    strip_table,
)
from cpf_jax.kernels.histogram import rect_reduce, squared_bhattacharyya, uses_window
from cpf_jax.likelihood import histogram_log_likelihood
from cpf_jax.rgbd.beta import clipped_area
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.depth import DepthTemplate, occluder_margin
from cpf_jax.rgbd.observe import Observation
from cpf_jax.rgbd.params import BodyParams, RGBDParams

__all__ = [
    "CellTerms",
    "cell_terms",
    "border_terms",
    "body_states",
    "body_log_likelihood",
]


class CellTerms(NamedTuple):
    """Per-cell pieces of the likelihood of ``N`` boxes (``[N, C]`` unless noted)."""

    l_vis: Array  # log-likelihood if visible: beta + colour + depth
    l_occ: Array  # log-likelihood if occluded (eq. 1 constant + depth ordering)
    l_beta: Array
    l_colour: Array
    l_depth: Array
    ratio: Array  # foreground ratio
    distance: Array  # Bhattacharyya distance to the colour template
    median_depth: Array  # mm (0: no foreground depth)
    occluder: Array  # occluder evidence e_i
    fg_count: Array
    area: Array  # pixels of the cell inside the frame
    l_border: Array  # [N, 8] Beta log-densities of the border strips (inner t/b/l/r, outer)
    border_ratio: Array  # [N, 8] their ratios
    l_body: Array  # [N, S] body colour term per state of ``body_states`` (zeros without it)
    windowed: Array  # bool []: every rect was counted in the static window


def body_states(config: RGBDConfig) -> np.ndarray:
    """``[S, C]`` visibility (1: visible; static) of the cells in each state the body term
    scores: every flag state of the full transition form (bit ``i`` of state ``s`` set:
    cell ``i`` occluded), else one state with every cell visible."""
    if config.occlusion and config.full_transition:
        s = np.arange(1 << config.n_cells)[:, None]
        return 1.0 - ((s >> np.arange(config.n_cells)[None]) & 1).astype(np.float32)
    return np.ones((1, config.n_cells), np.float32)


def body_log_likelihood(
    params: BodyParams, template: Array, counts: Array, vis: np.ndarray, n_fg: int
) -> Array:
    """Body colour term ``[m, S]`` of cell colour counts ``[m, C, B]``: per state of
    ``vis [S, C]`` the foreground counts of its visible cells pooled and compared with the
    whole-body ``template [n_fg]``, ``max(-(d^2 - ref^2) / (2 sigma^2), floor)``; 0 with
    fewer than ``min_pixels`` visible foreground pixels (neither reward nor punishment for
    a hidden target)."""
    fg = counts[..., :n_fg]  # [m, C, F]
    # The double where keeps gradients through the template's learning finite.
    sqrt_t = jnp.where(template > 0, jnp.sqrt(jnp.where(template > 0, template, 1.0)), 0.0)
    vis = np.asarray(vis)
    if len(vis) <= 64:
        # One fused sum per state over its visible cells, unrolled: on a CPU 3x faster
        # than one einsum over every state, which lays out an [m, S, F] tensor first.
        pooled = []
        for row in vis:
            cells = [fg[:, i] for i in np.flatnonzero(row)]
            pooled.append(sum(cells[1:], cells[0]) if cells else jnp.zeros_like(fg[:, 0]))
        totals = [jnp.sum(p, axis=-1) for p in pooled]
        d2 = jnp.stack(
            [squared_bhattacharyya(p, sqrt_t, t) for p, t in zip(pooled, totals, strict=True)],
            axis=-1,
        )
        total = jnp.stack(totals, axis=-1)  # [m, S]
    else:  # a full transition over many cells: not unrolled
        pooled = jnp.einsum("sc,mcf->msf", vis, fg)
        total = jnp.sum(pooled, axis=-1)
        d2 = squared_bhattacharyya(pooled, sqrt_t, total)
    # d^2 - ref^2 against sigma: the Gaussian of eq. 3.8 shifted to score 0 at ``ref``.
    l_body = jnp.maximum(histogram_log_likelihood(d2 - params.ref**2, params.sigma), params.floor)
    return jnp.where(total >= params.min_pixels, l_body, 0.0)


def border_terms(
    config: RGBDConfig,
    params: RGBDParams,
    obs: Observation,
    boxes_xywh: Array,
    mu: Array,
    margin: Array,
) -> tuple[Array, Array]:
    """``(l_border, ratio)`` ``[N, 8]`` of the border strips: the foreground share of the
    inner strips and the share at the target's depth or farther of the outer strips (a
    nearer occluder beside the box is not the target), from one two-channel summed-area
    table (4 rects a particle instead of 12 cell histograms)."""
    height, width = obs.foreground.shape
    nz, zlo, zhi = config.depth_bins, *config.depth_range
    have = mu > 0
    mu_box = jnp.sum(jnp.where(have, mu, 0.0)) / jnp.maximum(jnp.sum(have), 1)
    margin_box = jnp.sum(jnp.where(have, margin, 0.0)) / jnp.maximum(jnp.sum(have), 1)
    table, frac = strip_table(
        obs.colour_bins, config.n_fg_bins, obs.depth_bins, mu_box - margin_box, nz, zlo, zhi
    )
    strips = box_ops.xywh_to_rect(border_strips(boxes_xywh, config.border))  # [N, 8, 4]
    fg_strip, far_strip = strip_counts(table, frac, strips)
    area_strip = clipped_area(strips, width, height)
    counted = jnp.concatenate([fg_strip[:, :4], far_strip[:, 4:]], axis=-1)
    ratio = jnp.where(area_strip > 0, counted / jnp.maximum(area_strip, 1.0), 0.0)
    border = params.border
    l_border = params.beta.weight * beta_log_density(ratio, border.a, border.b)
    # A strip wholly outside the frame says nothing; the floor bounds one bad strip.
    l_border = jnp.where(area_strip > 0, jnp.maximum(l_border, border.floor), 0.0)
    return l_border, ratio


def _colour_stats(
    body: BodyParams,
    sqrt_q: Array,
    body_template: Array | None,
    vis_states: np.ndarray,
    n_fg: int,
    counts: Array,
) -> Array:
    """Per-cell ``[m, C, 3 (+ S)]``: pixels, squared distance to the template, background
    pixels (and the body term per state, pooled inside the reduction so that the
    ``[N, C, B]`` counts never exist at once) of cell counts ``[m, C, B]``."""
    total = jnp.sum(counts, axis=-1)
    d2 = squared_bhattacharyya(counts, sqrt_q, total)
    out = jnp.stack([total, d2, counts[..., -1]], axis=-1)
    if body_template is None:
        return out
    l_body = body_log_likelihood(body, body_template, counts, vis_states, n_fg)
    n_states = vis_states.shape[0]
    return jnp.concatenate(
        [out, jnp.broadcast_to(l_body[:, None, :], (*out.shape[:2], n_states))], axis=-1
    )


def _depth_stats(near_thr: Array, bins: tuple[int, float, float], counts: Array) -> Array:
    """Per-cell ``[m, C, 3]``: median depth, depth samples and the share nearer than
    ``near_thr [C]`` of depth-bin counts ``[m, C, Z]``."""
    med, total = histogram_quantile(counts, *bins)
    near = histogram_fraction_below(counts, near_thr, *bins)
    return jnp.stack([med, total, near], axis=-1)


def cell_terms(
    config: RGBDConfig,
    params: RGBDParams,
    colour_template: Array,
    depth: DepthTemplate,
    obs: Observation,
    boxes_xywh: Array,
    body_template: Array | None = None,
) -> CellTerms:
    """The per-cell likelihood terms of ``boxes_xywh [N, 4]`` (module docstring) against the
    cells' colour templates ``[C, B]`` and depth templates; ``body_template [B - 1]``
    (None: no body term) scores each state of ``body_states``."""
    height, width = obs.foreground.shape
    nz, zlo, zhi = config.depth_bins, *config.depth_range
    rects = box_ops.xywh_to_rect(grid_cells(boxes_xywh, config.k))  # [N, C, 4]
    sqrt_q = jnp.sqrt(colour_template)  # [C, B]
    mu = depth.depth  # [C]
    drift = jnp.minimum(params.depth.speed * depth.age, params.depth.max_drift)
    margin = occluder_margin(params, mu) + drift
    near_thr = mu - margin
    area = clipped_area(rects, width, height)
    vis_states = body_states(config)  # [S, C]
    n_states = vis_states.shape[0]
    colour_stats = functools.partial(
        _colour_stats, params.body, sqrt_q, body_template, vis_states, config.n_fg_bins
    )
    depth_stats = functools.partial(_depth_stats, near_thr, (nz, zlo, zhi))
    windows = config.count_windows
    cs = rect_reduce(obs.colour_bins, rects, colour_stats, n_bins=config.n_bins, window=windows)
    ds = rect_reduce(obs.depth_bins, rects, depth_stats, n_bins=nz, window=windows)
    if config.border > 0:
        l_border, strip_ratio = border_terms(config, params, obs, boxes_xywh, mu, margin)
    else:
        strip_ratio = jnp.zeros((boxes_xywh.shape[0], 8), jnp.float32)
        l_border = jnp.zeros_like(strip_ratio)
    fg_count = cs[..., 0] - (cs[..., 2] if config.background_bin else 0.0)
    ratio = jnp.where(area > 0, fg_count / jnp.maximum(area, 1.0), 0.0)
    d2 = cs[..., 1]
    l_body = (
        jnp.zeros((boxes_xywh.shape[0], n_states), jnp.float32)
        if body_template is None
        else cs[:, 0, 3:]
    )
    med, n_depth, near = ds[..., 0], ds[..., 1], ds[..., 2]
    beta = params.beta
    l_beta = jnp.maximum(beta.weight * beta_log_density(ratio, beta.a, beta.b), beta.floor)
    l_col = jnp.maximum(histogram_log_likelihood(d2, params.colour.sigma), params.colour.floor)
    has_depth = (n_depth >= config.min_depth_count) & (mu > 0)
    dp = params.depth
    sd = jnp.sqrt((dp.sigma + dp.sigma_rel * mu) ** 2 + drift**2)
    l_dep = jnp.where(has_depth, jnp.maximum(-0.5 * ((med - mu) / sd) ** 2, dp.floor), 0.0)
    occ = params.occlusion
    evidence = jnp.where(has_depth, near, occ.unknown) * ratio
    l_occ = occ.log_occluded + jnp.log(occ.eps + (1.0 - occ.eps) * evidence)
    return CellTerms(
        l_vis=l_beta + l_col + l_dep,
        l_occ=l_occ,
        l_beta=l_beta,
        l_colour=l_col,
        l_depth=l_dep,
        ratio=ratio,
        distance=jnp.sqrt(d2),
        median_depth=jnp.where(n_depth > 0, med, 0.0),
        occluder=evidence,
        fg_count=fg_count,
        area=area,
        l_border=l_border,
        border_ratio=strip_ratio,
        l_body=l_body,
        windowed=uses_window((height, width), rects, windows),
    )
