"""Colour-layer filter: structure (jit, scan, vmap, no retracing), degenerate inputs, tracking."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.colour import (
    CONTRAST_SCALE,
    ColourConfig,
    _box_columns,
    _estimate,
    _rect_columns,
    _to_xywh,
    bin_index,
    box_parts,
    build_colour_filter,
    contrast_table,
    default_colour_params,
    reference_histogram,
    track,
    track_boxes,
)
from cpf_jax.kernels.boxes import iou, xywh_to_rect
from cpf_jax.kernels.histogram import box_histograms, grid_ncc, integral_image, rect_sums
from cpf_jax.types import Filter, Frame

H, W = 120, 160


def _scene(t: int, x0: float = 30.0, speed: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A red-over-blue 'person' (20x50 px) moving right over a textured green-grey background."""
    rng = np.random.default_rng(t)
    img = np.empty((H, W, 3), np.uint8)
    img[..., 0] = 90 + rng.integers(0, 20, (H, W))
    img[..., 1] = 110 + rng.integers(0, 20, (H, W))
    img[..., 2] = 90 + rng.integers(0, 20, (H, W))
    x = int(round(x0 + speed * t))
    img[35:60, x : x + 20] = (200, 30, 40)  # shirt
    img[60:85, x : x + 20] = (30, 40, 150)  # trousers
    return img, np.array([x, 35, 20, 50], np.float32)


def _frames(n: int, **kw) -> tuple[Frame, np.ndarray]:
    imgs, boxes = zip(*(_scene(t, **kw) for t in range(n)), strict=True)
    colour = jnp.asarray(np.stack(imgs))
    return Frame(colour, jnp.zeros(colour.shape[:3], jnp.uint16)), np.stack(boxes)


@pytest.fixture(scope="module")
def seq():
    return _frames(30)


CONFIG = ColourConfig(n_particles=128)
FILTER = build_colour_filter(CONFIG)
PARAMS = default_colour_params()


def test_reference_histogram_parts_are_normalised():
    frames, boxes = _frames(1)
    ref = reference_histogram(Frame(frames.colour[0], frames.depth[0]), boxes[0], parts=2)
    assert ref.shape == (2, CONFIG.n_bins)
    np.testing.assert_allclose(np.asarray(ref.sum(-1)), 1.0, rtol=1e-6)
    # the two stripes see different colours (shirt vs trousers)
    assert int(jnp.argmax(ref[0])) != int(jnp.argmax(ref[1]))


def test_tracks_a_moving_box_under_scan(seq):
    frames, gt = seq
    boxes = np.asarray(
        jax.jit(lambda k: track_boxes(FILTER, PARAMS, k, frames, gt[0]))(jax.random.PRNGKey(0))
    )
    assert boxes.shape == (30, 4) and np.isfinite(boxes).all()
    ious = np.asarray(iou(boxes, gt))
    assert (ious >= 0.5).mean() >= 0.95, ious.round(2)


def test_motion_guided_walk_follows_a_fast_box_that_the_plain_walk_lags():
    """8 px/frame, 64 particles: the plain random walk's noise (about 4 px for this
    50 px box) trails the box; the guided share drifts with the estimate's velocity.
    The motion model is under test: the histogram-only likelihood, with which the
    thresholds were set (the default's guided IoUs: 0.85-0.92, plain 0.70-0.84)."""
    frames, gt = _frames(16, x0=5.0, speed=8.0)
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    mean_iou = {}
    for guided in (True, False):
        config = ColourConfig(n_particles=64, hierarchical=guided).histogram_only()
        filt = build_colour_filter(config)
        state, infos = jax.jit(
            jax.vmap(lambda k, filt=filt: track(filt, PARAMS, k, frames, gt[0]))
        )(keys)
        boxes = np.concatenate([np.broadcast_to(gt[:1], (4, 1, 4)), infos.estimate], axis=1)
        mean_iou[guided] = np.array([np.mean(np.asarray(iou(b, gt))) for b in boxes])
        if guided:  # the smoothed estimate velocity the guidance uses
            np.testing.assert_allclose(np.asarray(state.velocity), [[8.0, 0.0]] * 4, atol=1.0)
    assert (mean_iou[True] >= 0.85).all(), mean_iou
    assert mean_iou[True].mean() > mean_iou[False].mean() + 0.05, mean_iou


