"""cpf_jax.kernels.histogram against cv2.calcHist / cv2.compareHist, under jit and vmap."""

from __future__ import annotations

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel
from hypothesis import given, settings
from hypothesis import strategies as st

from cpf_jax.kernels import boxes as B
from cpf_jax.kernels import color
from cpf_jax.kernels import histogram as H

HB, SB = H.DEFAULT_BINS
NB = HB * SB
FH, FW = 240, 320  # 76,800 px: the general path cuts big rects into 2 uint16-safe pieces
WINDOW = (96, 128)  # fast-path window used throughout
EXACT = {"rtol": 0.0, "atol": 0.0}
#: |d^2 - d_exact^2| < 2e-6: the stated float32 bound of squared_bhattacharyya's 1 - BC form.
D2_TOLERANCE = {"rtol": 0.0, "atol": 2e-6}


# ----------------------------------------------------------------------------- references


def _frame(seed: int) -> np.ndarray:
    """A textured RGB frame: noise, smooth blobs and flat patches (grey, saturated)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (FH // 8, FW // 8, 3), dtype=np.uint8)
    img = cv2.resize(small, (FW, FH), interpolation=cv2.INTER_LINEAR)
    img = np.clip(img.astype(np.int16) + rng.integers(-20, 21, img.shape), 0, 255)
    img = img.astype(np.uint8)
    img[10:60, 10:90] = 128
    img[100:160, 200:300] = (200, 30, 40)
    return img


def _hsv(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2HSV)


def _ref_hist(hsv: np.ndarray, rect) -> np.ndarray:
    """cv2.calcHist of the clipped crop (zeros for an empty crop)."""
    fh, fw = hsv.shape[:2]
    x0, y0, x1, y1 = (int(v) for v in rect)
    x0, x1 = np.clip([x0, x1], 0, fw)
    y0, y1 = np.clip([y0, y1], 0, fh)
    if x1 <= x0 or y1 <= y0:
        return np.zeros(NB, np.float32)
    crop = np.ascontiguousarray(hsv[y0:y1, x0:x1])
    return cv2.calcHist([crop], [0, 1], None, [HB, SB], [0, 180, 0, 256]).ravel()


def _ref_hists(hsv, rects) -> np.ndarray:
    rects = np.asarray(rects)
    flat = rects.reshape(-1, 4)
    return np.stack([_ref_hist(hsv, r) for r in flat]).reshape(rects.shape[:-1] + (NB,))


def _np_counts(bins: np.ndarray, rects, n_bins: int) -> np.ndarray:
    """Plain NumPy counts ``[..., n_bins]`` of the bins in ``[0, n_bins)`` under each clipped
    rect (for synthetic bin images, where OpenCV has no image to look at)."""
    bins = np.asarray(bins)
    fh, fw = bins.shape
    rects = np.asarray(rects)
    out = []
    for x0, y0, x1, y1 in rects.reshape(-1, 4).tolist():
        x0, x1 = min(max(x0, 0), fw), min(max(x1, 0), fw)
        y0, y1 = min(max(y0, 0), fh), min(max(y1, 0), fh)
        crop = bins[y0 : max(y1, y0), x0 : max(x1, x0)].ravel()
        crop = crop[(crop >= 0) & (crop < n_bins)]
        out.append(np.bincount(crop, minlength=n_bins))
    return np.stack(out).reshape(rects.shape[:-1] + (n_bins,)).astype(np.float64)


def _cv_distance(h: np.ndarray, q: np.ndarray) -> float:
    return cv2.compareHist(h.astype(np.float32), q.astype(np.float32), cv2.HISTCMP_BHATTACHARYYA)


def _cv_squared_distances(hsv, rects, q) -> np.ndarray:
    """The per-particle baseline: crop, calcHist, compareHist, squared."""
    rects = np.asarray(rects)
    d = [_cv_distance(_ref_hist(hsv, r), q) ** 2 for r in rects.reshape(-1, 4)]
    return np.asarray(d).reshape(rects.shape[:-1])


def _assert_distances_close(d, ref):
    d, ref = np.asarray(d, np.float64), np.asarray(ref, np.float64)
    # 1 - BC in float32 cancels near d = 0: d^2 agrees to 2e-6, hence d to ~1e-3 there.
    np.testing.assert_allclose(d**2, ref**2, atol=2e-6)
    np.testing.assert_allclose(d, ref, atol=2e-3)


def _assert_squared_close(d2, ref_d2):
    np.testing.assert_allclose(np.asarray(d2, np.float64), np.asarray(ref_d2), **D2_TOLERANCE)


# Edge cases: (x0, y0, x1, y1) in a 320 x 240 frame.
EDGE_RECTS = np.array(
    [
        [40, 30, 100, 110],  # ordinary
        [-30, -40, 50, 60],  # negative coords, clipped
        [300, 220, 400, 300],  # crosses the bottom-right corner
        [330, 10, 400, 50],  # fully outside (right)
        [10, -80, 50, -5],  # fully outside (above)
        [-50, -50, 0, 0],  # touches the corner from outside: empty
        [60, 60, 60, 120],  # zero width
        [90, 90, 70, 120],  # x1 < x0
        [0, 0, FW, FH],  # the whole frame, touching every border
        [-100, -100, FW + 100, FH + 100],  # larger than the frame
        [FW - 1, FH - 1, FW, FH],  # last pixel
        [0, 100, 1, 101],  # one pixel on the left border
    ],
    np.int32,
)


@pytest.fixture(scope="module")
def frames():
    imgs = [_frame(s) for s in range(3)]
    bins = [np.asarray(_bins(img)) for img in imgs]
    return imgs, [_hsv(i) for i in imgs], bins


@jax.jit
def _bins(img):
    return color.hs_bin_index(img, HB, SB)


# ----------------------------------------------------------------------------- kernels


def _identity(counts):
    return counts


def _histograms(**options):
    """``rect_reduce``'s exact counts (no reduction) with these static options, jitted."""
    return jax.jit(functools.partial(H.rect_reduce, reduce_fn=_identity, n_bins=NB, **options))


def _squared_distances(bins, rects, ref, **options):
    """Squared Bhattacharyya distances of ``rects`` to the counts ``ref`` (normalised here),
    the way the filters compute them: ``rect_reduce`` with each rect's pixel count as the
    total of ``squared_bhattacharyya``."""
    sqrt_q = jnp.sqrt(H.normalise_counts(jnp.asarray(ref, jnp.float32)))
    return H.rect_reduce(
        bins,
        rects,
        lambda counts, area: H.squared_bhattacharyya(counts, sqrt_q, area),
        n_bins=NB,
        with_area=True,
        **options,
    )


_general = jax.jit(functools.partial(H.box_histograms, n_bins=NB))
_fast = _histograms(window=WINDOW)
_fast_nofb = _histograms(window=WINDOW, fallback=False)
_fast_i32 = _histograms(window=WINDOW, count_dtype=jnp.int32)
_sq_dist = jax.jit(functools.partial(_squared_distances, window=WINDOW))
_sq_dist_general = jax.jit(_squared_distances)
_bhatt = jax.jit(H.bhattacharyya)


