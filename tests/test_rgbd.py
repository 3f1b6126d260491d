"""RGB-D filter (grid cells, occlusion flags): learning, flag inference, structure, the
step's named pieces one at a time, tracking.

The tracking tests use a small toy RGB-D scene (120 x 160) so that they run in
seconds: a stick figure walks right behind a nearer grey box that moves the same
way more slowly, so the figure is partially, then fully (20 frames), then
partially hidden, then in full view again. The synthetic-generator scenarios
are run by ``experiments/occlusion_tables.py`` (and by a slow test here).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel, check_weighed_cloud
from scipy import stats

from cpf_jax.colour import ColourConfig, bin_index, build_colour_filter, default_colour_params
from cpf_jax.filter import Context, Filter, track, track_boxes
from cpf_jax.kernels.background import Background, median_background
from cpf_jax.kernels.boxes import iou
from cpf_jax.metrics import summarise
from cpf_jax.rgbd import (
    RGBDConfig,
    RGBDState,
    beta_fill_shift,
    build_rgbd_filter,
    cell_foreground_ratios,
    cell_terms,
    default_rgbd_params,
    fill_adapted,
    fit_beta,
    flag_bits,
    initial_fill,
    kronecker_transition,
)
from cpf_jax.rgbd.cells import CellTerms, body_states
from cpf_jax.rgbd.depth import (
    MAX_DEPTH_AGE,
    DepthTemplate,
    at_occluder,
    depth_template_update,
    remember_occluder,
    search_drift,
    target_gate,
    target_like,
)
from cpf_jax.rgbd.filter import rgbd_init, rgbd_step
from cpf_jax.rgbd.flags import flag_posterior, marginal_likelihood
from cpf_jax.rgbd.observe import Observation, cell_statistics, observe
from cpf_jax.rgbd.report import Extent, kept_lines, main_run, reported_box, target_extent
from cpf_jax.rgbd.templates import (
    BodyTemplate,
    CellColour,
    body_template_update,
    cell_colour_update,
)
from cpf_jax.types import Frame

H, W = 120, 160
T = 86
PERSON = (24, 50)  # w, h of the figure's box
Z_BG, Z_PERSON, Z_OCC = 4000, 2500, 1500

# A stick figure filling about 40 % of its box, like a walking person's silhouette:
# (row0, row1, col0, col1, rgb) in box coordinates.
_FIGURE = (
    (0, 8, 9, 15, (205, 150, 120)),  # head
    (8, 29, 8, 16, (200, 40, 40)),  # torso (shirt)
    (10, 27, 0, 3, (200, 40, 40)),  # arms
    (10, 27, 21, 24, (200, 40, 40)),
    (29, 50, 6, 10, (40, 50, 150)),  # legs (trousers)
    (29, 50, 14, 18, (40, 50, 150)),
)


# The eq. 8 test needs cells voted occluded. At the default colour.sigma (0.2) the toy's
# estimate lags at the grey occluder's edge on background and votes nothing (reported lost
# by coverage instead); at 0.08 the colour term makes the occluded cells vote.
SIGMA_RGB_TEST = 0.08


def _toy(t: int, rng: np.random.Generator, person: bool = True, occluder: bool = True):
    """Frame t of the toy scene -> (colour, depth, person mask).

    The figure walks right at 1.5 px/frame from x = 5; a 48 px wide grey box, nearer,
    moves right at 0.25 px/frame from x = 40: partial occlusion from t = 9, full for
    t = 28..47, partial again until t = 66, then the figure is in full view.
    """
    colour = np.empty((H, W, 3), np.uint8)
    colour[:] = np.array([90, 110, 95]) + rng.integers(-12, 13, (H, W, 3))
    depth = (Z_BG + rng.normal(0, 15, (H, W))).astype(np.uint16)
    mask = np.zeros((H, W), bool)
    if person:
        x, y = int(round(5 + 1.5 * t)), 40
        for r0, r1, c0, c1, rgb in _FIGURE:
            a0, a1 = max(x + c0, 0), min(x + c1, W)
            if a1 > a0:
                colour[y + r0 : y + r1, a0:a1] = rgb
                z = Z_PERSON + rng.normal(0, 15, (r1 - r0, a1 - a0))
                depth[y + r0 : y + r1, a0:a1] = z.astype(np.uint16)
                mask[y + r0 : y + r1, a0:a1] = True
    if occluder:
        ox = int(round(40 + 0.25 * t))
        o0, o1 = max(ox, 0), min(ox + 48, W)
        colour[15:115, o0:o1] = (120, 120, 125)
        depth[15:115, o0:o1] = Z_OCC
        mask[15:115, o0:o1] = False
    return colour, depth, mask


def _gt(mask: np.ndarray) -> np.ndarray:
    if not mask.any():
        return np.zeros(4, np.float32)
    r = np.nonzero(mask.any(1))[0]
    c = np.nonzero(mask.any(0))[0]
    return np.array([c[0], r[0], c[-1] - c[0] + 1, r[-1] - r[0] + 1], np.float32)


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(0)
    frames = [_toy(t, rng) for t in range(T)]
    colour = np.stack([f[0] for f in frames])
    depth = np.stack([f[1] for f in frames])
    gt = np.stack([_gt(f[2]) for f in frames])
    empty = [_toy(0, rng, person=False, occluder=False) for _ in range(9)]
    bg = median_background(np.stack([e[0] for e in empty]), np.stack([e[1] for e in empty]))
    return Frame(jnp.asarray(colour), jnp.asarray(depth)), gt, bg


def _config(variant: str, **kw) -> RGBDConfig:
    return RGBDConfig(variant=variant, n_particles=128, **kw).with_window(PERSON, (H, W))


_RUNS: dict = {}


def _run(toy, variant: str, seed: int = 0, **kw):
    frames, gt, bg = toy
    cfg = _config(variant, **kw)
    key = (cfg, seed)
    if key not in _RUNS:
        filt = build_rgbd_filter(cfg)
        params = default_rgbd_params(cfg)
        context = Context(background=bg)
        boxes, lost = jax.jit(lambda k: track_boxes(filt, params, k, frames, gt[0], context))(
            jax.random.PRNGKey(seed)
        )
        _RUNS[key] = (np.asarray(boxes), np.asarray(lost))
    return _RUNS[key]


def _templates(depth, age=None, velocity=0.0, reach=0.0, occluder=0.0) -> DepthTemplate:
    """Depth templates ``[C]`` mm (age 0 unless given) as the filter's state holds them."""
    depth = jnp.asarray(depth, jnp.float32)
    age = jnp.zeros_like(depth) if age is None else jnp.asarray(age, jnp.float32)
    return DepthTemplate(
        depth, age, jnp.float32(velocity), jnp.float32(reach), jnp.float32(occluder)
    )


# A red box (the target) on a grey wall, with the background model of the bare wall.
TEMPLATE_BOX = (40, 20, 40, 80)


def _box_scene(depth_of_box=Z_PERSON, box=TEMPLATE_BOX):
    """``(frame, background)``: a red ``box`` at ``depth_of_box`` (mm, or an ``[h, w]``
    array) on a grey wall at ``Z_BG``; ``box=None``: the bare wall."""
    colour = np.full((H, W, 3), 100, np.uint8)
    depth = np.full((H, W), Z_BG, np.uint16)
    if box is not None:
        x, y, w, h = box
        colour[y : y + h, x : x + w] = (200, 40, 40)
        depth[y : y + h, x : x + w] = depth_of_box
    bg = Background(jnp.full((H, W, 3), 100.0), jnp.full((H, W), float(Z_BG)))
    return Frame(jnp.asarray(colour), jnp.asarray(depth)), bg


# -- learning -----------------------------------------------------------------------------


def _beta_moments_reference(r):
    c = np.clip(np.asarray(r, np.float64), 1e-3, 1 - 1e-3)
    m, v = c.mean(), c.var()
    k = m * (1 - m) / v - 1
    return m * k, (1 - m) * k


def _beta_mle_reference(r):
    c = np.clip(np.asarray(r, np.float64), 1e-3, 1 - 1e-3)
    a, b, _, _ = stats.beta.fit(c, floc=0, fscale=1)
    return a, b


def test_fit_beta_moments_and_mle_match_references():
    rng = np.random.default_rng(1)
    shapes = [(3.5, 7.9), (1.2, 2.3), (0.8, 5.0)]
    data = np.stack([rng.beta(a, b, 4000) for a, b in shapes]).astype(np.float32)
    rows = [(r,) for r in data]
    check_kernel(fit_beta, _beta_moments_reference, rows[0], batch=rows, rtol=2e-3, atol=0.0)
    check_kernel(
        lambda r: fit_beta(r, method="mle"),
        _beta_mle_reference,
        rows[0],
        batch=rows,
        rtol=2e-2,
        atol=0.0,
    )


def test_fit_beta_weights_drop_samples():
    rng = np.random.default_rng(2)
    good = rng.beta(4.0, 8.0, 3000)
    junk = np.full(500, 0.99)
    r = np.concatenate([good, junk]).astype(np.float32)
    w = np.concatenate([np.ones(3000), np.zeros(500)]).astype(np.float32)
    a, b = fit_beta(r, w, method="mle")
    a0, b0 = fit_beta(good.astype(np.float32), method="mle")
    np.testing.assert_allclose([a, b], [a0, b0], rtol=1e-4)
    with pytest.raises(ValueError, match="method"):
        fit_beta(r, method="bayes")


def test_cell_foreground_ratios_match_numpy():
    rng = np.random.default_rng(3)
    masks = rng.uniform(size=(4, H, W)) < 0.3
    boxes = np.array(
        [[10, 5, 33, 41], [0, 0, 160, 120], [150, 110, 30, 30], [40.4, 20.6, 9, 9]], np.float32
    )
    got = np.asarray(cell_foreground_ratios(masks, boxes, 2))
    for t in range(4):
        x, y, w, h = boxes[t]
        for i in range(4):
            r, c = divmod(i, 2)
            x0 = int(np.floor(x + c * w / 2 + 0.5))
            x1 = int(np.floor(x + (c + 1) * w / 2 + 0.5))
            y0 = int(np.floor(y + r * h / 2 + 0.5))
            y1 = int(np.floor(y + (r + 1) * h / 2 + 0.5))
            cell = masks[t, max(y0, 0) : min(y1, H), max(x0, 0) : min(x1, W)]
            want = cell.mean() if cell.size else 0.0
            assert got[t, i] == pytest.approx(want, abs=1e-6)


def _initial_fill_reference(mask, box):
    x, y, w, h = np.asarray(box).astype(int)
    region = mask[max(y, 0) : max(min(y + h, H), 0), max(x, 0) : max(min(x + w, W), 0)]
    return region.mean() if region.size else 0.0


