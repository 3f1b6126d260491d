"""The colour layer's filter (thesis ch. 3): a box particle filter on H-S(V) histograms.

One ``step`` is a short list of named stages::

    follow camera     the image's shift moves the cloud and the estimate  (camera.py)
    propose           motion model, lost-target re-draws, bounds      (proposal.py)
    observe           the frame's bins and its summed-area planes      (observe)
    score             histogram, contrast and correlation log-likelihoods, then the
                      layout and aspect log-priors; reweight, estimate and the estimate's own stripe
                      histograms, all from one windowed integral histogram (weigh)
    judge             lost flag: best distance, weights, collapse
    learn             histogram template, layout template, guide      (templates.py),
                      correlation filter                               (correlation.py)
    resample          when ESS < ess_threshold * N (SIR every frame by default)

The log-likelihood of a particle's box ``b`` is::

    -d(b)^2 / (2 sigma^2)                     mean over the stripes (thesis eqs. 3.7-3.8)
    + contrast.weight * contrast_score(b)     centre-surround colour contrast
    + correlation.weight * response(b)        correlation filter at the box's centre
    + layout.weight * ncc(b)                  layout of cell luminances
    + log-normal prior on width / height

With ``parts = 1``, no contrast, no layout and no aspect prior it is the thesis's.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.colour.appearance import (
    box_columns,
    box_parts,
    contrast_scores,
    contrast_values,
    layout_scores,
    layout_values,
    stripe_distances,
    stripe_rects,
)
from cpf_jax.colour.camera import CameraTrack, camera_init, camera_shift, shift_state
from cpf_jax.colour.config import ColourConfig, bin_index
from cpf_jax.colour.correlation import (
    CorrelationModel,
    correlation_init,
    correlation_scores,
    correlation_update,
)
from cpf_jax.colour.params import ColourParams
from cpf_jax.colour.proposal import clamp, propose
from cpf_jax.colour.templates import (
    ContrastModel,
    Guide,
    HistogramTemplate,
    LayoutTemplate,
    contrast_model_init,
    guide_init,
    guide_update,
    histogram_template_init,
    histogram_template_update,
    layout_template_init,
    layout_template_update,
)
from cpf_jax.filter import (
    Cloud,
    Context,
    Filter,
    WeighedCloud,
    at_rest,
    memoised_build,
    uniform_cloud,
    weighed_cloud,
)
from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels.histogram import (
    bhattacharyya,
    integral_image,
    normalise_counts,
    rect_reduce,
    uses_window,
)
from cpf_jax.likelihood import aspect_log_prior, histogram_log_likelihood
from cpf_jax.types import Frame, check_frame, usable_box

__all__ = [
    "ColourState",
    "ColourInfo",
    "Observation",
    "Weighed",
    "build_colour_filter",
    "colour_init",
    "colour_step",
    "observe",
    "estimate_state",
    "judge_lost",
]


class ColourState(NamedTuple):
    cloud: Cloud
    histogram: HistogramTemplate
    contrast: ContrastModel
    layout: LayoutTemplate
    correlation: CorrelationModel
    camera: CameraTrack
    guide: Guide
    estimate: Array  # [4] xywh of the last frame
    lost: Array  # bool
    size0: Array  # [2] (w, h) of the initial box: the size of re-drawn particles


class ColourInfo(NamedTuple):
    box: Array  # [4] xywh, the estimate
    lost: Array  # bool
    ess: Array  # effective sample size before resampling
    log_evidence: Array  # log mean likelihood of the propagated particles
    estimate: Array  # [4] xywh, the state estimate (``box`` itself for the colour layer)
    # bool: the histograms came from the static window (False: no window, or the exact
    # whole-frame fallback ran, which is slower).
    windowed: Array
    best_distance: Array  # smallest Bhattacharyya distance among the particles
    estimate_distance: Array  # distance of the estimate's box
    resampled: Array  # bool
    weights_invalid: Array  # bool: every log-weight was NaN or -inf
    weighed_cloud: WeighedCloud | None = None  # before resampling (config.report_weights)


class Observation(NamedTuple):
    """What the step reads from a frame before it looks at any particle."""

    bins: Array  # [H, W] int32 colour bin of every pixel
    table: Array | None  # [H+1, W+1, c] int32 summed-area table: contrast (2), layout (c)


def observe(config: ColourConfig, state: ColourState, frame: Frame) -> Observation:
    """The frame's colour bins, and one summed-area table of every per-pixel plane the
    contrast and layout terms sum (one pass over the frame instead of one per term)."""
    bins = bin_index(frame.colour, config.bins)
    planes = []
    if config.contrast is not None:
        planes.append(contrast_values(bins, state.contrast.weights))
    if config.layout is not None:
        planes.append(layout_values(frame.colour, config.layout_feature))
    table = integral_image(jnp.concatenate(planes, axis=-1)) if planes else None
    return Observation(bins, table)


def _layout_table(config: ColourConfig, obs: Observation) -> Array | None:
    """The layout channels of the observation's table (after the contrast's two)."""
    if config.layout is None:
        return None
    return obs.table[..., 0 if config.contrast is None else 2 :]


def estimate_state(config: ColourConfig, particles: Array, lw: Array, robust_radius) -> Array:
    """State estimate ``[8]`` from normalised log-weights: the weighted mean (thesis 3.10),
    the MAP particle, or the weighted mean of the particles whose centres lie within
    ``robust_radius`` box sizes of the MAP's (the robust mean of thesis 3.1)."""
    w = jnp.exp(lw)
    mean = w @ particles
    if config.estimator == "mean":
        return mean
    best = particles[jnp.argmax(lw)]
    if config.estimator == "map":
        return best
    half = robust_radius * best[4:6]
    near = jnp.all(jnp.abs(particles[:, :2] - best[:2]) <= half, axis=-1)
    wn = jnp.where(near, w, 0.0)
    total = jnp.sum(wn)
    return jnp.where(total > 0, (wn @ particles) / jnp.where(total > 0, total, 1.0), best)


