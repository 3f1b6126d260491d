"""Background model and per-cell statistics kernels: NumPy / SciPy references, jit, vmap."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel
from scipy import stats

from cpf_jax.kernels.background import (
    UNSEEN,
    Background,
    behind_plane,
    foreground_mask,
    foreground_shares,
    masked_median,
    masked_quantile,
    median_background,
    quiet_frames,
    side_scene,
    update_background,
)
from cpf_jax.kernels.boxes import xywh_to_rect
from cpf_jax.kernels.cells import (
    beta_log_density,
    border_strips,
    depth_bin_edges,
    depth_bin_index,
    grid_cells,
    histogram_fraction_below,
    histogram_quantile,
    side_cells,
    strip_counts,
    strip_table,
)
from cpf_jax.kernels.histogram import box_histograms

H, W, K = 24, 32, 7
EXACT = {"rtol": 0.0, "atol": 0.0}
NZ, ZLO, ZHI = 64, 400.0, 10000.0
REL_BIN = (ZHI / ZLO) ** (1 / NZ) - 1  # 5.2 % per bin


def _stack(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    colour = rng.integers(0, 256, (K, H, W, 3)).astype(np.uint8)
    depth = rng.integers(500, 6000, (K, H, W)).astype(np.uint16)
    depth[rng.uniform(size=depth.shape) < 0.3] = 0
    depth[:, :2, :2] = 0  # never measured
    return colour, depth


def _nan_quiet(fn, *args, **kwargs):
    """A NumPy NaN reduction without its warning for all-NaN pixels (the never-measured
    corner), which the kernels report as 0."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nan_to_num(fn(*args, **kwargs), nan=0.0)


# -- background -------------------------------------------------------------------------


def test_median_background_matches_numpy():
    colour, depth = _stack(0)
    # The second batch member is the same frames in reverse order: the median ignores it.
    batch = [(colour, depth), (colour[::-1], depth[::-1])]
    check_kernel(
        lambda c, d: median_background(c, d).colour,
        lambda c, d: np.median(c, axis=0),
        batch[0],
        batch=batch,
        rtol=1e-7,
        atol=1e-4,
    )

    def depth_reference(c, d):
        measured = np.where(d > 0, d, np.nan).astype(np.float64)
        return _nan_quiet(np.nanmedian, measured, axis=0)

    check_kernel(
        lambda c, d: median_background(c, d).depth,
        depth_reference,
        batch[0],
        batch=batch,
        rtol=1e-6,
        atol=0.0,
    )
    assert (np.asarray(median_background(colour, depth).depth)[:2, :2] == 0).all()


def test_masked_median_even_and_odd_counts():
    v = jnp.array([[1.0, 5.0], [3.0, 7.0], [10.0, 2.0], [4.0, 9.0]])
    ok = jnp.array([[True, True], [True, False], [False, True], [True, True]])
    got = np.asarray(masked_median(v, ok, axis=0))
    np.testing.assert_allclose(got, [np.median([1, 3, 4]), np.median([5, 2, 9])])
    assert float(masked_median(v, jnp.zeros_like(ok), axis=0)[0]) == 0.0


def _fg_reference(colour, depth, bg_c, bg_d, abs_=150.0, rel=0.05, cthr=40.0):
    z = depth.astype(np.float64)
    both = (z > 0) & (bg_d > 0)
    nearer = (bg_d - z) > np.maximum(abs_, rel * bg_d)
    col = np.abs(colour.astype(np.float64) - bg_c).max(-1) > cthr
    return np.where(both, nearer, col)


def test_foreground_mask_matches_numpy():
    colour, depth = _stack(1)
    bg = median_background(colour, depth)
    bg_c, bg_d = np.asarray(bg.colour), np.asarray(bg.depth)
    batch = [(colour[i], depth[i], bg_c, bg_d) for i in range(3)]
    check_kernel(
        lambda c, d, b_c, b_d: foreground_mask(c, d, Background(b_c, b_d)),
        _fg_reference,
        batch[0],
        batch=batch,
    )


