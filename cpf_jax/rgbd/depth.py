"""The target's depth: per-cell depth templates that move with it (an alpha-beta filter
on their mean), age while unseen, and decide which pixels may be the target's.

Each step first predicts every known template by the depth velocity ``v``; the update
(gain ``depth.rate``, eq. 7, in the cells voted visible) corrects ``v`` by
``velocity_rate`` times the mean innovation of the updated cells, and ``v`` fades by
``velocity_fade`` per frame in which nothing is updated (a hidden person may stop or turn
round). A template not updated for ``age`` frames may be ``speed x age`` mm off (up to
``max_drift``): the depth Gaussian and the occluder margin widen by that much, and the
target gate by ``speed`` per frame hidden or stale (up to ``target.drift_max``). Depth
decides who occludes whom (paper 2.5): templates learn only from pixels not nearer than
the target by more than the occluder margin, unless nothing is seen at the templates'
own depth while they are stale, and pixels at the remembered occluder's depth are never
the target's by drift alone.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.observe import Observation, cell_statistics
from cpf_jax.rgbd.params import RGBDParams

__all__ = [
    "MAX_DEPTH_AGE",
    "DepthTemplate",
    "depth_template_init",
    "depth_template_predict",
    "depth_template_update",
    "mean_known_depth",
    "occluder_margin",
    "depth_tolerance",
    "search_drift",
    "target_gate",
    "target_like",
    "at_occluder",
    "remember_occluder",
]

#: Frames at which a cell's age saturates; a cell with no template counts as this stale,
#: the widest gate (``speed x MAX_DEPTH_AGE`` exceeds ``drift_max`` at the defaults).
MAX_DEPTH_AGE = 100.0


class DepthTemplate(NamedTuple):
    depth: Array  # [C] mm, 0 = unknown
    age: Array  # [C] frames since each template was last updated
    velocity: Array  # mm per frame, the target's estimated motion in depth
    # px mm: the initial box's height times its depth (0: unknown); reach / z is the
    # height the initial view of the target has at depth z.
    reach: Array
    # mm: median depth of the last occluder seen in front of the target (0: none yet).
    occluder: Array


def mean_known_depth(depth: Array) -> Array:
    """Mean of the known (``> 0``) entries of ``depth [..., C]`` (mm; 0: none)."""
    have = depth > 0
    total = jnp.sum(jnp.where(have, depth, 0.0), axis=-1)
    return total / jnp.maximum(jnp.sum(have, axis=-1), 1)


def depth_template_init(medians: Array, box: Array) -> DepthTemplate:
    """Templates from the initial box's cell medians ``[C]``."""
    c = medians.shape[0]
    zero = jnp.zeros((), jnp.float32)
    reach = box[3] * mean_known_depth(medians)
    return DepthTemplate(medians, jnp.zeros((c,), jnp.float32), zero, reach, zero)


def depth_template_predict(config: RGBDConfig, t: DepthTemplate) -> DepthTemplate:
    """Every known template one frame ahead by the depth velocity (at least the near end
    of ``depth_range``)."""
    depth = jnp.where(t.depth > 0, jnp.maximum(t.depth + t.velocity, config.depth_range[0]), 0.0)
    return t._replace(depth=depth)


def occluder_margin(params: RGBDParams, z: Array) -> Array:
    """How much nearer (mm) than depth ``z`` a pixel or cell must be to be an occluder."""
    return jnp.maximum(params.occlusion.margin, params.occlusion.margin_rel * z)


def depth_tolerance(params: RGBDParams, z: Array) -> Array:
    """Depth tolerance (mm) of "a pixel at depth ``z``" for fresh templates."""
    return jnp.maximum(params.target.gate, params.target.gate_rel * z)


def search_drift(params: RGBDParams, t: DepthTemplate, occluded_frames: Array) -> Array:
    """How far (mm) the target may have moved in depth since its templates last learnt:
    ``speed`` per frame hidden or stale, up to ``drift_max`` (a target found again by
    colour keeps the wide gate until its templates learn its depth)."""
    stale = jnp.min(jnp.where(t.depth > 0, t.age, MAX_DEPTH_AGE))
    hidden_for = jnp.maximum(occluded_frames.astype(jnp.float32), stale)
    return jnp.minimum(params.depth.speed * hidden_for, params.target.drift_max)


def target_gate(
    params: RGBDParams,
    t: DepthTemplate,
    occluded_frames: Array,
    target_z: Array,
    drift: bool = True,
) -> Array:
    """Depth tolerance (mm) of "a pixel of the target", widened by ``search_drift``
    (``drift=False``: the tolerance of fresh templates)."""
    base = depth_tolerance(params, target_z)
    return base + search_drift(params, t, occluded_frames) if drift else base


