"""The RGB-D filter's proposal: coarse-map kernels, the proposal densities, the detector
mixture, occlusion spreading and recovery draws one at a time, and tracking through jumps
that the motion prior cannot follow."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel
from scipy import stats

from cpf_jax.dynamics import propagate
from cpf_jax.filter import Context, track_boxes
from cpf_jax.kernels.background import Background, median_background
from cpf_jax.kernels.cells import coarse_counts, map_cell_of, window_areas, window_sums
from cpf_jax.metrics import summarise
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params
from cpf_jax.rgbd.filter import rgbd_init
from cpf_jax.rgbd.observe import observe
from cpf_jax.rgbd.proposal import (
    detector_draw,
    detector_log_density,
    detector_log_map,
    detector_mixture,
    fast_length,
    motion_position_log_density,
    motion_size_log_density,
    proposal_motion,
    recovery_draw,
    spread_when_occluded,
    target_pixels,
)
from cpf_jax.types import Frame

# -- kernels ------------------------------------------------------------------------------


def _window_sums_ref(g: np.ndarray, ry: int, rx: int) -> np.ndarray:
    h, w = g.shape
    out = np.zeros_like(g, dtype=np.float64)
    for i in range(h):
        for j in range(w):
            out[i, j] = g[max(i - ry, 0) : i + ry + 1, max(j - rx, 0) : j + rx + 1].sum()
    return out


def test_coarse_counts_match_numpy():
    rng = np.random.default_rng(0)
    masks = rng.random((3, 37, 50)) < 0.3
    items = [(m,) for m in masks]
    check_kernel(
        lambda m: coarse_counts(m, 4),
        lambda m: m[:36, :48].reshape(9, 4, 12, 4).sum((1, 3)),
        items[0],
        batch=items,
        rtol=0.0,
        atol=0.0,
    )


def test_window_sums_match_a_loop():
    rng = np.random.default_rng(1)
    grids = rng.integers(0, 9, (3, 11, 17)).astype(np.float32)
    radii = [(0, 0), (2, 3), (7, 20)]  # the last is wider than the map (clipped)
    items = [(g, np.int32(ry), np.int32(rx)) for g, (ry, rx) in zip(grids, radii, strict=True)]
    for i, args in enumerate(items):  # every radius plainly and under jit, all under vmap
        check_kernel(
            window_sums,
            lambda g, ry, rx: _window_sums_ref(g, int(ry), int(rx)),
            args,
            batch=items,
            rtol=1e-6,
            atol=0.0,
            variants=("plain", "jit", "vmap") if i == 0 else ("plain", "jit"),
        )


def test_window_areas_are_the_window_sums_of_ones():
    radii = [(0, 0), (2, 3), (7, 20), (-1, 4)]  # clipped at the edges; a negative radius is 0
    items = [(np.int32(ry), np.int32(rx)) for ry, rx in radii]
    ones = np.ones((11, 17), np.float32)
    for i, args in enumerate(items):
        check_kernel(
            lambda ry, rx: window_areas((11, 17), ry, rx),
            lambda ry, rx: _window_sums_ref(ones, max(int(ry), 0), max(int(rx), 0)),
            args,
            batch=items,
            rtol=0.0,
            atol=0.0,
            variants=("plain", "jit", "vmap") if i == 0 else ("plain", "jit"),
        )


def test_map_cell_of():
    xy = jnp.array([[0.0, 0.0], [7.9, 8.0], [39.9, 23.9], [40.0, 5.0], [-0.1, 5.0], [5.0, 24.0]])
    got = np.asarray(map_cell_of(xy, 8, (3, 5)))
    np.testing.assert_array_equal(got, [0, 5, 14, -1, -1, -1])


# -- proposal densities -------------------------------------------------------------------


def _tightness_ref(counts: np.ndarray, ry: int, rx: int, ty: int, tx: int) -> np.ndarray:
    ones = np.ones_like(counts)
    inner, inner_a = _window_sums_ref(counts, ry, rx), _window_sums_ref(ones, ry, rx)
    outer, outer_a = (
        _window_sums_ref(counts, ry + ty, rx + tx),
        _window_sums_ref(ones, ry + ty, rx + tx),
    )
    ring_a = outer_a - inner_a
    r_ring = np.where(ring_a > 0, (outer - inner) / np.maximum(ring_a, 1), 0.0)
    return inner / np.maximum(inner_a, 1) * (1.0 - r_ring)


def test_detector_map_is_a_normalised_density_and_draws_follow_it():
    cfg = RGBDConfig(
        variant="rgbd", detector_stride=4, detector_scales=(1, 1), detector_scale_step=(0.3, 0.3)
    )
    params = default_rgbd_params(cfg)
    pixels = np.zeros((40, 60), bool)
    pixels[8:28, 30:40] = True  # a 10 x 20 px blob
    pixels[0:4, 0:4] = True  # a speck: too small for a 10 x 20 box
    ref_wh = np.array([10.0, 20.0])
    log_map, ok, fit = detector_log_map(
        cfg,
        params.detector,
        jnp.asarray(pixels),
        jnp.asarray(ref_wh),
        jnp.array([35.0, 18.0]),
        50.0,
    )
    assert bool(ok)
    lm = np.asarray(log_map)
    assert lm.shape == (9 * 150,)
    np.testing.assert_allclose(np.log(np.exp(lm).sum()), 0.0, atol=1e-5)
    # Reference: tightness r (1 - r_ring) of boxes of 9 sizes (w, h x exp(-0.3, 0, 0.3))
    # at every cell; support within 3 sigma where >= 60 % of the best there and >= 10 %
    # (the speck's cells are out); density t^4 x N(cell; centre, 50^2) x the size prior.
    counts = pixels.reshape(10, 4, 15, 4).sum((1, 3)) / 16.0
    cy, cx = np.meshgrid((np.arange(10) + 0.5) * 4, (np.arange(15) + 0.5) * 4, indexing="ij")
    d2 = (cx - 35) ** 2 + (cy - 18) ** 2
    near = d2 <= 9 * 2500
    tights, priors = [], []
    for i in (-1, 0, 1):
        for j in (-1, 0, 1):
            bw, bh = 10.0 * np.exp(0.3 * i), 20.0 * np.exp(0.3 * j)
            rx, ry = int(np.round(bw / 8)), int(np.round(bh / 8))
            tx, ty = max(int(np.round(0.15 * bw / 4)), 1), max(int(np.round(0.15 * bh / 4)), 1)
            tights.append(_tightness_ref(counts, ry, rx, ty, tx))
            priors.append(-0.5 * ((0.3 * i) ** 2 + (0.3 * j) ** 2) / 0.2**2)
    tight = np.stack(tights)
    best = tight[:, near].max()
    ref = 4.0 * np.log(np.maximum(tight, 1e-6)) - 0.5 * d2 / 2500 + np.array(priors)[:, None, None]
    ref = np.where(near & (tight >= max(0.6 * best, 0.1)), ref, -np.inf).ravel()
    ref = ref - np.log(np.exp(ref).sum())
    assert np.isneginf(lm[4 * 150]) and 5 < np.isfinite(lm).sum() < 200
    np.testing.assert_array_equal(np.isfinite(lm), np.isfinite(ref))
    np.testing.assert_allclose(lm[np.isfinite(lm)], ref[np.isfinite(ref)], atol=1e-4)
    np.testing.assert_allclose(float(fit), tight[4, 18 // 4, 35 // 4] / best, rtol=1e-5)
    # The best pair is the blob's own box, 10 x 20 at its centre (35, 18).
    k, cell = divmod(int(np.argmax(lm)), 150)
    assert k == 4 and cell == (18 // 4) * 15 + 35 // 4
    # Draws: (size, cell) frequencies follow the map; sizes stay within half a step of
    # their grid size; the density of a draw is its pair's mass / (16 w h 0.3^2).
    boxes = detector_draw(jax.random.PRNGKey(0), cfg, log_map, (10, 15), jnp.asarray(ref_wh), 40000)
    b = np.asarray(boxes)
    cells = np.asarray(map_cell_of(boxes[:, :2], 4, (10, 15)))
    i = np.floor(np.log(b[:, 2] / 10.0) / 0.3 + 0.5).astype(int)
    j = np.floor(np.log(b[:, 3] / 20.0) / 0.3 + 0.5).astype(int)
    assert (np.abs(i) <= 1).all() and (np.abs(j) <= 1).all() and (cells >= 0).all()
    pair = ((i + 1) * 3 + (j + 1)) * 150 + cells
    freq = np.bincount(pair, minlength=9 * 150) / pair.size
    np.testing.assert_allclose(freq, np.exp(lm), atol=0.01)
    lq = np.asarray(detector_log_density(cfg, log_map, (10, 15), jnp.asarray(ref_wh), boxes))
    want = lm[pair] - np.log(16.0) - np.log(b[:, 2] * 0.3) - np.log(b[:, 3] * 0.3)
    np.testing.assert_allclose(lq, want, rtol=1e-4, atol=1e-4)
    # Centre-only density: the map's marginal over sizes.
    lq_c = np.asarray(
        detector_log_density(cfg, log_map, (10, 15), jnp.asarray(ref_wh), boxes, sizes=False)
    )
    with np.errstate(divide="ignore"):  # cells off the support: log 0 = -inf
        marg = np.log(np.exp(lm.reshape(9, 150)).sum(0))
    np.testing.assert_allclose(lq_c, marg[cells] - np.log(16.0), rtol=1e-4, atol=1e-4)
    far = jnp.array([[-5.0, 3.0, 10.0, 20.0], [35.0, 18.0, 40.0, 20.0]])  # off map / grid
    outside = detector_log_density(cfg, log_map, (10, 15), jnp.asarray(ref_wh), far)
    assert np.isneginf(np.asarray(outside)).all()


def test_motion_size_density_matches_samples():
    """The closed-form size density of ``propagate`` (correlated w / h noise, scaled by the
    aspect and the box height) against SciPy's bivariate normal, the moments of 100k
    draws, and normalised."""
    cfg = RGBDConfig(variant="rgbd")
    params = default_rgbd_params(cfg)
    m = 100_000
    anc = jnp.tile(jnp.array([50.0, 60.0, 3.0, 4.0, 40.0, 100.0, 1.0, -2.0]), (m, 1))
    scale = jnp.full((m,), 0.5)
    motion = params.motion._replace(size_velocity_decay=jnp.float32(1.0))
    draw = propagate(jax.random.PRNGKey(3), anc, anc, motion, model="ar1", scale=scale)
    wh = np.asarray(draw[:, 4:6])
    mean = np.array([41.0, 98.0])
    np.testing.assert_allclose(wh.mean(0), mean, atol=0.05)
    cov = np.cov(wh.T)
    # Density on a grid: integrates to 1, and its covariance matches the draws'.
    g = np.linspace(-8, 8, 161)
    gw, gh = np.meshgrid(mean[0] + g, mean[1] + g, indexing="ij")
    pts = np.stack([gw.ravel(), gh.ravel()], -1).astype(np.float32)
    k = pts.shape[0]

    def density(p):
        return motion_size_log_density(
            cfg,
            params.motion,
            jnp.tile(anc[:1], (k, 1)),
            jnp.tile(jnp.asarray(mean)[None], (k, 1)),
            p,
            jnp.full((k,), 0.5),
        )

    # Reference: heights sd tau_h s, widths sd tau_w s (aspect / 0.41), correlation rho.
    tau = np.asarray(params.motion.tau, np.float64)
    rho = float(params.motion.size_correlation)
    sw, sh = tau[4] * 0.5 * (0.4 / 0.41), tau[5] * 0.5
    ref_cov = [[sw * sw, rho * sw * sh], [rho * sw * sh, sh * sh]]

    def reference(p):
        return stats.multivariate_normal(mean, ref_cov).logpdf(np.asarray(p, np.float64))

    shifted = pts + np.float32(1.5)
    check_kernel(density, reference, (pts,), batch=[(pts,), (shifted,)], rtol=1e-4, atol=1e-4)
    lp = density(pts)
    p = np.exp(np.asarray(lp)) * 0.1**2
    assert abs(p.sum() - 1.0) < 0.01
    d = pts - mean
    cov_p = (d[:, :, None] * d[:, None, :] * p[:, None, None]).sum(0)
    np.testing.assert_allclose(cov_p, cov, rtol=0.03)


def test_detector_map_without_detections_is_flagged_and_finite():
    cfg = RGBDConfig(variant="rgbd")
    params = default_rgbd_params(cfg)
    log_map, ok, fit = detector_log_map(
        cfg, params.detector, jnp.zeros((48, 64), bool), jnp.array([10.0, 20.0]), jnp.zeros(2), 30.0
    )
    assert not bool(ok) and np.isfinite(np.asarray(log_map)).all() and float(fit) == 1.0


@pytest.mark.parametrize("hierarchical", [False, True])
def test_motion_position_density_matches_samples(hierarchical):
    """The closed-form centre density of ``propagate`` (one moving ancestor, occlusion
    spreading on top) against the frequencies of 200k draws in 6 x 6 bins."""
    cfg = RGBDConfig(variant="rgbd", hierarchical=hierarchical)
    params = default_rgbd_params(cfg)
    m = 200_000
    anc = jnp.tile(jnp.array([50.0, 60.0, 3.0, 4.0, 40.0, 100.0, 0.0, 0.0]), (m, 1))
    scale = jnp.full((m,), 0.5)
    extra = 0.7
    motion = params.motion._replace(size_velocity_decay=jnp.float32(1.0))
    draw = propagate(
        jax.random.PRNGKey(3),
        anc,
        anc,
        motion,
        model="ar1",
        hierarchical=hierarchical,
        scale=scale,
    )
    xy = draw[:, :2] + extra * params.motion.tau[:2] * 0.5 * jax.random.normal(
        jax.random.PRNGKey(4), (m, 2)
    )
    mean = jnp.array([53.0, 64.0])
    edges = [mean[i] + np.linspace(-24.0, 24.0, 7) for i in (0, 1)]
    hist, _, _ = np.histogram2d(np.asarray(xy[:, 0]), np.asarray(xy[:, 1]), bins=edges)
    # Integrate the density on a fine grid over the same bins.
    g = 240
    fine = [np.asarray(e[0]) + (np.arange(g) + 0.5) * 48.0 / g for e in edges]
    gx, gy = np.meshgrid(*fine, indexing="ij")
    pts = jnp.asarray(np.stack([gx.ravel(), gy.ravel()], -1), jnp.float32)
    k = pts.shape[0]
    lp = motion_position_log_density(
        cfg,
        params.motion,
        jnp.tile(anc[:1], (k, 1)),
        jnp.tile(mean[None], (k, 1)),
        pts,
        jnp.full((k,), 0.5),
        extra,
    )
    mass = (np.exp(np.asarray(lp)) * (48.0 / g) ** 2).reshape(6, g // 6, 6, g // 6).sum((1, 3))
    np.testing.assert_allclose(hist / m, mass, atol=0.004)
    assert abs(mass.sum() - hist.sum() / m) < 0.005


# -- proposal stages, one at a time --------------------------------------------------------

SH, SW = 120, 160  # the stages' scene: a red 24 x 50 target at 2500 mm on a wall at 4000 mm
FIGURE = (40, 40, 24, 50)


def _scene(boxes=(FIGURE,), depth_of=2500, wall_pillar=False):
    """``(frame, background)`` with red boxes at ``depth_of`` mm (a scalar or one per box);
    ``wall_pillar``: the wall has a pillar at 2500 mm (x 130..139) in frame and model."""
    colour = np.full((SH, SW, 3), 100, np.uint8)
    depth = np.full((SH, SW), 4000, np.uint16)
    bg_depth = np.full((SH, SW), 4000.0, np.float32)
    if wall_pillar:
        depth[:, 130:140] = 2500
        bg_depth[:, 130:140] = 2500.0
    zs = np.broadcast_to(np.asarray(depth_of), (len(boxes),))
    for (x, y, w, h), z in zip(boxes, zs, strict=True):
        colour[y : y + h, x : x + w] = (200, 40, 40)
        depth[y : y + h, x : x + w] = z
    bg = Background(jnp.full((SH, SW, 3), 100.0), jnp.asarray(bg_depth))
    return Frame(jnp.asarray(colour), jnp.asarray(depth)), bg


def _stage_state(cfg, params, occluded_frames=0, occluder=0.0, age=0.0):
    """The filter's state after ``init`` on the scene, templates exactly at 2500 mm."""
    frame, bg = _scene()
    state = rgbd_init(cfg, params, jax.random.PRNGKey(0), frame, FIGURE, Context(background=bg))
    c = cfg.n_cells
    depth = state.depth._replace(
        depth=jnp.full((c,), 2500.0), age=jnp.full((c,), age), occluder=jnp.float32(occluder)
    )
    occ = state.occlusion._replace(occluded_frames=jnp.int32(occluded_frames))
    return state._replace(depth=depth, occlusion=occ)