@pytest.mark.run_bound
def test_ar1_size_velocity_decay_stops_an_inherited_shrinking_drift():
    """AR1: every particle starts with the box shrinking 1 x 2.5 px/frame (5 %/frame,
    as a cloud that collapsed on a narrowing silhouette) on a standing person 50 px
    tall. Stated thresholds on the estimate's mean height over the last 5 of 40
    frames, 8 keys: with the default decay every key within 15 % of the person's;
    without it (the thesis's undamped velocity) at least three keys off by more
    than 15 %, as the velocity random-walks either way (measured with the default
    layout 7x3: 50.1-53.7 px, and 18-59 px with five keys of eight outside). The size hold is
    off: it damps the guided particles' size velocities too, since a standing
    person's particles move with noise velocities (with it, undamped: 35-52 px)."""
    frames, gt = _frames(40, speed=0.0)
    no_hold = PARAMS._replace(motion=PARAMS.motion._replace(size_hold=jnp.float32(0.0)))
    filt = build_colour_filter(ColourConfig(n_particles=128, model="ar1"))

    def init_shrinking(*args):
        state = filt.init(*args)
        return state._replace(particles=state.particles.at[:, 6].set(-1.0).at[:, 7].set(-2.5))

    shrinking = Filter(init=init_shrinking, step=filt.step)
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    run = jax.jit(
        lambda p: jax.lax.map(lambda k: track(shrinking, p, k, frames, gt[0])[1].estimate, keys)
    )
    default = float(PARAMS.size_velocity_decay)
    height = {}
    for decay in (default, 1.0):
        est = np.asarray(run(no_hold._replace(size_velocity_decay=jnp.float32(decay))))
        height[decay] = est[:, -5:, 3].mean(axis=1)
    assert default < 1.0
    assert (np.abs(height[default] / 50 - 1) <= 0.15).all(), height
    assert (np.abs(height[1.0] / 50 - 1) > 0.15).sum() >= 3, height


def test_step_state_and_info_are_finite_and_shaped(seq):
    frames, gt = seq
    f0 = Frame(frames.colour[0], frames.depth[0])
    state = jax.jit(FILTER.init)(PARAMS, jax.random.PRNGKey(0), f0, gt[0])
    state, info = jax.jit(FILTER.step)(
        PARAMS, jax.random.PRNGKey(1), state, Frame(frames.colour[1], frames.depth[1])
    )
    assert state.particles.shape == (128, 8) and state.log_weights.shape == (128,)
    assert 1.0 <= float(info.ess) <= 128.0
    for leaf in jax.tree_util.tree_leaves((state, info)):
        assert np.isfinite(np.asarray(leaf, np.float32)).all()


def test_no_retracing_from_frame_to_frame(seq):
    frames, gt = seq
    traces = []

    def counted(params, key, state, frame):
        traces.append(1)
        return FILTER.step(params, key, state, frame)

    step = jax.jit(counted)
    state = FILTER.init(
        PARAMS, jax.random.PRNGKey(0), Frame(frames.colour[0], frames.depth[0]), gt[0]
    )
    for t in range(1, 6):
        state, _ = step(
            PARAMS, jax.random.PRNGKey(t), state, Frame(frames.colour[t], frames.depth[t])
        )
    assert len(traces) == 1


def test_vmap_over_seeds_and_over_sigma(seq):
    frames, gt = seq
    short = jax.tree_util.tree_map(lambda x: x[:8], frames)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    by_seed = jax.vmap(lambda k: track_boxes(FILTER, PARAMS, k, short, gt[0]))(keys)
    assert by_seed.shape == (3, 8, 4)
    assert not np.allclose(np.asarray(by_seed[0]), np.asarray(by_seed[1]))  # seeds differ
    sigmas = jnp.array([0.05, 0.1, 0.3])
    by_sigma = jax.vmap(
        lambda s: track_boxes(FILTER, PARAMS._replace(sigma=s), keys[0], short, gt[0])
    )(sigmas)
    assert by_sigma.shape == (3, 8, 4) and np.isfinite(np.asarray(by_sigma)).all()


