"""The box the RGB-D filter reports (``info.box``, what metrics score).

``report="pixels"`` (default): the tight box of the target's pixels (foreground within
the target gate of the depth templates) in and around the estimate, keeping only the main
run of columns and of rows (lines at most ``report.gap`` times the estimate's size apart):
stray foreground at the target's depth among the furniture must not stretch it.
``"cells"`` (grid-occlusion): the union of the cells voted visible. ``"box"``: the
estimate. ``grid-occlusion`` reports no box (``info.lost``) when every cell is voted
occluded or the target's pixels cover less than ``target.min_coverage`` of the estimate,
as CLEAR-MOT asks of a tracker whose target is hidden.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels.cells import grid_cells
from cpf_jax.kernels.histogram import batch_all
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.observe import Observation
from cpf_jax.rgbd.params import ReportParams
from cpf_jax.rgbd.proposal import target_pixels

__all__ = ["Extent", "kept_lines", "main_run", "target_extent", "reported_box"]


class Extent(NamedTuple):
    box: Array  # [4] xywh tight box of the target's pixels (the estimate when none)
    coverage: Array  # target pixels found / the estimate's area (about 0 when hidden)
    held: Array  # the same with the gate of fresh templates (the target is where expected)


def kept_lines(counts: Array, min_pixels: Array) -> Array:
    """``counts [L]`` target pixels per column (row) -> ``[L]`` bool: the line has one and
    the line with its two neighbours holds ``min_pixels`` (isolated noise drops out, a
    1 px wide limb at an occluder's edge stays)."""
    window = jnp.convolve(counts, jnp.ones((3,), counts.dtype), mode="same")
    return (counts > 0) & (window >= min_pixels)


def main_run(counts: Array, kept: Array, gap: Array) -> Array:
    """``[L]`` bool: the kept lines of the run holding the most target pixels, kept lines at
    most ``gap`` apart forming one run (an arm or a leg a few lines off stays in it)."""
    idx = jnp.arange(counts.shape[0], dtype=jnp.float32)
    last = jax.lax.cummax(jnp.where(kept, idx, -jnp.inf))
    prev = jnp.concatenate([jnp.full((1,), -jnp.inf), last[:-1]])  # last kept line before
    start = kept & (idx - prev > gap)
    run = jnp.cumsum(start.astype(jnp.int32)) - 1  # run index of every line (-1: none yet)
    run = jnp.where(kept, run, counts.shape[0])  # not kept: an unused segment
    totals = jax.ops.segment_sum(counts, run, num_segments=counts.shape[0] + 1)
    return kept & (run == jnp.argmax(totals[:-1]))


def _line_counts(like: Array, tight: Array, inside: Array) -> tuple[Array, Array, Array]:
    """Target pixels ``like & inside`` ``[h, w]`` per column ``[w]`` and per row ``[h]``, and
    those also ``tight`` (their sum)."""
    t = (like & inside).astype(jnp.float32)
    return jnp.sum(t, axis=0), jnp.sum(t, axis=1), jnp.sum(t * tight)


def _search_counts(like: Array, tight: Array, bounds: Array, window) -> tuple[Array, Array, Array]:
    """``_line_counts`` of the pixels whose centres lie in ``bounds = (x0, y0, x1, y1)``,
    over the frame or, when they all lie in one, over a window of static shape ``(h, w)``
    placed on them (``lax.cond``). Counts of pixels are exact whatever the order of the
    sums, so both give the same numbers; the window spares the frame-wide passes."""
    height, width = like.shape
    x0, y0, x1, y1 = (bounds[i] for i in range(4))

    def inside(rows: Array, cols: Array) -> Array:
        rows = rows.astype(jnp.float32) + 0.5
        cols = cols.astype(jnp.float32) + 0.5
        return ((rows >= y0) & (rows < y1))[:, None] & ((cols >= x0) & (cols < x1))[None]

    def frame(_):
        return _line_counts(like, tight, inside(jnp.arange(height), jnp.arange(width)))

    if window is None:
        return frame(None)
    wh, ww = min(window[0], height), min(window[1], width)
    # Rows and columns that may hold an inside centre, a line wider on each side than the
    # bounds' rounding can reach; empty when last < first.
    r0, c0 = jnp.maximum(jnp.floor(y0) - 1, 0), jnp.maximum(jnp.floor(x0) - 1, 0)
    r1, c1 = jnp.minimum(jnp.ceil(y1) + 1, height - 1), jnp.minimum(jnp.ceil(x1) + 1, width - 1)
    oy = jnp.clip(r0, 0, height - wh).astype(jnp.int32)
    ox = jnp.clip(c0, 0, width - ww).astype(jnp.int32)
    fits = ((r1 < r0) | (r1 < oy + wh)) & ((c1 < c0) | (c1 < ox + ww))

    def windowed(_):
        cut = [jax.lax.dynamic_slice(a, (oy, ox), (wh, ww)) for a in (like, tight)]
        cols, rows, held = _line_counts(*cut, inside(oy + jnp.arange(wh), ox + jnp.arange(ww)))
        cols = jax.lax.dynamic_update_slice(jnp.zeros((width,), jnp.float32), cols, (ox,))
        rows = jax.lax.dynamic_update_slice(jnp.zeros((height,), jnp.float32), rows, (oy,))
        return cols, rows, held

    return jax.lax.cond(batch_all(fits), windowed, frame, None)


def target_extent(params, state, obs: Observation, depth: Array, est: Array, window=None) -> Extent:
    """The target's pixels in the estimate ``[4]`` grown by ``report.margin`` per side:
    their tight box (main runs of lines with ``report.min_pixels``), coverage and held
    coverage (``Extent``). Pixels without depth are left out: at depth edges and on dark
    hair they cannot be told from an occluder's. They are counted in a static ``window =
    (h, w)`` placed on the search area when it holds it (else over the frame)."""
    rp: ReportParams = params.report
    height, width = depth.shape
    like, tight = target_pixels(params, state, obs, depth)
    m = rp.margin
    x0 = est[0] - m * est[2]
    y0 = est[1] - m * est[3]
    x1 = est[0] + est[2] * (1 + m)
    y1 = est[1] + est[3] * (1 + m)
    cols = jnp.arange(width, dtype=jnp.float32) + 0.5
    rows = jnp.arange(height, dtype=jnp.float32) + 0.5
    col_count, row_count, n_held = _search_counts(like, tight, jnp.stack([x0, y0, x1, y1]), window)
    held = n_held / jnp.maximum(est[2] * est[3], 1.0)
    col_n = main_run(col_count, kept_lines(col_count, rp.min_pixels), rp.gap * est[2])
    row_n = main_run(row_count, kept_lines(row_count, rp.min_pixels), rp.gap * est[3])
    ok = jnp.any(col_n) & jnp.any(row_n)
    coverage = jnp.sum(col_count) / jnp.maximum(est[2] * est[3], 1.0)
    big = jnp.float32(1e9)
    bx0 = jnp.min(jnp.where(col_n, cols - 0.5, big))
    bx1 = jnp.max(jnp.where(col_n, cols + 0.5, -big))
    by0 = jnp.min(jnp.where(row_n, rows - 0.5, big))
    by1 = jnp.max(jnp.where(row_n, rows + 0.5, -big))
    box = jnp.where(ok, jnp.stack([bx0, by0, bx1 - bx0, by1 - by0]), est)
    return Extent(box, coverage, held)


def reported_box(config: RGBDConfig, est: Array, extent: Extent, voted: Array) -> Array:
    """``info.box`` of ``config.report`` from the estimate, the target's extent and the
    cells voted occluded ``[C]``."""
    if config.report == "pixels":
        return extent.box
    if config.occlusion and config.report == "cells":
        cells = grid_cells(est, config.k)  # [C, 4]
        x0 = jnp.min(jnp.where(voted, jnp.inf, cells[:, 0]))
        y0 = jnp.min(jnp.where(voted, jnp.inf, cells[:, 1]))
        x1 = jnp.max(jnp.where(voted, -jnp.inf, cells[:, 0] + cells[:, 2]))
        y1 = jnp.max(jnp.where(voted, -jnp.inf, cells[:, 1] + cells[:, 3]))
        return jnp.where(jnp.all(voted), est, jnp.stack([x0, y0, x1 - x0, y1 - y0]))
    return est