def test_spread_when_occluded_leaves_particles_alone_unless_hidden_then_keeps_sizes():
    params = default_rgbd_params(RGBDConfig())
    n = 20_000
    ancestors = jnp.tile(jnp.array([60.0, 50.0, 1.0, 0.0, 30.0, 70.0, 0.5, -0.5]), (n, 1))
    drawn = jnp.tile(jnp.array([61.0, 50.5, 1.0, 0.2, 33.0, 72.0, 1.0, -1.0]), (n, 1))
    key = jax.random.PRNGKey(0)
    scale = jnp.full((n,), 0.5)
    # Without flags (and with flags while the target is seen): nothing changes, spread 1.
    for variant, occluded in (("grid", 20), ("grid-occlusion", 0)):
        cfg = RGBDConfig(variant=variant)
        out, spread, extra = spread_when_occluded(
            cfg, params, key, drawn, ancestors, jnp.int32(occluded), scale
        )
        np.testing.assert_array_equal(np.asarray(out), np.asarray(drawn))
        assert (float(spread), float(extra)) == (1.0, 0.0)
    cfg = RGBDConfig(variant="grid-occlusion")
    tau = np.asarray(params.motion.tau)
    # 4 frames hidden: 1 + 0.15 x 4; 20 frames: capped at spread_max (3).
    for occluded, want in ((4, 1.6), (20, 3.0)):
        for s, sc in ((scale, 0.5), (None, 1.0)):
            out, spread, extra = spread_when_occluded(
                cfg, params, key, drawn, ancestors, jnp.int32(occluded), s
            )
            out = np.asarray(out)
            assert float(spread) == pytest.approx(want, rel=1e-6)
            assert float(extra) == pytest.approx(np.sqrt(want**2 - 1), rel=1e-6)
            # Extra isotropic position noise of extra x tau (x the particle's scale) ...
            sd = (out[:, :2] - np.asarray(drawn[:, :2])).std(0)
            np.testing.assert_allclose(sd, np.sqrt(want**2 - 1) * tau[:2] * sc, rtol=0.03)
            # ... velocities as drawn, and the ancestor's size with no size velocity.
            np.testing.assert_array_equal(out[:, 2:4], np.asarray(drawn[:, 2:4]))
            np.testing.assert_array_equal(out[:, 4:6], np.asarray(ancestors[:, 4:6]))
            np.testing.assert_array_equal(out[:, 6:8], 0.0)