# Each model with one of the two non-default estimators (both estimators twice): the
# model and the estimator are independent parts of the step, and every pair is a compile.
@pytest.mark.parametrize(
    "model, estimator",
    [("ar1_fixed", "map"), ("ar2", "robust"), ("ar2_fixed", "robust"), ("random_walk", "map")],
)
def test_every_model_and_estimator_runs(seq, model, estimator):
    frames, gt = seq
    short = jax.tree_util.tree_map(lambda x: x[:6], frames)
    filt = build_colour_filter(
        ColourConfig(
            n_particles=32,
            model=model,
            estimator=estimator,
            resampler="residual",
            ess_threshold=0.5,
        )
    )
    boxes = np.asarray(track_boxes(filt, PARAMS, jax.random.PRNGKey(0), short, gt[0]))
    assert np.isfinite(boxes).all()
    if model.endswith("_fixed"):
        np.testing.assert_allclose(boxes[:, 2:], np.tile(gt[0, 2:], (6, 1)), rtol=1e-5)


def test_invalid_weights_fall_back_to_uniform_without_nan(seq):
    frames, gt = seq
    bad = PARAMS._replace(sigma=jnp.float32(jnp.nan))
    _, infos = track(
        FILTER, bad, jax.random.PRNGKey(0), jax.tree_util.tree_map(lambda x: x[:4], frames), gt[0]
    )
    assert bool(jnp.all(infos.weights_invalid)) and bool(jnp.all(infos.lost))
    assert np.isfinite(np.asarray(infos.estimate)).all()


def test_lost_target_is_flagged_and_found_again():
    """The person vanishes for 5 frames, then reappears 60 px away: lost, then re-acquired."""
    imgs, boxes = [], []
    for t in range(24):
        img, box = _scene(t, x0=20.0, speed=1.0)
        if 8 <= t < 13:
            img, _ = _scene(t, x0=-1000.0)  # person out of view (empty slice)
        if t >= 13:
            img, box = _scene(t, x0=80.0, speed=1.0)
        imgs.append(img)
        boxes.append(box)
    colour = jnp.asarray(np.stack(imgs))
    frames = Frame(colour, jnp.zeros(colour.shape[:3], jnp.uint16))
    filt = build_colour_filter(ColourConfig(n_particles=256, recovery_fraction=0.3))
    _, infos = jax.jit(lambda k: track(filt, PARAMS, k, frames, boxes[0]))(jax.random.PRNGKey(2))
    lost = np.asarray(infos.lost)  # infos[t - 1] belongs to frame t
    assert lost[7:12].all() and not lost[:6].any()
    ious = np.asarray(iou(np.asarray(infos.estimate[-4:]), np.stack(boxes[-4:])))
    assert (ious > 0.5).all(), ious


def test_config_validation():
    with pytest.raises(ValueError, match="model"):
        ColourConfig(model="nope")
    with pytest.raises(ValueError, match="n_particles"):
        ColourConfig(n_particles=0)
    with pytest.raises(ValueError, match="estimator"):
        ColourConfig(estimator="median")
    with pytest.raises(ValueError, match="chunk"):
        ColourConfig(chunk=0)
    with pytest.raises(ValueError, match="rng"):
        ColourConfig(rng="mt19937")