def test_initial_fill_matches_numpy():
    rng = np.random.default_rng(4)
    masks = rng.uniform(size=(5, H, W)) < 0.4
    # Inside, partly outside (both sides), wholly outside, empty.
    boxes = np.array(
        [
            [10, 5, 33, 41],
            [-20, -10, 50, 40],
            [140, 100, 40, 40],
            [200, 10, 20, 20],
            [50, 50, 0, 9],
        ],
        np.float32,
    )
    items = list(zip(masks, boxes, strict=True))
    for i, args in enumerate(items):  # every box plainly and under jit, all under vmap
        variants = ("plain", "jit", "vmap") if i == 0 else ("plain", "jit")
        check_kernel(
            initial_fill,
            _initial_fill_reference,
            args,
            batch=items,
            rtol=0.0,
            atol=1e-6,
            variants=variants,
        )


def _logit(m):
    return np.log(m / (1 - m))


def _moved_reference(a, b, shift):
    """NumPy: Beta shapes with the mean moved by ``shift`` logits and ``a + b`` kept."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if shift == 0.0:
        return a, b
    k = a + b
    m = 1 / (1 + np.exp(-(_logit(a / k) + shift)))
    return m * k, (1 - m) * k


def test_fill_adapted_moves_the_beta_means_and_keeps_their_concentration():
    params = default_rgbd_params(RGBDConfig(variant="grid-occlusion"))
    beta, border = params.beta, params.border
    prior = float(beta.box_a / (beta.box_a + beta.box_b))
    fills = np.array([0.03, prior, 0.45, 0.88, 0.99], np.float32)
    dead = float(beta.fill_deadzone)

    def moved(f):
        b, s = fill_adapted(beta, border, beta_fill_shift(beta, f))
        return b.a, b.b, b.box_a, b.box_b, s.a, s.b

    def reference(f):
        gap = _logit(np.clip(float(f), 0.05, 0.95)) - _logit(prior)
        shift = float(beta.fill_adapt) * np.sign(gap) * max(abs(gap) - dead, 0.0)
        ba, bb = _moved_reference(beta.a, beta.b, shift)
        xa, xb = _moved_reference(beta.box_a, beta.box_b, shift)
        ia, ib = _moved_reference(border.a[:4], border.b[:4], shift)
        oa = np.concatenate([ia, np.asarray(border.a[4:], np.float64)])
        ob = np.concatenate([ib, np.asarray(border.b[4:], np.float64)])
        return ba, bb, xa, xb, oa, ob

    items = [(f,) for f in fills]
    for i, args in enumerate(items):  # every fill plainly and under jit, all under vmap
        variants = ("plain", "jit", "vmap") if i == 0 else ("plain", "jit")
        check_kernel(moved, reference, args, batch=items, rtol=1e-5, atol=1e-5, variants=variants)
    ba, bb, xa, xb, oa, ob = (np.asarray(o) for o in jax.jit(jax.vmap(moved))(fills))

    a0, b0 = np.asarray(beta.a, float), np.asarray(beta.b, float)
    oa0, ob0 = np.asarray(border.a, float), np.asarray(border.b, float)
    for i, f in enumerate(np.clip(fills, 0.05, 0.95)):
        gap = _logit(f) - _logit(prior)
        shift = np.sign(gap) * max(abs(gap) - dead, 0.0)
        # The whole box's mean moves to the fill, less the dead zone; every Beta keeps a + b.
        mean_box = xa[i] / (xa[i] + xb[i])
        assert mean_box == pytest.approx(1 / (1 + np.exp(-(_logit(prior) + shift))), abs=1e-5)
        if abs(gap) > dead:
            assert (mean_box - prior) * (f - prior) > 0 and abs(mean_box - prior) < abs(f - prior)
        else:
            assert mean_box == pytest.approx(prior, abs=1e-5)
        assert xa[i] + xb[i] == pytest.approx(float(beta.box_a + beta.box_b), 1e-5)
        want = 1 / (1 + np.exp(-(_logit(a0 / (a0 + b0)) + shift)))
        np.testing.assert_allclose(ba[i] / (ba[i] + bb[i]), want, atol=1e-5)
        np.testing.assert_allclose(ba[i] + bb[i], a0 + b0, rtol=1e-5)
        # Inner strips move; the outer ones (no person outside a tight box) do not.
        inner = 1 / (1 + np.exp(-(_logit(oa0[:4] / (oa0[:4] + ob0[:4])) + shift)))
        np.testing.assert_allclose(oa[i, :4] / (oa[i, :4] + ob[i, :4]), inner, atol=1e-5)
        np.testing.assert_allclose(oa[i, 4:], oa0[4:], rtol=1e-5)
        np.testing.assert_allclose(ob[i, 4:], ob0[4:], rtol=1e-5)
    # At the fitted mean nothing moves; no foreground in the box moves nothing either.
    np.testing.assert_allclose(ba[1], a0, rtol=1e-4)
    assert float(beta_fill_shift(beta, jnp.float32(0.0))) == 0.0
    off_beta = beta._replace(fill_adapt=jnp.float32(0.0))
    off, _ = fill_adapted(beta, border, beta_fill_shift(off_beta, 0.9))
    np.testing.assert_allclose(np.asarray(off.a), a0, rtol=1e-5)


def _body_reference(bins, boxes, template, vis, params, n_fg, k=2):
    """NumPy: pooled foreground histogram of the visible cells per state -> body term."""
    body = params.body
    sigma, ref = float(body.sigma), float(body.ref)
    floor, min_px = float(body.floor), float(body.min_pixels)
    out = np.zeros((len(boxes), len(vis)))
    for n, (x, y, w, h) in enumerate(boxes):
        counts = []
        for r in range(k):
            for c in range(k):  # row-major cells, corners rounded half-up
                x0, x1 = (int(np.floor(x + w * f + 0.5)) for f in (c / k, (c + 1) / k))
                y0, y1 = (int(np.floor(y + h * f + 0.5)) for f in (r / k, (r + 1) / k))
                cell = bins[max(y0, 0) : max(min(y1, H), 0), max(x0, 0) : max(min(x1, W), 0)]
                counts.append(np.bincount(cell.ravel(), minlength=n_fg + 1)[:n_fg])
        counts = np.array(counts, float)
        for s, v in enumerate(vis):
            pooled = (v[:, None] * counts).sum(0)
            if pooled.sum() < min_px:
                continue
            d2 = np.clip(1 - np.sum(np.sqrt(pooled / pooled.sum() * template)), 0, 1)
            out[n, s] = max(-(d2 - ref**2) / (2 * sigma**2), floor)
    return out


@pytest.mark.parametrize("variant", ["grid-occlusion", "grid", "grid-occlusion-3x3"])
def test_body_term_pools_the_visible_cells_like_numpy(variant):
    # 3 x 3 cells with the full transition: 512 states, the einsum path (not unrolled).
    k = 3 if variant.endswith("3x3") else 2
    cfg = RGBDConfig(
        variant=variant.removesuffix("-3x3"),
        n_particles=8,
        bins=(4, 4, 2),
        grid=k,
        flag_transition="full" if k == 3 else "auto",
    )
    params = default_rgbd_params(cfg)
    n_fg = cfg.n_fg_bins
    rng = np.random.default_rng(7)
    # A person-like blob of a few colours on background (the extra bin), some noise.
    bins = np.full((2, H, W), n_fg, np.int32)
    bins[:, 30:100, 50:90] = rng.choice([3, 7, 12, 20], size=(2, 70, 40))
    bins[:, 60:100, 50:90] = rng.choice([20, 25, 30], size=(2, 40, 40))
    bins[rng.uniform(size=bins.shape) < 0.05] = rng.integers(0, n_fg, size=1)[0]
    # Inside, over the blob's edge, partly and wholly outside the frame, empty, tiny.
    boxes = np.array(
        [
            [50, 30, 40, 70],
            [40, 20, 60, 90],
            [70, 60, 40, 40],
            [-20, -10, 80, 60],
            [150, 100, 30, 40],
            [200, 10, 20, 20],
            [60, 50, 0, 10],
            [55, 35, 6, 6],
        ],
        np.float32,
    )
    templates = rng.dirichlet(np.full(n_fg, 0.3), size=2).astype(np.float32)
    vis = np.asarray(body_states(cfg))
    c = k * k
    assert vis.shape == ((2**c, c) if variant.startswith("grid-occlusion") else (1, c))

    def l_body(b, tmpl):
        obs = Observation(b, jnp.full(b.shape, -1, jnp.int32), b < n_fg)
        terms = cell_terms(
            cfg,
            params,
            jnp.full((c, cfg.n_bins), 1.0 / cfg.n_bins),
            _templates(jnp.zeros(c)),
            obs,
            jnp.asarray(boxes),
            tmpl,
        )
        return terms.l_body

    def reference(b, tmpl):
        return _body_reference(b, boxes, tmpl, vis, params, n_fg, k)

    items = [(bins[i], templates[i]) for i in range(2)]
    # Under jit and vmap, as the filter runs it (eagerly, the 512-state case is slow).
    check_kernel(
        l_body, reference, items[0], batch=items, rtol=0.0, atol=2e-4, variants=("jit", "vmap")
    )
    for i in range(2):
        want = reference(*items[i])
        # The test means something: the states differ, and some boxes score below zero.
        assert np.ptp(want[0]) > 0.1 or variant == "grid"
        assert (want < -0.5).any() and (want == 0).any()


# -- occlusion flags ------------------------------------------------------------------------


def test_kronecker_transition_is_the_product_of_cell_chains():
    t = np.asarray(kronecker_transition(0.1, 0.3, 3))
    assert t.shape == (8, 8)
    np.testing.assert_allclose(t.sum(1), 1.0, rtol=1e-6)
    cell = np.array([[0.9, 0.1], [0.3, 0.7]])
    full = np.kron(np.kron(cell, cell), cell)  # bit 2 is the slow index
    np.testing.assert_allclose(t, full, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(flag_bits(2)), [[0, 0], [1, 0], [0, 1], [1, 1]])


def test_full_and_factorised_flag_inference_agree():
    rng = np.random.default_rng(4)
    n, c = 64, 4
    l_vis = jnp.asarray(rng.normal(-3, 3, (n, c)), jnp.float32)
    l_occ = jnp.asarray(rng.normal(-5, 2, (n, c)), jnp.float32)
    prev = jnp.asarray(rng.integers(0, 1 << c, n), jnp.int32)
    occ = default_rgbd_params(RGBDConfig()).occlusion
    key = jax.random.PRNGKey(0)
    full = flag_posterior(RGBDConfig(flag_transition="full"), occ, key, prev, l_vis, l_occ)
    fact = flag_posterior(RGBDConfig(flag_transition="factorised"), occ, key, prev, l_vis, l_occ)
    np.testing.assert_allclose(
        np.asarray(full.log_likelihood), np.asarray(fact.log_likelihood), rtol=1e-5, atol=1e-4
    )
    np.testing.assert_allclose(np.asarray(full.p_cell), np.asarray(fact.p_cell), atol=1e-5)
    # Sampled flags follow the per-cell posteriors (statistically, over many keys).
    keys = jax.random.split(key, 400)
    draws = jax.vmap(lambda k: flag_posterior(RGBDConfig(), occ, k, prev, l_vis, l_occ).flags)(keys)
    bits = (np.asarray(draws)[..., None] >> np.arange(c)) & 1
    np.testing.assert_allclose(bits.mean(0), np.asarray(full.p_cell), atol=0.1)


def test_custom_full_transition_matrix_is_used():
    n, c = 8, 4
    occ = default_rgbd_params(RGBDConfig()).occlusion
    # A matrix that forbids every state but "all visible": flags must all be 0.
    trans = np.zeros((16, 16), np.float32)
    trans[:, 0] = 1.0
    occ = occ._replace(transition=jnp.asarray(trans))
    l_vis = jnp.full((n, c), -20.0)
    l_occ = jnp.zeros((n, c))
    _, flags, p = flag_posterior(
        RGBDConfig(), occ, jax.random.PRNGKey(1), jnp.zeros(n, jnp.int32), l_vis, l_occ
    )
    assert (np.asarray(flags) == 0).all() and np.asarray(p).max() < 1e-6


# Cells of the 2 x 2 grid on each side of the box (top, bottom, left, right; row-major).
_SIDES_2X2 = np.array([[1, 1, 0, 0], [0, 0, 1, 1], [1, 0, 1, 0], [0, 1, 0, 1]], bool)


def _box_term_reference(beta, fg, area):
    """NumPy: the whole-box Beta term of pooled counts (0 for an empty area)."""
    ratio = np.clip(np.where(area > 0, fg / np.maximum(area, 1.0), 0.0), 1e-3, 1 - 1e-3)
    lp = stats.beta.logpdf(ratio, float(beta.box_a), float(beta.box_b))
    return np.where(area > 0, np.maximum(float(beta.weight) * lp, float(beta.floor)), 0.0)


def _marginal_reference(cfg, occ, beta, prev, terms):
    """NumPy, by enumeration: ``(log-likelihood [N], p_cell [N, C])`` of particles whose
    flags are marginalised (grid-occlusion), or scored all visible (the other variants)."""
    l_vis, l_occ = np.asarray(terms.l_vis, float), np.asarray(terms.l_occ, float)
    border, l_body = np.asarray(terms.l_border, float), np.asarray(terms.l_body, float)
    fg, area = np.asarray(terms.fg_count, float), np.asarray(terms.area, float)
    n, c = l_vis.shape
    side = border[:, :4] + border[:, 4:]
    prev = np.asarray(prev)
    po, pr = float(occ.p_occlude), float(occ.p_reveal)

    def all_visible():
        return side.sum(1) + l_body[:, 0] + _box_term_reference(beta, fg.sum(1), area.sum(1))

    if not cfg.occlusion:
        return l_vis.sum(1) + all_visible(), np.zeros((n, c))
    prev_bits = (prev[:, None] >> np.arange(c)) & 1
    if not cfg.full_transition:
        p1 = np.where(prev_bits == 1, 1 - pr, po)
        a0, a1 = np.log(1 - p1) + l_vis, np.log(p1) + l_occ
        lse = np.logaddexp(a0, a1)
        return lse.sum(1) + all_visible(), np.exp(a1 - lse)
    joint = np.zeros((n, 1 << c))
    for s in range(1 << c):
        z = (s >> np.arange(c)) & 1  # 1: cell occluded
        vis = 1 - z
        p_move = np.where(
            prev_bits == 1, np.where(z == 1, 1 - pr, pr), np.where(z == 1, po, 1 - po)
        )
        sides_on = [bool(np.all(vis[_SIDES_2X2[i]])) for i in range(4)]
        joint[:, s] = (
            np.log(p_move).sum(1)
            + np.where(z == 1, l_occ, l_vis).sum(1)
            + side[:, sides_on].sum(1)
            + l_body[:, s]
            + _box_term_reference(beta, fg @ vis, area @ vis)
        )
    log_lik = np.logaddexp.reduce(joint, axis=1)
    post = np.exp(joint - log_lik[:, None])
    bits = (np.arange(1 << c)[:, None] >> np.arange(c)) & 1
    return log_lik, post @ bits


def _random_terms(rng, n, c, n_states) -> CellTerms:
    area = rng.uniform(100, 400, (n, c)).astype(np.float32)
    fg = (area * rng.uniform(0, 1, (n, c))).astype(np.float32)
    zeros = np.zeros((n, c), np.float32)
    return CellTerms(
        l_vis=jnp.asarray(rng.normal(-3, 3, (n, c)), jnp.float32),
        l_occ=jnp.asarray(rng.normal(-5, 2, (n, c)), jnp.float32),
        l_beta=zeros,
        l_colour=zeros,
        l_depth=zeros,
        ratio=zeros,
        distance=zeros,
        median_depth=zeros,
        occluder=zeros,
        fg_count=jnp.asarray(fg),
        area=jnp.asarray(area),
        l_border=jnp.asarray(rng.normal(-2, 1, (n, 8)), jnp.float32),
        border_ratio=np.zeros((n, 8), np.float32),
        l_body=jnp.asarray(rng.normal(-1, 1, (n, n_states)), jnp.float32),
        windowed=jnp.array(True),
    )


@pytest.mark.parametrize("variant", ["grid-occlusion", "grid-occlusion-factorised", "grid"])
def test_marginal_likelihood_matches_an_enumeration_of_the_flag_states(variant):
    """The flags marginalised with the multi-cell terms (border sides whose cells are all
    visible, the body term and the pooled box ratio of each state) against NumPy."""
    cfg = RGBDConfig(
        variant=variant.removesuffix("-factorised"),
        flag_transition="factorised" if variant.endswith("factorised") else "auto",
    )
    params = default_rgbd_params(cfg)
    rng = np.random.default_rng(11)
    n, c = 32, 4
    n_states = body_states(cfg).shape[0]
    terms = _random_terms(rng, n, c, n_states)
    prev = jnp.asarray(rng.integers(0, 1 << c, n), jnp.int32)
    post = marginal_likelihood(
        cfg, params.occlusion, params.beta, jax.random.PRNGKey(0), prev, terms
    )
    want_ll, want_p = _marginal_reference(cfg, params.occlusion, params.beta, prev, terms)
    np.testing.assert_allclose(np.asarray(post.log_likelihood), want_ll, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(post.p_cell), want_p, atol=1e-5)
    if not cfg.occlusion:  # no flags: they stay as they were
        np.testing.assert_array_equal(np.asarray(post.flags), np.asarray(prev))
    else:
        assert 0.05 < want_p.mean() < 0.95  # the flags are uncertain: the test can tell
        assert not np.array_equal(np.asarray(post.flags), np.asarray(prev))


def test_depth_ordering_nearer_content_is_occluder_evidence(toy):
    frames, gt, bg = toy
    cfg = _config("grid-occlusion")
    params = default_rgbd_params(cfg)
    t = 40  # the figure (x = 65..89) is fully behind the box (x = 50..98)
    frame = Frame(frames.colour[t], frames.depth[t])
    obs = observe(cfg, params.foreground, frame, bg)
    colour_t = jnp.full((4, cfg.n_bins), 1.0 / cfg.n_bins)
    depth_t = _templates(jnp.full((4,), float(Z_PERSON)))
    behind = jnp.array([[65.0, 40.0, 24.0, 50.0]])  # where the figure is, behind the box
    empty = jnp.array([[10.0, 40.0, 24.0, 50.0]])  # bare background (farther)
    tb = cell_terms(cfg, params, colour_t, depth_t, obs, behind)
    te = cell_terms(cfg, params, colour_t, depth_t, obs, empty)
    assert (np.asarray(tb.occluder) > 0.9).all() and (np.asarray(te.occluder) < 0.05).all()
    assert (np.asarray(tb.l_occ) > np.asarray(tb.l_vis)).all()  # hidden: "occluded" wins
    assert (np.asarray(te.l_occ) < np.asarray(tb.l_occ) - 5).all()  # background can't hide it


# -- structure ------------------------------------------------------------------------------


def test_config_validation():
    with pytest.raises(ValueError, match="variant"):
        RGBDConfig(variant="depth-only")
    # The paper's RGB row is the colour layer now, not an RGB-D variant.
    with pytest.raises(ValueError, match="variant"):
        RGBDConfig(variant="rgb")
    with pytest.raises(ValueError, match="report"):
        RGBDConfig(report="all")
    with pytest.raises(ValueError, match="full 2"):
        RGBDConfig(grid=5, flag_transition="full")
    c = RGBDConfig(grid=5)
    assert c.n_cells == 25 and not c.full_transition
    assert RGBDConfig(variant="rgbd", grid=3).n_cells == 1


def test_reports_the_weights_before_resampling_when_asked(toy):
    frames, gt, bg = toy
    cfg = _config("grid-occlusion")
    filt, params = build_rgbd_filter(cfg), default_rgbd_params(cfg)
    f0 = Frame(frames.colour[0], frames.depth[0])
    state = jax.jit(filt.init)(params, jax.random.PRNGKey(0), f0, gt[0], Context(background=bg))
    later = [Frame(frames.colour[t], frames.depth[t]) for t in range(1, 4)]
    reporting = build_rgbd_filter(dataclasses.replace(cfg, report_weights=True))
    check_weighed_cloud(filt, reporting, params, state, later, "grid-occlusion")


def test_scan_vmap_and_no_retracing(toy):
    frames, gt, bg = toy
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    traces = []

    def step(p, k, s, f):
        traces.append(1)
        return filt.step(p, k, s, f)

    jstep = jax.jit(step)
    context = Context(background=bg)
    state = jax.jit(filt.init)(
        params, jax.random.PRNGKey(0), Frame(frames.colour[0], frames.depth[0]), gt[0], context
    )
    assert isinstance(state, RGBDState)
    for t in range(1, 4):
        state, info = jstep(
            params, jax.random.PRNGKey(t), state, Frame(frames.colour[t], frames.depth[t])
        )
    assert len(traces) == 1
    assert np.isfinite(np.asarray(info.box)).all() and info.vote.shape == (4,)
    # The step says whether its histograms came from the window: a cloud around the
    # person fits the 120 x 128 window; boxes as wide as the frame do not.
    frame = Frame(frames.colour[4], frames.depth[4])
    assert bool(info.windowed)
    p0 = state.cloud.particles
    wide = state._replace(
        cloud=state.cloud._replace(particles=p0.at[:, 0].set(W / 2).at[:, 4].set(float(W)))
    )
    assert not bool(jstep(params, jax.random.PRNGKey(9), wide, frame)[1].windowed)
    assert len(traces) == 1
    short = Frame(frames.colour[:6], frames.depth[:6])
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    _, infos = jax.jit(jax.vmap(lambda k: track(filt, params, k, short, gt[0], context)))(keys)
    assert infos.estimate.shape == (3, 5, 4)
    assert np.isfinite(np.asarray(infos.estimate)).all()
    # The filter proposes without the colour layer's size hold (its proposal densities
    # assume none): a cloud moving across with a size velocity is drawn alike.
    moving = state._replace(
        cloud=state.cloud._replace(particles=p0.at[:, 2].set(8.0).at[:, 6:8].set(2.0))
    )
    held = params._replace(motion=params.motion._replace(size_hold=jnp.float32(1.0)))
    a, b = (jstep(p, jax.random.PRNGKey(7), moving, frame)[0] for p in (params, held))
    np.testing.assert_array_equal(np.asarray(a.cloud.particles), np.asarray(b.cloud.particles))


def test_rgb_row_is_the_colour_layer_through_the_one_track(toy):
    """The paper's RGB row (the old "rgb" variant) is the colour layer with the RGB-D
    filter's motion model (ar1, hierarchical) and window growth: ``track_boxes`` runs it as
    it runs every box filter and gives the boxes of its own ``init`` and ``step`` called
    one frame at a time."""
    frames, gt, bg = toy
    cfg = ColourConfig(n_particles=128, model="ar1", hierarchical=True).with_window(
        PERSON, (H, W), growth=1.5
    )
    filt = build_colour_filter(cfg)
    params = default_colour_params()
    short = Frame(frames.colour[:5], frames.depth[:5])
    key = jax.random.PRNGKey(2)
    boxes, lost = track_boxes(filt, params, key, short, gt[0], Context(background=bg))
    assert boxes.shape == (5, 4) and lost.shape == (5,) and not np.asarray(lost).any()
    np.testing.assert_array_equal(np.asarray(boxes[0]), gt[0])
    k_init, k_run = jax.random.split(key)
    state = jax.jit(filt.init)(params, k_init, Frame(short.colour[0], short.depth[0]), gt[0])
    step = jax.jit(filt.step)
    for t, k in enumerate(jax.random.split(k_run, 4)):
        state, info = step(params, k, state, Frame(short.colour[t + 1], short.depth[t + 1]))
        # Equal up to float32 rounding (two programs compiled apart).
        np.testing.assert_allclose(np.asarray(boxes[t + 1]), np.asarray(info.box), atol=1e-4)
    # The boxes follow the walking figure (1.5 px/frame to the right).
    assert float(boxes[-1, 0]) > float(boxes[0, 0])


def test_spreading_while_occluded(toy):
    frames, gt, bg = toy
    # No resampling, no re-draws, no detector draws: the returned particles are the
    # propagated ones.
    cfg = _config("grid-occlusion", recovery_fraction=0.0, detector_fraction=0.0, ess_threshold=0.0)
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    f0 = Frame(frames.colour[0], frames.depth[0])
    state = jax.jit(filt.init)(params, jax.random.PRNGKey(0), f0, gt[0], Context(background=bg))
    step = jax.jit(filt.step)
    spreads = []
    for occluded in (0, 20):
        s = state._replace(occlusion=state.occlusion._replace(occluded_frames=jnp.int32(occluded)))
        s2, _ = step(params, jax.random.PRNGKey(1), s, f0)
        spreads.append(float(jnp.std(s2.cloud.particles[:, 0])))
    expected = float(params.occlusion.spread_max)  # 1 + 0.15 * 20 capped at spread_max
    assert spreads[1] / spreads[0] == pytest.approx(expected, rel=0.25)


def test_template_update_only_in_cells_voted_visible(toy):
    frames, gt, bg = toy
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    colour = params.colour._replace(rate=jnp.float32(0.5), sigma=jnp.float32(SIGMA_RGB_TEST))
    params = params._replace(colour=colour)
    step = jax.jit(filt.step)
    state = jax.jit(filt.init)(
        params,
        jax.random.PRNGKey(0),
        Frame(frames.colour[0], frames.depth[0]),
        gt[0],
        Context(background=bg),
    )
    checked = 0
    for t in range(1, 40):
        before = state.colour.histograms
        state, info = step(
            params, jax.random.PRNGKey(t), state, Frame(frames.colour[t], frames.depth[t])
        )
        voted = np.asarray(info.vote) > float(params.occlusion.vote_threshold)
        changed = np.abs(np.asarray(state.colour.histograms - before)).sum(-1) > 1e-6
        if voted.any():
            assert not changed[voted].any()  # eq. 8: occluded cells keep their template
            checked += 1
    assert checked >= 3  # the partial occlusion (t >= 10) was voted in some frames


def test_body_template_learns_a_running_mean_then_slowly_and_never_while_occluded(toy):
    frames, gt, bg = toy
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    params = params._replace(colour=params.colour._replace(sigma=jnp.float32(SIGMA_RGB_TEST)))
    step = jax.jit(filt.step)
    obs_of = jax.jit(lambda f, b: observe(cfg, params.foreground, f, b))
    state = jax.jit(filt.init)(
        params,
        jax.random.PRNGKey(0),
        Frame(frames.colour[0], frames.depth[0]),
        gt[0],
        Context(background=bg),
    )
    n_fg = cfg.n_fg_bins

    def histogram(t, box):  # NumPy: normalised foreground colours of a box
        frame = Frame(frames.colour[t], frames.depth[t])
        bins = np.asarray(obs_of(frame, state.background).colour_bins)
        x0, y0, x1, y1 = (int(np.floor(v + 0.5)) for v in (*box[:2], *(box[:2] + box[2:])))
        cut = bins[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)].ravel()
        h = np.bincount(cut[cut < n_fg], minlength=n_fg).astype(float)
        return h / max(h.sum(), 1)

    want = histogram(0, gt[0])
    np.testing.assert_allclose(np.asarray(state.body.histogram), want, atol=1e-6)
    # The toy figure's colours hardly change: start from a flat template so that the
    # learning rate shows.
    state = state._replace(body=state.body._replace(histogram=jnp.full((n_fg,), 1.0 / n_fg)))
    learnt, frozen = 0, 0
    for t in range(1, 40):
        before = np.asarray(state.body.histogram)
        n_before = int(state.body.frames)
        state, info = step(
            params, jax.random.PRNGKey(t), state, Frame(frames.colour[t], frames.depth[t])
        )
        after = np.asarray(state.body.histogram)
        assert after.sum() == pytest.approx(1.0, abs=1e-5)
        if int(state.body.frames) == n_before:
            # Not learnt: any cell voted (partial occlusion from t = 9), or lost.
            np.testing.assert_allclose(after, before, atol=1e-7)
            frozen += bool(np.any(np.asarray(info.vote) > 0.1) or bool(info.lost))
            continue
        assert not bool(info.lost) and np.max(np.asarray(info.vote)) < 0.1
        # A running mean over the warm-up steps, then the slow rate.
        body = params.body
        rate = 1.0 / (n_before + 2.0) if t <= float(body.warmup) else float(body.rate)
        mixed = (1 - rate) * before + rate * histogram(t, np.asarray(info.box))
        np.testing.assert_allclose(after, mixed / mixed.sum(), atol=2e-5)
        learnt += 1
    assert learnt >= 5 and frozen >= 5  # both branches ran


# -- the step's pieces, one at a time ---------------------------------------------------------
# Defaults the hand-computed expectations below use: occlusion.margin 400 mm (margin_rel
# 0.12), target.gate 300 mm (gate_rel 0.1), target.drift_max 900 mm, depth.speed 60 mm per
# frame, depth.max_drift 500, depth.rate 0.5, depth.velocity_rate 0.2, velocity_fade 0.3.


def test_search_drift_grows_with_hidden_or_stale_frames_up_to_its_cap():
    params = default_rgbd_params(RGBDConfig())
    fresh = _templates([2500.0] * 4, age=[0.0, 3.0, 5.0, 7.0])
    assert float(search_drift(params, fresh, jnp.int32(0))) == 0.0  # one cell just learnt
    assert float(search_drift(params, fresh, jnp.int32(4))) == pytest.approx(240.0)
    stale = _templates([2500.0] * 4, age=[20.0] * 4)
    assert float(search_drift(params, stale, jnp.int32(0))) == pytest.approx(900.0)  # capped
    # Cells without a template count as stale as can be; the known one decides.
    partly = _templates([2500.0, 0.0, 0.0, 0.0], age=[2.0, 0.0, 0.0, 0.0])
    assert float(search_drift(params, partly, jnp.int32(0))) == pytest.approx(120.0)
    unknown = _templates([0.0] * 4)
    assert float(search_drift(params, unknown, jnp.int32(0))) == pytest.approx(
        min(60.0 * MAX_DEPTH_AGE, 900.0)
    )


def test_target_gate_is_the_depth_tolerance_widened_by_the_drift():
    params = default_rgbd_params(RGBDConfig())
    t = _templates([2500.0] * 4)
    z = jnp.array([2500.0, 5000.0])
    np.testing.assert_allclose(np.asarray(target_gate(params, t, jnp.int32(0), z)), [300, 500])
    hidden = np.asarray(target_gate(params, t, jnp.int32(5), z))
    np.testing.assert_allclose(hidden, [300 + 300, 500 + 300])
    fresh = np.asarray(target_gate(params, t, jnp.int32(5), z, drift=False))
    np.testing.assert_allclose(fresh, [300, 500])


def test_at_occluder_is_within_the_tolerance_of_the_remembered_occluder():
    params = default_rgbd_params(RGBDConfig())
    z = jnp.array([1800.0, 1600.0, 2099.0, 2100.0, 1499.0])
    got = np.asarray(at_occluder(params, _templates([2500.0] * 4, occluder=1800.0), z))
    np.testing.assert_array_equal(got, [True, True, True, False, False])  # 300 mm either side
    none = np.asarray(at_occluder(params, _templates([2500.0] * 4), z))
    assert not none.any()  # no occluder seen yet


def test_target_like_excludes_the_occluders_depth():
    """Hidden 10 frames, the gate widens by 600 mm: a pixel 350 mm nearer than the
    target may be it, but the occluder's depth (1800 mm, 700 mm nearer) may not, though
    it lies within the widened gate; without a remembered occluder it may."""
    params = default_rgbd_params(RGBDConfig())
    z = jnp.array([2500.0, 2750.0, 2150.0, 1800.0, 1650.0, 1550.0, 3500.0])
    target_z = jnp.float32(2500.0)
    occluded = _templates([2500.0] * 4, occluder=1800.0)
    like, tight = target_like(params, occluded, jnp.int32(10), z, target_z)
    np.testing.assert_array_equal(np.asarray(tight), [1, 1, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(np.asarray(like), [1, 1, 1, 0, 0, 0, 0])
    like, _ = target_like(params, _templates([2500.0] * 4), jnp.int32(10), z, target_z)
    np.testing.assert_array_equal(np.asarray(like), [1, 1, 1, 1, 1, 0, 0])
    # Seen last frame: no drift, the tight gate only.
    like, _ = target_like(params, occluded, jnp.int32(0), z, target_z)
    np.testing.assert_array_equal(np.asarray(like), [1, 1, 0, 0, 0, 0, 0])


def test_remember_occluder_is_the_mean_of_the_nearer_cells():
    params = default_rgbd_params(RGBDConfig())
    t = _templates([2500.0] * 4, occluder=1234.0)  # near cut: 2500 - 400 = 2100 mm
    got = remember_occluder(params, t, jnp.array([1500.0, 1600.0, 2400.0, 0.0]))
    assert float(got) == pytest.approx(1550.0)
    # Nothing nearer than the cut (2101 mm is not): the last occluder is kept.
    got = remember_occluder(params, t, jnp.array([2400.0, 2101.0, 0.0, 2600.0]))
    assert float(got) == pytest.approx(1234.0)
    unknown = remember_occluder(params, _templates([0.0] * 4, occluder=1234.0), jnp.full(4, 900.0))
    assert float(unknown) == pytest.approx(1234.0)  # no template: no "nearer" either


def _cell_depth_scene(cell_depths):
    """The red target box with each 20 x 40 cell of ``TEMPLATE_BOX`` at its own depth."""
    x, y, w, h = TEMPLATE_BOX
    depth = np.empty((h, w), np.uint16)
    for i, z in enumerate(cell_depths):
        r, c = divmod(i, 2)
        depth[r * h // 2 : (r + 1) * h // 2, c * w // 2 : (c + 1) * w // 2] = z
    return _box_scene(depth)


def test_depth_template_update_learns_where_ok_and_the_rest_follows():
    """Eq. 7 in the cells voted visible, the others following the mean change; occluder
    pixels (1000 mm nearer) teach nothing; a cell without a template takes its median;
    the velocity is corrected by the mean innovation, and fades when nothing learns."""
    cfg = RGBDConfig(variant="grid-occlusion")
    params = default_rgbd_params(cfg)
    est = jnp.asarray(TEMPLATE_BOX, jnp.float32)
    frame, bg = _cell_depth_scene([2600, 2400, 1500, 2300])
    obs = observe(cfg, params.foreground, frame, bg)
    _, med, _ = (np.asarray(a, np.float64) for a in cell_statistics(cfg, obs, est))
    np.testing.assert_allclose(med, [2600, 2400, 1500, 2300], rtol=0.05)
    t = _templates([2500.0, 2500.0, 2500.0, 0.0], age=[3.0, 3.0, 3.0, 0.0], velocity=10.0)
    held = jnp.float32(1.0)  # the target is where its templates expect it

    def update(ok, templates=t, config=cfg):
        ok = jnp.asarray(ok)
        return depth_template_update(
            config, params, templates, jnp.int32(0), obs, frame.depth, est, ok, held
        )

    # Cell 1 is voted occluded; cell 2 is all occluder.
    new = update([True, False, True, True])
    learnt = 0.5 * 2500 + 0.5 * med[0]
    shift = learnt - 2500
    np.testing.assert_allclose(
        np.asarray(new.depth), [learnt, 2500 + shift, 2500 + shift, med[3]], rtol=1e-5
    )
    np.testing.assert_array_equal(np.asarray(new.age), [0, 0, 0, 0])
    assert float(new.velocity) == pytest.approx(10.0 + 0.2 * (med[0] - 2500), rel=1e-5)
    # Nothing voted visible: nothing moves, every template ages, the velocity fades.
    still = update([False] * 4)
    np.testing.assert_array_equal(np.asarray(still.depth), np.asarray(t.depth))
    np.testing.assert_array_equal(np.asarray(still.age), [4, 4, 4, 1])
    assert float(still.velocity) == pytest.approx(0.7 * 10.0)
    # Only the occluder's cell voted visible: its pixels are cut, nothing learns.
    cut = update([False, False, True, False])
    np.testing.assert_array_equal(np.asarray(cut.depth), np.asarray(t.depth))
    assert float(cut.velocity) == pytest.approx(7.0)
    # Without template updates (config) the templates stay as they are.
    frozen = update([True] * 4, config=RGBDConfig(variant="grid-occlusion", template_update=False))
    assert frozen is t


def test_depth_template_update_takes_a_jump_beyond_the_margin_for_an_occluder():
    cfg = RGBDConfig(variant="grid-occlusion")
    params = default_rgbd_params(cfg)
    est = jnp.asarray(TEMPLATE_BOX, jnp.float32)
    frame, bg = _cell_depth_scene([3100] * 4)  # 600 mm farther than the templates
    obs = observe(cfg, params.foreground, frame, bg)
    ok = jnp.ones(4, bool)

    def update(age):
        t = _templates([2500.0] * 4, age=[age] * 4)
        return depth_template_update(
            cfg, params, t, jnp.int32(0), obs, frame.depth, est, ok, jnp.float32(1.0)
        )

    fresh = update(0.0)  # 600 > the 400 mm margin: not the target
    np.testing.assert_array_equal(np.asarray(fresh.depth), [2500.0] * 4)
    stale = update(5.0)  # 600 < 400 + 60 x 5: the target may have walked that far
    assert np.all(np.abs(np.asarray(stale.depth) - (2500 + 3100) / 2) < 0.05 * 3100)


def _colour_learnt(cur, est, rate):
    """NumPy eq. 7 with the background bin: the estimate's foreground colours, scaled to
    the template's foreground share, mixed in at ``rate``; the background share stays."""
    fg = est[:-1] / est[:-1].sum() * (1 - cur[-1])
    mixed = (1 - rate) * cur + rate * np.append(fg, cur[-1])
    return mixed / mixed.sum()