def test_target_pixels_are_foreground_with_depth_near_the_templates():
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=8)
    params = default_rgbd_params(cfg)
    # The target (its left 4 columns without depth), a nearer occluder, a farther box,
    # and a pillar of the wall at the target's depth (not foreground).
    frame, bg = _scene(
        ((40, 40, 24, 50), (80, 30, 10, 60), (100, 30, 10, 60)), (2500, 1500, 3300), True
    )
    depth = np.asarray(frame.depth).copy()
    depth[40:90, 40:44] = 0
    frame = Frame(frame.colour, jnp.asarray(depth))
    obs = observe(cfg, params.foreground, frame, bg)
    state = _stage_state(cfg, params)
    like, tight = (np.asarray(a) for a in target_pixels(params, state, obs, frame.depth))
    want = np.zeros((SH, SW), bool)
    want[40:90, 44:64] = True
    np.testing.assert_array_equal(like, want)
    assert tight[40:90, 44:64].all() and tight[:, 130:140].all()  # depth alone
    assert not tight[30:90, 80:90].any() and not tight[30:90, 100:110].any()
    # Hidden 10 frames (gate 300 + 600 mm): the farther box at 800 mm may be the target,
    # the occluder at 1000 mm may not.
    far = _stage_state(cfg, params, occluded_frames=10)
    like, _ = (np.asarray(a) for a in target_pixels(params, far, obs, frame.depth))
    want[30:90, 100:110] = True
    np.testing.assert_array_equal(like, want)