def at_occluder(params: RGBDParams, t: DepthTemplate, z: Array) -> Array:
    """Depths ``z`` within the depth tolerance of the remembered occluder's depth."""
    occ = t.occluder
    return (occ > 0) & (jnp.abs(z - occ) < depth_tolerance(params, occ))


def target_like(
    params: RGBDParams, t: DepthTemplate, occluded_frames: Array, z: Array, target_z: Array
) -> tuple[Array, Array]:
    """``(like, tight)`` of depths ``z``: ``tight`` within the gate of fresh templates,
    ``like`` adds those within the stale drift that are not at the occluder's depth (after
    a long occlusion the occluder is nearer than the target by less than the drift)."""
    tight = jnp.abs(z - target_z) < target_gate(params, t, occluded_frames, target_z, False)
    wide = jnp.abs(z - target_z) < target_gate(params, t, occluded_frames, target_z)
    return tight | (wide & ~at_occluder(params, t, z)), tight


def remember_occluder(params: RGBDParams, t: DepthTemplate, medians: Array) -> Array:
    """The occluder depth to remember: the mean median of the estimate's cells ``[C]``
    nearer than the templates by more than the occluder margin (else the last one)."""
    z_pred = mean_known_depth(t.depth)
    near_cut = z_pred - occluder_margin(params, z_pred)
    occ_cell = (z_pred > 0) & (medians > 0) & (medians < near_cut)
    return jnp.where(
        jnp.any(occ_cell),
        jnp.sum(jnp.where(occ_cell, medians, 0.0)) / jnp.maximum(jnp.sum(occ_cell), 1),
        t.occluder,
    )


def _gated(
    params: RGBDParams,
    t: DepthTemplate,
    occluded_frames: Array,
    obs: Observation,
    depth: Array,
    held: Array,
) -> Observation:
    """The observation with the depth samples of occluders removed: pixels nearer than the
    predicted target by more than the occluder margin, widened by the drift (and at the
    occluder's depth) when nothing is seen at the templates' own depth."""
    z_pred = mean_known_depth(t.depth)
    near_cut = z_pred - occluder_margin(params, z_pred)
    drift = search_drift(params, t, occluded_frames)
    z_frame = depth.astype(jnp.float32)
    widen = held < params.target.min_coverage
    cut = (z_frame < near_cut - jnp.where(widen, drift, 0.0)) | (
        widen & (z_frame < near_cut) & at_occluder(params, t, z_frame)
    )
    return obs._replace(
        depth_bins=jnp.where((z_pred > 0) & (z_frame > 0) & cut, -1, obs.depth_bins)
    )


def depth_template_update(
    config: RGBDConfig,
    params: RGBDParams,
    t: DepthTemplate,
    occluded_frames: Array,
    obs: Observation,
    depth: Array,
    estimate: Array,
    ok: Array,
    held: Array,
) -> DepthTemplate:
    """Eq. 7 on the depth templates of the cells ``ok [C]`` (voted visible, target found)
    whose occluder-free median moved by less than the occluder margin plus the drift (a
    larger jump is an occluder); the other known templates follow the updated cells' mean
    change (the body moves in depth as a whole); then the velocity correction."""
    if not config.template_update:
        return t
    _, med, total = cell_statistics(
        config, _gated(params, t, occluded_frames, obs, depth, held), estimate
    )
    dp = params.depth
    dt = t.depth
    drift = search_drift(params, t, occluded_frames)
    jump = jnp.abs(med - dt) < (
        occluder_margin(params, dt)
        + jnp.maximum(jnp.minimum(dp.speed * t.age, dp.max_drift), drift)
    )
    d_ok = ok & (total >= config.min_depth_count) & ((dt <= 0) | jump)
    updated = jnp.where(dt > 0, (1.0 - dp.rate) * dt + dp.rate * med, med)
    moved = d_ok & (dt > 0)
    n_moved = jnp.maximum(jnp.sum(moved), 1)
    shift = jnp.sum(jnp.where(moved, updated - dt, 0.0)) / n_moved
    follow = (~d_ok) & (dt > 0) & jnp.any(moved)
    new_depth = jnp.where(d_ok, updated, jnp.where(follow, dt + shift, dt))
    age = jnp.where(d_ok | follow, 0.0, jnp.minimum(t.age + 1.0, MAX_DEPTH_AGE))
    innovation = jnp.sum(jnp.where(moved, med - dt, 0.0)) / n_moved
    velocity = jnp.where(
        jnp.any(moved),
        t.velocity + dp.velocity_rate * innovation,
        (1.0 - dp.velocity_fade) * t.velocity,
    )
    velocity = jnp.clip(velocity, -dp.max_drift, dp.max_drift)
    return t._replace(depth=new_depth, age=age, velocity=velocity)