def test_cell_colour_update_learns_only_cells_ok_and_still_alike():
    cfg = RGBDConfig(variant="grid-occlusion", bins=(2, 2, 0))  # 4 colours + background
    params = default_rgbd_params(cfg).colour._replace(rate=jnp.float32(0.5))
    current = np.tile(np.array([0.45, 0.2, 0.2, 0.05, 0.1], np.float32), (4, 1))
    est = np.array(
        [
            [0.5, 0.25, 0.2, 0.05, 0.0],  # alike, ok: learns
            [0.0, 0.0, 0.1, 0.9, 0.0],  # ok, but another colour (distance > gate): keeps
            [0.5, 0.25, 0.2, 0.05, 0.0],  # alike, voted occluded: keeps
            [0.45, 0.25, 0.25, 0.05, 0.0],  # alike, ok: learns
        ],
        np.float32,
    )
    ok = np.array([True, True, False, True])
    new = np.asarray(
        cell_colour_update(
            cfg, params, CellColour(jnp.asarray(current)), jnp.asarray(est), ok
        ).histograms
    )
    d = np.sqrt(np.maximum(1 - np.sum(np.sqrt(est * current), axis=1), 0))
    assert d[1] > float(params.gate) > max(d[0], d[2], d[3])  # the cases are what they say
    np.testing.assert_allclose(new[0], _colour_learnt(current[0], est[0], 0.5), atol=1e-6)
    np.testing.assert_allclose(new[1], current[1], atol=1e-6)
    np.testing.assert_allclose(new[2], current[2], atol=1e-6)
    np.testing.assert_allclose(new[3], _colour_learnt(current[3], est[3], 0.5), atol=1e-6)
    assert not np.allclose(new[0], current[0], atol=1e-3)  # it did learn
    # Without the background bin: plain eq. 7.
    plain = RGBDConfig(variant="grid-occlusion", bins=(2, 2, 0), background_bin=False)
    cur_fg = current[:, :4] / current[:, :4].sum(1, keepdims=True)
    est_fg = est[:, :4] / est[:, :4].sum(1, keepdims=True)
    got = np.asarray(
        cell_colour_update(
            plain, params, CellColour(jnp.asarray(cur_fg)), jnp.asarray(est_fg), ok
        ).histograms
    )
    np.testing.assert_allclose(got[0], 0.5 * cur_fg[0] + 0.5 * est_fg[0], atol=1e-6)
    np.testing.assert_allclose(got[1:3], cur_fg[1:3], atol=1e-6)
    # Without template updates the templates stay as they are.
    frozen = RGBDConfig(variant="grid-occlusion", bins=(2, 2, 0), template_update=False)
    same = CellColour(jnp.asarray(current))
    assert cell_colour_update(frozen, params, same, jnp.asarray(est), ok) is same