def test_recovery_draw_puts_a_share_on_target_pixels_only_while_hidden():
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=4000, recovery_stride=4)
    params = default_rgbd_params(cfg)
    target = (100, 32, 20, 40)  # where the target reappears (on the 4 px grid)
    frame, bg = _scene((target,))
    obs = observe(cfg, params.foreground, frame, bg)
    key = jax.random.PRNGKey(3)
    seen = _stage_state(cfg, params)
    redraw, _ = recovery_draw(cfg, params, key, seen, obs, frame.depth)
    assert not np.asarray(redraw).any()  # not hidden: no search
    hidden = _stage_state(cfg, params, occluded_frames=5)
    size = np.asarray(hidden.occlusion.visible_size)
    redraw, fresh = (
        np.asarray(a) for a in recovery_draw(cfg, params, key, hidden, obs, frame.depth)
    )
    assert abs(redraw.mean() - cfg.recovery_fraction) < 0.03
    x, y, w, h = target
    # Centres: a target pixel (uniform over them) plus up to 0.4 of the last visible size.
    cx, cy = fresh[:, 0], fresh[:, 1]
    assert np.all((cx >= x - 0.4 * size[0]) & (cx <= x + w + 0.4 * size[0]))
    assert np.all((cy >= y - 0.4 * size[1]) & (cy <= y + h + 0.4 * size[1]))
    assert abs(cx.mean() - (x + w / 2)) < 1.0 and abs(cy.mean() - (y + h / 2)) < 1.0
    np.testing.assert_array_equal(fresh[:, 4:6], np.tile(size, (4000, 1)))
    np.testing.assert_array_equal(fresh[:, [2, 3, 6, 7]], 0.0)
    # Hidden, but nothing at the target's depth anywhere: no search either.
    empty, _ = _scene(())
    obs0 = observe(cfg, params.foreground, empty, bg)
    redraw, _ = recovery_draw(cfg, params, key, hidden, obs0, empty.depth)
    assert not np.asarray(redraw).any()