def test_foreground_rules():
    bg = Background(jnp.full((1, 4, 3), 100.0), jnp.array([[3000.0, 3000.0, 0.0, 3000.0]]))
    colour = jnp.array(
        [[[100, 100, 100], [250, 250, 250], [250, 250, 250], [100, 100, 100]]], jnp.uint8
    )
    depth = jnp.array([[2000, 3100, 2000, 0]], jnp.uint16)
    fg = np.asarray(foreground_mask(colour, depth, bg))
    # nearer by 1 m: fg; farther (colour differs): not fg; no bg depth: colour; no depth: colour
    np.testing.assert_array_equal(fg, [[True, False, True, False]])


@pytest.mark.parametrize("stride", [1, 3])
def test_foreground_shares_match_numpy(stride):
    def reference(colour, depth):
        c = colour[:, ::stride, ::stride].astype(np.float64)
        z = depth[:, ::stride, ::stride].astype(np.float64)
        far = _nan_quiet(np.nanquantile, np.where(z > 0, z, np.nan), 0.8, axis=0)
        col = np.median(c, axis=0)
        want = []
        for i in range(K):
            both = (z[i] > 0) & (far > 0)
            neither = (z[i] == 0) & (far == 0)
            nearer = (far - z[i]) > np.maximum(150.0, 0.05 * far)
            col_fg = np.abs(c[i] - col).max(-1) > 40.0
            want.append(np.where(both, nearer, neither & col_fg).mean())
        return np.asarray(want)

    batch = [_stack(3), _stack(6)]
    for _, depth in batch:
        depth[:, 5:9, 5:9] = 0  # never measured: colour decides there
    want = reference(*batch[0])
    assert 0 < min(want) and max(want) < 1
    check_kernel(
        lambda c, d: foreground_shares(c, d, stride=stride),
        reference,
        batch[0],
        batch=batch,
        rtol=1e-7,
        atol=1e-6,
    )


@pytest.mark.parametrize("q", [0.0, 0.3, 0.5, 0.8, 1.0])
def test_masked_quantile_matches_nanquantile(q):
    colour, depth = _stack(5)
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):  # all-NaN corner
        ref = np.nanquantile(np.where(depth > 0, depth, np.nan).astype(np.float64), q, axis=0)
    got = jax.jit(masked_quantile)(depth, depth > 0, q)
    np.testing.assert_allclose(np.asarray(got), np.nan_to_num(ref, nan=0.0), rtol=1e-6)


def test_quiet_frames_rule():
    share = np.array([0.30, 0.001, 0.20, 0.004, 0.02, 0.25, 0.0, 0.011, 0.006, 0.40], np.float32)

    def expect(s, n_max, n_min, picked):
        """``quiet_frames(s, n_max, n_min)`` picks ``picked``: the indices in ascending
        order, padded with -1 to ``n_max``, and their count."""
        s = np.asarray(s, np.float32)
        want = (np.array(picked + [-1] * (n_max - len(picked)), np.int32), len(picked))
        check_kernel(lambda x: quiet_frames(x, n_max, n_min), lambda x: want, (s,), **EXACT)

    # Within 0.01 of the quietest (0.0): frames 1, 3, 6, 8; frame 7 (0.011) is not.
    expect(share, 8, 2, [1, 3, 6, 8])
    expect(share, 3, 2, [1, 3, 6])  # at most the 3 quietest
    expect(share, 8, 6, [1, 3, 4, 6, 7, 8])  # at least 6
    # Up to twice the quietest share plus the margin: 2 * 0.02 + 0.01 = 0.05.
    expect([0.048, 0.02, 0.049, 0.052, 0.3], 8, 1, [0, 1, 2])
    # Ties go to the earlier frame; n_max above the frame count pads with -1.
    expect(np.full((4,), 0.5), 6, 1, [0, 1, 2, 3])
    expect([0.5, 0.1, 0.1, 0.9], 1, 1, [1])
    with pytest.raises(ValueError, match="n_min <= n_max"):
        quiet_frames(jnp.asarray(share), 2, 3)