class Weighed(NamedTuple):
    log_weights: Array  # [N] normalised
    invalid: Array  # bool
    ess: Array
    log_evidence: Array
    estimate: Array  # [4] xywh
    estimate_histogram: Array  # [K, B] normalised stripe histograms of the estimate


def _weigh(
    config: ColourConfig,
    params: ColourParams,
    log_weights: Array,
    particles: Array,
    contrast: Array | None,
    correlation: Array | None,
    log_prior: Array | float,
    d2: Array,
    count,
) -> Weighed:
    """Reweight, estimate, and count the estimate's stripes from the table the particles
    were counted on (``rect_reduce``'s ``then``: exact for any rect, no second table)."""
    log_lik = histogram_log_likelihood(d2, params.histogram.sigma)
    if contrast is not None:
        log_lik = log_lik + params.contrast.weight * contrast
    if correlation is not None:
        log_lik = log_lik + params.correlation.weight * correlation
    lw, invalid, ess, log_evidence = rs.reweight(log_weights, log_lik + log_prior)
    est = estimate_state(config, particles, lw, params.estimate.robust_radius)
    est_xywh = jnp.stack(box_columns(est), axis=-1)
    est_rects = box_ops.xywh_to_rect(box_parts(est_xywh, config.parts))
    est_hist = normalise_counts(count(est_rects))
    return Weighed(lw, invalid, ess, log_evidence, est_xywh, est_hist)


def judge_lost(
    config: ColourConfig, params: ColourParams, state: ColourState, d2: Array, weighed: Weighed
) -> tuple[Array, Array]:
    """``(lost, best distance)``: the target is lost when even the best particle is farther
    than ``lost_distance``, when no weight is valid, or when the estimate's height has
    collapsed below ``collapse_ratio`` of the initial box's."""
    d = jnp.sqrt(d2)
    best_d = jnp.min(jnp.where(jnp.isfinite(d), d, 1.0))
    lost = (best_d > params.histogram.lost_distance) | weighed.invalid
    if config.collapse_ratio > 0:
        lost = lost | (weighed.estimate[3] < config.collapse_ratio * state.size0[1])
    return lost, best_d


def colour_init(
    config: ColourConfig,
    params: ColourParams,
    key: Array,
    frame: Frame,
    box: Array,
    context: Context | None = None,
) -> ColourState:
    """Templates from the initial box, and ``n_particles`` copies of it (jittered by
    ``init_spread``). The colour layer reads nothing from ``context``. A box that cannot
    start a track is a ``ValueError``; under ``jit`` it starts the filter lost."""
    del context
    check_frame(frame)
    box, box_ok = usable_box(box, frame)
    height, width = frame.colour.shape[:2]
    contrast = contrast_model_init(config, params.contrast, frame, box)
    table = None
    if config.layout is not None:
        table = integral_image(layout_values(frame.colour, config.layout_feature))
    particles = at_rest(box, config.n_particles)
    if config.init_spread > 0:
        jitter = jax.random.normal(key, (config.n_particles, 2)) * config.init_spread
        particles = particles.at[:, :2].add(jitter)
    particles = clamp(config, particles, width, height)
    return ColourState(
        cloud=uniform_cloud(particles),
        histogram=histogram_template_init(config, frame, box),
        contrast=contrast,
        layout=layout_template_init(config, table, box),
        correlation=correlation_init(config.correlation, frame, box),
        camera=camera_init(config.camera_motion, frame.colour),
        guide=guide_init(),
        estimate=box,
        lost=~box_ok,
        size0=box[2:4],
    )


