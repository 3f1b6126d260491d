"""What the RGB-D filter learns about the target's appearance, each an ``init`` / ``update``
pair over its own ``NamedTuple``: the cells' colour templates (paper eqs. 7-8) and a
whole-body colour template.

The cells' templates describe the first box's layout, which may say little about the
whole body later (a head and shoulders at 1 m, the whole man at 4 m). The body template
scores identity without layout: the pooled foreground colours of the visible cells
(``cells.body_log_likelihood``). It starts as the initial box's foreground histogram, is
a running mean of the reported boxes of the unoccluded frames among the first
``body.warmup`` steps (the first box may show part of the person), then forgets at
``body.rate``; frames with any cell voted (vote above 0.1) or lost teach it nothing.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels.histogram import bhattacharyya, normalise_counts
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.observe import Observation, body_histogram, cell_statistics
from cpf_jax.rgbd.params import BodyParams, CellColourParams

__all__ = [
    "CellColour",
    "cell_colour_init",
    "cell_colour_update",
    "BodyTemplate",
    "body_template_init",
    "body_template_update",
]


class CellColour(NamedTuple):
    histograms: Array  # [C, B] normalised histograms of the cells' foreground (+ background bin)


def cell_colour_init(config: RGBDConfig, obs: Observation, box: Array) -> CellColour:
    """The initial box's cell histograms."""
    hist, _, _ = cell_statistics(config, obs, box)
    return CellColour(hist)


def cell_colour_update(
    config: RGBDConfig,
    params: CellColourParams,
    template: CellColour,
    estimate_histograms: Array,
    ok: Array,
) -> CellColour:
    """Eq. 7 in the cells ``ok [C]`` (voted visible, target found) whose estimate still
    resembles the template (distance below ``colour.gate``: a misplaced estimate would
    teach the template its own error); other cells keep theirs (eq. 8). With the
    background bin only the colours adapt: each cell keeps its initial share of
    background, or a drifting box would learn to expect the background it drifted onto."""
    if not config.template_update:
        return template
    current = template.histograms
    hist = estimate_histograms
    est_d = bhattacharyya(hist, current)
    rate = jnp.where(ok & (est_d < params.gate), params.rate, 0.0)[:, None]
    if config.background_bin:
        fill = 1.0 - current[:, -1:]
        fg_new = normalise_counts(hist[:, :-1]) * fill
        hist = jnp.concatenate([fg_new, current[:, -1:]], axis=-1)
    return CellColour(normalise_counts((1.0 - rate) * current + rate * hist))


class BodyTemplate(NamedTuple):
    histogram: Array  # [B - 1] normalised foreground colour histogram of the whole target
    frames: Array  # int32 unoccluded frames learnt from (-1: the first box was empty)
    steps: Array  # int32 steps since init


def body_template_init(config: RGBDConfig, obs: Observation, box: Array) -> BodyTemplate:
    """The initial box's foreground histogram; an empty box counts for nothing (the first
    frame learnt replaces it)."""
    hist, count = body_histogram(config, obs, box)
    frames = jnp.where(count > 0, 0, -1).astype(jnp.int32)
    return BodyTemplate(hist, frames, jnp.zeros((), jnp.int32))


def body_template_update(
    config: RGBDConfig,
    params: BodyParams,
    template: BodyTemplate,
    obs: Observation,
    report: Array,
    vote: Array,
    lost: Array,
) -> BodyTemplate:
    """Learn from the reported box of an unoccluded frame (module docstring)."""
    steps = jnp.minimum(template.steps + 1, 1 << 30)
    if not config.body_term:
        return template._replace(steps=steps)
    body_hist, body_count = body_histogram(config, obs, report)
    learn = (~lost) & (jnp.max(vote) < 0.1) & (body_count >= params.min_pixels)
    warm = template.steps < params.warmup
    n_seen = template.frames.astype(jnp.float32)
    rate = jnp.maximum(1.0 / (n_seen + 2.0), params.rate)
    rate = jnp.where(warm, rate, params.rate)
    rate = jnp.where(learn, rate, 0.0)
    mixed = (1.0 - rate) * template.histogram + rate * body_hist
    histogram = mixed / jnp.maximum(jnp.sum(mixed), 1e-12)
    return BodyTemplate(histogram, template.frames + learn.astype(jnp.int32), steps)