def _motion_draws(cfg, params, state, key):
    """The motion model's draws of ``propose`` and their scale."""
    cloud = state.cloud
    scale = cloud.particles[:, 5] / cfg.tau_height
    particles = propagate(
        key,
        cloud.particles,
        cloud.previous,
        proposal_motion(params.motion),
        model=cfg.model,
        hierarchical=cfg.hierarchical,
        scale=scale,
    )
    return particles, scale


def test_detector_mixture_weights_are_exact_importance_weights():
    """The figure moved: a share ``detector_fraction`` of the boxes moves onto it, the
    others keep their motion draws, and ``p / q`` averages 1 over the draws (exact
    importance weights; with the fast component off, ``p`` is the motion model, so
    ``p / q <= 1 / (1 - detector_fraction)``). Wide motion noise makes the two components
    overlap, so that the detector's density counts in the weights of both."""
    cfg = RGBDConfig(variant="rgbd", n_particles=4000, detector_stride=4)
    default = default_rgbd_params(cfg)
    tau = default.motion.tau.at[jnp.array([0, 1, 4, 5])].set(jnp.array([20.0, 20.0, 12.0, 24.0]))
    params = default._replace(
        motion=default.motion._replace(tau=tau),
        detector=default.detector._replace(fast_fraction=jnp.float32(0.0)),
    )
    state = _stage_state(cfg, params)
    mix = jax.jit(detector_mixture, static_argnums=0)
    one, zero = jnp.float32(1.0), jnp.float32(0.0)

    def run(p, moved_to, key=2, s=state):
        frame, bg = _scene((moved_to,) if moved_to else ())
        obs = observe(cfg, p.foreground, frame, bg)
        drawn, scale = _motion_draws(cfg, p, s, jax.random.PRNGKey(1))
        k = jax.random.PRNGKey(key)
        out, corr = mix(cfg, p, k, s, obs, frame.depth, drawn, scale, one, zero)
        return np.asarray(out), np.asarray(corr), np.asarray(drawn)

    for p, moved_to in ((params, (46, 40, 24, 50)), (default, (70, 40, 24, 50))):
        out, corr, drawn = run(p, moved_to)
        moved = np.any(out != drawn, axis=1)
        assert abs(moved.mean() - cfg.detector_fraction) < 0.03
        np.testing.assert_array_equal(out[~moved], drawn[~moved])
        np.testing.assert_array_equal(out[:, [2, 3, 6, 7]], drawn[:, [2, 3, 6, 7]])
        x, y, w, h = moved_to
        inside = (out[moved, 0] > x) & (out[moved, 0] < x + w)
        assert np.all(inside & (out[moved, 1] > y) & (out[moved, 1] < y + h))
        bound = -np.log(1 - cfg.detector_fraction) + 1e-5
        assert np.isfinite(corr).all() and corr.max() <= (bound if p is params else np.inf)
    # 6 px (the first case): the detector's draws overlap the motion model's.
    out, corr, drawn = run(params, (46, 40, 24, 50))
    moved = np.any(out != drawn, axis=1)
    assert 0.2 < np.exp(corr[moved]).mean() < 1.0
    assert abs(np.exp(corr).mean() - 1.0) < 0.025, np.exp(corr).mean()
    # While the target is voted occluded neither the detector nor the fast component is
    # used: the draws stay, and their weights are the motion model's own (correction 0).
    hidden = state._replace(occlusion=state.occlusion._replace(occluded_frames=jnp.int32(3)))
    out, corr, drawn = run(default, (70, 40, 24, 50), s=hidden)
    np.testing.assert_array_equal(out, drawn)
    np.testing.assert_array_equal(corr, 0.0)
    # Seen, but nothing near the prediction: no detector draw; the fast component alone
    # adds to the weights (p = 0.95 p_motion + 0.05 p_fast over q = p_motion).
    out, corr, drawn = run(default, None)
    np.testing.assert_array_equal(out, drawn)
    assert corr.min() >= np.log(0.95) - 1e-5 and corr.max() > np.log(0.95) + 1e-3