# Library bug (reported, not fixed here): ``cell_colour_update`` takes the foreground part of
# the estimate's (normalised) histogram through ``normalise_counts``, which leaves sums
# below 1 as they are, so the learnt template sums to less than 1 and its background share
# grows whenever the estimate's cell holds background.
@pytest.mark.xfail(strict=True, reason="cpf_jax/rgbd/templates.py: foreground not renormalised")
def test_cell_colour_update_keeps_the_background_share_of_the_template():
    cfg = RGBDConfig(variant="grid-occlusion", bins=(2, 2, 0))
    params = default_rgbd_params(cfg).colour._replace(rate=jnp.float32(0.5))
    current = np.array([[0.4, 0.1, 0.1, 0.0, 0.4]], np.float32)
    est = np.array([[0.3, 0.2, 0.1, 0.0, 0.4]], np.float32)  # alike, with background
    new = cell_colour_update(
        cfg, params, CellColour(jnp.asarray(current)), jnp.asarray(est), np.array([True])
    )
    got = np.asarray(new.histograms[0])
    np.testing.assert_allclose(got, _colour_learnt(current[0], est[0], 0.5), atol=1e-6)


def _bins_scene(n_fg, box, bins_in_box):
    """Observation: background (the extra bin) with ``bins_in_box [h, w]`` in ``box``."""
    bins = np.full((H, W), n_fg, np.int32)
    x, y, w, h = box
    bins[y : y + h, x : x + w] = bins_in_box
    return Observation(jnp.asarray(bins), jnp.full((H, W), -1, jnp.int32), jnp.asarray(bins < n_fg))