@pytest.mark.parametrize(
    "box, message, traced",
    [
        ([np.nan, 10, 20, 30], "four finite numbers", [np.nan, 10, 20, 30]),
        ([10, 10, 1, 30], "smaller than 2x2", [10, 10, 0, 30]),
        ([W + 5, 10, 20, 30], "outside the 160x120 frame", None),
        ([-40, -40, 20, 30], "outside", None),
    ],
)
def test_init_rejects_a_box_that_cannot_start_a_track(seq, box, message, traced):
    """A concrete bad box is a ValueError naming it; under jit (no value to check) a box
    that is not finite or has no size (``traced``) starts from the whole frame, lost,
    never NaN."""
    frames, _ = seq
    f0 = Frame(frames.colour[0], frames.depth[0])
    with pytest.raises(ValueError, match=message):
        FILTER.init(PARAMS, jax.random.key(0), f0, jnp.asarray(box, jnp.float32))
    if traced is not None:
        bad = jnp.asarray(traced, jnp.float32)
        state = jax.jit(FILTER.init)(PARAMS, jax.random.key(0), f0, bad)
        assert bool(state.lost)
        np.testing.assert_array_equal(state.estimate, [0, 0, W, H])
        f1 = Frame(frames.colour[1], frames.depth[1])
        state, info = jax.jit(FILTER.step)(PARAMS, jax.random.key(1), state, f1)
        assert np.isfinite(np.asarray(info.estimate)).all()


def test_frames_of_the_wrong_kind_are_a_clear_error(seq):
    """Colour must be [H, W, 3] uint8 and depth [H, W]: checked from shapes and dtypes, so
    under jit too, before a float image in [0, 1] or an RGBA one is binned as 8-bit RGB."""
    from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params

    frames, boxes = seq
    colour, depth = frames.colour[0], frames.depth[0]
    box = jnp.asarray(boxes[0])
    state = FILTER.init(PARAMS, jax.random.key(0), Frame(colour, depth), box)
    step = jax.jit(FILTER.step)
    bad = [
        (Frame(colour.astype(jnp.float32) / 255.0, depth), "uint8 RGB, got float32"),
        (Frame(jnp.pad(colour, ((0, 0), (0, 0), (0, 1))), depth), "shape (120, 160, 4)"),
        (Frame(colour[..., 0], depth), "shape (120, 160)"),
    ]
    for frame, message in bad:
        with pytest.raises(ValueError, match=re.escape(message)):
            FILTER.init(PARAMS, jax.random.key(0), frame, box)
        with pytest.raises(ValueError, match=re.escape(message)):
            step(PARAMS, jax.random.key(1), state, frame)
    # The colour layer never reads depth: none, or raw depth of another size, is fine.
    FILTER.init(PARAMS, jax.random.key(0), Frame(colour, None), box)
    FILTER.init(PARAMS, jax.random.key(0), Frame(colour, depth[::2]), box)
    config = RGBDConfig(n_particles=16)
    rgbd, rgbd_params = build_rgbd_filter(config), default_rgbd_params(config)
    for depth_in, message in [
        (None, "RGB-D models need"),
        (depth[::2], "like the colour, got shape [60, 160]"),
    ]:
        with pytest.raises(ValueError, match=re.escape(message)):
            rgbd.init(rgbd_params, jax.random.key(0), Frame(colour, depth_in), box)


def test_builders_return_one_filter_per_config():
    """``memoised_build``: equal configs (built apart) give the same ``Filter`` object, so
    ``jax.jit`` of its step reuses JAX's caches; a different config gets its own."""
    import dataclasses

    from cpf_jax.cascade import CascadeConfig, build_cascade
    from cpf_jax.points import PointFilterConfig, build_point_filter
    from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter

    a = ColourConfig(n_particles=77).with_window((40, 90), (H, W))
    b = ColourConfig(n_particles=77).with_window((40.0, 90.0), (H, W))
    assert a == b and a is not b
    assert build_colour_filter(a) is build_colour_filter(b)
    other = dataclasses.replace(a, estimator="map")
    assert build_colour_filter(a) is not build_colour_filter(other)
    for build, config, change in [
        (build_rgbd_filter, RGBDConfig(n_particles=33), {"n_particles": 34}),
        (build_point_filter, PointFilterConfig(n_particles=9), {"n_particles": 10}),
        (build_cascade, CascadeConfig(box=RGBDConfig(n_particles=33)), {"foreground": True}),
    ]:
        assert build(config) is build(dataclasses.replace(config))
        assert build(config) is not build(dataclasses.replace(config, **change))