def _origin_and_covers(rects, window=WINDOW, dtype=jnp.uint16):
    r = B.clip_rect(jnp.asarray(rects), FW, FH)
    o = H.window_origin(r, window, (FH, FW))
    return np.asarray(o), bool(H.window_covers(r, o, window, dtype))


def _cloud_rects(seed, n=64, centre=(150, 120), size=(40, 56), spread=4.0):
    rng = np.random.default_rng(seed)
    c = np.asarray(centre) + rng.normal(0, spread, (n, 2))
    wh = np.asarray(size) * (1 + 0.1 * rng.uniform(-1, 1, (n, 2)))
    xywh = np.concatenate([c - wh / 2, wh], axis=1).astype(np.float32)
    return xywh, np.array(B.xywh_to_rect(xywh))


# ----------------------------------------------------------------------------- histograms


def test_general_path_matches_calchist_on_edge_cases(frames):
    _, hsvs, bins = frames
    ref = _ref_hists(hsvs[0], EDGE_RECTS)
    # Few rects: masked scatter-add per rect.
    assert len(EDGE_RECTS) <= H.SCATTER_MAX_RECTS
    out = np.asarray(_general(bins[0], EDGE_RECTS))
    assert out.shape == (len(EDGE_RECTS), NB) and out.dtype == np.float32
    np.testing.assert_array_equal(out, ref)
    # Many rects: the full-frame integral histogram.
    many = np.concatenate([EDGE_RECTS, EDGE_RECTS + 3])
    assert len(many) > H.SCATTER_MAX_RECTS
    np.testing.assert_array_equal(np.asarray(_general(bins[0], many)), _ref_hists(hsvs[0], many))
    np.testing.assert_array_equal(np.asarray(_histograms()(bins[0], EDGE_RECTS)), ref)


def test_general_path_with_many_rects_counts_in_uint32_exactly(monkeypatch):
    # From WIDE_COUNTS_MIN_RECTS rects on, the whole-frame path counts from a uint32
    # table without pieces; rects above 65,535 px (the whole 76,800 px frame) included.
    # One colour over most of the frame: the whole frame's count of its bin is over 65,535.
    img = _frame(1)
    img[:, 40:] = (200, 30, 40)
    hsv, bins = _hsv(img), np.asarray(_bins(img))
    rng = np.random.default_rng(5)
    n = H.WIDE_COUNTS_MIN_RECTS
    xy = rng.integers(-40, max(FW, FH), (n, 2))
    wh = rng.integers(0, max(FW, FH) + 80, (n, 2))
    rects = np.concatenate([xy, xy + wh], axis=1).astype(np.int32)
    rects[: len(EDGE_RECTS)] = EDGE_RECTS
    count = jax.jit(functools.partial(H.box_histograms, n_bins=NB))
    wide = np.asarray(count(bins, rects))
    picks = np.concatenate([np.arange(len(EDGE_RECTS)), rng.choice(n, 40, replace=False)])
    ref = _ref_hists(hsv, rects[picks])
    assert ref.max() >= 65536
    np.testing.assert_array_equal(wide[picks], ref)
    # Under vmap over frames (each frame's call sees n rects: the same path).
    other = _frame(2)
    both = jax.jit(jax.vmap(functools.partial(H.box_histograms, n_bins=NB), in_axes=(0, None)))
    batched = np.asarray(both(np.stack([bins, np.asarray(_bins(other))]), rects))
    np.testing.assert_array_equal(batched[0], wide)
    np.testing.assert_array_equal(batched[1, picks], _ref_hists(_hsv(other), rects[picks]))
    # The uint16 table with pieces, forced: the same counts for every rect.
    monkeypatch.setattr(H, "WIDE_COUNTS_MIN_RECTS", n + 1)
    narrow = np.asarray(jax.jit(functools.partial(H.box_histograms, n_bins=NB))(bins, rects))
    np.testing.assert_array_equal(wide, narrow)


@pytest.mark.parametrize("shape", [(240, 320), (424, 512), (37, 53), (1080, 1920), (70000, 3)])
def test_whole_frame_path_counts_rects_of_any_size_exactly(shape):
    # The uint16 whole-frame table cuts each rect into pieces of fewer than 65,536 px
    # (a full-HD frame, a 70,000-row column strip): a piece at the limit or above would
    # wrap its count. Two bins, the first covering most of the frame, so that the whole
    # frame's count of it is far above 65,535.
    h, w = shape
    rng = np.random.default_rng(h + w)
    bins = (rng.random(shape) < 0.1).astype(np.int32)
    rects = np.array([[0, 0, w, h], [1, 3, w, h - 2], [2, 5, 2, 9], [-4, -7, w + 9, h + 1]])
    got = jax.jit(functools.partial(H.rect_reduce, reduce_fn=_identity, n_bins=2))(bins, rects)
    want = _np_counts(bins, rects, 2)
    np.testing.assert_array_equal(np.asarray(got), want)
    assert h * w < 65536 or want[0, 0] >= 65536


def test_rect_reduce_with_custom_reduction(frames):
    # Several scores from one pass: e.g. (distance, count of bin 0) per box.
    _, hsvs, bins = frames
    xywh, rects = _cloud_rects(15, n=40)
    q = _ref_hist(hsvs[0], rects[0])

    def reduce_fn(counts):
        d = H.bhattacharyya(counts, q)
        return jnp.stack([d, counts[..., 0], counts.sum(-1)], axis=-1)

    f = jax.jit(
        functools.partial(H.rect_reduce, reduce_fn=reduce_fn, n_bins=NB, window=WINDOW, chunk=16)
    )
    out = np.asarray(f(bins[0], rects))
    ref = _ref_hists(hsvs[0], rects)
    assert out.shape == (40, 3)
    np.testing.assert_array_equal(out[:, 1], ref[:, 0])
    np.testing.assert_array_equal(out[:, 2], ref.sum(-1))
    _assert_distances_close(out[:, 0], [_cv_distance(h, q) for h in ref])


@pytest.mark.parametrize("window", [WINDOW, None], ids=["window", "general"])
def test_rect_reduce_with_area(frames, window):
    # with_area passes each clipped rect's pixel count: equal to the counts' total
    # here (every pixel has an H-S bin), for rects inside, across and outside the
    # frame, on the fast path (with fallback), the general path and under vmap.
    _, hsvs, bins = frames
    _, cloud = _cloud_rects(16, n=24)
    rects = np.concatenate([np.asarray(cloud), np.asarray(EDGE_RECTS)]).astype(np.int32)

    def reduce_fn(counts, area):
        return jnp.stack([area, counts.sum(-1)], axis=-1)

    f = jax.jit(
        functools.partial(
            H.rect_reduce, reduce_fn=reduce_fn, n_bins=NB, window=window, chunk=8, with_area=True
        )
    )
    out = np.asarray(f(bins[0], rects))
    ref = _ref_hists(hsvs[0], rects).sum(-1)
    np.testing.assert_array_equal(out[:, 0], ref)
    np.testing.assert_array_equal(out[:, 1], ref)
    batched = np.asarray(jax.vmap(f, in_axes=(0, None))(np.stack(bins[:2]), rects))
    np.testing.assert_array_equal(batched[1, :, 0], _ref_hists(hsvs[1], rects).sum(-1))


