"""The RGB-D box filter with grid cells and occlusion flags (the RGB-D occlusion paper).

One ``step`` is a short list of named stages::

    predict    the depth templates one frame ahead                 (depth.py)
    observe    foreground, colour and depth bins                   (observe.py)
    propose    motion, spreading, detector mixture, recovery       (proposal.py)
    score      per-cell terms, marginalised over the flags         (cells.py, flags.py)
               + aspect prior + proposal correction; reweight
    estimate   weighted mean, occlusion votes, reported box        (report.py)
    learn      cell colours, depth templates, body, background     (templates.py, depth.py)
    resample   particles, previous states and flags together

The vote ``v_i`` of a cell is the posterior expectation of its flag over the particles;
cells with ``v_i > vote_threshold`` are voted occluded (paper 3.1) and keep their
templates (eq. 8). Variants (``RGBDConfig.variant``) are compositions of the same
stages: ``"rgbd"`` one cell, ``"grid"`` ``k x k`` cells, ``"grid-occlusion"`` adds the
flags, the spreading, the recovery draws and the reported hiding.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

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
from cpf_jax.kernels.background import (
    Background,
    behind_plane,
    masked_quantile,
    side_scene,
    update_background,
)
from cpf_jax.likelihood import aspect_log_prior
from cpf_jax.rgbd.beta import beta_fill_shift, fill_adapted, initial_fill
from cpf_jax.rgbd.cells import cell_terms
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.depth import (
    DepthTemplate,
    depth_template_init,
    depth_template_predict,
    depth_template_update,
    remember_occluder,
)
from cpf_jax.rgbd.flags import marginal_likelihood
from cpf_jax.rgbd.observe import as_background, cell_statistics, observe
from cpf_jax.rgbd.params import RGBDParams
from cpf_jax.rgbd.proposal import clamp, propose
from cpf_jax.rgbd.report import reported_box, target_extent
from cpf_jax.rgbd.templates import (
    BodyTemplate,
    CellColour,
    body_template_init,
    body_template_update,
    cell_colour_init,
    cell_colour_update,
)
from cpf_jax.types import Frame, check_frame, usable_box

__all__ = [
    "OcclusionTrack",
    "RGBDState",
    "RGBDInfo",
    "rgbd_init",
    "unseen_scene",
    "score_particles",
    "rgbd_step",
    "build_rgbd_filter",
]


class OcclusionTrack(NamedTuple):
    vote: Array  # [C] occlusion votes of the last frame
    occluded_frames: Array  # int32, consecutive frames with the target voted occluded
    visible_size: Array  # [2] (w, h) of the last estimate with no cell voted occluded


class RGBDState(NamedTuple):
    cloud: Cloud
    flags: Array  # [N] int32 bit masks (bit i: cell i occluded)
    colour: CellColour
    depth: DepthTemplate
    body: BodyTemplate
    background: Background
    occlusion: OcclusionTrack
    estimate: Array  # [4] xywh, the weighted mean of the last frame
    fill_shift: Array  # logit shift of the Beta means towards the first box's fill


class RGBDInfo(NamedTuple):
    box: Array  # [4] xywh, the reported box (``report.py``)
    lost: Array  # bool: no box is reported this frame
    ess: Array
    log_evidence: Array  # log mean likelihood of the propagated particles
    estimate: Array  # [4] xywh, the weighted mean of the particles (the whole-body box)
    windowed: Array  # bool: the cells' histograms came from the static window
    vote: Array  # [C] posterior probability that each cell is occluded
    target_occluded: Array  # bool: more than half of the cells voted occluded (or hidden)
    resampled: Array
    weights_invalid: Array
    weighed_cloud: WeighedCloud | None = None  # before resampling (config.report_weights)


def rgbd_init(
    config: RGBDConfig,
    params: RGBDParams,
    key: Array,
    frame: Frame,
    box: Array,
    context: Context | None = None,
) -> RGBDState:
    """Templates from the initial box against ``context.background`` (None: the frame's own
    scene, ``config.side_scene``), ``n_particles`` copies of the box, the
    Beta means moved towards its foreground fill (``beta.py``)."""
    check_frame(frame, needs_depth=True)
    box, _ = usable_box(box, frame)  # an unusable box under jit: the whole frame
    height, width = frame.colour.shape[:2]
    background = None if context is None else context.background
    bg = as_background(background, frame)
    obs = observe(config, params.foreground, frame, bg)
    _, med, _ = cell_statistics(config, obs, box)
    if background is None and config.side_scene is not None:
        # The box's depths against no background give the target's depth, and with it the
        # frame's scene.
        obs = observe(config, params.foreground, frame, unseen_scene(config, bg, frame, box, med))
        _, med, _ = cell_statistics(config, obs, box)
    particles = at_rest(box, config.n_particles)
    if config.init_spread > 0:
        jitter = jax.random.normal(key, (config.n_particles, 2)) * config.init_spread
        particles = particles.at[:, :2].add(jitter)
    particles = clamp(config, particles, width, height)
    c = config.n_cells
    fill_shift = (
        jnp.zeros((), jnp.float32)
        if background is None and config.side_scene is None
        else beta_fill_shift(params.beta, initial_fill(obs.foreground, box))
    )
    return RGBDState(
        cloud=uniform_cloud(particles),
        flags=jnp.zeros((config.n_particles,), jnp.int32),
        colour=cell_colour_init(config, obs, box),
        depth=depth_template_init(med, box),
        body=body_template_init(config, obs, box),
        background=bg,
        occlusion=OcclusionTrack(jnp.zeros((c,), jnp.float32), jnp.zeros((), jnp.int32), box[2:4]),
        estimate=box,
        fill_shift=fill_shift,
    )


def target_depth(medians: Array) -> Array:
    """The target's depth (mm): the median of the known cell depths ``[C]`` (0: none)."""
    return masked_quantile(medians, medians > 0, 0.5)