def test_quiet_frames_find_the_empty_room_a_median_of_all_frames_misses():
    # An empty room (wall at 4 m) in frames 0, 5, 6 and 11; in the 8 others a person
    # (1.5 m) stands in the middle, shifting by a few pixels. Where he stands the median
    # of all 12 frames (and of any 6 evenly spaced) is the person; the quiet frames'
    # median is the room. Judged against that median instead of the far quantile, the
    # empty frames would not be the quiet ones: their poster's colour differs from the
    # median's (the person) where neither has depth.
    rng = np.random.default_rng(4)
    n, h, w = 12, 40, 48
    colour = np.full((n, h, w, 3), 90, np.uint8)
    depth = (4000 + rng.integers(-20, 20, (n, h, w))).astype(np.uint16)
    # A dark poster on the wall, behind where he stands, returns no depth.
    colour[:, 10:20, 14:36] = 20
    depth[:, 10:20, 14:36] = 0
    empty = [0, 5, 6, 11]
    for t in sorted(set(range(n)) - set(empty)):
        x = 14 + (t % 3) * 2
        colour[t, 5:38, x : x + 16] = (200, 40, 40)
        depth[t, 5:38, x : x + 16] = 1500
    share = jax.jit(foreground_shares, static_argnames="stride")(colour, depth, stride=2)
    idx, count = quiet_frames(share, 25 if n > 25 else n, 3)
    picked = np.asarray(idx)[: int(count)].tolist()
    assert picked == empty, (picked, np.asarray(share).round(3))
    room = median_background(colour[picked], depth[picked])
    assert np.abs(np.asarray(room.depth)[20, 24] - 4000) < 30
    everything = median_background(colour, depth)
    assert np.asarray(everything.depth)[20, 24] == 1500  # the person, not the room


def test_running_update_only_touches_background_pixels():
    colour, depth = _stack(2)
    bg = median_background(colour, depth)
    fg = np.zeros((H, W), bool)
    fg[5:10, 5:10] = True
    new = jax.jit(update_background)(bg, colour[0], depth[0], fg, 0.5)
    c0, d0 = np.asarray(bg.colour), np.asarray(bg.depth)
    c1, d1 = np.asarray(new.colour), np.asarray(new.depth)
    np.testing.assert_array_equal(c1[fg], c0[fg])
    np.testing.assert_array_equal(d1[fg], d0[fg])
    want = 0.5 * c0[~fg] + 0.5 * colour[0][~fg]
    np.testing.assert_allclose(c1[~fg], want, atol=1e-4)
    z = depth[0].astype(np.float64)
    upd = ~fg & (z > 0) & (d0 > 0)
    np.testing.assert_allclose(d1[upd], 0.5 * d0[upd] + 0.5 * z[upd], rtol=1e-6)
    miss = ~fg & (z == 0)
    np.testing.assert_array_equal(d1[miss], d0[miss])


def _behind_plane_reference(colour, depth, z):
    unseen = colour[..., 0] < 0
    return np.where(unseen, np.broadcast_to(z, depth.shape), depth).astype(np.float32)


def test_behind_plane_gives_only_the_unseen_pixels_a_depth():
    colour, depth = _stack(3)
    items = []
    for k, z in enumerate((np.float32(2500.0), depth[2].astype(np.float32) + 7.0)):
        col = colour[k].astype(np.float32)
        col[2 + k : 9, 4:12] = UNSEEN
        items.append((col, depth[k].astype(np.float32), np.broadcast_to(z, depth[k].shape)))
    check_kernel(
        lambda c, d, z: behind_plane(Background(c, d), z).depth,
        _behind_plane_reference,
        items[0],
        batch=items,
        atol=0.0,
        rtol=0.0,
    )