@pytest.mark.parametrize("window", [WINDOW, None], ids=["window", "general"])
def test_rect_columns_count_like_the_stacked_rects(frames, window):
    # RectColumns (x0, y0, x1, y1) are the same rects as the [..., 4] array: same counts
    # through rect_reduce (cells [N, C], a `then` counter, fallback included), rect_sums
    # and uses_window, under jit and vmap.
    _, hsvs, bins = frames
    _, cloud = _cloud_rects(17, n=24)
    rects = np.concatenate([np.asarray(cloud), np.asarray(EDGE_RECTS)]).astype(np.int32)
    cells = np.stack([rects, rects + np.array([3, 2, 5, 9], np.int32)], axis=1)  # [N, 2, 4]
    cols = tuple(jnp.asarray(cells[..., i]) for i in range(4))
    assert [c.shape for c in H.rect_columns(cells)] == [cells.shape[:-1]] * 4

    def count(rects):
        return H.rect_reduce(
            bins[0],
            rects,
            lambda counts: counts,
            n_bins=NB,
            window=window,
            chunk=8,
            then=lambda out, counter: counter(rects_more),
        )

    rects_more = jnp.asarray(rects[:3])
    (a, a_more), (b, b_more) = jax.jit(count)(cells), jax.jit(count)(cols)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(a_more), np.asarray(b_more))
    np.testing.assert_array_equal(np.asarray(b)[:, 0], _ref_hists(hsvs[0], rects))
    np.testing.assert_array_equal(np.asarray(b_more), _ref_hists(hsvs[0], rects[:3]))
    np.testing.assert_array_equal(
        np.asarray(H.uses_window((FH, FW), cells, window)),
        np.asarray(H.uses_window((FH, FW), cols, window)),
    )
    table = H.integral_image(np.asarray(bins[0])[..., None].astype(np.int32))
    np.testing.assert_array_equal(
        np.asarray(H.rect_sums(table, cells)), np.asarray(H.rect_sums(table, cols))
    )
    batched = jax.vmap(lambda c: count(c)[0])(tuple(jnp.stack([c, c]) for c in cols))
    np.testing.assert_array_equal(np.asarray(batched[1]), np.asarray(a))
    with pytest.raises(ValueError, match="x0, y0, x1, y1"):
        H.rect_columns(cols[:3])


def test_general_path_single_rect(frames):
    _, hsvs, bins = frames
    out = np.asarray(_general(bins[0], EDGE_RECTS[0]))
    np.testing.assert_array_equal(out, _ref_hist(hsvs[0], EDGE_RECTS[0]))


def test_fast_path_inside_window_matches_calchist(frames):
    _, hsvs, bins = frames
    _, rects = _cloud_rects(1)
    rects[0] = (0, 0, 0, 0)  # an empty rect does not move the window
    _, covers = _origin_and_covers(rects)
    assert covers, "cloud should fit the window: this test must exercise the fast branch"
    np.testing.assert_array_equal(np.asarray(_fast(bins[0], rects)), _ref_hists(hsvs[0], rects))
    np.testing.assert_array_equal(
        np.asarray(_fast_nofb(bins[0], rects)), _ref_hists(hsvs[0], rects)
    )


def test_fast_path_window_at_frame_border(frames):
    _, hsvs, bins = frames
    # A cloud in the bottom-right corner, boxes sticking out of the frame.
    _, rects = _cloud_rects(2, centre=(FW - 10, FH - 10), size=(60, 50))
    origin, covers = _origin_and_covers(rects)
    assert covers and tuple(origin) == (FH - WINDOW[0], FW - WINDOW[1])
    np.testing.assert_array_equal(np.asarray(_fast(bins[0], rects)), _ref_hists(hsvs[0], rects))


def test_fast_path_falls_back_exactly_when_window_does_not_cover(frames):
    _, hsvs, bins = frames
    _, rects = _cloud_rects(3)
    rects = np.concatenate([rects[:20], EDGE_RECTS])  # edge cases spread over the frame
    _, covers = _origin_and_covers(rects)
    assert not covers
    np.testing.assert_array_equal(np.asarray(_fast(bins[0], rects)), _ref_hists(hsvs[0], rects))


def test_without_fallback_counts_exactly_the_part_inside_the_window(frames):
    # The documented bound of fallback=False: exact for rects in the window; a rect
    # leaving it gets the histogram of its intersection with the window.
    _, hsvs, bins = frames
    _, rects = _cloud_rects(4, n=16)
    wide = np.array([[0, 100, FW, 140]], np.int32)  # wider than the window
    all_rects = np.concatenate([rects, wide])
    origin, covers = _origin_and_covers(all_rects)
    assert not covers
    oy, ox = (int(v) for v in origin)
    window_rect = np.array([ox, oy, ox + WINDOW[1], oy + WINDOW[0]])
    clipped = np.concatenate(
        [
            np.maximum(all_rects[:, :2], window_rect[:2]),
            np.minimum(all_rects[:, 2:], window_rect[2:]),
        ],
        axis=1,
    )
    out = np.asarray(_fast_nofb(bins[0], all_rects))
    np.testing.assert_array_equal(out, _ref_hists(hsvs[0], clipped))
    assert out[-1].sum() < _ref_hist(hsvs[0], wide[0]).sum()  # ... which is not the full rect


def test_uses_window_is_the_path_rect_reduce_takes(frames):
    # uses_window reports the fast path exactly when counting in the window alone is
    # exact: compare fallback=False (window only) with calcHist on clouds that fit,
    # stick out of the frame, or leave the window; no window means no fast path.
    _, hsvs, bins = frames
    cases = {
        "fits": _cloud_rects(1)[1],
        "frame edge": _cloud_rects(2, centre=(FW - 10, FH - 10), size=(60, 50))[1],
        "leaves window": np.concatenate([_cloud_rects(4, n=16)[1], [[0, 100, FW, 140]]]),
    }
    seen = set()
    for name, rects in cases.items():
        rects = np.asarray(rects, np.int32)
        fast = H.uses_window((FH, FW), jnp.asarray(rects), WINDOW)
        exact = np.array_equal(np.asarray(_fast_nofb(bins[0], rects)), _ref_hists(hsvs[0], rects))
        assert bool(fast) == exact, name
        assert bool(fast) == _origin_and_covers(rects)[1], name
        seen.add(bool(fast))
    assert seen == {True, False}
    # A given origin places the first window as is (here one that misses the cloud, which
    # the grown window of the ladder then covers at its own origin), a 1D rect works.
    far = jnp.asarray([FH - WINDOW[0], FW - WINDOW[1]], jnp.int32)
    fits = B.clip_rect(jnp.asarray(cases["fits"]), FW, FH)
    assert not bool(H.window_covers(fits, far, WINDOW))
    assert bool(H.uses_window((FH, FW), fits, WINDOW, far))
    assert bool(H.uses_window((FH, FW), jnp.asarray([5, 5, 20, 20]), WINDOW))
    assert not bool(H.uses_window((FH, FW), jnp.asarray(cases["fits"]), None))
    # Under jit and vmap (over clouds).
    clouds = jnp.stack([jnp.asarray(cases["fits"][:17]), jnp.asarray(cases["leaves window"])])
    got = jax.jit(jax.vmap(lambda r: H.uses_window((FH, FW), r, WINDOW)))(clouds)
    assert list(np.asarray(got)) == [True, False]


