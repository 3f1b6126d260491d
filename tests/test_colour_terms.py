"""Optional likelihood terms of the colour layer: "mixture" contrast weights and the
luminance layout term, against NumPy references under jit and vmap, and in the filter."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax import params as pp
from cpf_jax.colour import (
    COLOUR_BINS,
    ColourConfig,
    bin_index,
    build_colour_filter,
    contrast_weights,
    default_colour_params,
    layout_table,
    layout_vectors,
    luminance,
    mirror_layout,
    mixture_weights,
    n_bins_of,
)
from cpf_jax.colour.appearance import MIXTURE_MAX
from cpf_jax.filter import track_boxes
from cpf_jax.kernels.boxes import iou
from cpf_jax.kernels.histogram import grid_ncc, integral_image
from cpf_jax.types import Frame

H, W = 120, 160


def _frame(seed: int = 0, x: int = 60) -> tuple[Frame, np.ndarray]:
    """Red shirt over blue trousers (20 x 50 px) on a noisy grey-green floor that also
    fills the gap between the legs (the box is 30 px wide: a third of it is floor)."""
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3), np.uint8)
    img[..., 0] = 90 + rng.integers(0, 20, (H, W))
    img[..., 1] = 110 + rng.integers(0, 20, (H, W))
    img[..., 2] = 90 + rng.integers(0, 20, (H, W))
    img[35:60, x : x + 30] = (200, 30, 40)  # shirt
    img[60:85, x : x + 10] = (30, 40, 150)  # left leg
    img[60:85, x + 20 : x + 30] = (30, 40, 150)  # right leg
    frame = Frame(jnp.asarray(img), jnp.zeros((H, W), jnp.uint16))
    return frame, np.array([x, 35, 30, 50], np.float32)


def _box_and_ring(img: np.ndarray, box, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Plain NumPy: bin counts in the box and in the ring around it, by slicing (for
    boxes whose ring the frame does not cut off)."""
    idx = np.asarray(bin_index(jnp.asarray(img), COLOUR_BINS))
    n = n_bins_of(COLOUR_BINS)
    x, y, w, h = box

    def counts(x0, y0, x1, y1):
        x0, y0 = max(int(np.floor(x0 + 0.5)), 0), max(int(np.floor(y0 + 0.5)), 0)
        x1, y1 = min(int(np.floor(x1 + 0.5)), W), min(int(np.floor(y1 + 0.5)), H)
        return np.bincount(idx[y0:y1, x0:x1].ravel(), minlength=n).astype(np.float64)

    inside = counts(x, y, x + w, y + h)
    grown = counts(x - margin * w, y - margin * h, x + w + margin * w, y + h + margin * h)
    return inside, grown - inside


def _mixture_reference(img: np.ndarray, box, margin: float, fill: float) -> np.ndarray:
    """Plain NumPy: bin counts in the box and in the ring by slicing, then the LLR."""
    inside, ring = _box_and_ring(img, box, margin)
    n = inside.shape[0]
    p_bg = ring + 1e-3 * max(ring.sum(), 1.0) / n + 1e-6
    p_bg /= p_bg.sum()
    p_obj = np.maximum(inside / inside.sum() - (1 - fill) * p_bg, 0.0) + 1e-6
    p_obj /= p_obj.sum()
    return np.clip(np.log((1 - fill) + fill * p_obj / p_bg), -MIXTURE_MAX, MIXTURE_MAX)


@pytest.mark.parametrize("fill", [0.5, 0.7, 0.9])
def test_mixture_weights_match_numpy(fill):
    frame, box = _frame()
    got = jax.jit(lambda f, b, r: mixture_weights(f, b, COLOUR_BINS, 0.5, r))(frame, box, fill)
    want = _mixture_reference(np.asarray(frame.colour), box, 0.5, fill)
    np.testing.assert_allclose(np.asarray(got), want, atol=2e-4)


def test_mixture_weights_vmap_over_fill_and_boxes():
    frame, box = _frame()
    fills = jnp.array([0.6, 0.8])
    boxes = jnp.stack([box, box + np.array([-20, 10, 0, 0], np.float32)])
    got = jax.vmap(lambda b, r: mixture_weights(frame, b, COLOUR_BINS, 0.5, r))(boxes, fills)
    for k in range(2):
        want = _mixture_reference(
            np.asarray(frame.colour), np.asarray(boxes[k]), 0.5, float(fills[k])
        )
        np.testing.assert_allclose(np.asarray(got[k]), want, atol=2e-4)