def test_chunk_size_does_not_change_the_step(seq):
    # Blocking the gathers is a speed setting only: chunked and unchunked steps agree.
    frames, boxes = seq
    frame = Frame(frames.colour[1], frames.depth[1])
    outs = []
    for chunk in (None, 48):
        config = ColourConfig(n_particles=200, chunk=chunk).with_window((20, 50), (H, W))
        filt = build_colour_filter(config)
        f0 = Frame(frames.colour[0], frames.depth[0])
        state = filt.init(PARAMS, jax.random.key(0), f0, jnp.asarray(boxes[0]))
        state, info = jax.jit(filt.step)(PARAMS, jax.random.key(1), state, frame)
        outs.append((np.asarray(state.particles), np.asarray(info.estimate)))
    np.testing.assert_allclose(outs[0][0], outs[1][0], atol=1e-4)
    np.testing.assert_allclose(outs[0][1], outs[1][1], atol=1e-3)


def test_contrast_sums_equal_histogram_dot_weights(seq):
    """The contrast table gives each box's ``counts @ weights`` (to 1 / 4096 per pixel)."""
    frames, _ = seq
    idx = bin_index(frames.colour[0], CONFIG.bins)
    weights = jnp.asarray(np.random.default_rng(0).uniform(-0.4, 0.6, CONFIG.n_bins), jnp.float32)
    boxes = jnp.array([[30, 35, 20, 50], [-5, 10, 40, 40], [150, 100, 30, 30], [0, 0, 160, 120.0]])
    rects = xywh_to_rect(boxes)
    counts = box_histograms(idx, rects, CONFIG.n_bins)
    sums = jax.jit(lambda i, w, r: rect_sums(contrast_table(i, w), r))(idx, weights, rects)
    area = np.asarray(counts.sum(-1))
    tol = area / (2 * CONTRAST_SCALE) + 1e-3
    got = np.asarray(sums) / CONTRAST_SCALE
    assert (np.abs(got[:, 0] - np.asarray(counts @ weights)) <= tol).all()
    assert (np.abs(got[:, 1] - np.asarray(counts @ jnp.maximum(weights, 0))) <= tol).all()


@pytest.mark.parametrize("contain", [True, False])
def test_windowed_filter_tracks_with_and_without_containment(seq, contain):
    """Stated threshold: mean IoU >= 0.6 with the fast windowed path, either window placement."""
    frames, boxes = seq
    config = ColourConfig(n_particles=128, contain=contain).with_window((20, 50), (H, W))
    assert config.window[0] < H or config.window[1] < W
    out = np.asarray(
        jax.jit(lambda k, f, b: track_boxes(build_colour_filter(config), PARAMS, k, f, b))(
            jax.random.key(1), frames, jnp.asarray(boxes[0])
        )
    )
    assert np.mean(np.asarray(iou(jnp.asarray(out), jnp.asarray(boxes)))) >= 0.6


def test_info_reports_whether_the_window_path_ran(seq):
    # A settled cloud is counted in the window; particles whose boxes outgrow the
    # window take the exact whole-frame fallback and the step says so; without a
    # window there is no windowed path. The estimate stays the same either way.
    frames, boxes = seq
    config = ColourConfig(n_particles=64).with_window((20, 50), (H, W))
    filt = build_colour_filter(config)
    f1 = Frame(frames.colour[1], frames.depth[1])
    state = jax.jit(filt.init)(
        PARAMS, jax.random.key(0), Frame(frames.colour[0], frames.depth[0]), boxes[0]
    )
    step = jax.jit(filt.step)
    _, info = step(PARAMS, jax.random.key(1), state, f1)
    assert bool(info.windowed)
    big = state._replace(particles=state.particles.at[0, 5].set(config.window[0] + 10.0))
    _, info_big = step(PARAMS, jax.random.key(1), big, f1)
    assert not bool(info_big.windowed)
    plain = build_colour_filter(ColourConfig(n_particles=64))
    state = plain.init(
        PARAMS, jax.random.key(0), Frame(frames.colour[0], frames.depth[0]), boxes[0]
    )
    assert not bool(jax.jit(plain.step)(PARAMS, jax.random.key(1), state, f1)[1].windowed)