def test_body_template_update_is_a_running_mean_then_slow_and_skips_occluded_frames():
    cfg = RGBDConfig(variant="grid-occlusion", bins=(2, 2, 0))
    body = default_rgbd_params(cfg).body
    n_fg = cfg.n_fg_bins
    box = (40, 20, 10, 10)  # 100 px: 60 of colour 0, 40 of colour 2
    in_box = np.zeros((10, 10), np.int32)
    in_box[6:] = 2
    obs = _bins_scene(n_fg, box, in_box)
    report = jnp.asarray(box, jnp.float32)
    seen = np.array([0.6, 0.0, 0.4, 0.0])
    flat = np.full(n_fg, 0.25, np.float32)
    calm, lost = jnp.zeros(4), jnp.array(False)

    def update(frames, steps, vote=calm, is_lost=lost, r=report):
        t = BodyTemplate(jnp.asarray(flat), jnp.int32(frames), jnp.int32(steps))
        return body_template_update(cfg, body, t, obs, r, vote, is_lost)

    warm = update(1, 1)  # the second frame of the warm-up: a third of the way
    np.testing.assert_allclose(np.asarray(warm.histogram), flat + (seen - flat) / 3, atol=1e-6)
    assert (int(warm.frames), int(warm.steps)) == (2, 2)
    slow = update(5, 10)  # after the warm-up: the slow rate
    rate = float(body.rate)
    np.testing.assert_allclose(np.asarray(slow.histogram), flat + rate * (seen - flat), atol=1e-6)
    for skipped in (
        update(1, 1, vote=jnp.array([0.0, 0.2, 0.0, 0.0])),  # a cell voted
        update(1, 1, is_lost=jnp.array(True)),
        update(1, 1, r=jnp.array([100.0, 20.0, 10.0, 10.0])),  # no foreground in the box
    ):
        np.testing.assert_array_equal(np.asarray(skipped.histogram), flat)
        assert (int(skipped.frames), int(skipped.steps)) == (1, 2)