def test_batch_all_is_one_flag_for_the_whole_batch():
    flags = jnp.asarray([True, False, True])
    assert bool(H.batch_all(jnp.asarray(True))) and not bool(H.batch_all(jnp.asarray(False)))
    # Under vmap the flag is no longer batched: it is the AND over the members (which a
    # mapped output then broadcasts), under jit and nested vmap too.
    np.testing.assert_array_equal(jax.vmap(H.batch_all)(flags), [False] * 3)
    np.testing.assert_array_equal(jax.jit(jax.vmap(H.batch_all))(flags[::2]), [True] * 2)
    nested = jax.vmap(jax.vmap(H.batch_all))(jnp.stack([flags, flags[::-1]]))
    np.testing.assert_array_equal(nested, np.zeros((2, 3), bool))

    # As a cond predicate it keeps gradients through the branch taken.
    def f(x):
        return lax_cond(H.batch_all(x > -1.0), x)

    grads = jax.jit(jax.vmap(jax.grad(f)))(jnp.asarray([0.5, 2.0]))
    np.testing.assert_allclose(grads, 2 * np.cos(2 * np.asarray([0.5, 2.0])), rtol=1e-6)


def lax_cond(pred, x):
    return jax.lax.cond(pred, lambda v: jnp.sin(2 * v), lambda v: v, x)


def test_vmap_keeps_the_fallback_a_branch_and_stays_exact(frames):
    # A batch of clouds (filter keys, say): one member leaves the window. Every member
    # is still counted exactly (the batch takes the exact fallback), and the vmapped
    # program holds a real conditional, not a select that would run both paths for
    # every member.
    _, hsvs, bins = frames
    fits = _cloud_rects(1, n=17)[1]
    leaves = np.concatenate([_cloud_rects(4, n=16)[1], [[0, 100, FW, 140]]])
    batched = jax.jit(jax.vmap(_fast, in_axes=(None, 0)))
    for clouds in (np.stack([fits, fits + 3]), np.stack([fits, leaves])):
        got = np.asarray(batched(bins[0], clouds))
        for g, r in zip(got, clouds, strict=True):
            np.testing.assert_array_equal(g, _ref_hists(hsvs[0], r))
    text = batched.lower(bins[0], np.stack([fits, leaves])).as_text()
    assert "stablehlo.case" in text or "stablehlo.if" in text


def test_window_ladder_counts_a_cloud_wider_than_the_window_on_a_grown_window(frames):
    # The ladder: the window, then each side grown by LADDER_GROWTH (to 16 px) while the
    # grown window holds less than LADDER_MAX_SHARE of the frame. A cloud that leaves the
    # window but fits the grown one is counted there (reported windowed), exactly, under
    # jit and vmap, in a real branch; one that fits neither takes the general path.
    _, hsvs, bins = frames
    assert H.window_ladder(WINDOW, (FH, FW)) == ((96, 128), (128, 160), (160, 208))
    assert H.window_ladder((200, 300), (FH, FW)) == ((200, 300),)  # grown: > 85 % of frame
    assert H.window_ladder((400, 500), (FH, FW)) == ((FH, FW),)
    left, right = _cloud_rects(5, n=9, centre=(70, 120)), _cloud_rects(6, n=8, centre=(200, 120))
    wide = np.concatenate([left[1], right[1]])  # about 170 x 70 px: the last rung only
    leaves = np.concatenate([_cloud_rects(4, n=16)[1], [[0, 100, FW, 140]]])
    assert not _origin_and_covers(wide)[1] and _origin_and_covers(wide, (160, 208))[1]
    assert bool(H.uses_window((FH, FW), jnp.asarray(wide), WINDOW))
    assert not bool(H.uses_window((FH, FW), jnp.asarray(leaves), WINDOW))
    np.testing.assert_array_equal(np.asarray(_fast(bins[0], wide)), _ref_hists(hsvs[0], wide))
    batched = jax.jit(jax.vmap(_fast, in_axes=(None, 0)))
    fits = _cloud_rects(1, n=len(wide))[1]
    for clouds in (np.stack([fits, wide]), np.stack([wide, leaves])):
        got = np.asarray(batched(bins[0], clouds))
        for g, r in zip(got, clouds, strict=True):
            np.testing.assert_array_equal(g, _ref_hists(hsvs[0], r))
    text = batched.lower(bins[0], np.stack([fits, wide])).as_text()
    assert "stablehlo.case" in text


def test_several_windows_are_tried_smallest_first_and_count_exactly(frames):
    # window=(small, window): the ladder is the small window, the window, then the window
    # grown; each cloud is counted exactly on the first that holds it, under jit and vmap.
    _, hsvs, bins = frames
    small = (48, 64)
    windows = (small, WINDOW)
    assert H.window_sizes(windows) == (small, WINDOW) and H.window_sizes(WINDOW) == (WINDOW,)
    assert H.window_ladder(windows, (FH, FW)) == (small, (96, 128), (128, 160), (160, 208))
    assert H.window_ladder((WINDOW, WINDOW), (FH, FW)) == H.window_ladder(WINDOW, (FH, FW))
    tight = _cloud_rects(7, n=12, size=(20, 24), spread=2.0)[1]  # inside 48 x 64
    fits = _cloud_rects(1, n=12)[1]  # leaves 48 x 64, inside 96 x 128
    leaves = np.concatenate([_cloud_rects(4, n=11)[1], [[0, 100, FW, 140]]])
    assert _origin_and_covers(tight, small)[1] and not _origin_and_covers(fits, small)[1]
    for rects in (tight, fits, leaves):
        reached = bool(H.uses_window((FH, FW), jnp.asarray(rects), windows))
        assert reached == bool(H.uses_window((FH, FW), jnp.asarray(rects), WINDOW))
    f = functools.partial(H.rect_reduce, reduce_fn=_identity, n_bins=NB, window=windows)
    check_kernel(
        lambda b, r: f(b, r),
        lambda b, r: _ref_hists(hsvs[0], r),
        (bins[0], tight),
        batch=[(bins[0], tight), (bins[0], fits), (bins[0], leaves)],
        **EXACT,
    )
    # box_histograms scatters over the first given window that holds its few rects.
    few = jax.jit(lambda b, r: H.box_histograms(b, r, NB, windows))
    for rects in (tight[:4], fits[:4], leaves[-4:]):
        np.testing.assert_array_equal(np.asarray(few(bins[0], rects)), _ref_hists(hsvs[0], rects))


def test_uint16_limit_falls_back_and_int32_table_stays_fast(frames):
    _, hsvs, bins = frames
    # 100 x 96 = 9,600 px fits uint16; make the window big and a rect of >= 65,536 px.
    big = np.array([[0, 0, 300, 220], [10, 10, 50, 50]], np.int32)  # 66,000 px
    window = (FH, FW)
    _, covers16 = _origin_and_covers(big, window, jnp.uint16)
    _, covers32 = _origin_and_covers(big, window, jnp.int32)
    assert not covers16 and covers32
    ref = _ref_hists(hsvs[0], big)
    f16 = _histograms(window=window)
    f32 = _histograms(window=window, count_dtype=jnp.int32)
    np.testing.assert_array_equal(np.asarray(f16(bins[0], big)), ref)
    np.testing.assert_array_equal(np.asarray(f32(bins[0], big)), ref)