def _side_scene_reference(depth, offsets):
    """The side scene by a loop over pixels and offsets."""
    h, w = depth.shape
    out = np.zeros((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            for o in np.round(offsets).astype(int):
                for c in (x - o, x + o):
                    if 0 <= c < w:
                        out[y, x] = max(out[y, x], float(depth[y, c]))
    return out


def test_side_scene_is_the_farthest_depth_at_the_offsets_along_the_row():
    _, depth = _stack(4)
    depth = depth.copy()
    depth[0, 3:9] = 0  # holes are skipped
    items = [(depth[k], np.array([3.4 + k, 7.0], np.float32)) for k in range(3)]
    check_kernel(side_scene, _side_scene_reference, items[0], batch=items, atol=0.0, rtol=0.0)
    # A person narrower than the offsets in front of a wall over a level floor: the person
    # is nearer than the scene, the floor's rows and the wall are their own scene.
    scene = np.full((12, 40), 5000, np.uint16)
    scene[8:] = np.array([3000, 2700, 2400, 2100], np.uint16)[:, None]  # a floor, nearer by row
    person = scene.copy()
    person[2:10, 18:24] = 2000
    got = np.asarray(side_scene(person, np.array([5.0, 10.0], np.float32)))
    assert (got[2:8, 18:24] == 5000).all() and (got[8:10, 18:24] == person[8:10, :1]).all()
    assert (got[:, :12] == scene[:, :12]).all()


def test_grid_cells_tile_the_box_exactly():
    boxes = jnp.array([[3.3, 4.6, 17.2, 13.9], [0.0, 0.0, 10.0, 10.0]])
    for k in (1, 2, 3):
        cells = grid_cells(boxes, k)
        assert cells.shape == (2, k * k, 4)
        idx = np.zeros((H, W), np.int32)
        counts = np.asarray(box_histograms(jnp.asarray(idx), xywh_to_rect(cells[0]), 1))[:, 0]
        box_count = np.asarray(box_histograms(jnp.asarray(idx), xywh_to_rect(boxes[:1]), 1))
        assert counts.sum() == box_count.sum()  # cells partition the box's pixels
        # row-major: cell 1 is right of cell 0
        if k > 1:
            assert float(cells[0, 1, 0]) > float(cells[0, 0, 0])
            assert float(cells[0, k, 1]) > float(cells[0, 0, 1])


def test_border_strips_and_sides():
    b = jnp.array([10.0, 20.0, 30.0, 50.0])
    s = np.asarray(border_strips(b, 0.1))
    np.testing.assert_allclose(s[0], [10, 20, 30, 5])  # inner top
    np.testing.assert_allclose(s[1], [10, 65, 30, 5])  # inner bottom
    np.testing.assert_allclose(s[3], [37, 20, 3, 50])  # inner right
    np.testing.assert_allclose(s[4], [10, 15, 30, 5])  # outer top
    np.testing.assert_allclose(s[6], [7, 20, 3, 50])  # outer left
    sides = side_cells(2)
    np.testing.assert_array_equal(sides, [[1, 1, 0, 0], [0, 0, 1, 1], [1, 0, 1, 0], [0, 1, 0, 1]])


def _cell_depths(seed: int, n_cells: int = 40) -> list[np.ndarray]:
    """Depth samples of cells: unimodal, bimodal (occluder + target), tiny and skewed."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_cells):
        kind = i % 4
        if kind == 0:
            z = rng.normal(3000, 80, rng.integers(20, 400))
        elif kind == 1:
            n = rng.integers(50, 400)
            z = np.concatenate([rng.normal(1800, 50, n // 3), rng.normal(3500, 100, n - n // 3)])
        elif kind == 2:
            z = rng.uniform(800, 9000, rng.integers(1, 6))
        else:
            z = 500 + rng.exponential(1500, rng.integers(30, 300))
        out.append(np.clip(z, 450, 9500).round())
    return out


def _counts(samples: list[np.ndarray]) -> np.ndarray:
    edges = depth_bin_edges(NZ, ZLO, ZHI)
    return np.stack([np.histogram(z, edges)[0] for z in samples]).astype(np.float32)


def test_depth_bins_agree_with_edges():
    z = np.array([[450, 1000, 2999, 9999, 0, 300, 20000]], np.uint16)
    idx = np.asarray(depth_bin_index(jnp.asarray(z), None, NZ, ZLO, ZHI))[0]
    edges = depth_bin_edges(NZ, ZLO, ZHI)
    for zz, i in zip(z[0], idx, strict=True):
        if zz == 0:
            assert i == -1
        else:
            assert i == np.clip(np.searchsorted(edges, zz, side="right") - 1, 0, NZ - 1)
    mask = np.ones_like(z, bool)
    mask[0, 1] = False
    assert int(depth_bin_index(jnp.asarray(z), jnp.asarray(mask), NZ, ZLO, ZHI)[0, 1]) == -1


def test_histogram_median_within_stated_tolerance_of_numpy():
    sample_sets = [_cell_depths(3), _cell_depths(6)]
    batch = [(_counts(z),) for z in sample_sets]
    # The samples behind each batch member's counts (the references need them; the
    # kernel sees the counts only).
    samples = {id(c): z for (c,), z in zip(batch, sample_sets, strict=True)}

    def median(c):
        return histogram_quantile(c, NZ, ZLO, ZHI)[0]

    def total(c):
        return histogram_quantile(c, NZ, ZLO, ZHI)[1]

    def sizes(c):
        return np.array([len(z) for z in samples[id(c)]])

    def lower_median(c):
        return np.array([np.sort(z)[(len(z) - 1) // 2] for z in samples[id(c)]])

    check_kernel(total, sizes, batch[0], batch=batch, **EXACT)
    # Stated bound (kernels.cells): within one bin (5.2 %) of the lower median, which is
    # np.median for odd counts, i.e. |med - lower| <= REL_BIN * lower + 1e-3 ...
    check_kernel(median, lower_median, batch[0], batch=batch, rtol=REL_BIN, atol=1e-3)
    # ... and a small fraction of a bin from np.median on cells with enough pixels.
    med = np.asarray(median(batch[0][0]))
    ref = np.array([np.median(z) for z in sample_sets[0]])
    rel = np.abs(med - ref) / ref
    big = np.array([len(z) >= 20 for z in sample_sets[0]])
    assert np.median(rel[big]) < 0.25 * REL_BIN and rel[big].max() < REL_BIN


def test_histogram_quantile_empty_and_fraction_below():
    empty = jnp.zeros((NZ,))
    med, total = histogram_quantile(empty, NZ, ZLO, ZHI)
    assert float(med) == 0.0 and float(total) == 0.0
    samples = _cell_depths(4)
    counts = jnp.asarray(_counts(samples))
    thr = jnp.asarray(np.linspace(1000, 5000, len(samples)), jnp.float32)
    got = np.asarray(
        jax.jit(lambda c, t: histogram_fraction_below(c, t, NZ, ZLO, ZHI))(counts, thr)
    )
    ref = np.array([(z < t).mean() for z, t in zip(samples, np.asarray(thr), strict=True)])
    # Error: at most the share of the samples in the threshold's own bin.
    edges = depth_bin_edges(NZ, ZLO, ZHI)
    for g, r, z, t in zip(got, ref, samples, np.asarray(thr), strict=True):
        j = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, NZ - 1)
        in_bin = ((z >= edges[j]) & (z < edges[j + 1])).mean()
        assert abs(g - r) <= in_bin + 1e-6
    assert float(histogram_fraction_below(empty, jnp.float32(3000), NZ, ZLO, ZHI)) == 0.0


def test_strip_counts_equal_the_histogram_path_and_numpy():
    """Foreground and not-nearer counts of rects from the strip table against a NumPy loop
    (foreground: exact) and against ``total * (1 - histogram_fraction_below)`` of each
    rect's exact depth histogram (to float rounding), for thresholds below, inside and
    above the bin range, rects partly or wholly outside the frame and empty ones."""
    rng = np.random.default_rng(5)
    n_colour = 9  # colour bins 0..8 foreground, 9 a background bin, -1 not counted
    colour_bins = rng.integers(-1, n_colour + 1, (H, W)).astype(np.int32)
    _, depth = _stack(2)
    depth_bins = np.asarray(depth_bin_index(depth[0], None, NZ, ZLO, ZHI))
    xywh = np.concatenate(
        [
            np.stack([rng.uniform(-8, W, 40), rng.uniform(-8, H, 40)], 1),
            rng.uniform(0, 16, (40, 2)),
        ],
        1,
    ).astype(np.float32)
    xywh[:3, 2:] = 0.0  # empty
    xywh[3] = (W + 2, 0, 5, 5)  # outside the frame
    rects = np.asarray(xywh_to_rect(jnp.asarray(xywh)))
    thresholds = np.array([100.0, 1500.0, 2718.0, 5000.0, 20000.0], np.float32)

    def counts(thr):
        table, frac = strip_table(colour_bins, n_colour, depth_bins, thr, NZ, ZLO, ZHI)
        return strip_counts(table, frac, jnp.asarray(rects))

    depth_hist = np.asarray(box_histograms(jnp.asarray(depth_bins), jnp.asarray(rects), NZ))
    total = depth_hist.sum(-1)
    ref_fg = []
    for x0, y0, x1, y1 in rects:
        x0, x1 = np.clip([x0, x1], 0, W)
        y0, y1 = np.clip([y0, y1], 0, H)
        cut = colour_bins[y0:y1, x0:x1]
        ref_fg.append(((cut >= 0) & (cut < n_colour)).sum())

    def reference(thr):
        # Foreground: exact (integer counts, the tolerance is below 1); far: to rounding.
        near = np.asarray(histogram_fraction_below(jnp.asarray(depth_hist), thr, NZ, ZLO, ZHI))
        return np.asarray(ref_fg), total * (1.0 - near)

    batch = [(t,) for t in thresholds]
    check_kernel(counts, reference, batch[0], batch=batch, rtol=1e-7, atol=1e-3)
    got = [jax.jit(counts)(t) for t in thresholds]
    assert np.asarray(got[0][1]).max() > 0  # every counted pixel is farther than 100 mm
    np.testing.assert_allclose(np.asarray(got[0][1]), total, atol=1e-3)
    np.testing.assert_array_equal(np.asarray(got[-1][1]), 0.0)  # all nearer than 20 m
    assert (np.asarray(got[0][0])[:4] == 0).all()  # empty and outside rects count nothing


def test_beta_log_density_matches_scipy():
    r = np.linspace(0.01, 0.99, 25).astype(np.float32)
    a = np.array([0.8, 1.0, 3.5, 7.9], np.float32)
    b = np.array([2.3, 1.0, 7.9, 1.5], np.float32)
    check_kernel(
        beta_log_density,
        lambda r, a, b: stats.beta.logpdf(np.asarray(r, np.float64), a, b),
        (r[:, None], a, b),
        batch=[(r[i, None], a, b) for i in range(len(r))],
        rtol=2e-4,
        atol=2e-4,
    )
    # Ratios of exactly 0 or 1 are clipped, never -inf / nan.
    edge = np.asarray(beta_log_density(jnp.array([0.0, 1.0]), 3.5, 7.9))
    assert np.isfinite(edge).all()