def test_mixture_weights_penalise_background_inside_the_initial_box():
    """The floor fills a third of the box: the linear weights barely count it, the mixture
    weights count it as background (about log(1 - fill)), and person colours positive."""
    frame, box = _frame()
    idx = np.asarray(bin_index(frame.colour, COLOUR_BINS))
    shirt, floor = idx[40, 65], idx[5, 5]
    mix = np.asarray(mixture_weights(frame, box, fill=0.7))
    lin = np.asarray(contrast_weights(frame, box, threshold=0.3))
    assert mix[shirt] > 1.0 and mix[floor] < -0.5, (mix[shirt], mix[floor])
    assert lin[floor] > -0.3 + 0.05  # near-neutral: the floor is also in the box
    # so a box grown over the floor loses under the mixture weights

    def counts(x0, y0, x1, y1):
        return np.bincount(idx[y0:y1, x0:x1].ravel(), minlength=mix.shape[0])

    tight, wide = counts(60, 35, 90, 85), counts(50, 30, 100, 95)
    assert tight @ mix > wide @ mix


@pytest.mark.parametrize("unseen", ["background", "neutral"])
def test_linear_contrast_weights_match_numpy_under_jit_and_vmap(unseen):
    """``P(object | bin) - threshold`` with a prior of k = 1 % of the box's pixels at 0
    ("background") or at the threshold ("neutral"): colours seen neither in the box nor
    in its ring weigh -threshold or 0."""
    frame, box = _frame()
    boxes = jnp.stack([box, box + np.array([-20, 10, 0, 0], np.float32)])
    thr = 0.3
    run = jax.jit(
        jax.vmap(lambda b: contrast_weights(frame, b, COLOUR_BINS, 0.5, thr, unseen=unseen))
    )
    got = np.asarray(run(boxes))
    for k in range(2):
        inside, ring = _box_and_ring(np.asarray(frame.colour), np.asarray(boxes[k]), 0.5)
        prior = 0.01 * max(inside.sum(), 1.0)
        p0 = thr if unseen == "neutral" else 0.0
        want = (inside + prior * p0) / (inside + ring + prior) - thr
        np.testing.assert_allclose(got[k], want, atol=1e-5)
        never = (inside + ring) == 0
        assert never.sum() > 30  # most of the 72 bins occur in neither region
        unseen_weight = -thr if unseen == "background" else 0.0
        np.testing.assert_allclose(got[k][never], unseen_weight, atol=1e-6)


def test_neutral_unseen_colours_do_not_penalise_a_box_grown_over_them():
    """A white stripe (seen in neither the first box nor its ring) next to the person: a
    box grown over it loses contrast score with unseen colours as background, and keeps
    it with them neutral."""
    frame, box = _frame()
    img = np.asarray(frame.colour).copy()
    img[35:85, 90:100] = 255  # beside the person, outside the first box ...
    later = Frame(jnp.asarray(img), frame.depth)
    idx = np.asarray(bin_index(later.colour, COLOUR_BINS))
    tight, grown = idx[35:85, 60:90], idx[35:85, 60:100]
    for unseen, loses in (("background", True), ("neutral", False)):
        w = np.asarray(
            contrast_weights(frame, box, threshold=0.3, unseen=unseen)
        )  # ... and its ring
        assert abs(w[idx[40, 95]] - (-0.3 if loses else 0.0)) < 1e-6
        assert (w[grown].sum() < w[tight].sum() - 100) == loses, unseen
    with pytest.raises(ValueError, match="unseen"):
        contrast_weights(frame, box, unseen="ignore")


def test_luminance_matches_opencv():
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (37, 41, 3), dtype=np.uint8)
    want = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.int32)
    got = np.asarray(jax.jit(luminance)(jnp.asarray(img)))
    assert np.abs(got - want).max() <= 1  # OpenCV rounds in fixed point


def _layout_reference(feat: np.ndarray, box, rows: int, cols: int) -> np.ndarray:
    """feat [h, w] or [h, w, c] -> the zero-mean unit-norm vector of cell means."""
    feat = feat.reshape(*feat.shape[:2], -1).astype(np.float64)
    h, w = feat.shape[:2]
    x, y, bw, bh = box
    ys = [min(max(int(np.floor(y + bh * i / rows + 0.5)), 0), h) for i in range(rows + 1)]
    xs = [min(max(int(np.floor(x + bw * j / cols + 0.5)), 0), w) for j in range(cols + 1)]
    means = np.zeros((rows, cols, feat.shape[2]))
    for i in range(rows):
        for j in range(cols):
            cell = feat[ys[i] : ys[i + 1], xs[j] : xs[j + 1]]
            means[i, j] = cell.mean(axis=(0, 1)) if cell.size else 0.0
    v = means.ravel() - means.mean()
    return v / max(np.linalg.norm(v), 1e-3)