# -- tracking -----------------------------------------------------------------------------

H, W = 120, 160
PERSON = (24, 50)
# The figure stands, then jumps 30 px (more than its width) per frame, stands, jumps back.
_X = [5.0] * 8 + [35.0, 65.0, 95.0] + [95.0] * 8 + [65.0, 35.0] + [35.0] * 6


def _jumps():
    rng = np.random.default_rng(0)

    def frame(x: float | None):
        colour = np.empty((H, W, 3), np.uint8)
        colour[:] = np.array([90, 110, 95]) + rng.integers(-12, 13, (H, W, 3))
        depth = (4000 + rng.normal(0, 15, (H, W))).astype(np.uint16)
        if x is not None:
            x0 = int(x)
            colour[40:48, x0 + 9 : x0 + 15] = (205, 150, 120)  # head
            colour[48:69, x0 : x0 + 24] = (200, 40, 40)  # torso and arms
            colour[69:90, x0 + 5 : x0 + 19] = (40, 50, 150)  # legs
            depth[40:48, x0 + 9 : x0 + 15] = 2500
            depth[48:90, x0 : x0 + 24] = 2500
            depth[69:90, x0 + 10 : x0 + 14] = 4000  # gap between the legs
            colour[69:90, x0 + 10 : x0 + 14] = (90, 110, 95)
        return colour, depth

    frames = [frame(x) for x in _X]
    gt = np.array([[x, 40.0, 24.0, 50.0] for x in _X], np.float32)
    empty = [frame(None) for _ in range(7)]
    bg = median_background(np.stack([e[0] for e in empty]), np.stack([e[1] for e in empty]))
    fr = Frame(
        jnp.asarray(np.stack([f[0] for f in frames])), jnp.asarray(np.stack([f[1] for f in frames]))
    )
    return fr, gt, bg