def test_signed_16_bit_table_is_refused(frames):
    # int16 would wrap counts >= 32,768 to negative values: not a valid count dtype.
    with pytest.raises(ValueError, match="count_dtype"):
        H.rect_reduce(
            frames[2][0], EDGE_RECTS, _identity, n_bins=NB, window=WINDOW, count_dtype=jnp.int16
        )


def test_int32_table_fast_path(frames):
    _, hsvs, bins = frames
    _, rects = _cloud_rects(5)
    np.testing.assert_array_equal(np.asarray(_fast_i32(bins[0], rects)), _ref_hists(hsvs[0], rects))


def test_cell_rects_and_explicit_origin(frames):
    # Per-cell histograms: k x k cells of each particle box, rects [N, k*k, 4].
    _, hsvs, bins = frames
    _, rects = _cloud_rects(6, n=32)
    k = 3
    x0, y0, x1, y1 = (rects[:, i : i + 1] for i in range(4))
    fx = np.arange(k + 1) / k
    xs = np.floor(x0 + (x1 - x0) * fx + 0.5).astype(np.int32)
    ys = np.floor(y0 + (y1 - y0) * fx + 0.5).astype(np.int32)
    cells = np.stack(
        [
            np.stack([xs[:, j], ys[:, i], xs[:, j + 1], ys[:, i + 1]], axis=-1)
            for i in range(k)
            for j in range(k)
        ],
        axis=1,
    )
    assert cells.shape == (32, k * k, 4)
    origin, covers = _origin_and_covers(cells)
    assert covers
    out = np.asarray(_fast(bins[0], cells, origin=jnp.asarray(origin)))
    ref = _ref_hists(hsvs[0], cells)
    np.testing.assert_array_equal(out, ref)
    chunked = _histograms(window=WINDOW, chunk=7)
    np.testing.assert_array_equal(np.asarray(chunked(bins[0], cells)), ref)
    # Cell histograms add up to the box histogram.
    np.testing.assert_array_equal(out.sum(axis=1), _ref_hists(hsvs[0], rects))


def test_odd_frame_small_window():
    # 37 x 53 frame, 16 x 20 window: most random rects fall back to the general path.
    rng = np.random.default_rng(7)
    img = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    hsv = _hsv(img)
    bins = _bins(img)
    rects = rng.integers(-10, 60, (40, 4)).astype(np.int32)
    out = _histograms(window=(16, 20))(bins, rects)
    np.testing.assert_array_equal(np.asarray(out), _ref_hists(hsv, rects))