@pytest.mark.parametrize("window", [True, False], ids=["window", "whole-frame"])
def test_estimate_distance_equals_a_direct_count(seq, window):
    # The estimate's histogram comes from the particles' integral table (rect_reduce
    # then=); it must equal a direct count of the estimate's stripes.
    frames, boxes = seq
    config = ColourConfig(n_particles=64)
    if window:
        config = config.with_window((20, 50), (H, W))
    filt = build_colour_filter(config)
    state = jax.jit(filt.init)(
        PARAMS, jax.random.key(0), Frame(frames.colour[0], frames.depth[0]), jnp.asarray(boxes[0])
    )
    step = jax.jit(filt.step)
    for t in range(1, 6):
        frame = Frame(frames.colour[t], frames.depth[t])
        # The distance is to the reference the step weighed with (before its update).
        ref = np.asarray(state.reference)
        state, info = step(PARAMS, jax.random.key(t), state, frame)
        idx = bin_index(frame.colour, config.bins)
        rects = xywh_to_rect(box_parts(info.estimate, config.parts))
        hist = np.asarray(box_histograms(idx, rects, config.n_bins))
        hist = hist / np.maximum(hist.sum(-1, keepdims=True), 1.0)
        d2 = 1.0 - np.sum(np.sqrt(hist * ref), axis=-1)
        np.testing.assert_allclose(
            float(info.estimate_distance), np.sqrt(np.mean(np.clip(d2, 0, 1))), atol=2e-3
        )


def test_collapsed_box_counts_as_lost_and_redraws_full_size_particles(seq):
    """A cloud shrunk onto a patch (height < collapse_ratio x initial) is flagged lost; the
    re-drawn particles take sizes around the initial box's, so the filter can grow back."""
    frames, boxes = seq
    frame0 = jax.tree_util.tree_map(lambda a: a[0], frames)
    state = FILTER.init(PARAMS, jax.random.key(0), frame0, jnp.asarray(boxes[0]))
    tiny = state.particles.at[:, 4:6].set(jnp.array([8.0, 8.0]))
    state = state._replace(particles=tiny, previous=tiny)
    step = jax.jit(FILTER.step)
    state, info = step(PARAMS, jax.random.key(1), state, frame0)
    assert bool(info.lost)  # 8 px < 0.25 x 50 px
    state, info = step(PARAMS, jax.random.key(2), state, frame0)
    h = np.asarray(state.particles[:, 5])
    assert (h > 25).any() and np.median(h[h > 25]) > 35  # re-drawn near the initial 50 px
    no_check = build_colour_filter(ColourConfig(n_particles=128, collapse_ratio=0.0))
    s2 = no_check.init(PARAMS, jax.random.key(0), frame0, jnp.asarray(boxes[0]))
    s2 = s2._replace(particles=tiny, previous=tiny)
    _, info2 = jax.jit(no_check.step)(PARAMS, jax.random.key(1), s2, frame0)
    assert not bool(info2.lost)


def _estimate_reference(estimator, particles, lw, radius):
    """The three estimates with NumPy loops: weighted mean (thesis 3.10), the heaviest
    particle, and the weighted mean of the particles whose centre is within ``radius``
    x the heaviest particle's size of its centre (per axis)."""
    w = np.exp(lw.astype(np.float64))
    if estimator == "mean":
        return (w[:, None] * particles).sum(0)
    best = particles[np.argmax(lw)]
    if estimator == "map":
        return best
    num, den = np.zeros(particles.shape[1]), 0.0
    for p, wi in zip(particles, w, strict=True):
        if abs(p[0] - best[0]) <= radius * best[4] and abs(p[1] - best[1]) <= radius * best[5]:
            num, den = num + wi * p, den + wi
    return num / den if den > 0 else best