@pytest.fixture(scope="module")
def jumps():
    return _jumps()


def _success(jumps, variant: str, detector_fraction: float) -> float:
    frames, gt, bg = jumps
    cfg = RGBDConfig(
        variant=variant, n_particles=128, detector_fraction=detector_fraction, detector_stride=4
    ).with_window(PERSON, (H, W))
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    context = Context(background=bg)
    # lax.map over the keys (vmap is tested in test_rgbd.py).
    boxes, lost = jax.jit(
        lambda ks, fr: jax.lax.map(
            lambda k: track_boxes(filt, params, k, fr, jnp.asarray(gt[0]), context), ks
        )
    )(keys, frames)
    vis = np.ones(len(gt), bool)
    scores = [
        summarise(np.asarray(b), gt, vis, np.asarray(lo))["success_rate"]
        for b, lo in zip(boxes, lost, strict=True)
    ]
    assert np.isfinite(np.asarray(boxes)).all()
    return float(np.mean(scores))


# "rgbd" carries the stronger check (20 points); "grid-occlusion", whose recovery search
# also finds the figure, is one more 35-s compile, run with -m slow.
@pytest.mark.parametrize(
    "variant", ["rgbd", pytest.param("grid-occlusion", marks=pytest.mark.slow)]
)
def test_detector_proposal_follows_jumps_the_motion_prior_cannot(jumps, variant):
    """Stated threshold: success rate >= 90 % with the detector proposal (2 keys). With
    the motion prior alone, "rgbd" loses the figure at the first 30 px jump (success
    rate at least 20 points lower: 61 % at colour.sigma 0.2, below 60 % at 0.08);
    "grid-occlusion" finds it again later by its recovery search."""
    with_det = _success(jumps, variant, 0.2)
    without = _success(jumps, variant, 0.0)
    assert with_det >= 90.0, (with_det, without)
    assert without < (with_det - 20.0 if variant == "rgbd" else with_det), (with_det, without)