def _state_at(templates: DepthTemplate, occluded_frames: int = 0) -> RGBDState:
    """An RGB-D state on the box scene with the given depth templates."""
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=8)
    frame, bg = _box_scene()
    params = default_rgbd_params(cfg)
    state = rgbd_init(
        cfg, params, jax.random.PRNGKey(0), frame, TEMPLATE_BOX, Context(background=bg)
    )
    occ = state.occlusion._replace(occluded_frames=jnp.int32(occluded_frames))
    return state._replace(depth=templates, occlusion=occ)


def test_target_extent_is_the_main_run_of_the_target_pixels():
    """The target (40 x 80 px at 2500 mm) in a larger estimate, with a stray column of
    target-depth pixels beyond the gap, a lone pixel and a nearer occluder beside it."""
    cfg = RGBDConfig(variant="grid-occlusion")
    params = default_rgbd_params(cfg)
    frame, bg = _box_scene()
    depth = np.asarray(frame.depth).copy()
    depth[30:60, 110:112] = Z_PERSON  # 31 columns (> 0.3 x 80) right of the target
    depth[110, 100] = Z_PERSON  # a lone pixel: no neighbour holds one
    depth[20:100, 85:95] = 1500  # an occluder, foreground but not the target's depth
    frame = Frame(frame.colour, jnp.asarray(depth))
    obs = observe(cfg, params.foreground, frame, bg)
    est = jnp.array([20.0, 10.0, 80.0, 100.0])  # searched in x 0..120, y -15..135
    state = _state_at(_templates([float(Z_PERSON)] * 4))
    ext = target_extent(params, state, obs, frame.depth, est)
    np.testing.assert_allclose(np.asarray(ext.box), TEMPLATE_BOX)
    assert float(ext.coverage) == pytest.approx((3200 + 60 + 1) / 8000, abs=1e-6)
    assert float(ext.held) == pytest.approx((3200 + 60 + 1) / 8000, abs=1e-6)
    # The target walked 400 mm nearer while its templates went stale (10 frames): it is
    # found by the drift but not held by the fresh gate.
    frame2, _ = _box_scene(Z_PERSON - 400)
    obs2 = observe(cfg, params.foreground, frame2, bg)
    stale = _state_at(_templates([float(Z_PERSON)] * 4, age=[10.0] * 4))
    ext = target_extent(params, stale, obs2, frame2.depth, jnp.asarray(TEMPLATE_BOX, jnp.float32))
    np.testing.assert_allclose(np.asarray(ext.box), TEMPLATE_BOX)
    assert float(ext.coverage) == pytest.approx(1.0) and float(ext.held) == 0.0
    # No target pixel: the estimate itself, and no coverage.
    empty, _ = _box_scene(box=None)
    obs3 = observe(cfg, params.foreground, empty, bg)
    ext = target_extent(params, state, obs3, empty.depth, est)
    np.testing.assert_array_equal(np.asarray(ext.box), np.asarray(est))
    assert float(ext.coverage) == 0.0


def test_target_extent_in_a_window_equals_the_frame_wide_one():
    """Counted in a static window placed on the search area (when it holds it) the extent is
    the frame-wide one bit for bit, for estimates inside, at the edges of and beyond the
    frame, and one whose search area the window cannot hold; under jit and vmap."""
    cfg = RGBDConfig(variant="grid-occlusion")
    params = default_rgbd_params(cfg)
    frame, bg = _box_scene()
    depth = np.asarray(frame.depth).copy()
    depth[30:60, 110:112] = Z_PERSON
    frame = Frame(frame.colour, jnp.asarray(depth))
    obs = observe(cfg, params.foreground, frame, bg)
    state = _state_at(_templates([float(Z_PERSON)] * 4))
    ests = jnp.array(
        [
            [20.0, 10.0, 80.0, 100.0],
            [20.3, 10.7, 79.6, 99.2],
            [40.0, 30.0, 40.0, 30.0],  # rows 22-66 of the target's 20-99
            [-30.0, -20.0, 60.0, 70.0],
            [150.0, 100.0, 80.0, 90.0],
            [500.0, 400.0, 30.0, 30.0],
            [0.0, 0.0, 150.0, 150.0],  # the search area exceeds the window: frame-wide
        ]
    )

    def extent(e, window):
        return target_extent(params, state, obs, frame.depth, e, window)

    full = jax.jit(jax.vmap(lambda e: extent(e, None)))(ests)
    for got in (
        jax.jit(jax.vmap(lambda e: extent(e, (120, 130))))(ests),
        [jax.jit(lambda e: extent(e, (120, 130)))(e) for e in ests],
        [jax.jit(lambda e: extent(e, (70, 130)))(e) for e in ests],
    ):
        got = jax.tree.map(lambda *x: jnp.stack(x), *got) if isinstance(got, list) else got
        for a, b in zip(full, got, strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(full.coverage[0]) > 0.3


def test_kept_lines_and_main_run_on_hand_made_counts():
    counts = jnp.array([0, 1, 0, 0, 3, 4, 0, 1, 0, 0, 0, 5, 5, 0], jnp.float32)
    kept = np.asarray(kept_lines(counts, jnp.float32(2.0)))
    # The lone 1s (lines 1 and 7) drop out; the others have 2 pixels among 3 lines.
    np.testing.assert_array_equal(np.flatnonzero(kept), [4, 5, 11, 12])
    limb = np.asarray(kept_lines(jnp.array([0, 1, 1, 1, 0, 0], jnp.float32), jnp.float32(2.0)))
    np.testing.assert_array_equal(limb, [0, 1, 1, 1, 0, 0])  # a 1 px wide limb stays
    kept = jnp.asarray(kept)
    # Gap 3: two runs, 7 and 10 pixels, the second wins; gap 6 (not more than 6 apart):
    # one run; 5.9: two again.
    np.testing.assert_array_equal(np.flatnonzero(main_run(counts, kept, 3.0)), [11, 12])
    np.testing.assert_array_equal(np.flatnonzero(main_run(counts, kept, 6.0)), [4, 5, 11, 12])
    np.testing.assert_array_equal(np.flatnonzero(main_run(counts, kept, 5.9)), [11, 12])
    ties = jnp.array([0, 2, 2, 0, 0, 0, 4, 0], jnp.float32)
    tied = main_run(ties, ties > 0, 1.0)
    np.testing.assert_array_equal(np.flatnonzero(tied), [1, 2])  # equal totals: the first
    assert not np.asarray(main_run(counts, jnp.zeros(14, bool), 3.0)).any()


def test_reported_box_of_each_report_mode():
    est = jnp.array([10.0, 20.0, 40.0, 80.0])  # cells 20 x 40, row-major
    extent = Extent(jnp.array([12.0, 25.0, 30.0, 70.0]), jnp.float32(0.5), jnp.float32(0.5))
    none = jnp.zeros(4, bool)
    top = jnp.array([True, True, False, False])
    left = jnp.array([True, False, True, False])
    every = jnp.ones(4, bool)

    def report(config, voted):
        return np.asarray(reported_box(config, est, extent, voted))

    pixels = RGBDConfig(variant="grid-occlusion")
    np.testing.assert_array_equal(report(pixels, top), [12, 25, 30, 70])
    cells = RGBDConfig(variant="grid-occlusion", report="cells")
    np.testing.assert_array_equal(report(cells, none), [10, 20, 40, 80])
    np.testing.assert_array_equal(report(cells, top), [10, 60, 40, 40])  # the bottom row
    np.testing.assert_array_equal(report(cells, left), [30, 20, 20, 80])  # the right column
    np.testing.assert_array_equal(report(cells, every), [10, 20, 40, 80])  # hidden: estimate
    # Without flags nothing is voted: "cells" is the estimate, as is "box".
    np.testing.assert_array_equal(report(RGBDConfig(variant="grid", report="cells"), top), est)
    np.testing.assert_array_equal(report(RGBDConfig(report="box"), top), est)


def test_rgbd_init_starts_from_the_box_and_its_cells():
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=16)
    params = default_rgbd_params(cfg)
    frame, bg = _box_scene()
    box = jnp.asarray(TEMPLATE_BOX, jnp.float32)
    state = rgbd_init(cfg, params, jax.random.PRNGKey(0), frame, box, Context(background=bg))
    one = np.array([60.0, 60.0, 0.0, 0.0, 40.0, 80.0, 0.0, 0.0], np.float32)
    np.testing.assert_array_equal(np.asarray(state.cloud.particles), np.tile(one, (16, 1)))
    np.testing.assert_array_equal(np.asarray(state.cloud.previous), np.tile(one, (16, 1)))
    np.testing.assert_allclose(np.asarray(state.cloud.log_weights), -np.log(16.0), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(state.estimate), TEMPLATE_BOX)
    assert not np.asarray(state.flags).any() and not np.asarray(state.occlusion.vote).any()
    assert int(state.occlusion.occluded_frames) == 0
    np.testing.assert_array_equal(np.asarray(state.occlusion.visible_size), [40.0, 80.0])
    # Templates: the cells' median depths (log-spaced bins, 5 % wide), no age, no velocity;
    # the reach is the box height at their depth.
    d = state.depth
    np.testing.assert_allclose(np.asarray(d.depth), Z_PERSON, rtol=0.05)
    assert not np.asarray(d.age).any() and float(d.velocity) == 0.0 and float(d.occluder) == 0.0
    assert float(d.reach) == pytest.approx(80.0 * float(np.mean(np.asarray(d.depth))), rel=1e-6)
    # Colours: every cell and the body are all red (no background in the box).
    red = int(np.asarray(bin_index(frame.colour, cfg.bins))[30, 50])
    want = np.zeros((4, cfg.n_bins))
    want[:, red] = 1.0
    np.testing.assert_allclose(np.asarray(state.colour.histograms), want, atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.body.histogram), want[0, :-1], atol=1e-6)
    assert (int(state.body.frames), int(state.body.steps)) == (0, 0)
    # The box is all foreground: the Beta means move from the fitted mean towards a fill of
    # 1 (clipped to 0.95), less the dead zone.
    beta = params.beta
    prior = float(beta.box_a / (beta.box_a + beta.box_b))
    gap = _logit(0.95) - _logit(prior)
    assert float(state.fill_shift) == pytest.approx(gap - float(beta.fill_deadzone), rel=1e-5)
    # Without a background the frame is its own scene: the box stands in front of the wall
    # found along its rows, all of it foreground, and the Betas move as with one.
    own = rgbd_init(cfg, params, jax.random.PRNGKey(0), frame, box)
    assert float(own.fill_shift) == pytest.approx(float(state.fill_shift), rel=1e-5)
    np.testing.assert_allclose(np.asarray(own.colour.histograms), want, atol=1e-6)
    # Without it every pixel is foreground and nothing moves the Betas.
    blind = dataclasses.replace(cfg, side_scene=None)
    plain = rgbd_init(blind, params, jax.random.PRNGKey(0), frame, box)
    assert float(plain.fill_shift) == 0.0
    # A box on the bare wall: the cells hold background only, the body template nothing.
    wall = rgbd_init(
        cfg,
        params,
        jax.random.PRNGKey(0),
        frame,
        jnp.array([100.0, 20.0, 40.0, 80.0]),
        Context(background=bg),
    )
    np.testing.assert_allclose(np.asarray(wall.colour.histograms[:, -1]), 1.0, atol=1e-6)
    assert int(wall.body.frames) == -1
    assert not np.asarray(wall.depth.depth).any() and float(wall.depth.reach) == 0.0