def unseen_scene(
    config: RGBDConfig, background: Background, frame: Frame, est: Array, medians: Array
) -> Background:
    """``background`` with a scene behind its unseen pixels: the nearer of the plane
    ``config.behind_mm`` behind the target's depth (cell ``medians [C]``) and the frame's
    own scene along the row (``config.side_scene`` times the estimate's width ``est[2]`` to
    either side); either alone where the other is unknown."""
    z = target_depth(medians)
    plane = jnp.where(z > 0, z + config.behind_mm, 0.0)
    sides = side_scene(frame.depth, jnp.asarray(config.side_scene, jnp.float32) * est[2])
    known = (sides > 0) & (plane > 0)
    return behind_plane(
        background, jnp.where(known, jnp.minimum(sides, plane), jnp.maximum(sides, plane))
    )


def score_particles(
    config: RGBDConfig, params: RGBDParams, key: Array, state: RGBDState, obs, proposal
):
    """Log-likelihood ``[N]`` of the proposed particles (flags marginalised, aspect prior,
    proposal correction), their new flags and per-cell occlusion posteriors ``[N, C]``,
    and the cell terms."""
    particles = proposal.particles
    beta, border = fill_adapted(params.beta, params.border, state.fill_shift)
    adapted = params._replace(beta=beta, border=border)
    boxes = box_ops.cxcywh_to_xywh(particles[..., jnp.array([0, 1, 4, 5])])
    body = state.body.histogram if config.body_term else None
    terms = cell_terms(config, adapted, state.colour.histograms, state.depth, obs, boxes, body)
    post = marginal_likelihood(config, params.occlusion, beta, key, proposal.flags, terms)
    log_lik = post.log_likelihood
    if config.aspect_prior:
        log_lik = log_lik + aspect_log_prior(particles, params.aspect)
    return log_lik + proposal.log_correction, post, terms


def _learn(
    config: RGBDConfig,
    params: RGBDParams,
    state: RGBDState,
    obs,
    frame: Frame,
    est: Array,
    report: Array,
    vote: Array,
    voted: Array,
    lost: Array,
    held: Array,
):
    """The templates' updates: cell colours and depths where voted visible (eqs. 7-8), the
    occluder's depth, the body, and a given background on its own pixels."""
    est_hist, est_med, _ = cell_statistics(config, obs, est)
    ok = (~voted) & (~lost)
    occluded_frames = state.occlusion.occluded_frames
    depth = depth_template_update(
        config, params, state.depth, occluded_frames, obs, frame.depth, est, ok, held
    )
    depth = depth._replace(occluder=remember_occluder(params, state.depth, est_med))
    colour = cell_colour_update(config, params.colour, state.colour, est_hist, ok)
    body = body_template_update(config, params.body, state.body, obs, report, vote, lost)
    background = state.background
    if config.background_update:
        background = update_background(
            background,
            frame.colour,
            frame.depth,
            obs.foreground,
            params.foreground.background_rate,
        )
    return colour, depth, body, background


