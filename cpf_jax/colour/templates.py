"""The colour layer's learnt state, each an ``init`` / ``update`` pair over its own
``NamedTuple``: the reference histograms, the contrast weights (learnt once), the layout
template and the estimate's smoothed velocity that guides the random walk."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.colour.appearance import (
    contrast_weights,
    layout_vectors,
    mixture_weights,
    reference_histogram,
)
from cpf_jax.colour.config import ColourConfig
from cpf_jax.colour.params import ContrastParams, LayoutParams, TemplateParams
from cpf_jax.kernels.histogram import normalise_counts
from cpf_jax.types import Frame

__all__ = [
    "ContrastModel",
    "contrast_model_init",
    "HistogramTemplate",
    "histogram_template_init",
    "histogram_template_update",
    "LayoutTemplate",
    "layout_template_init",
    "layout_template_update",
    "Guide",
    "guide_init",
    "guide_update",
]


class ContrastModel(NamedTuple):
    weights: Array  # [B] per-bin contrast weight (zeros without the contrast term)


def contrast_model_init(
    config: ColourConfig, params: ContrastParams, frame: Frame, box: Array
) -> ContrastModel:
    """The per-bin weights of ``config.contrast`` from the initial box and its surround."""
    if config.contrast is None:
        return ContrastModel(jnp.zeros((config.n_bins,), jnp.float32))
    if config.contrast == "mixture":
        return ContrastModel(
            mixture_weights(frame, box, config.bins, config.surround_margin, params.fill_ratio)
        )
    return ContrastModel(
        contrast_weights(
            frame, box, config.bins, config.surround_margin, params.threshold, config.unseen
        )
    )


class HistogramTemplate(NamedTuple):
    reference: Array  # [K, B] normalised histogram of each of the K stripes


def histogram_template_init(config: ColourConfig, frame: Frame, box: Array) -> HistogramTemplate:
    """The initial box's stripe histograms."""
    return HistogramTemplate(reference_histogram(frame, box, config.bins, config.parts))


def histogram_template_update(
    config: ColourConfig,
    params: TemplateParams,
    template: HistogramTemplate,
    estimate_histogram: Array,
    estimate_distance: Array,
    lost: Array,
) -> HistogramTemplate:
    """Blend the estimate's stripe histograms ``[K, B]`` in at ``params.rate`` while the
    target is found and the estimate still resembles the template (``max_distance``), so
    that a misplaced estimate does not teach the template its own error."""
    if not config.template_update:
        return template
    ok = (~lost) & (estimate_distance < params.max_distance)
    rate = jnp.where(ok, params.rate, 0.0)
    reference = (1.0 - rate) * template.reference + rate * estimate_histogram
    return HistogramTemplate(normalise_counts(reference))


class LayoutTemplate(NamedTuple):
    vector: Array  # [rows * cols * c] zero-mean, unit-norm cell means ([1] zeros: no layout)


def layout_template_init(config: ColourConfig, table: Array | None, box: Array) -> LayoutTemplate:
    """The initial box's layout vector from the layout feature's summed-area table."""
    if config.layout is None:
        return LayoutTemplate(jnp.zeros((1,), jnp.float32))
    return LayoutTemplate(layout_vectors(table, box, config.layout))


def layout_template_update(
    config: ColourConfig,
    params: LayoutParams,
    template: LayoutTemplate,
    table: Array | None,
    estimate: Array,
    lost: Array,
) -> LayoutTemplate:
    """Blend the estimate's layout vector in at ``params.rate`` (0 keeps the initial box's)
    while the target is found; the blend is renormalised."""
    if config.layout is None:
        return template
    rate = jnp.where(lost, 0.0, params.rate)
    blend = (1.0 - rate) * template.vector + rate * layout_vectors(table, estimate, config.layout)
    return LayoutTemplate(blend / jnp.maximum(jnp.sqrt(jnp.sum(blend * blend)), 1e-6))


class Guide(NamedTuple):
    velocity: Array  # [2] smoothed motion of the estimate's centre, px per frame


def guide_init() -> Guide:
    return Guide(jnp.zeros(2, jnp.float32))


def guide_update(
    config: ColourConfig,
    guide: Guide,
    previous: Array,
    estimate: Array,
    lost: Array,
    was_lost: Array,
) -> Guide:
    """Move the velocity ``velocity_rate`` of the way to the estimate's last centre
    displacement; zero when the target is lost now or was lost (no trustworthy motion)."""
    moved = (estimate[:2] + estimate[2:4] / 2) - (previous[:2] + previous[2:4] / 2)
    velocity = (1.0 - config.velocity_rate) * guide.velocity + config.velocity_rate * moved
    return Guide(jnp.where(lost | was_lost, 0.0, velocity))