def test_rgbd_step_follows_a_standing_target_and_loses_a_vanished_one():
    """One step on the initial frame reports the target's tight box and learns; one on
    the bare wall reports it lost (nothing at its depth) and learns nothing."""
    cfg = RGBDConfig(variant="grid-occlusion", n_particles=64)
    params = default_rgbd_params(cfg)
    frame, bg = _box_scene()
    empty, _ = _box_scene(box=None)
    step = jax.jit(rgbd_step, static_argnums=0)
    state = rgbd_init(
        cfg, params, jax.random.PRNGKey(0), frame, TEMPLATE_BOX, Context(background=bg)
    )
    seen, info = step(cfg, params, jax.random.PRNGKey(1), state, frame)
    np.testing.assert_allclose(np.asarray(info.box), TEMPLATE_BOX, atol=1e-4)
    assert not bool(info.lost) and not bool(info.target_occluded)
    assert np.asarray(info.vote).max() < 0.1 and int(seen.occlusion.occluded_frames) == 0
    assert np.abs(np.asarray(info.estimate) - np.asarray(TEMPLATE_BOX)).max() < 4.0
    assert float(jax.nn.logsumexp(seen.cloud.log_weights)) == pytest.approx(0.0, abs=1e-5)
    assert 1.0 <= float(info.ess) <= 64.0
    assert not np.asarray(seen.depth.age).any()  # every cell learnt its depth
    assert (int(seen.body.frames), int(seen.body.steps)) == (1, 1)
    gone, info = step(cfg, params, jax.random.PRNGKey(2), seen, empty)
    assert bool(info.lost) and bool(info.target_occluded)
    assert int(gone.occlusion.occluded_frames) == 1
    np.testing.assert_allclose(
        np.asarray(gone.depth.depth),
        np.asarray(seen.depth.depth) + float(seen.depth.velocity),
        rtol=1e-6,
    )
    np.testing.assert_array_equal(np.asarray(gone.depth.age), [1.0] * 4)
    np.testing.assert_allclose(
        np.asarray(gone.colour.histograms), np.asarray(seen.colour.histograms), atol=1e-6
    )
    assert int(gone.body.frames) == 1
    np.testing.assert_array_equal(
        np.asarray(gone.occlusion.visible_size), np.asarray(seen.occlusion.visible_size)
    )


def _main_run_reference(counts, kept, gap):
    """Plain-Python runs: kept lines more than ``gap`` apart start a new run."""
    runs, last = [], None
    for i in np.flatnonzero(kept):
        if last is None or i - last > gap:
            runs.append([])
        runs[-1].append(i)
        last = i
    out = np.zeros(len(kept), bool)
    if runs:
        best = max(runs, key=lambda r: counts[r].sum())  # first of equal totals
        out[best] = True
    return out


def test_main_run_matches_reference():
    """The pixel report's main run (``main_run``) against a plain loop over lines."""
    rng = np.random.default_rng(3)
    n, length = 64, 50
    counts = rng.integers(0, 6, (n, length)).astype(np.float32)
    kept = rng.random((n, length)) < rng.uniform(0.05, 0.9, (n, 1))
    counts = np.where(kept, counts + 1, 0).astype(np.float32)
    gaps = rng.uniform(0.0, 6.0, n).astype(np.float32)
    kept[0] = False  # no kept line at all: nothing
    # A person (lines 10-29 with a 3-line gap at 18-20) and stray pixels at 36-38.
    kept[1] = False
    kept[1, 10:18] = kept[1, 21:30] = kept[1, 36:39] = True
    counts[1] = np.where(kept[1], 5.0, 0.0)
    counts[1, 36:39] = 9.0
    gaps[1] = 4.0
    items = [(counts[i], kept[i], gaps[i]) for i in range(n)]
    for i in range(n):  # every line set plainly and under jit, all under vmap
        variants = ("plain", "jit", "vmap") if i == 0 else ("plain", "jit")
        check_kernel(main_run, _main_run_reference, items[i], batch=items, variants=variants)
    got = np.asarray(jax.vmap(main_run)(counts, kept, gaps))
    assert not got[0].any()
    np.testing.assert_array_equal(np.flatnonzero(got[1]), [*range(10, 18), *range(21, 30)])
    assert got.any(axis=1).sum() == kept.any(axis=1).sum()


# -- tracking ---------------------------------------------------------------------------------


def test_grid_occlusion_tracks_through_a_long_full_occlusion(toy):
    """Stated thresholds: MOTA >= 90 %, no box in >= 80 % of the hidden frames, and the
    person found again within 5 frames of reappearing (IoU >= 0.5 from then on)."""
    _, gt, _ = toy
    # The flags, spreading and recovery search alone (the detector proposal is tested in
    # test_rgbd_proposal.py; with it, this toy scores MOTA 86-88 over keys 0-2, as
    # without it over keys 1-2).
    boxes, lost = _run(toy, "grid-occlusion", detector_fraction=0.0)
    vis = gt[:, 2] > 0
    s = summarise(boxes, gt, vis, lost)
    assert s["mota"] >= 90.0, s
    hidden = ~vis
    assert hidden.sum() >= 15 and lost[hidden].mean() >= 0.8
    back = np.nonzero(vis & (np.arange(T) > np.nonzero(hidden)[0][-1]))[0]
    ious = np.asarray(iou(boxes[back], gt[back]))
    assert (ious[5:] >= 0.5).all()


def test_flags_beat_the_variants_without_them_on_the_toy_occlusion(toy):
    """The flags alone (no detector proposal in any variant; the grid-occlusion run is
    the one of the test above, cached) against the variants without them."""
    _, gt, _ = toy
    vis = gt[:, 2] > 0
    mota = {}
    for v in ("rgbd", "grid", "grid-occlusion"):
        boxes, lost = _run(toy, v, detector_fraction=0.0)
        mota[v] = summarise(boxes, gt, vis, lost)["mota"]
    # Without flags the filters keep reporting a box while the person is hidden.
    assert mota["grid-occlusion"] >= max(mota["rgbd"], mota["grid"]) + 10, mota


def test_depth_templates_follow_a_target_walking_away():
    """A figure recedes 80 mm per frame (no occluder): the alpha-beta depth templates
    learn the velocity and stay on the figure's depth (stated: velocity within 25 % of
    80 mm/frame after 25 frames, templates within 3 %); without the velocity term
    (``depth.velocity_rate = 0``) they lag behind by several times more."""
    rng = np.random.default_rng(1)
    n = 30
    z_true = 1500.0 + 80.0 * np.arange(n)
    frames = []
    for t in range(n):
        colour, depth, mask = _toy(10, rng, occluder=False)
        depth = np.where(mask, (z_true[t] + rng.normal(0, 15, mask.shape)), depth)
        frames.append((colour, depth.astype(np.uint16), mask))
    fr = Frame(
        jnp.asarray(np.stack([f[0] for f in frames])), jnp.asarray(np.stack([f[1] for f in frames]))
    )
    empty = [_toy(0, rng, person=False, occluder=False) for _ in range(5)]
    bg = median_background(np.stack([e[0] for e in empty]), np.stack([e[1] for e in empty]))
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    box = jnp.asarray(_gt(frames[0][2]))
    lags = {}
    context = Context(background=bg)
    run = jax.jit(lambda k, p, fr: track(filt, p, k, fr, box, context))  # one compile for both
    for rate in (0.2, 0.0):
        p = params._replace(depth=params.depth._replace(velocity_rate=jnp.float32(rate)))
        state, _ = run(jax.random.PRNGKey(0), p, fr)
        tpl = np.asarray(state.depth.depth)
        lags[rate] = float(np.max(np.abs(tpl - z_true[-1])))
        if rate > 0:
            assert abs(float(state.depth.velocity) - 80.0) < 20.0, float(state.depth.velocity)
            assert lags[rate] < 0.03 * z_true[-1], tpl
    assert lags[0.0] > 2.0 * lags[0.2], lags