def colour_step(
    config: ColourConfig, params: ColourParams, key: Array, state: ColourState, frame: Frame
) -> tuple[ColourState, ColourInfo]:
    """One frame: propose, observe, score and weigh, judge, learn, resample."""
    check_frame(frame)
    height, width = frame.colour.shape[:2]
    k_prop, k_rec, k_res = jax.random.split(key, 3)
    camera = state.camera
    if config.camera_motion is not None:
        camera = camera_shift(
            config.camera_motion, camera, frame.colour, state.estimate, config.camera_min_peak
        )
        state = shift_state(state, camera.shift)
    particles, origin = propose(config, params.motion, (k_prop, k_rec), state, width, height)
    obs = observe(config, state, frame)
    boxes = box_columns(particles)
    rects = stripe_rects(boxes, config.parts)
    area = state.estimate[2] * state.estimate[3]
    contrast = None if config.contrast is None else contrast_scores(config, obs.table, boxes, area)
    correlation = None
    if config.correlation is not None:
        correlation = correlation_scores(
            config.correlation, state.correlation, frame, state.estimate, particles[:, :2]
        )
    log_prior = 0.0
    layout_table = _layout_table(config, obs)
    if config.layout is not None:
        ncc = layout_scores(config, layout_table, boxes, state.layout.vector)
        log_prior = params.layout.weight * ncc
    if config.aspect_prior:
        log_prior = log_prior + aspect_log_prior(particles, params.aspect)
    sqrt_q = jnp.sqrt(state.histogram.reference)  # [K, B]
    weigh = functools.partial(
        _weigh, config, params, state.cloud.log_weights, particles, contrast, correlation, log_prior
    )
    d2, weighed = rect_reduce(
        obs.bins,
        rects,
        functools.partial(stripe_distances, sqrt_q),
        n_bins=config.n_bins,
        window=config.window,
        origin=origin,
        with_area=True,
        then=weigh,
        chunk=config.chunk,
    )
    est = weighed.estimate
    est_hist = weighed.estimate_histogram
    est_d = jnp.sqrt(jnp.mean(bhattacharyya(est_hist, state.histogram.reference) ** 2))
    lost, best_d = judge_lost(config, params, state, d2, weighed)
    histogram = histogram_template_update(
        config, params.template, state.histogram, est_hist, est_d, lost
    )
    layout = layout_template_update(config, params.layout, state.layout, layout_table, est, lost)
    learnt = correlation_update(
        config.correlation, params.correlation, state.correlation, frame, est, lost
    )
    (new_particles, previous), lw, resampled = rs.resample_if(
        k_res,
        weighed.log_weights,
        (particles, state.cloud.particles),
        config.ess_threshold,
        rs.SCHEMES[config.resampler],
    )
    new_state = ColourState(
        cloud=Cloud(new_particles, previous, lw),
        histogram=histogram,
        contrast=state.contrast,
        layout=layout,
        correlation=learnt,
        camera=camera,
        guide=guide_update(config, state.guide, state.estimate, est, lost, state.lost),
        estimate=est,
        lost=lost,
        size0=state.size0,
    )
    info = ColourInfo(
        box=est,
        lost=lost,
        ess=weighed.ess,
        log_evidence=weighed.log_evidence,
        estimate=est,
        windowed=uses_window((height, width), rects, config.window, origin),
        best_distance=best_d,
        estimate_distance=est_d,
        resampled=resampled,
        weights_invalid=weighed.invalid,
        weighed_cloud=weighed_cloud(config, particles, weighed.log_weights),
    )
    return new_state, info


@memoised_build
def build_colour_filter(config: ColourConfig) -> Filter:
    """The colour layer's ``Filter(init, step)`` for a static ``config``."""

    def init(params, key, frame, box, context=None):
        return colour_init(config, params, key, frame, box, context)

    def step(params, key, state, frame):
        return colour_step(config, params, key, state, frame)

    return Filter(init, step)