def test_masked_pixels_are_not_counted(frames):
    _, hsvs, bins = frames
    masked = np.asarray(bins[0]).copy()
    masked[:, : FW // 2] = -1
    rect = np.array([[100, 50, 220, 150]], np.int32)
    out = np.asarray(_general(masked, rect))
    ref = _ref_hist(hsvs[0], [FW // 2, 50, 220, 150])
    np.testing.assert_array_equal(out[0], ref)


@pytest.mark.parametrize("window", [WINDOW, None], ids=["window", "general"])
def test_histograms_of_frames_equal_calchist(frames, window):
    # One body three ways: plainly, under jit and vmapped over frames and rect sets (the
    # third set leaves the window: the batch takes the exact fallback).
    imgs, _, _ = frames
    _, rects = _cloud_rects(8, n=24)
    rect_sets = [rects, rects + 7, np.concatenate([rects[:12], EDGE_RECTS])]

    def kernel(img, rects):
        return H.rect_reduce(_bins(img), rects, _identity, n_bins=NB, window=window)

    def reference(img, rects):
        return _ref_hists(_hsv(np.asarray(img)), rects)

    batch = list(zip(imgs, rect_sets, strict=True))
    check_kernel(kernel, reference, batch[0], batch=batch, **EXACT)
    # box_histograms (scatter-add for few rects, the whole-frame table for more) too,
    # with and without a window to scatter in (the third set's edge rects leave it).
    few = [(img, rects[:10]) for img, rects in batch[:2]] + [(batch[2][0], EDGE_RECTS[:10])]
    for scatter_window in (None, WINDOW):
        check_kernel(
            lambda img, rects, w=scatter_window: H.box_histograms(_bins(img), rects, NB, w),
            reference,
            few[0],
            batch=few,
            **EXACT,
        )


@pytest.mark.parametrize("n_bins,count_dtype", [(9, jnp.uint16), (72, jnp.uint16), (9, jnp.int32)])
@pytest.mark.parametrize("window", [(20, 24), None], ids=["window", "general"])
def test_counts_ignore_out_of_range_bins_on_every_table_layout(n_bins, count_dtype, window):
    # The integral histogram stores its channels padded to whole vectors (9 -> 16, 72 -> 80
    # uint16 channels; 9 -> 16 int32): bins -1 and n_bins..n_bins + 20 (some of which land
    # in the padding channels) count nowhere, for frames of every size against NumPy.
    for shape in [(1, 1), (7, 5), (37, 53)]:
        rng = np.random.default_rng(sum(shape) + n_bins)
        bins = rng.integers(-1, n_bins + 21, shape).astype(np.int32)
        h, w = shape
        x0, y0 = rng.integers(-3, w, 30), rng.integers(-3, h, 30)
        rects = np.stack([x0, y0, x0 + rng.integers(0, 30, 30), y0 + rng.integers(0, 30, 30)], -1)
        rects[:2] = [[0, 0, w, h], [-5, -5, w + 5, h + 5]]
        count = jax.jit(
            functools.partial(
                H.rect_reduce,
                reduce_fn=_identity,
                n_bins=n_bins,
                window=window,
                count_dtype=count_dtype,
                chunk=8,
            )
        )
        got = np.asarray(count(bins, rects.astype(np.int32)))
        np.testing.assert_array_equal(got, _np_counts(bins, rects, n_bins))


# ----------------------------------------------------------------------------- window placement


@settings(max_examples=25, deadline=None)
@given(
    st.integers(-60, FW + 20),
    st.integers(-60, FH + 20),
    st.lists(
        st.tuples(st.integers(0, 40), st.integers(0, 40), st.integers(0, 80), st.integers(0, 50)),
        min_size=8,
        max_size=8,
    ),
)
def test_window_origin_covers_any_cloud_that_fits(x, y, offsets):
    rects = np.array([[x + a, y + b, x + a + w, y + b + h] for a, b, w, h in offsets], np.int32)
    clipped = np.asarray(B.clip_rect(jnp.asarray(rects), FW, FH))
    ne = (clipped[:, 2] > clipped[:, 0]) & (clipped[:, 3] > clipped[:, 1])
    origin, covers = _origin_and_covers(rects)
    oy, ox = origin
    assert 0 <= oy <= FH - WINDOW[0] and 0 <= ox <= FW - WINDOW[1]
    if ne.any():
        span_x = clipped[ne, 2].max() - clipped[ne, 0].min()
        span_y = clipped[ne, 3].max() - clipped[ne, 1].min()
        assert covers == (span_x <= WINDOW[1] and span_y <= WINDOW[0])
    else:
        assert covers


@pytest.mark.parametrize("x,y", [(50, 40), (51, 41), (0, 0), (FW - WINDOW[1], FH - WINDOW[0])])
def test_window_origin_covers_cloud_of_exactly_window_size(x, y):
    wh, ww = WINDOW
    rects = np.array([[x, y, x + 10, y + 10], [x + ww - 7, y + wh - 3, x + ww, y + wh]], np.int32)
    origin, covers = _origin_and_covers(rects)
    assert covers and tuple(origin) == (y, x)
    # One pixel more in either direction no longer fits.
    assert not _origin_and_covers(rects + np.int32([0, 0, 1, 0]))[1] or x + ww == FW
    assert not _origin_and_covers(rects + np.int32([0, 0, 0, 1]))[1] or y + wh == FH


def test_suggest_window():
    frame = (424, 512)
    sizes = [H.suggest_window((150, 200), 20, frame, n_particles=n) for n in (20, 1000, 100_000)]
    assert sizes[0] < sizes[1] < sizes[2]  # more particles, wider cloud extremes
    for wh, ww in sizes:
        assert wh % 16 == 0 and ww % 16 == 0 and wh >= 220 and ww >= 165
    assert H.suggest_window((400, 500), 30, frame) == frame  # capped at the frame
    # explicit extent: box * 1.1 + n_std * spread, rounded up to 16
    assert H.suggest_window((150, 200), 15, frame, n_std=6) == (320, 256)
    # a target not in view has an empty box: refused, not a zero-size window
    for wh in ((0.0, 0.0), (50.0, 0.0), (float("nan"), 80.0)):
        with pytest.raises(ValueError, match="positive width and height"):
            H.suggest_window(wh, 15, frame)


# ----------------------------------------------------------------------------- tables and sums


def _summed_area(values: np.ndarray) -> np.ndarray:
    """NumPy summed-area table ``[h + 1, w + 1, c]`` in the dtype of ``values`` (unsigned
    integers wrap modulo 2^bits, as the kernel's do)."""
    out = np.zeros((values.shape[0] + 1, values.shape[1] + 1, values.shape[2]), values.dtype)
    out[1:, 1:] = values.cumsum(0, dtype=values.dtype).cumsum(1, dtype=values.dtype)
    return out


@pytest.mark.parametrize("n", [1, 7, 8, 9, 16, 53, 289])
def test_integral_image_equals_numpy_for_every_row_length(n):
    # The blocked prefix sums along x pad the rows to whole blocks of PREFIX_BLOCK when it
    # does not divide their length: every length, exact for integers (uint16 wraps modulo
    # 2^16, as the uint16 tables rely on), the reference loops ("loop") bit for bit, plain,
    # under jit and vmap; float sums to rounding.
    # The padding depends on the length alone, so two lengths (a partial and a multi-block
    # row) run all three ways and the others under jit.
    variants = ("plain", "jit", "vmap") if n in (9, 289) else ("jit",)
    rng = np.random.default_rng(n)
    wraps = [rng.integers(0, 60_000, (5, n, 3)).astype(np.uint16) for _ in range(2)]
    batch = [(v,) for v in wraps]
    check_kernel(H.integral_image, _summed_area, batch[0], batch=batch, variants=variants, **EXACT)
    ints = [rng.integers(-1000, 1000, (4, n, 2)).astype(np.int32) for _ in range(2)]
    batch = [(v,) for v in ints]
    check_kernel(H.integral_image, _summed_area, batch[0], batch=batch, variants=variants, **EXACT)
    loop = functools.partial(H.integral_image, method="loop")
    check_kernel(loop, _summed_area, (ints[1],), variants=("jit",), **EXACT)
    floats = rng.random((6, n, 4)).astype(np.float32)
    check_kernel(H.integral_image, _summed_area, (floats,), variants=variants, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="method"):
        H.integral_image(ints[0], method="scan")


def _np_rect_sums(values: np.ndarray, rects, channels: int | None = None) -> np.ndarray:
    """Plain NumPy sums ``[..., c]`` of ``values [h, w, c]`` under each clipped rect."""
    h, w = values.shape[:2]
    rects = np.asarray(rects)
    out = []
    for x0, y0, x1, y1 in rects.reshape(-1, 4).tolist():
        a, b = max(x0, 0), max(y0, 0)
        c, d = min(max(x1, a), w), min(max(y1, b), h)
        out.append(values[b:d, a:c, :channels].reshape(-1, values[..., :channels].shape[-1]).sum(0))
    return np.stack(out).reshape(rects.shape[:-1] + (out[0].shape[-1],))


def test_integral_image_and_rect_sums_match_numpy():
    rng = np.random.default_rng(3)
    values = rng.integers(-4096, 4097, (37, 53, 2)).astype(np.int32)
    rects = np.array(
        [
            [0, 0, 53, 37],
            [5, 7, 20, 30],
            [-10, -4, 12, 9],
            [40, 30, 90, 80],
            [8, 8, 8, 20],
            [60, 0, 70, 10],
            [20, 10, 5, 30],
        ],
        np.int32,
    )

    def kernel(v, r):
        return H.rect_sums(H.integral_image(v), r)

    batch = [(values, rects), (-values, rects[::-1].copy())]
    check_kernel(kernel, _np_rect_sums, batch[0], batch=batch, **EXACT)
    # float tables too
    table = H.integral_image(values.astype(np.float32))
    np.testing.assert_allclose(
        np.asarray(H.rect_sums(table, rects)), _np_rect_sums(values, rects), rtol=1e-6
    )


@pytest.mark.parametrize("n", [3, 8, 16, 21, 40])
def test_rect_sums_in_chunks_equal_the_numpy_sums(n):
    # ``chunk``: gathers in sequential blocks of 8 rects (one block, exact blocks, a
    # partial last block) whose inputs are handed on through the loop; the same sums
    # for a [N, 2] rect axis too; the partial block all three ways, the others under jit.
    rng = np.random.default_rng(n)
    values = rng.integers(-4096, 4097, (37, 53, 3)).astype(np.int32)
    x0, y0 = rng.integers(-15, 60, n), rng.integers(-10, 45, n)
    rects = np.stack([x0, y0, x0 + rng.integers(-3, 40, n), y0 + rng.integers(-3, 30, n)], -1)
    rects = rects.astype(np.int32)

    def sums(v, r):
        return H.rect_sums(H.integral_image(v), r, 2, 8)

    batch = [(values, rects), (-values, rects[::-1].copy())]
    variants = ("plain", "jit", "vmap") if n == 21 else ("jit",)
    reference = functools.partial(_np_rect_sums, channels=2)
    check_kernel(sums, reference, batch[0], batch=batch, variants=variants, **EXACT)
    cols = tuple(jnp.asarray(rects[:, k].reshape(-1, 1).repeat(2, 1)) for k in range(4))
    paired = jax.jit(sums)(values, cols)
    np.testing.assert_array_equal(
        np.asarray(paired), _np_rect_sums(values, rects, 2)[:, None].repeat(2, 1)
    )


@pytest.mark.parametrize("n", [3, 16, 21])
def test_chunked_counts_and_ncc_equal_the_references(n, frames):
    # Blocks of 8 rects or boxes (one block, exact blocks, a partial last block):
    # rect_reduce slices each block's inputs in place, grid_ncc hands them on through the
    # loop (cut along the minor box axis); plainly, under jit and vmap (the second rect
    # set leaves the window: the batch takes the exact fallback).
    # The partial last block (21) runs all three ways, the other block counts under jit.
    variants = ("plain", "jit", "vmap") if n == 21 else ("jit",)
    imgs, _, _ = frames
    _, cloud = _cloud_rects(n, n=n)
    cloud_sets = [cloud, np.concatenate([cloud[: n // 2], EDGE_RECTS, cloud])[:n]]
    check_kernel(
        lambda img, r: H.rect_reduce(_bins(img), r, _identity, n_bins=NB, window=WINDOW, chunk=8),
        lambda img, r: _ref_hists(_hsv(np.asarray(img)), r),
        (imgs[0], cloud_sets[0]),
        batch=list(zip(imgs[:2], cloud_sets, strict=True)),
        variants=variants,
        **EXACT,
    )

    rng = np.random.default_rng(n)
    values = rng.integers(-4096, 4097, (37, 53, 3)).astype(np.int32)
    boxes = np.concatenate([rng.uniform(-10, 45, (n, 2)), rng.uniform(0, 30, (n, 2))], axis=1)
    boxes = boxes.astype(np.float32)
    template = rng.normal(size=3 * 2 * 3)
    template = (template - template.mean()) / np.linalg.norm(template - template.mean())
    template = template.astype(np.float32)

    def ncc(v, b):
        return H.grid_ncc(H.integral_image(v), b, template, 3, 2, chunk=8)

    def ncc_reference(v, b):
        out = []
        for box in np.asarray(b):
            s, c = _grid_reference(np.asarray(v), box, 3, 2)
            means = (s / np.maximum(c, 1)[..., None]).ravel()
            centred = means - means.mean()
            out.append(centred @ template / max(np.linalg.norm(centred), 1e-3))
        return np.asarray(out)

    batch = [(values, boxes), (-values, boxes)]
    check_kernel(ncc, ncc_reference, batch[0], batch=batch, variants=variants, rtol=1e-4, atol=1e-4)


def _grid_reference(values, box, rows, cols):
    """Plain-loop grid sums and pixel counts of one (x, y, w, h) box."""
    h, w = values.shape[:2]
    x, y, bw, bh = (float(v) for v in box)
    ys = [min(max(int(np.floor(y + bh * i / rows + 0.5)), 0), h) for i in range(rows + 1)]
    xs = [min(max(int(np.floor(x + bw * j / cols + 0.5)), 0), w) for j in range(cols + 1)]
    sums = np.zeros((rows, cols, values.shape[2]), values.dtype)
    counts = np.zeros((rows, cols), np.int32)
    for i in range(rows):
        for j in range(cols):
            cell = values[ys[i] : ys[i + 1], xs[j] : xs[j + 1]]
            sums[i, j] = cell.reshape(-1, values.shape[2]).sum(0)
            counts[i, j] = cell.shape[0] * cell.shape[1]
    return sums, counts


@pytest.mark.parametrize("rows,cols", [(1, 1), (3, 2), (12, 3)])
def test_grid_sums_match_loop(rows, cols):
    rng = np.random.default_rng(rows * 10 + cols)
    values = rng.integers(0, 256, (41, 57, 2)).astype(np.int32)
    boxes = np.array(
        [
            [3.2, 4.7, 20.0, 30.3],  # inside, fractional corners
            [-6.0, -3.0, 17.0, 21.0],  # partly outside (top-left)
            [45.5, 30.0, 25.0, 22.0],  # partly outside (bottom-right)
            [80.0, 50.0, 10.0, 10.0],  # wholly outside: empty cells
            [10.0, 10.0, 2.0, 2.0],  # smaller than the grid: some cells empty
        ],
        np.float32,
    )

    def kernel(v, b):
        return H.grid_sums(H.integral_image(v), b, rows, cols)

    def reference(v, b):
        expected = [_grid_reference(np.asarray(v), box, rows, cols) for box in np.asarray(b)]
        return np.stack([e[0] for e in expected]), np.stack([e[1] for e in expected])

    batch = [(values, boxes), (2 * values, boxes[::-1].copy())]
    check_kernel(kernel, reference, batch[0], batch=batch, **EXACT)
    # the cells partition the clipped rect: their sums add up to rect_sums
    table = H.integral_image(values)
    sums, _ = kernel(values, boxes)
    whole = H.rect_sums(table, B.xywh_to_rect(boxes))
    np.testing.assert_array_equal(np.asarray(sums.sum((1, 2))), np.asarray(whole))


# ----------------------------------------------------------------------------- distances


def test_bhattacharyya_matches_compare_hist():
    rng = np.random.default_rng(9)
    p = rng.random((20, NB)).astype(np.float32) * 100
    p[:5, : NB // 2] = 0  # sparse histograms
    q = rng.random(NB).astype(np.float32)
    d = np.asarray(_bhatt(p, q))
    ref = np.array([_cv_distance(h, q) for h in p])
    np.testing.assert_allclose(d, ref, atol=1e-6)


def test_bhattacharyya_special_cases():
    q = np.arange(NB, dtype=np.float32)
    disjoint = np.zeros(NB, np.float32)
    disjoint[0] = 5  # q[0] == 0: no overlap with q
    empty = np.zeros(NB, np.float32)
    d = np.asarray(_bhatt(np.stack([q * 3, disjoint, empty]), q))
    np.testing.assert_allclose(d, [0.0, 1.0, 1.0], atol=1e-6)
    assert np.isfinite(d).all()
    assert _cv_distance(disjoint, q) == pytest.approx(1.0)
    assert float(_bhatt(empty, empty)) == 1.0


def test_bhattacharyya_gradients_are_finite():
    q = jnp.zeros(NB).at[: NB // 2].set(1.0)
    for p in (q, q.at[0].set(0.0), jnp.zeros(NB)):
        g = jax.grad(lambda p: H.bhattacharyya(p, q))(p)
        assert np.isfinite(np.asarray(g)).all()


def _np_normalised(h) -> np.ndarray:
    """Each row divided by its sum when that is at least 1 (counts), else left as it is."""
    return np.stack([r / r.sum() if r.sum() >= 1 else r for r in np.asarray(h, np.float64)])


def test_normalise_counts_sums_to_one_and_leaves_empty_histograms_empty():
    counts = np.array([[3.0, 1.0, 0.0, 4.0], [0.0] * 4, [0.1, 0.2, 0.3, 0.4]], np.float32)
    np.testing.assert_allclose(
        _np_normalised(counts), [[3 / 8, 1 / 8, 0.0, 4 / 8], [0.0] * 4, [0.1, 0.2, 0.3, 0.4]]
    )
    check_kernel(H.normalise_counts, _np_normalised, (counts,), batch=[(counts,), (5 * counts,)])


def test_squared_bhattacharyya_matches_compare_hist():
    # d^2 from counts and their pixel count against cv2.compareHist squared: dense,
    # sparse, identical (d = 0), disjoint (d = 1) and empty histograms.
    rng = np.random.default_rng(9)
    q = rng.random(NB).astype(np.float32)
    q[:3] = 0
    counts = np.floor(rng.random((20, NB)) * 100).astype(np.float32)
    counts[:5, : NB // 2] = 0
    counts[5] = q * 1000  # proportional to q: d = 0
    counts[6] = 0
    counts[6, 0] = 7  # q[0] == 0: d = 1
    counts[7] = 0  # empty: d = 1
    sqrt_q = np.sqrt(q / q.sum()).astype(np.float32)

    def kernel(c, s):
        return H.squared_bhattacharyya(c, s, jnp.sum(c, axis=-1))

    def reference(c, s):
        q_ = np.asarray(s, np.float64) ** 2
        return np.array([_cv_distance(h, q_) ** 2 if h.sum() else 1.0 for h in np.asarray(c)])

    check_kernel(
        kernel,
        reference,
        (counts, sqrt_q),
        batch=[(counts, sqrt_q), (counts[::-1].copy(), sqrt_q)],
        **D2_TOLERANCE,
    )
    d2 = np.asarray(kernel(counts, sqrt_q))
    assert d2[5] == pytest.approx(0.0, abs=2e-6) and d2[6] == 1.0 and d2[7] == 1.0


def test_squared_distances_match_opencv_loop(frames):
    _, hsvs, bins = frames
    xywh, rects = _cloud_rects(10, n=200)
    q = _ref_hist(hsvs[0], rects[0])
    xywh[1] = xywh[0]  # identical histogram: d = 0
    rects = np.asarray(B.xywh_to_rect(xywh))
    assert _origin_and_covers(rects)[1]
    ref = _cv_squared_distances(hsvs[0], rects, q)
    _assert_squared_close(_sq_dist(bins[0], rects, q), ref)
    _assert_squared_close(_sq_dist_general(bins[0], rects, q), ref)


def test_squared_distances_of_edge_boxes_and_fallback(frames):
    _, hsvs, bins = frames
    xywh, _ = _cloud_rects(11, n=40)
    edge = np.array(
        [[-500, -500, 30, 30], [10, 10, 0, 0], [-20.4, -10.6, 60.2, 40.9], [300, 200, 80, 80]],
        np.float32,
    )
    rects = np.asarray(B.xywh_to_rect(np.concatenate([xywh, edge])))
    assert not _origin_and_covers(rects)[1]
    q = _ref_hist(hsvs[0], [120, 80, 180, 160])
    d2 = np.asarray(_sq_dist(bins[0], rects, q))
    _assert_squared_close(d2, _cv_squared_distances(hsvs[0], rects, q))
    assert d2[-4] == 1.0 and d2[-3] == 1.0  # empty boxes: the worst distance


def test_squared_distances_to_an_empty_reference_are_one(frames):
    _, _, bins = frames
    _, rects = _cloud_rects(12, n=8)
    d2 = np.asarray(_sq_dist(bins[0], rects, np.zeros(NB, np.float32)))
    np.testing.assert_array_equal(d2, 1.0)


def test_squared_distances_under_vmap_over_frames_and_box_sets(frames):
    imgs, hsvs, _ = frames
    xywh, rects = _cloud_rects(13, n=50)
    q = _ref_hist(hsvs[0], rects[0])
    box_sets = [xywh, xywh + np.float32([5, -3, 0, 0]), xywh * np.float32([1, 1, 1.1, 0.9])]
    rect_sets = [np.asarray(B.xywh_to_rect(b)) for b in box_sets]

    def kernel(img, rects):
        return _squared_distances(_bins(img), rects, q, window=WINDOW)

    def reference(img, rects):
        return _cv_squared_distances(_hsv(np.asarray(img)), rects, q)

    batch = list(zip(imgs, rect_sets, strict=True))
    check_kernel(kernel, reference, batch[0], batch=batch, **D2_TOLERANCE)
    # vmap over box sets only (one frame).
    out = np.asarray(
        jax.jit(jax.vmap(_sq_dist, in_axes=(None, 0, None)))(_bins(imgs[1]), np.stack(rect_sets), q)
    )
    for i in range(3):
        _assert_squared_close(out[i], _cv_squared_distances(hsvs[1], rect_sets[i], q))


def test_cell_distances_with_per_cell_references(frames):
    _, hsvs, bins = frames
    _, rects = _cloud_rects(14, n=30)
    half = (rects[:, 0] + rects[:, 2]) // 2
    cells = np.stack(
        [
            np.stack([rects[:, 0], rects[:, 1], half, rects[:, 3]], -1),
            np.stack([half, rects[:, 1], rects[:, 2], rects[:, 3]], -1),
        ],
        axis=1,
    )
    refs = _ref_hists(hsvs[0], cells[0])  # [2, NB]: one reference per cell
    d2 = np.asarray(_sq_dist(bins[0], cells, refs))
    assert d2.shape == (30, 2)
    ref = np.array(
        [
            [_cv_distance(_ref_hist(hsvs[0], c), refs[j]) ** 2 for j, c in enumerate(row)]
            for row in cells
        ]
    )
    _assert_squared_close(d2, ref)


def test_no_retrace_between_frames(frames):
    _, hsvs, bins = frames
    traces = []

    def distances(bins, rects, q):
        traces.append(None)  # runs once per trace, not per call
        return _squared_distances(bins, rects, q, window=WINDOW)

    f = jax.jit(distances)
    q = _ref_hist(hsvs[0], [10, 10, 60, 60])
    for seed in range(3):
        _, rects = _cloud_rects(20 + seed)
        f(bins[seed], rects, q).block_until_ready()
    assert len(traces) == 1


def test_box_histograms_count_each_rect_in_its_own_window(frames):
    # ``each``: every rect counted over a window of its own (placed on it, moved back inside
    # the frame at the edges); a rect larger than that window sends the call to the shared
    # window or the frame. Against the reference, under jit and vmap.
    _, hsvs, bins = frames
    cells = np.array(
        [
            [40, 30, 70, 70],
            [70, 30, 100, 70],
            [300, 200, 330, 245],
            [-10, -5, 20, 30],
            [5, 5, 5, 9],
        ],
        np.int32,
    )
    big = np.concatenate([cells[:2], [[10, 10, 90, 120]]]).astype(np.int32)
    count = jax.jit(lambda b, r: H.box_histograms(b, r, NB, WINDOW, each=(48, 32)))
    for rects in (cells, big, EDGE_RECTS[:4]):
        np.testing.assert_array_equal(np.asarray(count(bins[0], rects)), _ref_hists(hsvs[0], rects))
    both = jax.jit(jax.vmap(lambda b: H.box_histograms(b, cells, NB, WINDOW, each=(48, 32))))
    out = np.asarray(both(np.stack(bins[:2])))
    for i in range(2):
        np.testing.assert_array_equal(out[i], _ref_hists(hsvs[i], cells))