def _reversal_toy(rng: np.random.Generator):
    """The toy occlusion scene, but the figure walks away at 40 mm per frame until it is
    hidden behind the box (t = 38, 3320 mm) and comes back at 40 mm per frame (2200 mm
    when it is in full view again at t = 66)."""
    t_turn, z0, v = 38, 1800.0, 40.0
    frames = []
    for t in range(T):
        colour, depth, mask = _toy(t, rng)
        z = z0 + v * t if t <= t_turn else z0 + v * (2 * t_turn - t)
        depth = np.where(mask, z + rng.normal(0, 15, mask.shape), depth).astype(np.uint16)
        frames.append((colour, depth, mask))
    colour = np.stack([f[0] for f in frames])
    depth = np.stack([f[1] for f in frames])
    gt = np.stack([_gt(f[2]) for f in frames])
    return Frame(jnp.asarray(colour), jnp.asarray(depth)), gt


# Documents a non-default setting against the default's known failure (12 runs, 35-45 s);
# the fade itself runs in every grid-occlusion test at its default 0.05. Run with -m slow.
@pytest.mark.slow
def test_velocity_fade_finds_a_target_that_turns_back_while_hidden(toy):
    """A target walking away turns round behind the occluder and comes back nearer than
    where it was hidden. Stated: with ``depth.velocity_fade`` 0.3 (the templates stop
    extrapolating the old velocity while nothing is measured) the success rate over the
    frames after it reappears in full is >= 70 % over six keys (measured 83 %: one key in
    six misses it); with the default 0.05
    the templates run on past the target, its own pixels count as an occluder and that
    rate stays below 50 % (the known failure the default keeps; ``default_rgbd_params``)."""
    _, _, bg = toy
    frames, gt = _reversal_toy(np.random.default_rng(3))
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    # lax.map over the keys (vmap itself is tested in test_scan_vmap_*): the measured
    # rates below were taken this way.
    context = Context(background=bg)
    run = jax.jit(
        lambda ks, p, fr, b: jax.lax.map(lambda k: track_boxes(filt, p, k, fr, b, context), ks)
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 6)
    after = np.arange(T) >= 66
    rates = {}
    fade = params.depth._replace(velocity_fade=jnp.float32(0.05))
    variants = {
        "default": params,
        "fade 0.05": params._replace(depth=fade),
        "fade 0.05, no drift": params._replace(
            depth=fade, target=params.target._replace(drift_max=jnp.float32(0.0))
        ),
    }
    for name, p in variants.items():
        boxes, lost = (np.asarray(a) for a in run(keys, p, frames, jnp.asarray(gt[0])))
        rates[name] = np.mean(
            [
                summarise(boxes[i][after], gt[after], np.ones(after.sum(), bool), lost[i][after])[
                    "success_rate"
                ]
                for i in range(len(keys))
            ]
        )
    print(rates)
    assert rates["default"] >= 70.0, rates
    assert rates["fade 0.05"] >= 70.0, rates
    assert rates["fade 0.05, no drift"] < 50.0, rates


def _step_with_templates(depth_of_box: np.ndarray, age: float):
    """One grid-occlusion step on a red box (depth ``depth_of_box``, [h, w] mm) on grey,
    from a state whose depth templates all sit at ``Z_PERSON``, ``age`` frames old, with
    no depth velocity. Returns ``(new_state, info)``."""
    cfg = _config("grid-occlusion", detector_fraction=0.0, recovery_fraction=0.0)
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    params = params._replace(depth=params.depth._replace(velocity_rate=jnp.float32(0.0)))
    colour = np.full((H, W, 3), 100, np.uint8)
    depth = np.full((H, W), Z_BG, np.uint16)
    x, y, w, h = TEMPLATE_BOX
    colour[y : y + h, x : x + w] = (200, 40, 40)
    depth[y : y + h, x : x + w] = depth_of_box
    bg = median_background(
        jnp.asarray(np.full((1, H, W, 3), 100, np.uint8)),
        jnp.asarray(np.full((1, H, W), Z_BG, np.uint16)),
    )
    frame = Frame(jnp.asarray(colour), jnp.asarray(depth))
    box = jnp.asarray(TEMPLATE_BOX, jnp.float32)
    state = jax.jit(filt.init)(params, jax.random.PRNGKey(0), frame, box, Context(background=bg))
    c = cfg.n_cells
    state = state._replace(
        depth=state.depth._replace(
            depth=jnp.full((c,), float(Z_PERSON)),
            age=jnp.full((c,), age),
            velocity=jnp.float32(0.0),
        ),
        occlusion=state.occlusion._replace(vote=jnp.zeros((c,))),
    )
    return jax.jit(filt.step)(params, jax.random.PRNGKey(1), state, frame)


@pytest.mark.parametrize("age", [0.0, 15.0])
def test_stale_templates_learn_a_target_found_nearer(age):
    # The target reappears 1000 mm nearer than its templates, nothing at their depth.
    # Fresh templates (age 0): that is more than the occluder margin, an occluder; they
    # must not learn it. Stale ones (15 frames, the target may have walked 60 x 15 mm):
    # the gate and the occluder cut widen (search_drift) and they learn its depth; else
    # the target stays "hidden" behind its own pixels (occlusion_box, rgbd docstring).
    _, _, w, h = TEMPLATE_BOX
    found = Z_PERSON - 1000
    new, info = _step_with_templates(np.full((h, w), found, np.uint16), age)
    tmpl = np.asarray(new.depth.depth)
    if age == 0.0:
        assert np.all(np.abs(tmpl - Z_PERSON) < 120), tmpl
    else:
        # depth_rate 0.5: half way to the found depth in one step.
        assert not bool(info.lost)
        assert np.all(np.abs(tmpl - (Z_PERSON + found) / 2) < 120), tmpl


def test_depth_templates_ignore_nearer_occluder_pixels():
    # A cell 70 % covered by an occluder 550 mm nearer than the target: more than the
    # occluder margin (400 mm), but within the aged jump gate (400 + 60 x 5 mm). The
    # cell's median is the occluder's; the template must learn from the target's pixels
    # only (depth decides), so it stays at the target's depth. The target is seen at
    # its templates' depth, so the occluder cut does not widen with their age.
    _, _, w, h = TEMPLATE_BOX
    box_depth = np.full((h, w), Z_PERSON, np.uint16)
    box_depth[:, : int(0.7 * w)] = Z_PERSON - 550  # the left cells, and 40 % of the right ...
    new, _ = _step_with_templates(box_depth, 5.0)
    tmpl = np.asarray(new.depth.depth)
    # ... so that the two left cells (of a 2x2 grid) are all occluder where they are
    # near, and the rest is target: no template may move towards the occluder's depth.
    assert np.all(np.abs(tmpl - Z_PERSON) < 120), tmpl


def _solid_toy(n_frames: int, rng: np.random.Generator):
    """A person who fills his box (a shirt over trousers, 24 x 50 px) walks right at
    1.5 px/frame in front of a wall with two pillars at his depth, as real people seen
    from the front fill 60-90 % of theirs (the synthetic figure: 40 %)."""
    frames, gts = [], []
    for t in range(n_frames):
        colour, depth, _ = _toy(t, rng, person=False, occluder=False)
        x, y = int(round(30 + 1.5 * t)), 40
        colour[y : y + 28, x : x + 24] = (200, 40, 40)
        colour[y + 28 : y + 50, x : x + 24] = (40, 50, 150)
        depth[y : y + 50, x : x + 24] = Z_PERSON
        for px in (5, 140):  # pillars at the person's depth, another colour
            colour[20:110, px : px + 12] = (150, 150, 60)
            depth[20:110, px : px + 12] = Z_PERSON
        frames.append((colour, depth))
        gts.append((x, y, 24, 50))
    colour = np.stack([f[0] for f in frames])
    depth = np.stack([f[1] for f in frames])
    return Frame(jnp.asarray(colour), jnp.asarray(depth)), np.asarray(gts, np.float32)


def test_fill_adaptation_keeps_the_box_on_a_person_who_fills_it(toy):
    """Stated thresholds: with the Beta means moved to the initial box's fill (default),
    the tracked box's mean width over frames 10-40 stays within 25 % of the person's;
    with the fitted synthetic means (fill_adapt = 0) it is more than 20 % too wide
    (measured: 24.4 and 32.2 px)."""
    _, _, bg = toy  # the empty toy room
    frames, gt = _solid_toy(41, np.random.default_rng(7))
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)
    context = Context(background=bg)
    run = jax.jit(
        lambda p: track(filt, p, jax.random.PRNGKey(0), frames, gt[0], context)[1].estimate
    )
    width = {}
    for gain in (1.0, 0.0):
        est = np.asarray(
            run(params._replace(beta=params.beta._replace(fill_adapt=jnp.float32(gain))))
        )
        width[gain] = float(np.mean(est[9:, 2]))
    assert abs(width[1.0] / 24 - 1) <= 0.25, width
    assert width[0.0] / 24 > 1.2, width


def test_size_velocity_decay_stops_an_inherited_shrinking_drift(toy):
    """Every particle starts with the box shrinking 1 px/frame (4 %/frame, as a cloud
    that collapsed on a turning walker's narrowing silhouette) on a person of constant
    width. Stated thresholds, on the estimate's mean width over the last 5 of 40 frames:
    with the default decay at least 70 % of the person's; without it (the plain AR
    model's velocity random walk) at most 50 % (measured: 26 and 8 px of 24)."""
    _, _, bg = toy
    frames, gt = _solid_toy(41, np.random.default_rng(3))
    cfg = _config("grid-occlusion")
    filt = build_rgbd_filter(cfg)
    params = default_rgbd_params(cfg)

    def init_shrinking(*args):
        state = filt.init(*args)
        p = state.cloud.particles
        return state._replace(
            cloud=state.cloud._replace(particles=p.at[:, 6].set(-1.0).at[:, 7].set(-2.0))
        )

    shrinking = Filter(init=init_shrinking, step=filt.step)
    context = Context(background=bg)
    run = jax.jit(
        lambda p: track(shrinking, p, jax.random.PRNGKey(0), frames, gt[0], context)[1].estimate
    )

    default = float(params.motion.size_velocity_decay)
    width = {}
    for decay in (default, 1.0):
        motion = params.motion._replace(size_velocity_decay=jnp.float32(decay))
        est = np.asarray(run(params._replace(motion=motion)))
        width[decay] = float(np.mean(est[-5:, 2]))
    assert width[default] >= 0.7 * 24, width
    assert width[1.0] <= 0.5 * 24, width