@pytest.mark.parametrize("estimator", ["mean", "map", "robust"])
def test_estimators_match_numpy_under_jit_and_vmap(estimator):
    rng = np.random.default_rng(7)
    # Two clusters: the heaviest particle is in the smaller, wider one, so the robust
    # mean (the part of its cluster within the window) differs from the weighted mean
    # (both), from the MAP particle and from a window of another size.
    parts = np.concatenate(
        [
            rng.normal([100, 80, 0, 0, 40, 90, 0, 0], [12, 12, 1, 1, 2, 2, 1, 1], (5, 16, 8)),
            rng.normal([200, 90, 0, 0, 40, 90, 0, 0], [3, 3, 1, 1, 2, 2, 1, 1], (5, 48, 8)),
        ],
        axis=1,
    ).astype(np.float32)
    logits = rng.normal(0, 0.3, (5, 64))
    logits[:, 0] += 3.0  # in the small cluster
    lw = (logits - np.log(np.exp(logits).sum(1, keepdims=True))).astype(np.float32)
    config = ColourConfig(estimator=estimator)
    radius = jnp.float32(0.25)
    one = jax.jit(lambda p, l: _estimate(config, p, l, radius))
    many = jax.jit(jax.vmap(lambda p, l: _estimate(config, p, l, radius)))(parts, lw)
    for i in range(len(parts)):
        ref = _estimate_reference(estimator, parts[i], lw[i], 0.25)
        np.testing.assert_allclose(one(parts[i], lw[i]), ref, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(many[i], ref, rtol=1e-4, atol=1e-3)
    if estimator == "robust":  # part of the small cluster: near it, not the mean's
        assert np.all(np.abs(np.asarray(many)[:, 0] - 100) < 25)
        wider = [_estimate_reference("robust", parts[i], lw[i], 0.5) for i in range(len(parts))]
        assert np.abs(np.asarray(many) - np.array(wider))[:, :2].max() > 0.5


@pytest.mark.parametrize("parts", [None, 1, 2, 3])
def test_rect_columns_are_the_stacked_rects_of_the_particles(parts):
    # The step's rects come from particle columns (no [N, parts, 4] stack); they must be
    # xywh_to_rect(box_parts(...)) exactly, corner rounding at x.5 included.
    rng = np.random.default_rng(3)
    n = 4000
    p = np.zeros((n, 8), np.float32)
    p[:, [0, 1]] = rng.uniform(-20, 200, (n, 2))
    p[:, [4, 5]] = rng.uniform(0.5, 120, (n, 2))
    p[: n // 4, [0, 1, 4, 5]] = np.round(p[: n // 4, [0, 1, 4, 5]] * 2) / 2  # halves
    particles = jnp.asarray(p)
    boxes = _to_xywh(particles)
    want = xywh_to_rect(boxes if parts is None else box_parts(boxes, parts))
    got = jax.jit(lambda q: jnp.stack(_rect_columns(_box_columns(q), parts), -1))(particles)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    # grid_ncc takes the (x, y, w, h) columns too.
    table = integral_image(jnp.asarray(rng.integers(0, 255, (H, W, 1)), jnp.int32))
    template = jnp.asarray(rng.normal(size=21), jnp.float32)
    np.testing.assert_array_equal(
        np.asarray(grid_ncc(table, _box_columns(particles), template, 7, 3)),
        np.asarray(grid_ncc(table, boxes, template, 7, 3)),
    )


def test_one_frame_table_holds_the_contrast_and_layout_tables(seq):
    # The step sums the contrast values and the layout feature in one integral image
    # (one row loop); its channels must be contrast_table's and layout_table's exactly,
    # and rect_sums(channels=2) the first two channels' sums.
    from cpf_jax.colour import contrast_values, layout_table, layout_values

    frames, _ = seq
    colour = frames.colour[3]
    idx = bin_index(colour, CONFIG.bins)
    weights = jnp.linspace(-0.7, 0.9, CONFIG.n_bins)
    for feature in ("luminance", "gradient"):
        merged = jax.jit(
            lambda c, i, w, f=feature: integral_image(
                jnp.concatenate([contrast_values(i, w), layout_values(c, f)], -1)
            )
        )(colour, idx, weights)
        np.testing.assert_array_equal(merged[..., :2], contrast_table(idx, weights))
        np.testing.assert_array_equal(merged[..., 2:], layout_table(colour, feature))
    rects = jnp.asarray([[5, 7, 60, 90], [-10, 20, 30, 200], [100, 50, 100, 80]])
    np.testing.assert_array_equal(
        rect_sums(merged, rects, channels=2), rect_sums(merged, rects)[..., :2]
    )
