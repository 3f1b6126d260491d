"""Exact hue-saturation histograms of image rectangles and Bhattacharyya distances.

Conventions (those of ``cpf_jax.kernels.boxes``):

* ``bins``: ``[H, W] int32`` flat bin index per pixel (``color.hs_bin_index``).
  Pixels whose bin lies outside ``[0, n_bins)`` (e.g. ``-1``) are not counted,
  so a mask is applied by setting bins to ``-1``.
* ``rects``: ``[..., 4] (x0, y0, x1, y1) int32`` half-open pixel rectangles (or
  ``RectColumns``), clipped to the frame here; a rect outside the frame, or with
  ``x1 <= x0`` / ``y1 <= y0``, is empty.
* ``boxes``: ``[..., 4] (x, y, w, h) float32`` top-left boxes; they count the
  pixels of ``boxes.xywh_to_rect(boxes)`` (corners rounded with ``floor(v + 0.5)``).
* Histograms are exact pixel counts (``float32``), equal bin for bin to
  ``cv2.calcHist`` on the same clipped crop.

Bhattacharyya distance (thesis eq. 3.7), on histograms normalised to sum 1::

    d = sqrt(1 - sum_i sqrt(p_i q_i))

``bhattacharyya`` evaluates it in the equal Hellinger form
``sqrt(0.5 * sum_i (sqrt(p_i) - sqrt(q_i))^2)``: a sum of squares (never negative),
accurate near ``d = 0`` in float32 and with finite gradients.
``squared_bhattacharyya`` evaluates ``d^2 = 1 - sum_i sqrt(c_i) sqrt(q_i) / sqrt(n)``
from exact counts ``c`` of ``n`` pixels instead: two plain reductions that XLA fuses
with the corner gathers, whose float32 cancellation error stays below ``2e-6`` in
``d^2`` (the quantity a likelihood ``exp(-d^2 / 2 sigma^2)`` sees). An empty
histogram gives ``d = 1``, as ``cv2.compareHist(h1, h2, cv2.HISTCMP_BHATTACHARYYA)``
does (it normalises internally).

Windowed integral histograms (``rect_reduce``)
----------------------------------------------
An integral histogram ``T[y, x, b]`` (count of bin ``b`` in ``[0, x) x [0, y)``)
gives any rect's exact histogram from four corner rows, ``T[y1, x1] - T[y0, x1] -
T[y1, x0] + T[y0, x0]``. Building ``T`` is memory-bound, so with ``window=(wh, ww)``
it covers only a window of static shape whose origin is dynamic, placed over the
bounding rectangle of the non-empty rects (``window_origin``), and it counts in
``uint16``: modular arithmetic keeps the four-corner difference exact for every
rect of fewer than 65,536 pixels, whatever the table's own values. The table is
laid out ``[y, x, bins]`` so that each corner is one contiguous row; it is
prefix-summed along x in blocks and along y by an in-place row loop. The corner
rows are computed once, corner-major, then gathered and reduced in sequential
chunks of ``chunk`` rects, so that no ``[N, n_bins]`` block exists.

Exactness is never traded for speed. When some non-empty rect is not inside the
window, or has 65,536 pixels or more, ``fallback=True`` switches with ``lax.switch``
to the next window of ``window_ladder`` that covers them (the window grown, a table
of more pixels), and past the last one to the general path: one full-frame table,
in ``uint16`` with each rect cut into the few pieces that keep every piece under
65,536 pixels, or in ``uint32`` with whole rects from ``WIDE_COUNTS_MIN_RECTS``
rects on. The predicates go through ``batch_all``, so that under ``vmap`` the
``switch`` stays a branch and only the path taken runs. ``fallback=False`` skips
the check and counts each rect's intersection with the window (exact for the rects
inside it, which ``window_covers`` tells); ``window=None`` is the general path
directly. ``suggest_window`` sizes a window for a cloud of particle boxes.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax import Array, lax

from .boxes import clip_rect

__all__ = [
    "DEFAULT_BINS",
    "integral_image",
    "rect_sums",
    "grid_sums",
    "grid_ncc",
    "window_origin",
    "window_covers",
    "window_ladder",
    "window_sizes",
    "batch_all",
    "uses_window",
    "suggest_window",
    "DEFAULT_CHUNK",
    "rect_reduce",
    "RectColumns",
    "rect_columns",
    "box_histograms",
    "normalise_counts",
    "squared_bhattacharyya",
    "bhattacharyya",
]

#: Default (h_bins, s_bins): 8x8 = 64 bins. 16x16 quadruples the integral table (not
#: the gathers); the two are different likelihoods, not approximations of each other.
DEFAULT_BINS: tuple[int, int] = (8, 8)

_U16_LIMIT = 1 << 16

#: The window ladder (``window_ladder``): when the rects leave the configured window,
#: ``rect_reduce`` tries windows grown by this factor per side, at most this many in all,
#: each smaller than this share of the frame, before the whole-frame path. A table's
#: cost is proportional to its pixels, so a cloud a little wider than the window pays a
#: little more rather than the whole frame; two rungs of 1.25 reach about as far as one
#: of 1.6 and give the clouds in between a table a fifth smaller.
LADDER_GROWTH = 1.25
LADDER_RUNGS = 3
LADDER_MAX_SHARE = 0.85

#: Rects per sequential chunk: bounds the ``[chunk, n_bins]`` temporaries, which
#: unchunked would be fresh pages on every call. 4096 keeps a chunk's integer counts
#: (4096 boxes x 2 parts x 72 bins x 2 bytes = 1.2 MB) in a 2 MB L2 cache; a GPU
#: wants larger chunks (pass ``chunk``).
DEFAULT_CHUNK = 4096

#: From this many rects (static: N x parts) the whole-frame path counts with a uint32
#: table, one piece per rect, instead of a uint16 table whose rects are cut into the
#: pieces that keep each count under 65,536 (4 on a 512 x 424 frame). The uint32 table
#: costs more to build and the pieces multiply the corner gathers, so that uint32 pays
#: only for many rects; the two tie near 40,000 rects. The counts are the same either way.
WIDE_COUNTS_MIN_RECTS = 65_536

#: Up to this many rects (static), ``box_histograms`` counts each rect by a masked
#: scatter-add over the frame, which for a few rects costs less than building the
#: full-frame integral histogram.
SCATTER_MAX_RECTS = 16


# ----------------------------------------------------------------------------- integral table


def _prefix_sums_yx(table: Array) -> Array:
    """In-place 2D prefix sums of ``table [h + 1, w + 1, c]`` (row 0 / column 0 are zero):
    the reference loops of ``integral_image(method="loop")``.

    Rows first (each step adds one contiguous row to the next), then columns: XLA
    updates the loop-carried buffer in place, and the column pass reads rows already
    summed, in cache order.
    """

    def along_x(x, t):
        col = lax.dynamic_slice_in_dim(t, x, 1, axis=1) + lax.dynamic_slice_in_dim(
            t, x + 1, 1, axis=1
        )
        return lax.dynamic_update_slice_in_dim(t, col, x + 1, axis=1)

    table = _prefix_rows(table)
    return lax.fori_loop(0, table.shape[1] - 1, along_x, table)


def _prefix_rows(table: Array) -> Array:
    """In-place prefix sums of ``table [h + 1, ...]`` along its first axis (row 0 stays as
    it is): one ``fori_loop`` step adds each contiguous row to the next."""

    def along_y(y, t):
        row = lax.dynamic_slice_in_dim(t, y, 1, axis=0) + lax.dynamic_slice_in_dim(
            t, y + 1, 1, axis=0
        )
        return lax.dynamic_update_slice_in_dim(t, row, y + 1, axis=0)

    return lax.fori_loop(0, table.shape[0] - 1, along_y, table)


#: Block length of the blocked prefix sums (``_cumsum``): longer blocks cost more adds
#: per element (up to ``block``), shorter ones a longer loop over the block totals.
PREFIX_BLOCK = 8


def _cumsum(x: Array, axis: int, block: int = PREFIX_BLOCK) -> Array:
    """Inclusive prefix sum of ``x`` along ``axis``, blocked for XLA on CPU.

    The axis is cut into blocks of ``block`` (zero-padded at the end when it does
    not divide the length). The block totals are summed in one pass, their
    exclusive prefix is a loop over the (``block`` times shorter) totals, and one
    last fused, vectorised pass writes each block as an unrolled chain of adds on
    top of its offset (an element at position ``k`` in its block costs ``k + 1``
    adds). ``jnp.cumsum`` lowers to a quadratic ``reduce_window`` on CPU. The
    totals' prefix is a loop because XLA fuses a chain of adds into the last pass
    and recomputes it for every element. Integer sums are exact (unsigned ones
    modulo 2^bits, in any order); float sums round differently from a sequential loop.
    """
    n = x.shape[axis]
    pad = -n % block
    if pad:
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, pad)
        x = jnp.pad(x, widths)
    n_blocks = x.shape[axis] // block
    xb = x.reshape(x.shape[:axis] + (n_blocks, block) + x.shape[axis + 1 :])
    totals = jnp.sum(xb, axis=axis + 1, dtype=x.dtype)  # [..., n_blocks, ...]

    def link(b, before):
        row = lax.dynamic_slice_in_dim(before, b - 1, 1, axis)
        row = row + lax.dynamic_slice_in_dim(totals, b - 1, 1, axis)
        return lax.dynamic_update_slice_in_dim(before, row, b, axis)

    before = lax.fori_loop(1, n_blocks, link, jnp.zeros_like(totals))
    acc = jnp.expand_dims(before, axis + 1)
    parts = []
    for k in range(block):
        acc = acc + lax.index_in_dim(xb, k, axis + 1)
        parts.append(acc)
    out = lax.concatenate(parts, axis + 1).reshape(x.shape)
    return lax.slice_in_dim(out, 0, n, axis=axis) if pad else out


def _materialise(x: Array, bands: int = 4) -> Array:
    """``x`` copied band by band (rows) in a loop: the result is a buffer of its own.

    XLA fuses cheap producers (a ``dynamic_slice`` of the frame, a one-hot, a
    per-pixel weight look-up) into every consumer. The blocked prefix sums read
    their input twice, in passes whose vectorisation the fused index arithmetic of
    such a producer defeats. A loop boundary stops the fusion, which
    ``lax.optimization_barrier`` does not on XLA:CPU. Bands overlap at the end when
    ``bands`` does not divide the rows.
    """
    h = x.shape[0]
    bands = max(1, min(bands, h))
    band = -(-h // bands)

    def copy(i, out):
        start = jnp.minimum(i * band, h - band)
        return lax.dynamic_update_slice_in_dim(
            out, lax.dynamic_slice_in_dim(x, start, band, 0), start, 0
        )

    return lax.fori_loop(0, bands, copy, jnp.zeros_like(x))


def _integral(values: Array) -> Array:
    """``[h, w, c]`` -> ``[h + 1, w + 1, c]`` 2D exclusive prefix sums (row 0 and column 0
    zero) in the dtype of ``values``: blocked prefix sums along x (``_cumsum``), then
    the zero row and column, then the in-place row loop along y
    (``_prefix_rows``, also ``_prefix_sums_yx``'s first pass).

    The row loop comes last so that the table is a buffer of its own: XLA fuses a
    cheap last pass into every consumer (the corner gathers), recomputing it per
    gathered count.
    """
    return _prefix_rows(jnp.pad(_cumsum(values, 1), ((1, 0), (1, 0), (0, 0))))


#: Ways to build an integral table (``integral_image``): blocked prefix sums, or the
#: reference row and column loops; equal bit for bit on integers.
TABLE_METHODS = ("blocked", "loop")


def _check_method(method: str) -> None:
    if method not in TABLE_METHODS:
        raise ValueError(f"method must be one of {TABLE_METHODS}, got {method!r}")


#: The integral histogram's channel axis is stored padded with empty channels to a
#: multiple of this many bytes (``_table_channels``), so that the row loop's copies and
#: adds run on whole vectors: XLA:CPU compiles a ``[1, 289, 72]`` uint16 row as scalar
#: code and a ``[1, 289, 80]`` one as vector code.
TABLE_ROW_ALIGN = 32


def _table_channels(n_bins: int, dtype) -> int:
    """Channels of a stored integral histogram: ``n_bins`` padded to ``TABLE_ROW_ALIGN``."""
    per = max(1, TABLE_ROW_ALIGN // jnp.dtype(dtype).itemsize)
    return -(-n_bins // per) * per


def _histogram_table(bins: Array, n_bins: int, dtype) -> Array:
    """``[h, w] int32`` bins -> ``[h + 1, w + 1, channels]`` integral histogram in ``dtype``:
    ``T[y, x, b]`` = number of pixels of bin ``b`` in ``[0, x) x [0, y)``, modulo 2^bits.

    The channels are ``n_bins`` padded to ``_table_channels``; the padding channels
    count nothing. This is the form the corner gathers read (``_corner_counts``).
    """
    channels = _table_channels(n_bins, dtype)

    def one_hot(b: Array) -> Array:
        if channels > n_bins:
            # Bins outside [0, n_bins) count nowhere, also not in the padding channels.
            b = jnp.where((b >= 0) & (b < n_bins), b, -1)
        return (b[..., None] == jnp.arange(channels, dtype=b.dtype)).astype(dtype)

    return _integral(one_hot(_materialise(bins)))


def integral_image(values: Array, method: str = "blocked") -> Array:
    """``[h, w, c]`` values -> ``[h+1, w+1, c]`` summed-area tables (``T[y, x]`` = sum over
    ``[0, x) x [0, y)``), in the dtype of ``values``. Integer values give exact sums
    (int32: while the frame's total magnitude stays below 2^31). ``method``: ``"blocked"``
    (``_integral``) or ``"loop"`` (the row and column loops of ``_prefix_sums_yx``); float
    sums round differently."""
    _check_method(method)
    if method == "loop":
        return _prefix_sums_yx(jnp.pad(values, ((1, 0), (1, 0), (0, 0))))
    return _integral(_materialise(values))


def _take(table: Array, idx: Array, channels: int | None = None) -> Array:
    """``table[idx]`` (``table[idx, :channels]`` when ``channels`` is given) for flat row
    indices ``idx`` that are in range by construction: no bounds handling and no wrap
    of negative indices (``jnp`` indexing otherwise adds a compare and select per index
    inside the gather's fusion). Bit-identical to plain indexing for in-range indices."""
    at = table.at[idx] if channels is None else table.at[idx, :channels]
    return at.get(mode="promise_in_bounds", wrap_negative_indices=False)


def rect_sums(
    table: Array, rects: Array, channels: int | None = None, chunk: int | None = None
) -> Array:
    """Sums ``[..., c]`` of the values under ``rects [..., 4] (x0, y0, x1, y1)`` (or
    ``RectColumns``) from an ``integral_image`` table ``[h+1, w+1, c]``; rects are clipped
    to the frame (an empty or outside rect sums to 0). ``channels`` (static): only the
    first ``channels`` of the table's channels are read and summed. ``chunk`` (static):
    gather in sequential blocks of that many rects along the first axis (``_chunked``),
    whose corner rows are then computed once and handed to the gathers as buffers
    (unchunked, XLA:CPU fuses the rounding and clipping into the gathers); ``None``:
    all at once. The sums are the same either way."""
    height, width = table.shape[0] - 1, table.shape[1] - 1
    r = _clip_columns(rect_columns(rects), width, height)
    # Flat corner rows, materialised once (see _corner_index): fused, XLA would redo the
    # index arithmetic for every channel of every corner.
    idx = _corner_index(r, width + 1)
    flat = table.reshape(-1, table.shape[-1])

    def sums(i0: Array, i1: Array, i2: Array, i3: Array) -> Array:
        return (
            _take(flat, i0, channels)
            - _take(flat, i1, channels)
            - _take(flat, i2, channels)
            + _take(flat, i3, channels)
        )

    if chunk is None or idx[0].ndim == 0:
        return sums(*idx)
    return _chunked(sums, idx, chunk, (0, 0, 0, 0), carry_inputs=True)


def _lattice_edges(
    boxes: Array, rows: int, cols: int, height: int, width: int, box_axis_last: bool = False
) -> tuple[Array, Array]:
    """Cell edges ``ys [..., rows + 1]`` and ``xs [..., cols + 1]`` (int32) of a ``rows x
    cols`` grid of equal cells of each ``(x, y, w, h)`` box in ``boxes [..., 4]``: rounded
    like ``boxes.xywh_to_rect`` (``floor(v + 0.5)``) and clipped to a ``height x width``
    frame. ``box_axis_last``: ``[rows + 1, ...]`` and ``[cols + 1, ...]`` instead (built
    in that layout: a transposed copy costs more than the edges)."""
    if isinstance(boxes, (tuple, list)):  # (x, y, w, h) columns
        x, y, w, h = (jnp.asarray(c, jnp.float32) for c in boxes)
    else:
        b = jnp.asarray(boxes, jnp.float32)
        x, y, w, h = b[..., 0], b[..., 1], b[..., 2], b[..., 3]

    def edges(start: Array, size: Array, n: int, limit: int) -> Array:
        f = jnp.arange(n + 1, dtype=jnp.float32) / n
        if box_axis_last:
            v = start[None] + size[None] * f.reshape(-1, *([1] * start.ndim))
        else:
            v = start[..., None] + size[..., None] * f
        return jnp.clip(jnp.floor(v + 0.5), 0, limit).astype(jnp.int32)

    return edges(y, h, rows, height), edges(x, w, cols, width)


def grid_sums(table: Array, boxes: Array, rows: int, cols: int) -> tuple[Array, Array]:
    """Sums ``[..., rows, cols, c]`` over a ``rows x cols`` grid of equal cells of each
    ``(x, y, w, h)`` box in ``boxes [..., 4]``, from an ``integral_image`` table
    ``[h+1, w+1, c]``, and the cells' pixel counts ``[..., rows, cols]`` (as a second
    output).

    Cell edges are rounded like ``boxes.xywh_to_rect`` (``floor(v + 0.5)``) and
    clipped to the frame, so the cells partition the box's clipped rect exactly;
    a cell outside the frame is empty (sum 0, count 0). The ``(rows + 1) x
    (cols + 1)`` lattice corners are gathered once and shared by neighbouring
    cells (instead of ``4 rows cols`` corner reads per box).
    """
    height, width = table.shape[0] - 1, table.shape[1] - 1
    ys, xs = _lattice_edges(boxes, rows, cols, height, width)
    idx = lax.optimization_barrier(ys[..., :, None] * (width + 1) + xs[..., None, :])
    flat = table.reshape(-1, table.shape[-1])
    corners = _take(flat, idx)  # [..., rows + 1, cols + 1, c]
    sums = (
        corners[..., 1:, 1:, :]
        - corners[..., :-1, 1:, :]
        - corners[..., 1:, :-1, :]
        + corners[..., :-1, :-1, :]
    )
    counts = (ys[..., 1:] - ys[..., :-1])[..., :, None] * (xs[..., 1:] - xs[..., :-1])[..., None, :]
    return sums, counts


def grid_ncc(
    table: Array,
    boxes: Array,
    template: Array,
    rows: int,
    cols: int,
    chunk: int | None = DEFAULT_CHUNK,
) -> Array:
    """Normalised cross-correlation ``[N]`` of each box's ``rows x cols`` cell means with
    ``template``, for ``boxes [N, 4] (x, y, w, h)`` (or a tuple of those four ``[N]``
    columns) and an ``integral_image`` table
    ``[h+1, w+1, c]``; ``[N, T]`` for ``T`` templates ``[T, rows * cols * c]`` (the cell
    means are computed once).

    ``template [rows * cols * c]`` is zero-mean and unit-norm, cells row-major and
    channels last (as ``colour.layout_vectors`` makes them). The result equals
    ``layout_vectors(table, boxes, (rows, cols)) @ template`` (``@ template.T``): cells as in
    :func:`grid_sums`, a cell outside the frame has mean 0, a box of uniform
    feature scores 0.

    Laid out for a CPU (the same maths as ``grid_sums`` then a dot product): the box
    axis is the minor one (each ``(rows + 1) x (cols + 1)`` lattice corner and each
    cell is one contiguous vector over the boxes), every channel's corners are
    gathered from its own plane as scalars (fused into the cell differences, each
    corner would be gathered four times), the sums over cells are products with
    small matrices, and the boxes go through in blocks of ``chunk`` (one block's
    corners fit in cache; ``None``: one block, e.g. on a GPU). Each block's edges
    arrive as loop-carried buffers (``_chunked(carry_inputs=True)``), because sliced
    in place the cell areas' broadcast product compiles to scalar code. XLA:CPU drops
    the ``optimization_barrier`` calls below before fusion: the corners are a buffer
    as the gather's output, and the three fusions that read the cell means each
    recompute them.
    """
    height, width = table.shape[0] - 1, table.shape[1] - 1
    c = table.shape[-1]
    n_cells = rows * cols * c
    ys, xs = _lattice_edges(boxes, rows, cols, height, width, box_axis_last=True)
    ys, xs = lax.optimization_barrier((ys, xs))  # [rows + 1, N], [cols + 1, N]
    planes = jnp.moveaxis(table, -1, 0).reshape(c, -1)
    # Channel-major cells, to match the stacked planes below.
    template = jnp.asarray(template, jnp.float32)
    several = template.ndim == 2
    t = template.reshape(-1, rows, cols, c)
    t = jnp.moveaxis(t, -1, 1).reshape(-1, n_cells)  # [T, n_cells]
    ones = jnp.ones((1, n_cells), jnp.float32)

    def block(ys: Array, xs: Array) -> Array:
        n = ys.shape[-1]
        idx = lax.optimization_barrier(ys[:, None, :] * (width + 1) + xs[None, :, :])
        corners = lax.optimization_barrier(
            jnp.stack([_take(planes[k], idx) for k in range(c)])
        )  # [c, rows + 1, cols + 1, n]
        sums = corners[:, 1:, 1:] - corners[:, :-1, 1:] - corners[:, 1:, :-1] + corners[:, :-1, :-1]
        area = (ys[1:] - ys[:-1])[:, None, :] * (xs[1:] - xs[:-1])[None, :, :]
        inv = 1.0 / jnp.maximum(area, 1).astype(jnp.float32)
        means = lax.optimization_barrier((sums.astype(jnp.float32) * inv).reshape(n_cells, n))
        # Centred before the dot product too: a uniform box then scores exactly 0
        # (its cell means times a template summing to zero only up to rounding).
        centred = means - (ones @ means) / n_cells
        dot = t @ centred  # [T, n]
        norm = jnp.sqrt((ones @ (centred * centred))[0])
        ncc = dot / jnp.maximum(norm, 1e-3)
        return ncc.T if several else ncc[0]

    return _chunked(block, (ys, xs), chunk, (1, 1), carry_inputs=True)


# ----------------------------------------------------------------------------- window placement


#: Rects as four int32 arrays ``(x0, y0, x1, y1)`` of one shape ``[N, *C]``: the form the
#: kernels work in. Callers may pass it instead of a ``[N, *C, 4]`` array (``rect_reduce``,
#: ``rect_sums``, ``uses_window``): built from a filter's particle columns, no
#: ``[..., 4]`` stack ever exists, because on XLA:CPU stacking corners on a minor axis
#: and taking them apart again for the corner rows are transposing copies.
RectColumns = tuple[Array, Array, Array, Array]


def rect_columns(rects) -> RectColumns:
    """``(x0, y0, x1, y1)`` int32 arrays of ``rects``: a ``[..., 4]`` array or such a tuple."""
    if isinstance(rects, (tuple, list)):
        if len(rects) != 4:
            raise ValueError(f"rect columns must be (x0, y0, x1, y1), got {len(rects)} arrays")
        cols = tuple(jnp.asarray(c, jnp.int32) for c in rects)
        shape = jnp.broadcast_shapes(*(c.shape for c in cols))
        return tuple(jnp.broadcast_to(c, shape) for c in cols)
    r = jnp.asarray(rects, jnp.int32)
    return tuple(r[..., i] for i in range(4))


def _clip_columns(cols: RectColumns, width: int, height: int) -> RectColumns:
    """``boxes.clip_rect`` on columns."""
    x0, y0, x1, y1 = cols
    x0 = jnp.clip(x0, 0, width)
    y0 = jnp.clip(y0, 0, height)
    return x0, y0, jnp.clip(x1, x0, width), jnp.clip(y1, y0, height)


def _clipped_columns(rects, width: int, height: int) -> tuple[RectColumns, bool]:
    """Clipped ``RectColumns`` of ``rects`` (a ``[4]`` rect becomes ``[1]`` columns) and
    whether it was that single rect."""
    single = not isinstance(rects, (tuple, list)) and jnp.ndim(rects) == 1
    cols = rect_columns(jnp.asarray(rects)[None] if single else rects)
    return _clip_columns(cols, width, height), single


def _nonempty(cols: RectColumns) -> Array:
    x0, y0, x1, y1 = cols
    return (x1 > x0) & (y1 > y0)


def _flat(cols: RectColumns) -> RectColumns:
    return tuple(c.reshape(-1) for c in cols)


def window_origin(rects: Array, window: tuple[int, int], frame_shape: tuple[int, int]) -> Array:
    """Origin ``(oy, ox) int32`` of a ``window = (wh, ww)`` window for clipped ``rects [..., 4]``.

    Centres the window on the bounding rectangle of the non-empty rects and
    keeps it inside the frame, so it covers them whenever that rectangle fits
    (``window_covers``). With no non-empty rect the origin is ``(0, 0)``.
    """
    fh, fw = frame_shape
    wh, ww = min(window[0], fh), min(window[1], fw)
    r = _flat(rect_columns(rects))
    ne = _nonempty(r)
    big = jnp.iinfo(jnp.int32).max
    x0 = jnp.min(jnp.where(ne, r[0], big))
    y0 = jnp.min(jnp.where(ne, r[1], big))
    x1 = jnp.max(jnp.where(ne, r[2], 0))
    y1 = jnp.max(jnp.where(ne, r[3], 0))
    any_ne = jnp.any(ne)
    # origin = lo - slack // 2 covers [lo, hi) whenever slack = size - (hi - lo) >= 0;
    # clamping into the frame keeps the cover because clipped rects lie in the frame.
    ox = jnp.where(any_ne, x0 - (ww - (x1 - x0)) // 2, 0)
    oy = jnp.where(any_ne, y0 - (wh - (y1 - y0)) // 2, 0)
    ox = jnp.clip(ox, 0, fw - ww)
    oy = jnp.clip(oy, 0, fh - wh)
    return jnp.stack([oy, ox]).astype(jnp.int32)


def _check_count_dtype(count_dtype) -> jnp.dtype:
    dtype = jnp.dtype(count_dtype)
    if dtype not in (jnp.uint16, jnp.uint32, jnp.int32):
        raise ValueError(f"count_dtype must be uint16, uint32 or int32, not {dtype}")
    return dtype


@jax.custom_batching.custom_vmap
def batch_all(flag: Array) -> Array:
    """``flag`` (a bool scalar) itself; under ``vmap``, one unbatched flag: whether it
    holds for every member of the batch.

    As the predicate of a ``lax.cond`` that chooses between two exact paths to the same
    result (the windowed table or the whole-frame fallback), it keeps the ``cond`` a real
    branch under ``vmap``: with a batched predicate JAX turns ``cond`` into a ``select``
    that runs both branches for every member. The batch takes the fast path when every
    member can, and the fallback (exact too) otherwise. Works under ``jit``, nested
    ``vmap`` and ``grad`` (a bool has no tangent).
    """
    return flag


@batch_all.def_vmap
def _batch_all_vmap(axis_size, in_batched, flag):
    (batched,) = in_batched
    return (jnp.all(flag) if batched else flag), False


def window_covers(
    rects: Array,
    origin: Array,
    window: tuple[int, int],
    count_dtype=jnp.uint16,
) -> Array:
    """True when the fast path is exact for clipped ``rects [..., 4]``.

    Every non-empty rect lies inside ``[ox, ox+ww) x [oy, oy+wh)`` and, for a
    ``uint16`` table, has fewer than 65,536 pixels.
    """
    wh, ww = window
    r = _flat(rect_columns(rects))
    x0, y0, x1, y1 = r
    oy, ox = origin[0], origin[1]
    ok = (x0 >= ox) & (y0 >= oy) & (x1 <= ox + ww) & (y1 <= oy + wh)
    if _check_count_dtype(count_dtype) == jnp.uint16:
        ok = ok & ((x1 - x0) * (y1 - y0) < _U16_LIMIT)
    return jnp.all(ok | ~_nonempty(r))


def suggest_window(
    box_wh: tuple[float, float],
    spread: float,
    frame_shape: tuple[int, int],
    *,
    n_particles: int | None = None,
    size_margin: float = 0.1,
    quantum: int = 16,
    n_std: float | None = None,
) -> tuple[int, int]:
    """A static window ``(wh, ww)`` for a cloud of particle boxes around ``box_wh = (w, h)``.

    Covers the box grown by ``size_margin`` plus the extent of the centres,
    taken as ``2 * sqrt(2 ln N)`` standard deviations ``spread`` (pixels): the
    expected range of N normal samples, so that the exact fallback stays rare
    for every N (8 standard deviations when ``n_particles`` is None), or
    ``n_std`` standard deviations when given (a filter that keeps its particles
    inside the window). Rounded up to ``quantum``, capped at the frame. Pure
    Python: call it outside ``jit``; a box without a positive, finite width and height
    (a target not in view) is refused with a ``ValueError``.
    """
    w, h = box_wh
    if not (0 < w < math.inf and 0 < h < math.inf):
        raise ValueError(
            f"a histogram window needs a box of positive width and height, got {w:g} x {h:g}"
        )
    fh, fw = frame_shape
    if n_std is None:
        n = n_particles
        n_std = 8.0 if n is None else 2.0 * math.sqrt(2.0 * math.log(max(n, 2)))
        n_std = max(n_std, 4.0)
    ww = math.ceil((w * (1 + size_margin) + n_std * spread) / quantum) * quantum
    wh = math.ceil((h * (1 + size_margin) + n_std * spread) / quantum) * quantum
    return min(int(wh), fh), min(int(ww), fw)


# ----------------------------------------------------------------------------- corner gathers


def _corner_index(rects, stride: int) -> tuple[Array, Array, Array, Array]:
    """Flat table rows ``int32`` of the corners (x1,y1), (x1,y0), (x0,y1), (x0,y0) of rects
    (``[..., 4]`` or ``RectColumns``): four arrays of the rects' shape.

    Corner-major: each corner's rows are one contiguous vector, so cutting them into
    chunks moves long runs (with a trailing axis of 4 every chunk copy is an
    element-by-element transpose), and separate arrays, not one ``[4, ...]`` stack
    (whose concatenation compiles to scalar code).
    """
    x0, y0, x1, y1 = rect_columns(rects)
    idx = (y1 * stride + x1, y0 * stride + x1, y1 * stride + x0, y0 * stride + x0)
    # The indices are materialised: fused, the whole index arithmetic (rounding,
    # clipping, window shift) would run in the gather, once for each of the n_bins
    # outputs of every rect. XLA:CPU drops the barrier before fusion; the rows are
    # materialised as operands of the chunk loop (``_chunked``).
    return lax.optimization_barrier(idx)


def _corner_counts(table_flat: Array, idx: tuple[Array, ...], n_bins: int) -> Array:
    """Counts ``[..., n_bins] float32`` from a flat table (``[rows, channels]``, channels
    padded, ``_histogram_table``) and the four corner rows ``idx`` (``_corner_index``)."""

    def row(k):
        # Indices are in range by construction (rects clamped to the window).
        return _take(table_flat, idx[k], n_bins)

    # Modular arithmetic in the table's dtype: exact when the true count fits. XLA:CPU
    # drops the barrier before fusion: the gathers, the conversion and the caller's
    # element-wise terms form one fusion, vectorised along the bins, and the caller's
    # sum over bins is a separate pass.
    counts = lax.optimization_barrier(row(0) - row(1) - row(2) + row(3))
    return counts.astype(jnp.float32)


def _chunked(
    fn, args: tuple, chunk: int | None, axis: tuple[int, ...], *, carry_inputs: bool = False
):
    """``fn(*args)`` over sequential blocks of ``chunk`` rows of each arg's ``axis``.

    ``args[i]`` is cut along ``axis[i]`` (the rect axis, length N in every arg);
    results are concatenated along their leading axis. Each block is a
    ``dynamic_slice`` of the args in place (no transposed copy of them) and is
    written into the preallocated result (``fori_loop``).

    ``carry_inputs``: each block's inputs are sliced by the previous iteration and
    handed on as loop-carried buffers. XLA:CPU fuses a block's ``dynamic_slice``
    into its consumers and there reloads the slice offset for every element when
    the consumer also broadcasts (``a[:, None] * b[None]``), which leaves such a loop
    scalar code. Carried inputs are plain buffers; the price is one copy of each
    block's inputs.
    """
    n = args[0].shape[axis[0]]
    if chunk is None or n <= chunk:
        return fn(*args)
    n_chunks = n // chunk
    n_main = n_chunks * chunk
    pairs = tuple(zip(args, axis, strict=True))

    def cut(start, size):
        return tuple(lax.dynamic_slice_in_dim(a, start, size, axis=ax) for a, ax in pairs)

    # Every block runs the same loop body (one compiled reduction for all).
    shapes = jax.eval_shape(lambda: fn(*cut(0, chunk)))
    out = jax.tree_util.tree_map(lambda r: jnp.zeros((n_main,) + r.shape[1:], r.dtype), shapes)

    def write(out, res, i):
        return jax.tree_util.tree_map(
            lambda o, r: lax.dynamic_update_slice_in_dim(o, r, i * chunk, axis=0), out, res
        )

    if carry_inputs:

        def body(i, carry):
            out, block_args = carry
            # The next block's inputs (the last iteration's are not used).
            following = cut(jnp.minimum(i + 1, n_chunks - 1) * chunk, chunk)
            return write(out, fn(*block_args), i), following

        main, _ = lax.fori_loop(0, n_chunks, body, (out, cut(0, chunk)))
    else:
        main = lax.fori_loop(0, n_chunks, lambda i, o: write(o, fn(*cut(i * chunk, chunk)), i), out)
    if n_main == n:
        return main
    rest = fn(*cut(n_main, n - n_main))
    return jax.tree_util.tree_map(lambda m, r: jnp.concatenate([m, r], axis=0), main, rest)


def _split_grid(shape: tuple[int, int]) -> tuple[int, int]:
    """Fewest pieces ``(ky, kx)`` that cut any rect inside ``shape`` into parts of < 65,536 px.

    A rect of height ``h <= shape[0]`` cut into ``ky`` near-equal rows has rows
    of at most ``ceil(shape[0] / ky)`` pixels, likewise for columns.
    """
    h, w = shape
    best = (h, w)  # one-pixel pieces always fit
    for ky in range(1, h + 1):
        ph = -(-h // ky)
        max_w = (_U16_LIMIT - 1) // ph  # widest piece of height ph that fits
        if max_w >= 1:
            kx = -(-w // max_w)
            if ky * kx < best[0] * best[1]:
                best = (ky, kx)
        if ky >= best[0] * best[1]:
            break
    return best


def _pieces(rects, ky: int, kx: int) -> RectColumns:
    """Rects (``[..., 4]`` or ``RectColumns``) -> ``RectColumns`` ``[..., ky * kx]``: near-equal
    pieces tiling each rect (piece axis last)."""
    x0, y0, x1, y1 = (c[..., None] for c in rect_columns(rects))
    if ky == kx == 1:
        return x0, y0, x1, y1
    xs = x0 + ((x1 - x0) * jnp.arange(kx + 1)) // kx
    ys = y0 + ((y1 - y0) * jnp.arange(ky + 1)) // ky
    reps = (1,) * (xs.ndim - 1) + (ky,)
    px0 = jnp.tile(xs[..., :-1], reps)
    px1 = jnp.tile(xs[..., 1:], reps)
    py0 = jnp.repeat(ys[..., :-1], kx, axis=-1)
    py1 = jnp.repeat(ys[..., 1:], kx, axis=-1)
    return px0, py0, px1, py1


def _window_counts(
    bins: Array,
    rects: Array,
    origin: Array,
    shape: tuple[int, int],
    *,
    n_bins: int,
    dtype,
    chunk: int | None,
    pieces: tuple[int, int] = (1, 1),
    reduce_fn=None,
    with_area: bool = False,
    then=None,
    window_check: bool = False,
) -> Array:
    """Exact counts ``[N, *C, n_bins] float32`` of ``rects`` ∩ window, or ``reduce_fn`` of them.

    ``rects`` are clipped frame rects (``RectColumns``); ``origin = (oy, ox)`` places the static
    ``shape = (h, w)`` window (inside the frame). Each rect is cut into
    ``pieces = (ky, kx)`` parts, counted separately and summed (so that a
    uint16 table stays exact for rects of 65,536 pixels or more).
    ``reduce_fn`` is applied to the counts chunk by chunk; with ``with_area``
    it is called as ``reduce_fn(counts, area)`` with each rect's pixel count
    ``area [c, *C] float32`` (within the window). ``then`` (see ``rect_reduce``)
    gets a counter on the same table; with ``window_check`` its rects that are
    not inside the window are counted by the exact general path instead.
    """
    h, w = shape
    oy, ox = origin[0], origin[1]
    window = lax.dynamic_slice(bins, (oy, ox), (h, w))
    table = _histogram_table(window, n_bins, dtype)
    table = table.reshape(-1, table.shape[-1])

    def to_window(cols: RectColumns) -> RectColumns:
        # Clamping both corners into the same interval keeps x0 <= x1: empty stays empty.
        x0, y0, x1, y1 = cols
        return (
            jnp.clip(x0, ox, ox + w) - ox,
            jnp.clip(y0, oy, oy + h) - oy,
            jnp.clip(x1, ox, ox + w) - ox,
            jnp.clip(y1, oy, oy + h) - oy,
        )

    local = to_window(rects)
    area = ((local[2] - local[0]) * (local[3] - local[1])).astype(jnp.float32)
    reduce_fn = reduce_fn or (lambda counts, *_: counts)
    idx = _corner_index(_pieces(local, *pieces), w + 1)  # 4 x [N, *C, P]

    def count(i0, i1, i2, i3, a):
        counts = jnp.sum(_corner_counts(table, (i0, i1, i2, i3), n_bins), axis=-2)
        return reduce_fn(counts, a) if with_area else reduce_fn(counts)

    out = _chunked(count, (*idx, area), chunk, (0, 0, 0, 0, 0))
    if then is None:
        return out

    def table_counts(more: Array) -> Array:
        cols = _clip_columns(rect_columns(more), *bins.shape[::-1])
        counts = jnp.sum(
            _corner_counts(table, _corner_index(_pieces(to_window(cols), *pieces), w + 1), n_bins),
            -2,
        )
        if not window_check:
            return counts
        return lax.cond(
            batch_all(window_covers(cols, origin, shape, dtype)),
            lambda: counts,
            lambda: box_histograms(bins, jnp.stack(cols, axis=-1), n_bins),
        )

    return out, then(out, table_counts)


def _frame_counts(
    bins: Array,
    rects: Array,
    *,
    n_bins: int,
    chunk: int | None,
    reduce_fn=None,
    with_area: bool = False,
    then=None,
):
    """Exact counts of any clipped rects from one full-frame table: uint16 with pieces
    where needed, uint32 from ``WIDE_COUNTS_MIN_RECTS`` rects on."""
    fh, fw = bins.shape
    wide = math.prod(rects[0].shape) >= WIDE_COUNTS_MIN_RECTS
    return _window_counts(
        bins,
        rects,
        jnp.zeros(2, jnp.int32),
        (fh, fw),
        n_bins=n_bins,
        dtype=jnp.uint32 if wide else jnp.uint16,
        chunk=chunk,
        pieces=(1, 1) if wide else _split_grid((fh, fw)),
        reduce_fn=reduce_fn,
        with_area=with_area,
        then=then,
    )


def rect_reduce(
    bins: Array,
    rects: Array,
    reduce_fn,
    *,
    n_bins: int,
    window: tuple | None = None,
    origin: Array | None = None,
    count_dtype=jnp.uint16,
    fallback: bool = True,
    chunk: int | None = DEFAULT_CHUNK,
    with_area: bool = False,
    then=None,
):
    """Exact counts of ``rects [N, *C, 4]`` (or ``RectColumns`` ``[N, *C]``) reduced per
    rect by ``reduce_fn``: the engine behind every histogram here (module docstring).

    Clips the rects, counts them with the windowed integral histogram (``window = (wh,
    ww)``, or several windows smallest first, each tried in turn before the grown ones of
    ``window_ladder``; exact ``lax.cond`` fallback unless ``fallback=False``, which uses
    the first window) or the full-frame one
    (``window=None``), and applies ``reduce_fn(counts [c, *C, n_bins] float32) -> [c,
    *C, ...]`` (row-wise) chunk by chunk, so that the ``[N, *C, n_bins]`` counts never
    exist at once; a custom ``reduce_fn`` computes several per-box scores in one pass.
    With ``with_area=True`` it is called as ``reduce_fn(counts, area)``, ``area [c, *C]
    float32`` being each clipped rect's pixel count (the counts' total when every pixel
    has a bin, without summing the bins). ``origin (oy, ox)`` is dynamic (default:
    ``window_origin`` of the rects); ``reduce_fn``, ``then`` and the keyword arguments
    other than ``origin`` are static.

    ``then(out, count) -> result`` runs after the reduction on the same table and makes
    ``rect_reduce`` return ``(out, result)``: ``count(rects [M, ..., 4]) -> [M, ...,
    n_bins] float32`` gives exact histograms of a few more rects that depend on ``out``
    (e.g. the estimate a filter derives from the particles' scores) without a second
    table; on the windowed path those outside the window are counted by
    ``box_histograms`` instead (a ``lax.cond``).
    """
    fh, fw = bins.shape
    count_dtype = _check_count_dtype(count_dtype)
    rects, single = _clipped_columns(rects, fw, fh)
    options = {
        "n_bins": n_bins,
        "chunk": chunk,
        "reduce_fn": reduce_fn,
        "with_area": with_area,
        "then": then,
    }
    general = functools.partial(_frame_counts, bins, **options)
    if window is None:
        out = general(rects)
    else:
        shape, origin = _window_placement(rects, window, origin, (fh, fw))
        fast = functools.partial(
            _window_counts,
            bins,
            origin=origin,
            shape=shape,
            dtype=count_dtype,
            window_check=True,
            **options,
        )
        if fallback:
            placed = _ladder_placements(rects, window, origin, (fh, fw))
            branches = [fast] + [
                functools.partial(
                    _window_counts,
                    bins,
                    origin=rung_origin,
                    shape=rung,
                    dtype=count_dtype,
                    window_check=True,
                    **options,
                )
                for rung, rung_origin in placed[1:]
            ]
            index = _rung_index(rects, placed, count_dtype)
            out = lax.switch(index, [*branches, general], rects)
        else:
            out = fast(rects)
    if single:
        out = (out[0][0], out[1]) if then is not None else out[0]
    return out


def window_sizes(window) -> tuple[tuple[int, int], ...]:
    """A ``window`` argument as its static windows, smallest first: one ``(h, w)``, or a
    tuple of them (``rect_reduce``'s ladder starts with them all)."""
    if isinstance(window[0], (tuple, list)):
        return tuple((int(h), int(w)) for h, w in window)
    return ((int(window[0]), int(window[1])),)


def _window_placement(rects, window, origin, frame_shape):
    """The static shape of the first window (capped at the frame) and its origin (default:
    the rects')."""
    fh, fw = frame_shape
    first = window_sizes(window)[0]
    shape = (min(first[0], fh), min(first[1], fw))
    if origin is None:
        origin = window_origin(rects, shape, (fh, fw))
    return shape, jnp.asarray(origin, jnp.int32)


def uses_window(
    frame_shape: tuple[int, int],
    rects: Array,
    window: tuple | None,
    origin: Array | None = None,
    count_dtype=jnp.uint16,
) -> Array:
    """Whether ``rect_reduce`` with these arguments counts ``rects`` on the windowed path.

    ``False`` when ``window`` is None or when the exact whole-frame fallback
    runs (a rect outside the window or too large for the count dtype): the
    same test ``rect_reduce`` makes, for reporting (a filter's step info) and
    for sizing windows.
    """
    if window is None:
        return jnp.asarray(False)
    fh, fw = frame_shape
    r, _ = _clipped_columns(rects, fw, fh)
    _, origin = _window_placement(r, window, origin, (fh, fw))
    placed = _ladder_placements(r, window, origin, (fh, fw))
    index = _rung_index(r, placed, _check_count_dtype(count_dtype), vmapped=False)
    return index < len(placed)


def window_ladder(window, frame_shape: tuple[int, int]) -> tuple[tuple[int, int], ...]:
    """The static windows ``rect_reduce`` tries in turn: the windows of ``window`` (one
    ``(h, w)`` or several, smallest first; capped at the frame), then the last one's sides
    grown by ``LADDER_GROWTH`` (rounded up to 16 px, capped) while the grown window holds
    less than ``LADDER_MAX_SHARE`` of the frame, at most ``LADDER_RUNGS - 1`` times; past
    the last one the whole-frame path counts."""
    fh, fw = frame_shape
    rungs = []
    for h, w in window_sizes(window):
        capped = (min(h, fh), min(w, fw))
        if capped not in rungs:
            rungs.append(capped)
    given = len(rungs)
    while len(rungs) < given + LADDER_RUNGS - 1:
        h, w = rungs[-1]
        grown = (
            min(math.ceil(h * LADDER_GROWTH / 16) * 16, fh),
            min(math.ceil(w * LADDER_GROWTH / 16) * 16, fw),
        )
        if grown == (h, w) or grown[0] * grown[1] >= LADDER_MAX_SHARE * fh * fw:
            break
        rungs.append(grown)
    return tuple(rungs)


def _ladder_placements(rects, window, origin, frame_shape) -> list[tuple[tuple[int, int], Array]]:
    """``(window, origin)`` of each window of ``window_ladder(window)``: the first at
    ``origin``, the others at their own ``window_origin`` of the clipped ``rects``."""
    rungs = window_ladder(window, frame_shape)
    return [(rungs[0], origin)] + [(r, window_origin(rects, r, frame_shape)) for r in rungs[1:]]


def _rung_index(rects, placed, count_dtype, vmapped: bool = True) -> Array:
    """Index ``int32 []`` of the first placed window (``_ladder_placements``) that covers
    the clipped ``rects`` (``window_covers``), or the number of windows when none does.
    With ``vmapped`` each test goes through ``batch_all``, so that the index stays
    unbatched under ``vmap``."""
    covers = [window_covers(rects, o, rung, count_dtype) for rung, o in placed]
    if vmapped:
        covers = [batch_all(c) for c in covers]
    misses = jnp.stack([~c for c in covers] + [jnp.asarray(False)])
    return jnp.argmin(misses).astype(jnp.int32)


# ----------------------------------------------------------------------------- histograms


def _scatter_counts(bins: Array, rects: Array, n_bins: int) -> Array:
    """Exact counts ``[..., n_bins]`` of clipped ``rects [..., 4]``: one masked scatter-add each."""
    fh, fw = bins.shape
    rows = jnp.arange(fh)
    cols = jnp.arange(fw)
    flat = bins.reshape(-1)
    valid = (flat >= 0) & (flat < n_bins)
    index = jnp.where(valid, flat, 0)

    def one(r):
        inside = ((rows >= r[1]) & (rows < r[3]))[:, None] & ((cols >= r[0]) & (cols < r[2]))[None]
        weight = (inside.reshape(-1) & valid).astype(jnp.float32)
        return jax.ops.segment_sum(weight, index, num_segments=n_bins)

    flat_rects = rects.reshape(-1, 4)
    return jax.vmap(one)(flat_rects).reshape(rects.shape[:-1] + (n_bins,))


def _each_counts(bins: Array, rects: Array, n_bins: int, shape: tuple[int, int]) -> Array:
    """Counts ``[..., n_bins]`` of clipped ``rects [..., 4]`` that each fit ``shape = (h,
    w)`` (static, inside the frame): a masked scatter-add per rect over a window of that
    shape placed at its top-left corner, moved back inside the frame where it would leave."""
    fh, fw = bins.shape
    h, w = shape

    def one(r):
        ox = jnp.clip(r[0], 0, fw - w)
        oy = jnp.clip(r[1], 0, fh - h)
        crop = lax.dynamic_slice(bins, (oy, ox), shape)
        return _scatter_counts(crop, r - jnp.stack([ox, oy, ox, oy]), n_bins)

    flat = rects.reshape(-1, 4)
    return jax.vmap(one)(flat).reshape(rects.shape[:-1] + (n_bins,))


def box_histograms(
    bins: Array,
    rects: Array,
    n_bins: int,
    window: tuple | None = None,
    each: tuple[int, int] | None = None,
) -> Array:
    """Exact histograms ``[N, n_bins] float32`` of ``rects [N, 4] (x0, y0, x1, y1) int32``.

    General, simple path for any rect list (clipped, empty, outside, larger than the
    frame). Up to ``SCATTER_MAX_RECTS`` rects (a static count) are counted by a masked
    scatter-add each: with ``each = (h, w)`` over a window of that static shape placed on
    each rect alone when every rect fits one (``_each_counts``; the cells of one box are
    a fraction of the box's window), else over the first static window of ``window``
    (one ``(h, w)`` or several, smallest first) that covers them all, placed on them
    (``window_origin``, ``window_covers``), else over the frame; all give the same counts,
    and a window a sixth of the frame costs a sixth. More rects are counted by the
    full-frame integral histogram (``rect_reduce`` with ``window=None``). ``n_bins`` is
    static.
    """
    rects = jnp.asarray(rects, jnp.int32)
    n_rects = math.prod(rects.shape[:-1])
    if n_rects > SCATTER_MAX_RECTS:
        return rect_reduce(bins, rects, lambda counts: counts, n_bins=n_bins)
    fh, fw = bins.shape
    rects = clip_rect(rects, fw, fh)
    if each is not None:
        shape = (min(each[0], fh), min(each[1], fw))
        fits = jnp.all(
            (rects[..., 2] - rects[..., 0] <= shape[1])
            & (rects[..., 3] - rects[..., 1] <= shape[0])
        )
        return lax.cond(
            batch_all(fits),
            lambda: _each_counts(bins, rects, n_bins, shape),
            lambda: box_histograms(bins, rects, n_bins, window),
        )
    shapes = []
    for h, w in window_sizes(window) if window is not None else ():
        shape = (min(h, fh), min(w, fw))
        if shape != (fh, fw) and shape not in shapes:
            shapes.append(shape)
    if not shapes:
        return _scatter_counts(bins, rects, n_bins)
    placed = [(shape, window_origin(rects, shape, (fh, fw))) for shape in shapes]

    def in_window(shape, origin):
        def count(_):
            crop = lax.dynamic_slice(bins, (origin[0], origin[1]), shape)
            shift = jnp.stack([origin[1], origin[0], origin[1], origin[0]])
            return _scatter_counts(crop, rects - shift, n_bins)

        return count

    index = _rung_index(rects, placed, jnp.int32)
    branches = [in_window(shape, origin) for shape, origin in placed]
    return lax.switch(index, [*branches, lambda _: _scatter_counts(bins, rects, n_bins)], None)


# ----------------------------------------------------------------------------- distances


def _safe_sqrt(x: Array) -> Array:
    # sqrt with a finite (zero) gradient at 0, where jnp.sqrt's is infinite.
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _normalise(h: Array) -> tuple[Array, Array]:
    total = jnp.sum(h, axis=-1, keepdims=True)
    p = h / jnp.where(total > 0, total, 1.0)
    return p, total[..., 0] > 0


def normalise_counts(h: Array) -> Array:
    """Counts ``[..., B]`` divided by their sum; a sum below 1 (no pixel, or a histogram
    already normalised) is left as it is, so that no division by zero occurs."""
    return h / jnp.maximum(jnp.sum(h, axis=-1, keepdims=True), 1.0)


def squared_bhattacharyya(counts: Array, sqrt_q: Array, total: Array) -> Array:
    """Squared Bhattacharyya distances ``d^2 = 1 - sum_i sqrt(c_i q_i) / sqrt(n)`` (thesis
    eq. 3.7) of count histograms ``counts [..., B]`` with ``total [...]`` pixels to a
    normalised reference given as ``sqrt_q [..., B]`` (broadcasting): ``[...]``.

    The ``1 - BC`` form takes two plain reductions that XLA fuses with the corner gathers;
    float32 cancellation bounds its error to ``|d^2 - d_exact^2| < 2e-6``. Clamped to
    ``[0, 1]``; an empty histogram (``total = 0``) gives 1, as in OpenCV.
    """
    bc = jnp.sum(jnp.sqrt(counts) * sqrt_q, axis=-1) * lax.rsqrt(jnp.maximum(total, 1.0))
    return jnp.where(total > 0, jnp.clip(1.0 - bc, 0.0, 1.0), 1.0)


def bhattacharyya(p: Array, q: Array) -> Array:
    """Bhattacharyya distance of histograms ``p, q [..., n_bins]`` (broadcasting) -> ``[...]``.

    Both are normalised to sum 1 first; ``d = sqrt(1 - sum sqrt(p q))`` in the
    Hellinger form (module docstring). ``d`` is in ``[0, 1]``; an empty
    histogram on either side gives ``1``. Equals
    ``cv2.compareHist(p, q, cv2.HISTCMP_BHATTACHARYYA)``. Gradients are finite.
    """
    p, p_ok = _normalise(jnp.asarray(p, jnp.float32))
    q, q_ok = _normalise(jnp.asarray(q, jnp.float32))
    diff = _safe_sqrt(p) - _safe_sqrt(q)
    d = _safe_sqrt(jnp.minimum(0.5 * jnp.sum(diff * diff, axis=-1), 1.0))
    return jnp.where(p_ok & q_ok, d, 1.0)