def _fast_length_ref(reach, tmpl, h):
    out = []
    for r, t, hh in zip(reach, tmpl, h, strict=True):
        known = t[t > 0]
        z = known.mean() if known.size else 0.0
        out.append(min(hh, r / z) if r > 0 and z > 0 else hh)
    return np.array(out, np.float32)


def test_fast_length_caps_the_height_by_the_initial_view_at_the_target_depth():
    # A 144 px head-and-shoulders box at 1 m: at 4 m the same view is 36 px high, so a
    # 196 px box there may jump no further than the 36 px view would; unknown depth or
    # reach leaves the box height.
    reach = np.array([144e3, 144e3, 0.0, 144e3, 144e3], np.float32)
    tmpl = np.array(
        [[4000, 4000, 0, 4000], [900, 1100, 1000, 1000], [4000] * 4, [0] * 4, [500] * 4],
        np.float32,
    )
    h = np.array([196.0, 150.0, 196.0, 196.0, 196.0], np.float32)
    ref = _fast_length_ref(reach, tmpl, h)
    np.testing.assert_allclose(ref, [36.0, 144.0, 196.0, 196.0, 196.0], rtol=1e-6)
    items = list(zip(reach, tmpl, h, strict=True))
    for i, args in enumerate(items):  # every case plainly and under jit, all under vmap
        check_kernel(
            fast_length,
            lambda r, t, x: _fast_length_ref([r], [t], [x])[0],
            args,
            batch=items,
            rtol=1e-6,
            atol=0.0,
            variants=("plain", "jit", "vmap") if i == 0 else ("plain", "jit"),
        )
    # Per-particle heights against one state's cap broadcast.
    hs = jnp.array([20.0, 36.0, 80.0])
    np.testing.assert_allclose(np.asarray(fast_length(reach[0], tmpl[0], hs)), [20, 36, 36])


def test_init_records_the_reach_of_the_initial_box(jumps):
    frames, gt, bg = jumps
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=16).with_window(PERSON, (H, W))
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    first = jax.tree_util.tree_map(lambda x: x[0], frames)
    state = filt.init(
        params, jax.random.PRNGKey(0), first, jnp.asarray(gt[0]), Context(background=bg)
    )
    # The figure stands at 2500 mm; the cell medians come from a log-depth histogram
    # whose bins are 5 % wide.
    np.testing.assert_allclose(float(state.depth.reach), 50.0 * 2500.0, rtol=0.05)


def test_depth_cap_is_on_for_grid_occlusion_only_unless_set():
    assert RGBDConfig(variant="grid-occlusion").depth_cap
    assert not RGBDConfig(variant="grid").depth_cap
    assert not RGBDConfig(variant="rgbd").depth_cap
    assert RGBDConfig(variant="rgbd", fast_depth_cap=True).depth_cap
    assert not RGBDConfig(variant="grid-occlusion", fast_depth_cap=False).depth_cap