def _gradient_reference(lum: np.ndarray) -> np.ndarray:
    """[h, w] luminance -> [h, w, 4] rounded gradient magnitude per orientation bin, from
    np.gradient and arctan2 (the kernel bins without either)."""
    gy, gx = np.gradient(np.pad(lum.astype(np.float64), 1, mode="edge"))
    gy, gx = gy[1:-1, 1:-1], gx[1:-1, 1:-1]
    theta = np.degrees(np.arctan2(gy, gx)) % 180.0
    b = np.floor(((theta + 22.5) % 180.0) / 45.0).astype(int)
    out = np.zeros((*lum.shape, 4))
    np.put_along_axis(out, b[..., None], np.round(np.hypot(gx, gy))[..., None], axis=-1)
    return out


def test_gradient_layout_table_matches_numpy_under_jit_and_vmap():
    frame, _ = _frame()
    lum = np.asarray(luminance(frame.colour))
    f = jax.jit(lambda c: layout_table(c, "gradient"))
    got = np.asarray(f(frame.colour))
    want = _gradient_reference(lum)
    assert got.shape == (H + 1, W + 1, 4) and got.dtype == np.int32
    per_pixel = np.diff(np.diff(got, axis=0), axis=1)
    # exact except where an angle sits on a bin edge (float rounding picks a side)
    assert (per_pixel == want).all(axis=-1).mean() > 0.999
    np.testing.assert_array_equal(per_pixel.sum(-1), want.sum(-1))
    # vmap over frames; a uniform frame has no edges
    flat = jnp.full_like(frame.colour, 90)
    both = np.asarray(jax.vmap(f)(jnp.stack([frame.colour, flat])))
    np.testing.assert_array_equal(both[0], got)
    assert both[1].max() == 0
    # luminance table: the plain summed-area table of the luminance
    lt = np.asarray(layout_table(frame.colour))
    np.testing.assert_array_equal(lt[1:, 1:, 0], lum.cumsum(0).cumsum(1))


@pytest.mark.parametrize("grid", [(12, 3), (6, 2)])
def test_gradient_layout_vectors_match_numpy(grid):
    frame, box = _frame()
    feat = _gradient_reference(np.asarray(luminance(frame.colour)))
    boxes = np.array([box, [3.3, 7.6, 40.2, 70.9], [-10, -5, 40, 50]], np.float32)
    table = layout_table(frame.colour, "gradient")
    f = jax.jit(jax.vmap(lambda b: layout_vectors(table, b, grid)))
    got = np.asarray(f(boxes))
    want = np.stack([_layout_reference(feat, b, *grid) for b in boxes])
    assert got.shape == (3, grid[0] * grid[1] * 4)
    np.testing.assert_allclose(got, want, atol=2e-3)


