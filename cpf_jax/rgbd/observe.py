"""What the RGB-D filter reads from a frame: foreground against the background model
(paper 2.3), colour bins of the foreground, log-spaced depth bins, and the statistics of
one box's cells (templates, the estimate's cells, the whole body)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.colour.config import bin_index, n_bins_of
from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.background import Background, foreground_mask
from cpf_jax.kernels.cells import depth_bin_index, grid_cells, histogram_quantile
from cpf_jax.kernels.histogram import box_histograms, normalise_counts
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.params import ForegroundParams
from cpf_jax.types import Frame

__all__ = [
    "Observation",
    "as_background",
    "no_background",
    "observe",
    "cell_statistics",
    "body_histogram",
]


class Observation(NamedTuple):
    colour_bins: Array  # [H, W] int32; background pixels: the extra bin (or -1)
    depth_bins: Array  # [H, W] int32, -1 off the foreground or without depth
    foreground: Array  # [H, W] bool


def no_background(frame: Frame) -> Background:
    """A background model under which every pixel is foreground (its colour is -1000)."""
    h, w = frame.colour.shape[:2]
    return Background(jnp.full((h, w, 3), -1000.0, jnp.float32), jnp.zeros((h, w), jnp.float32))


def as_background(background: Background | None, frame: Frame) -> Background:
    """``background`` as float32 arrays, or ``no_background`` when there is none."""
    if background is None:
        return no_background(frame)
    return Background(
        jnp.asarray(background.colour, jnp.float32), jnp.asarray(background.depth, jnp.float32)
    )


def observe(
    config: RGBDConfig, params: ForegroundParams, frame: Frame, background: Background
) -> Observation:
    """Foreground mask, colour bins (background pixels in the extra bin) and depth bins."""
    fg = foreground_mask(
        frame.colour,
        frame.depth,
        background,
        depth_abs=params.depth_abs,
        depth_rel=params.depth_rel,
        colour_threshold=params.colour,
    )
    if config.side_scene is not None:
        # An unseen pixel without depth is nobody's: neither depth nor colour can tell.
        fg = fg & ~((background.colour[..., 0] < 0) & (frame.depth == 0))
    off = n_bins_of(config.bins) if config.background_bin else -1
    cbins = jnp.where(fg, bin_index(frame.colour, config.bins), off)
    dbins = depth_bin_index(frame.depth, fg, config.depth_bins, *config.depth_range)
    return Observation(cbins, dbins, fg)


def cell_statistics(
    config: RGBDConfig, obs: Observation, box_xywh: Array
) -> tuple[Array, Array, Array]:
    """Normalised colour histograms ``[C, B]``, median foreground depths ``[C]`` (mm, from
    the depth histogram) and depth sample counts ``[C]`` of one box's cells, each counted in
    a window of its own (``config.cell_window``) when they fit one, else in the histogram
    window when it holds the box."""
    rects = box_ops.xywh_to_rect(grid_cells(box_xywh, config.k))
    windows, each = config.count_windows, config.cell_window
    hist = box_histograms(obs.colour_bins, rects, config.n_bins, windows, each)
    dh = box_histograms(obs.depth_bins, rects, config.depth_bins, windows, each)
    med, total = histogram_quantile(dh, config.depth_bins, *config.depth_range)
    return normalise_counts(hist), med, total


def body_histogram(config: RGBDConfig, obs: Observation, box_xywh: Array) -> tuple[Array, Array]:
    """Normalised foreground colour histogram ``[B - 1]`` of one box and its pixel count."""
    rect = box_ops.xywh_to_rect(box_xywh)[None]
    hist = box_histograms(obs.colour_bins, rect, config.n_bins, config.count_windows)[0]
    fg = hist[: config.n_fg_bins]
    total = jnp.sum(fg)
    return fg / jnp.maximum(total, 1.0), total