def rgbd_step(
    config: RGBDConfig, params: RGBDParams, key: Array, state: RGBDState, frame: Frame
) -> tuple[RGBDState, RGBDInfo]:
    """One frame: predict, observe, propose, score, estimate, learn, resample."""
    check_frame(frame, needs_depth=True)
    k_prop, k_spread, k_flag, k_res, k_rec = jax.random.split(key, 5)
    k_det = jax.random.fold_in(key, 6)
    state = state._replace(depth=depth_template_predict(config, state.depth))
    scene = state.background
    if config.side_scene is not None:
        scene = unseen_scene(config, scene, frame, state.estimate, state.depth.depth)
    obs = observe(config, params.foreground, frame, scene)
    proposal = propose(config, params, (k_prop, k_spread, k_det, k_rec), state, obs, frame.depth)
    log_lik, post, terms = score_particles(config, params, k_flag, state, obs, proposal)
    lw, invalid, ess, log_evidence = rs.reweight(state.cloud.log_weights, log_lik)
    w = jnp.exp(lw)
    est = box_ops.cxcywh_to_xywh((w @ proposal.particles)[..., jnp.array([0, 1, 4, 5])])
    vote = w @ post.p_cell  # [C]
    voted = vote > params.occlusion.vote_threshold
    target_occluded = jnp.mean(voted.astype(jnp.float32)) > 0.5
    extent = target_extent(params, state, obs, frame.depth, est, config.window)
    # Nothing at the target's depth in or around the estimate: it is hidden (or lost),
    # whatever the cells' votes say.
    hidden = extent.coverage < params.target.min_coverage
    report = reported_box(config, est, extent, voted)
    lost = invalid | ((jnp.all(voted) | hidden) if config.occlusion else False)
    if config.occlusion:
        target_occluded = target_occluded | hidden
    colour, depth, body, background = _learn(
        config, params, state, obs, frame, est, report, vote, voted, lost, extent.held
    )
    occluded_frames = jnp.where(target_occluded, state.occlusion.occluded_frames + 1, 0)
    before_resampling = weighed_cloud(config, proposal.particles, lw)
    (particles, previous, flags), lw, resampled = rs.resample_if(
        k_res,
        lw,
        (proposal.particles, state.cloud.particles, post.flags),
        config.ess_threshold,
        rs.SCHEMES[config.resampler],
    )
    unoccluded = (jnp.max(vote) < 0.1) & ~lost
    new_state = RGBDState(
        cloud=Cloud(particles, previous, lw),
        flags=flags,
        colour=colour,
        depth=depth,
        body=body,
        background=background,
        occlusion=OcclusionTrack(
            vote,
            occluded_frames.astype(jnp.int32),
            jnp.where(unoccluded, est[2:4], state.occlusion.visible_size),
        ),
        estimate=est,
        fill_shift=state.fill_shift,
    )
    info = RGBDInfo(
        box=report,
        lost=lost,
        ess=ess,
        log_evidence=log_evidence,
        estimate=est,
        windowed=terms.windowed,
        vote=vote,
        target_occluded=target_occluded,
        resampled=resampled,
        weights_invalid=invalid,
        weighed_cloud=before_resampling,
    )
    return new_state, info


@memoised_build
def build_rgbd_filter(config: RGBDConfig) -> Filter:
    """The RGB-D box filter's ``Filter(init, step)`` for a static ``config``; ``init`` reads
    ``context.background``."""

    def init(params, key, frame, box, context=None):
        return rgbd_init(config, params, key, frame, box, context)

    def step(params, key, state, frame):
        return rgbd_step(config, params, key, state, frame)

    return Filter(init, step)