@pytest.mark.parametrize("grid", [(12, 3), (4, 1), (5, 4)])
def test_layout_vectors_match_numpy_under_jit_and_vmap(grid):
    frame, box = _frame()
    lum = np.asarray(luminance(frame.colour))
    boxes = np.array(
        [box, [3.3, 7.6, 40.2, 70.9], [-10, -5, 40, 50], [150, 110, 30, 30]], np.float32
    )
    f = jax.jit(lambda c, b: layout_vectors(integral_image(luminance(c)[..., None]), b, grid))
    got = np.asarray(f(frame.colour, boxes))
    want = np.stack([_layout_reference(lum, b, *grid) for b in boxes])
    np.testing.assert_allclose(got, want, atol=1e-4)
    # unit norm (or zero for a box of uniform brightness), NCC with itself 1
    np.testing.assert_allclose(got[0] @ got[0], 1.0, atol=1e-5)
    # vmap over frames: a brightness gain and offset leaves the person's vector unchanged
    # (up to the rounding of the darker image; the noise-only boxes are all rounding)
    darker = (frame.colour.astype(jnp.int32) // 2 + 40).astype(jnp.uint8)
    both = jax.vmap(f, in_axes=(0, None))(jnp.stack([frame.colour, darker]), boxes[:1])
    np.testing.assert_allclose(np.asarray(both[0]), got[:1], atol=1e-5)
    np.testing.assert_allclose(np.asarray(both[1]), got[:1], atol=0.03)


def test_layout_tells_an_upside_down_box_apart():
    frame, box = _frame()
    table = integral_image(luminance(frame.colour)[..., None])
    v = layout_vectors(table, jnp.asarray(box), (12, 3))
    flipped = layout_vectors(
        integral_image(luminance(frame.colour[::-1])[..., None]),
        jnp.asarray([box[0], H - box[1] - box[3], box[2], box[3]]),
        (12, 3),
    )
    assert float(v @ flipped) < 0.0


@pytest.mark.parametrize("feature,grid", [("luminance", (12, 3)), ("gradient", (6, 2))])
def test_grid_ncc_matches_numpy_under_jit_and_vmap(feature, grid):
    """The step's fused NCC (``grid_ncc``, blocks of boxes) equals the NumPy cell-mean
    vectors' dot product with the template, for boxes inside, across and outside the
    frame, a uniform box, and a box count that leaves a partial last block."""
    frame, box = _frame()
    lum = np.asarray(luminance(frame.colour))
    feat = lum if feature == "luminance" else _gradient_reference(lum)
    rng = np.random.default_rng(5)
    n = 37
    lo, hi = [-30, -30, 4, 4], [W, H, 70, 90]
    boxes = rng.uniform(lo, hi, (n, 4)).astype(np.float32)
    boxes[:4] = [box, [-10, -5, 40, 50], [W + 5, 10, 20, 30], [3.3, 7.6, 40.2, 70.9]]
    template = _layout_reference(feat, box, *grid)
    want = np.stack([_layout_reference(feat, b, *grid) for b in boxes]) @ template
    table = layout_table(frame.colour, feature)
    t = jnp.asarray(template, jnp.float32)
    f = jax.jit(lambda b: grid_ncc(table, b, t, *grid, chunk=16))  # 16 + 16 + 5 boxes
    got = np.asarray(f(jnp.asarray(boxes)))
    np.testing.assert_allclose(got, want, atol=2e-3)
    assert abs(got[0] - 1.0) < 1e-3 and got[2] == 0.0  # itself; a box off the frame
    # one block (chunk=None) and vmap over two templates agree with the blocks
    g = jax.jit(jax.vmap(lambda tt: grid_ncc(table, jnp.asarray(boxes), tt, *grid, chunk=None)))
    both = np.asarray(g(jnp.stack([t, -t])))
    np.testing.assert_allclose(both[0], got, atol=1e-5)
    np.testing.assert_allclose(both[1], -got, atol=1e-5)
    # two templates at once: [N, 2], the same as one at a time
    two = np.asarray(
        jax.jit(lambda b: grid_ncc(table, b, jnp.stack([t, -t]), *grid, chunk=16))(
            jnp.asarray(boxes)
        )
    )
    assert two.shape == (n, 2)
    np.testing.assert_allclose(two, np.stack([got, -got], -1), atol=1e-5)
    # a box of uniform feature scores 0, not NaN
    flat = layout_table(jnp.full_like(frame.colour, 90), feature)
    assert float(grid_ncc(flat, jnp.asarray(boxes[:1]), t, *grid)[0]) == 0.0


@pytest.mark.parametrize("feature,grid", [("luminance", (12, 3)), ("gradient", (6, 2))])
def test_mirrored_layout_is_the_layout_of_the_mirrored_frame(feature, grid):
    """``mirror_layout`` of a box's template equals the template of the same box in the
    horizontally flipped frame (NumPy reference features), so a person who turns round
    scores as his first view did."""
    frame, box = _frame()
    lum = np.asarray(luminance(frame.colour))
    flip = lum[:, ::-1]
    feat, feat_flip = (
        (lum, flip)
        if feature == "luminance"
        else (_gradient_reference(lum), _gradient_reference(flip))
    )
    mirrored_box = np.array([W - box[0] - box[2], box[1], box[2], box[3]], np.float32)
    want = _layout_reference(feat_flip, mirrored_box, *grid)
    got = np.asarray(mirror_layout(jnp.asarray(_layout_reference(feat, box, *grid)), grid, feature))
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert abs(float(np.dot(got, want)) - 1.0) < 1e-4


def _moving(n: int) -> tuple[Frame, np.ndarray]:
    frames, boxes = zip(*(_frame(seed=t, x=20 + 3 * t) for t in range(n)), strict=True)
    colour = jnp.stack([f.colour for f in frames])
    return Frame(colour, jnp.zeros(colour.shape[:3], jnp.uint16)), np.stack(boxes)


@pytest.mark.parametrize(
    "contrast,layout,feature",
    [
        ("mixture", None, "luminance"),
        ("linear", (12, 3), "luminance"),
        ("mixture", (12, 3), "luminance"),
        ("linear", (6, 2), "gradient"),
    ],
)
def test_filter_tracks_with_the_optional_terms(contrast, layout, feature):
    """Stated threshold: IoU >= 0.5 on >= 95 % of 30 frames, with the term switched on."""
    frames, gt = _moving(30)
    # (The mirrored layout runs through a filter in tests/test_cli.py.)
    config = ColourConfig(n_particles=128, contrast=contrast, layout=layout, layout_feature=feature)
    params = pp.replace(default_colour_params(), "layout.rate", jnp.float32(0.05))
    filt = build_colour_filter(config)
    boxes, lost = jax.jit(lambda k: track_boxes(filt, params, k, frames, gt[0]))(
        jax.random.PRNGKey(0)
    )
    boxes = np.asarray(boxes)
    assert np.isfinite(boxes).all() and not np.asarray(lost).any()
    ious = np.asarray(iou(jnp.asarray(boxes), jnp.asarray(gt)))
    assert (ious >= 0.5).mean() >= 0.95, ious.round(2)


@pytest.mark.parametrize("layout", [None, (7, 3)])
def test_no_contrast_term_is_the_linear_contrast_at_weight_zero(layout):
    """``contrast=None`` drops the centre-surround term and its summed-area table: the
    same boxes as the linear contrast with ``contrast.weight = 0``, whatever the weight
    (then unused); with a layout, the layout reads the table's first channel."""
    frames, gt = _moving(8)
    zero = pp.replace(default_colour_params(), "contrast.weight", jnp.float32(0.0))

    def run(contrast, params):
        config = ColourConfig(n_particles=64, contrast=contrast, layout=layout)
        filt = build_colour_filter(config)
        return np.asarray(
            jax.jit(lambda k: track_boxes(filt, params, k, frames, gt[0])[0])(jax.random.PRNGKey(3))
        )

    off = run(None, default_colour_params())
    np.testing.assert_allclose(off, run("linear", zero), rtol=1e-6, atol=1e-4)
    if layout is None:
        # The default weight moves the boxes, so the comparison above can fail.
        assert np.abs(off - run("linear", default_colour_params())).max() > 0.1


def test_config_rejects_bad_terms():
    with pytest.raises(ValueError, match="contrast"):
        ColourConfig(contrast="ratio")
    with pytest.raises(ValueError, match="layout"):
        ColourConfig(layout=(0, 3))
    with pytest.raises(ValueError, match="layout_feature"):
        ColourConfig(layout=(6, 2), layout_feature="hog")
    with pytest.raises(ValueError, match="unseen"):
        ColourConfig(unseen="ignore")


def test_contrast_weights_do_not_depend_on_how_much_ring_the_frame_cuts_off():
    """A person filling the frame's height (close to the camera): the ring above and
    below is mostly outside the frame. The floor's weight must match the one computed
    with the whole ring in view (the same scene padded with more floor): a cut-off
    ring must not make a background colour look like the person's (walk_away)."""
    rng = np.random.default_rng(5)
    big = np.empty((220, 160, 3), np.uint8)
    big[..., 0] = 90 + rng.integers(0, 20, big.shape[:2])
    big[..., 1] = 110 + rng.integers(0, 20, big.shape[:2])
    big[..., 2] = 90 + rng.integers(0, 20, big.shape[:2])
    big[60:110, 60:90] = (200, 30, 40)  # shirt
    big[110:160, 60:70] = (30, 40, 150)  # legs, floor between them
    big[110:160, 80:90] = (30, 40, 150)
    box_big = np.array([60, 60, 30, 100], np.float32)
    crop = big[50:170]  # 120 rows: 10 px of ring left above and below the box
    box_crop = box_big - np.array([0, 50, 0, 0], np.float32)
    weights = jax.jit(lambda f, b: contrast_weights(f, b, threshold=0.3))
    full = np.asarray(weights(Frame(jnp.asarray(big), jnp.zeros(big.shape[:2])), box_big))
    cut = np.asarray(weights(Frame(jnp.asarray(crop), jnp.zeros(crop.shape[:2])), box_crop))
    idx = np.asarray(bin_index(jnp.asarray(crop), COLOUR_BINS))
    floor = np.bincount(idx[120 - 10 :, :50].ravel(), minlength=full.shape[0])
    floor = floor / floor.sum()
    # the floor's weight, averaged over its noisy bins, with and without the cut
    assert abs(floor @ full - floor @ cut) < 0.02, (floor @ full, floor @ cut)
    assert floor @ cut < -0.15  # background, not neutral
    shirt = idx[60, 70]
    np.testing.assert_allclose(cut[shirt], full[shirt], atol=0.02)
