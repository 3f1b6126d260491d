"""The batched point filter on a small rendered figure with known body points."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import FIGURE_SEGMENTS, figure_joints

from cpf_jax.filter import Context, track
from cpf_jax.kernels import depth as dk
from cpf_jax.points import (
    PointConfig,
    PointFrame,
    body_model,
    build_point_filter,
    default_point_params,
)
from cpf_jax.points import body as pb
from cpf_jax.points import filter as pf
from cpf_jax.types import Intrinsics

H, W = 120, 128
INTR = Intrinsics(365.0, 365.0, 63.5, 59.5)
K = 0.3  # figure size relative to an adult


def _joints(t: int):
    """Figure joints (mm, camera frame) at frame t: walks right, swings its left arm."""
    x0 = -150.0 + 9.0 * t
    z0 = 2000.0
    arm = 0.35 + 0.25 * np.sin(t / 3.0)
    j = figure_joints(arm)
    return {n: np.array([x0 + K * x, K * y, z0]) for n, (x, y) in j.items()}


def render(t: int, seed: int = 0):
    """Depth frame ``[H, W] uint16`` of the figure in front of a wall, its tight box and joints."""
    rng = np.random.default_rng(seed + t)
    j = _joints(t)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    fx, fy, cx, cy = INTR
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    segs = FIGURE_SEGMENTS
    tt = np.full((H, W), np.inf)
    for a, b, r in segs:
        pa, pb, r = j[a], j[b], r * K
        for s in np.linspace(0, 1, max(2, int(np.linalg.norm(pb - pa) / (0.25 * r)))):
            c = pa + s * (pb - pa)
            bb = d @ c
            disc = bb * bb - (c @ c - r * r)
            tt = np.minimum(tt, np.where(disc > 0, bb - np.sqrt(np.maximum(disc, 0)), np.inf))
    person = np.isfinite(tt)
    z = np.where(person, tt * d[..., 2], 3000.0) + rng.normal(0, 1.0, (H, W))
    z[rng.random((H, W)) < 0.02] = 0
    rr, cc = np.nonzero(person)
    box = np.array([cc.min(), rr.min(), np.ptp(cc) + 1, np.ptp(rr) + 1], np.float32)
    # joint projections in the box convention (pixel centre = index + 0.5)
    uv = {n: np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy]) + 0.5 for n, p in j.items()}
    return np.round(z).astype(np.uint16), box, person, uv, j


T = 14


@pytest.fixture(scope="module")
def sequence():
    frames = [render(t) for t in range(T)]
    inputs = PointFrame(
        jnp.asarray(np.stack([f[0] for f in frames])), jnp.asarray(np.stack([f[1] for f in frames]))
    )
    return frames, inputs


BASE = PointConfig(
    n_particles=48,
    window=(112, 64),
    intrinsics=INTR,
    patch_radius=16,
    spin_batch=48,
    threshold_depth_mm=None,
    floor_max_tilt_deg=None,
    normal_smoothing=1,
    seg_max_dz_mm=20.0,
    surface_max_dist_mm=30.0,
)


def _start(frames):
    # the left hand, slightly inside the hand, and the head
    return jnp.asarray(np.stack([frames[0][3]["lh"], frames[0][3]["head"]]), jnp.float32)


def test_config_validation():
    with pytest.raises(ValueError):
        PointConfig(weighting="colour")
    with pytest.raises(ValueError):
        PointConfig(references=("knee",))
    with pytest.raises(ValueError):
        PointConfig(n_particles=0)
    with pytest.raises(ValueError, match="visibility"):
        PointConfig(visibility=True)  # the modes are named: "off", "report", "particles"


def test_init_needs_the_points_in_its_context(sequence):
    frames, inputs = sequence
    filt = build_point_filter(BASE)
    first = jax.tree_util.tree_map(lambda x: x[0], inputs)
    for context in (None, Context(), Context(background=None)):
        with pytest.raises(ValueError, match="points"):
            filt.init(default_point_params(), jax.random.PRNGKey(0), first, first.box, context)


def test_body_model_segments_the_figure(sequence):
    frames, inputs = sequence
    bm = jax.jit(lambda d, b: body_model(BASE, d, b))(inputs.depth[3], inputs.box[3])
    rows, cols = np.asarray(bm.rows), np.asarray(bm.cols)
    ok = (rows[:, None] >= 0) & (rows[:, None] < H) & (cols[None] >= 0) & (cols[None] < W)
    person = frames[3][2][np.clip(rows, 0, H - 1)][:, np.clip(cols, 0, W - 1)] & ok
    body = np.asarray(bm.body)
    # the largest component is the figure, not the (larger) wall around it
    assert (body & person).sum() / (body | person).sum() > 0.9
    assert np.isfinite(np.asarray(bm.geodesic)[0][body]).mean() > 0.9
    assert 3 <= float(bm.mesh_resolution) <= 10


# "combined" (the default) holds the geodesic term; "geodesic" alone is one more 20-s
# compile, run with -m slow.
@pytest.mark.parametrize(
    "weighting", [pytest.param("geodesic", marks=pytest.mark.slow), "combined"]
)
def test_tracks_a_swinging_hand(sequence, weighting):
    frames, inputs = sequence
    cfg = dataclasses.replace(BASE, weighting=weighting)
    filt = build_point_filter(cfg)
    params = default_point_params()
    run = jax.jit(lambda k, inp, p0: track(filt, params, k, inp, inp.box[0], Context(points=p0)))
    _, info = run(jax.random.PRNGKey(0), inputs, _start(frames))
    gt = np.stack([np.stack([f[3]["lh"], f[3]["head"]]) for f in frames[1:]])
    err = np.linalg.norm(np.asarray(info.mean) - gt, axis=-1)
    assert np.all(np.isfinite(err))
    assert np.median(err[:, 0]) < 3.0 and err[-1, 0] < 5.0  # hand, px
    assert np.median(err[:, 1]) < 3.0  # head
    # without the likelihood the cloud only follows the box: the hand is lost
    assert not np.asarray(info.recovered).any()
    gt3 = np.stack([np.stack([f[4]["lh"], f[4]["head"]]) for f in frames[1:]])
    err3 = np.linalg.norm(np.asarray(info.mean3d) - gt3, axis=-1)
    assert np.median(err3[:, 0]) < 40.0  # mm (the hand capsule's radius is 13.5 mm)


def test_step_weights_only_body_particles_and_compiles_once(sequence):
    frames, inputs = sequence
    traces = []
    cfg = dataclasses.replace(BASE, weighting="spin")
    filt = build_point_filter(cfg)
    params = default_point_params()

    def counted(*a):
        traces.append(1)
        return filt.step(*a)

    step = jax.jit(counted)
    first = jax.tree_util.tree_map(lambda x: x[0], inputs)
    state = jax.jit(filt.init)(
        params, jax.random.PRNGKey(1), first, first.box, Context(points=_start(frames))
    )
    bmf = jax.jit(lambda d, b: body_model(cfg, d, b))
    for t in range(1, 5):
        frame = jax.tree_util.tree_map(lambda x, t=t: x[t], inputs)
        state, info = step(params, jax.random.PRNGKey(t), state, frame)
        assert info.mean.shape == (2, 2) and info.mean3d.shape == (2, 3)
        assert np.all(np.asarray(info.ess) >= 1) and np.all(np.isfinite(np.asarray(info.mean3d)))
        # after resampling every particle descends from an on-body particle
        bm = bmf(frame.depth, frame.box)
        ji = np.asarray(dk.frame_to_window(bm.window, state.particles[..., :2]))
        r, c = np.floor(ji[..., 1]).astype(int), np.floor(ji[..., 0]).astype(int)
        assert np.asarray(bm.body)[np.clip(r, 0, 111), np.clip(c, 0, 63)].all()
        assert (r >= 0).all() and (r < 112).all() and (c >= 0).all() and (c < 64).all()
    assert len(traces) == 1


def test_recovery_when_every_particle_is_off_the_body(sequence):
    frames, inputs = sequence
    cfg = dataclasses.replace(BASE, weighting="geodesic", follow_box=False)
    filt = build_point_filter(cfg)
    params = default_point_params()
    first = jax.tree_util.tree_map(lambda x: x[0], inputs)
    state = jax.jit(filt.init)(
        params, jax.random.PRNGKey(0), first, first.box, Context(points=_start(frames))
    )
    # the figure jumps 40 px to the right: the hand's cloud lands on the wall
    z, box, person, uv, _ = render(0)
    shifted = np.full_like(z, 3000)
    shifted[:, 40:] = z[:, :-40]
    box = box + np.array([40, 0, 0, 0], np.float32)
    state, info = jax.jit(filt.step)(
        params, jax.random.PRNGKey(3), state, PointFrame(jnp.asarray(shifted), jnp.asarray(box))
    )
    rec = np.asarray(info.recovered)
    assert rec[0]
    bm = jax.jit(lambda d, b: body_model(cfg, d, b))(jnp.asarray(shifted), jnp.asarray(box))
    ji = np.asarray(dk.frame_to_window(bm.window, info.mean))
    r, c = int(ji[0, 1]), int(ji[0, 0])
    body = np.asarray(bm.body)
    # the recovered estimate sits on (or next to) the body, nearest to the old estimate
    assert body[max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3].any()


def test_vmap_over_keys(sequence):
    frames, inputs = sequence
    filt = build_point_filter(dataclasses.replace(BASE, weighting="geodesic"))
    params = default_point_params()
    short = jax.tree_util.tree_map(lambda x: x[:4], inputs)
    context = Context(points=_start(frames))
    run = jax.jit(jax.vmap(lambda k: track(filt, params, k, short, short.box[0], context)[1].mean))
    means = np.asarray(run(jax.random.split(jax.random.PRNGKey(0), 3)))
    assert means.shape == (3, 3, 2, 2)
    assert not np.allclose(means[0], means[1])  # different keys, different clouds
    gt = np.stack([np.stack([f[3]["lh"], f[3]["head"]]) for f in frames[1:4]])
    assert np.all(np.linalg.norm(means - gt, axis=-1) < 6.0)


def _weight_inputs(sequence, cfg):
    """A body model of frame 3, a state made on frame 0 and particles around its points."""
    frames, inputs = sequence
    params = default_point_params()
    first = jax.tree_util.tree_map(lambda x: x[0], inputs)
    state = jax.jit(build_point_filter(cfg).init)(
        params, jax.random.PRNGKey(0), first, first.box, Context(points=_start(frames))
    )
    bm = jax.jit(lambda d, b: body_model(cfg, d, b))(inputs.depth[3], inputs.box[3])
    xy = state.estimate[:, None, :] + 4.0 * jax.random.normal(jax.random.PRNGKey(5), (2, 48, 2))
    return params.weights, bm, state, xy


def test_weight_terms_match_their_formulas_under_jit_and_vmap(sequence):
    cfg = BASE
    wp, bm, state, xy = _weight_inputs(sequence, cfg)
    rc, inside = jax.jit(lambda b, x: pb.window_pixels(b, x, cfg.window))(bm, xy)
    r, c = np.asarray(rc[..., 0]), np.asarray(rc[..., 1])
    geo = np.asarray(bm.geodesic)[:, r, c]  # [R, P, N]
    ref = np.asarray(state.ref_geodesic).T[:, :, None]  # [R, P, 1]
    dev = ((geo - ref) / float(wp.geo_sigma)) ** 2
    want_geo = np.where(np.isfinite(geo).all(0), -0.5 * dev.sum(0), -np.inf)
    z_pred = jnp.asarray([1900.0, 0.0])  # the second point has no depth yet: no term
    dz = (np.asarray(bm.depth)[r, c] - np.asarray(z_pred)[:, None]) / float(wp.depth_sigma)
    want_depth = np.where(np.asarray(z_pred)[:, None] > 0, -0.5 * dz * dz, 0.0)
    geo_j = jax.jit(pf.geodesic_term)(wp, bm, state, rc)
    depth_j = jax.jit(pf.depth_term)(wp, bm, rc, z_pred)
    np.testing.assert_allclose(np.asarray(geo_j), want_geo, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(depth_j), want_depth, rtol=1e-5, atol=1e-4)
    assert 0.2 < np.isfinite(want_geo).mean() < 1  # reached and unreached particles both
    # vmapped over stacked particle sets, each set as alone
    rcs = jnp.stack([rc, rc[:, ::-1]])
    geo_v = jax.vmap(pf.geodesic_term, in_axes=(None, None, None, 0))(wp, bm, state, rcs)
    np.testing.assert_allclose(np.asarray(geo_v[0]), want_geo, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(geo_v[1]), want_geo[:, ::-1], rtol=1e-5, atol=1e-4)
    # the weights are the sum of the terms on the body and -inf off it
    on = np.asarray(inside) & np.asarray(bm.body)[r, c]
    spin, _ = jax.jit(lambda b, s, q, o: pf.spin_term(cfg, wp, b, s, q, o))(bm, state, rc, on)
    hidden = jnp.zeros(xy.shape[:2], bool)
    lw, on_w, _ = jax.jit(lambda b, s, x, h, z: pf.point_weights(cfg, wp, b, s, x, h, z))(
        bm, state, xy, hidden, z_pred
    )
    # the spin term is relative to its median over the point's particles on the body
    spin = np.asarray(spin)
    level = np.nanmedian(np.where(on & np.isfinite(spin), spin, np.nan), axis=1)
    spin = spin - np.nan_to_num(level)[:, None]
    want = np.where(on, spin + want_geo + want_depth, -np.inf)
    want = np.where(np.isnan(want), -np.inf, want)
    np.testing.assert_array_equal(np.asarray(on_w), on)
    np.testing.assert_allclose(np.asarray(lw), want, rtol=1e-5, atol=1e-3)
    assert 0 < on.mean() < 1  # both branches of the mask are exercised


def test_resample_leaves_a_recovered_cloud_and_resamples_a_degenerate_one():
    cfg = dataclasses.replace(BASE, ess_threshold=0.5)
    n = cfg.n_particles
    particles = jnp.broadcast_to(jnp.arange(n, dtype=jnp.float32)[:, None], (2, n, 4))
    lw = jnp.full((2, n), -30.0).at[:, 7].set(0.0)  # one particle holds all the weight
    lw = jax.vmap(lambda w: w - jax.nn.logsumexp(w))(lw)
    recovered = jnp.array([True, False])
    out, new_lw, resampled = jax.jit(lambda k, w, p, r: pf.point_resample(cfg, k, w, p, r))(
        jax.random.PRNGKey(0), lw, particles, recovered
    )
    assert resampled.tolist() == [False, True]
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(particles[0]))
    np.testing.assert_array_equal(np.asarray(out[1]), 7.0)
    np.testing.assert_allclose(np.exp(np.asarray(new_lw[1])), 1.0 / n, rtol=1e-5)


def test_body_model_stages_each_do_their_part(sequence):
    _, inputs = sequence
    depth, box = inputs.depth[3], inputs.box[3]
    seg = jax.jit(lambda d, b: pb.segment_body(BASE, d, b))(depth, box)
    surface = jax.jit(lambda s: pb.body_surface_graph(BASE, s))(seg)
    ref, geo, _ = jax.jit(lambda s, f: pb.body_geodesics(BASE, s, f))(seg, surface)
    body = np.asarray(seg.body)
    # the figure (about 2 m away) and not the wall (3 m) behind it
    assert 0.1 < body.mean() < 0.6
    assert np.asarray(seg.depth)[body].max() < 2500
    # mean edge length: a pixel's pitch (z * scale / f) and more along the diagonals
    pitch = 2000.0 * float(seg.window.scale) / INTR.fx
    assert pitch <= float(surface.mesh_resolution) <= 1.6 * pitch
    assert not np.any(np.asarray(surface.spin_valid) & ~body)
    g = np.asarray(geo[0])
    r, c = np.asarray(ref[0])
    assert body[r, c] and g[r, c] == 0.0
    assert np.isfinite(g[body]).mean() > 0.9 and np.all(np.isinf(g[~body]))


def _border_median_reference(d, roi, valid, share):
    """The border ring as ``roi & ~erode(roi)`` over the whole window."""
    h = roi.shape[0]
    rows = np.nonzero(roi.any(axis=1))[0]
    r0, r1 = (rows[0], rows[-1]) if len(rows) else (0, h - 1)
    edge = roi & ~np.asarray(dk.erode(jnp.asarray(roi)))
    upper = (np.arange(h) < r0 + share * (r1 - r0))[:, None]
    vals = d[edge & upper & valid]
    return np.median(vals) if len(vals) else np.nan


def test_roi_border_median_is_the_median_of_the_eroded_ring_under_jit_and_vmap():
    rng = np.random.default_rng(0)
    h, w = 24, 20
    cases = []
    for r0, r1, c0, c1 in [(3, 17, 2, 15), (0, 23, 0, 19), (5, 5, 1, 18), (2, 20, 7, 7)]:
        roi = np.zeros((h, w), bool)
        roi[r0 : r1 + 1, c0 : c1 + 1] = True
        cases.append(roi)
    cases.append(np.zeros((h, w), bool))  # an empty ROI: no border, NaN
    d = rng.integers(500, 4000, (len(cases), h, w)).astype(np.float32)
    valid = rng.random((len(cases), h, w)) > 0.2
    f = jax.jit(lambda a, b, c: pb.roi_border_median(a, b, c, 0.6))
    batched = jax.jit(jax.vmap(lambda a, b, c: pb.roi_border_median(a, b, c, 0.6)))
    got_v = np.asarray(batched(jnp.asarray(d), jnp.asarray(np.stack(cases)), jnp.asarray(valid)))
    for k, roi in enumerate(cases):
        want = _border_median_reference(d[k], roi, valid[k], 0.6)
        got = float(f(jnp.asarray(d[k]), jnp.asarray(roi), jnp.asarray(valid[k])))
        np.testing.assert_equal(got, want)
        np.testing.assert_equal(got_v[k], want)
    # no border: the empty ROI, and the one-row ROI (its row is not above 60 % of it)
    assert np.isnan(got_v[[2, 4]]).all() and np.isfinite(got_v[[0, 1, 3]]).all()


def test_geodesic_edges_can_bridge_a_depth_jump_the_surface_graph_cuts():
    # A side-on trunk and, beside it, a near arm 150 mm in front: the surface graph's 15 mm
    # edges cut the arm off, so from the head it is unreachable; the geodesic graph with
    # edges up to 200 mm reaches it across the jump, no shorter than the jump itself.
    depth = np.full((H, W), 3000, np.uint16)
    depth[20:110, 40:70] = 2000  # trunk, the head at its top
    depth[50:90, 70:80] = 1850  # arm
    box = jnp.asarray([30.0, 10.0, 60.0, 105.0])
    cut = dataclasses.replace(BASE, min_component_fraction=0.05, floor_max_tilt_deg=None)
    bridged = dataclasses.replace(cut, geodesic_max_dist_mm=200.0)
    for config in (cut, bridged):
        seg = jax.jit(lambda d, b, c=config: pb.segment_body(c, d, b))(jnp.asarray(depth), box)
        surface = jax.jit(lambda s, c=config: pb.body_surface_graph(c, s))(seg)
        _, geo, _ = jax.jit(lambda s, f, c=config: pb.body_geodesics(c, s, f))(seg, surface)
        body, g = np.asarray(seg.body), np.asarray(geo[0])
        arm = body & (np.asarray(seg.depth) < 1900)
        trunk = body & ~arm
        assert arm.sum() > 20 and trunk.sum() > 100, (arm.sum(), trunk.sum())
        assert np.isfinite(g[trunk]).all()
        if config is cut:
            assert np.isinf(g[arm]).all()
        else:
            assert np.isfinite(g[arm]).all()
            # every path onto the arm crosses the 150 mm jump from the trunk's edge beside it
            a_col = np.nonzero(arm.any(0))[0][0]
            edge = trunk[:, a_col - 1] & arm[:, a_col]
            assert edge.any() and g[arm].min() >= g[edge, a_col - 1].min() + 140.0


HIDDEN = range(5, 9)  # frames in which a board in front hides the left hand


def _occluded(frames):
    """The sequence with a 41 x 41 px board 500 mm in front of the figure over its left hand
    and arm in the ``HIDDEN`` frames: the hand's ground truth is hidden there."""
    depth = np.stack([f[0] for f in frames])
    for t in HIDDEN:
        x, y = np.floor(frames[t][3]["lh"]).astype(int)
        depth[t, max(y - 20, 0) : y + 21, max(x - 20, 0) : x + 21] = 1500
    return PointFrame(jnp.asarray(depth), jnp.asarray(np.stack([f[1] for f in frames])))


def test_a_hidden_hand_is_reported_hidden_without_moving_its_estimate(sequence):
    """Ground truth: a board hides the hand in ``HIDDEN``. With ``visibility="report"`` the
    hand is reported hidden in at least two of those four frames and in none before the
    board comes, and every estimate is the one the filter without flags makes with the same
    key (the flag is a report, not part of the cloud); without flags nothing is reported."""
    frames, _ = sequence
    inputs = _occluded(frames)
    hidden_gt = np.isin(np.arange(1, T), list(HIDDEN))
    infos = {}
    for visibility in ("report", "off"):
        cfg = dataclasses.replace(BASE, weighting="geodesic", visibility=visibility)
        filt = build_point_filter(cfg)
        run = jax.jit(
            lambda k, inp, p0, f=filt: track(
                f, default_point_params(), k, inp, inp.box[0], Context(points=p0)
            )[1]
        )
        infos[visibility] = run(jax.random.PRNGKey(0), inputs, _start(frames))
    reported = np.asarray(infos["report"].hidden)[:, 0]
    assert reported[hidden_gt].sum() >= 2, reported
    assert not reported[: min(HIDDEN) - 1].any(), reported
    assert not np.asarray(infos["off"].hidden).any()
    np.testing.assert_array_equal(np.asarray(infos["report"].mean), np.asarray(infos["off"].mean))
    share = np.asarray(infos["report"].hidden_share)
    assert np.all((share >= 0) & (share <= 1))


def test_hidden_evidence_and_update_match_their_formulas_under_jit_and_vmap(sequence):
    """``hidden_evidence``: log of the cloud-weighted mean of ``exp(hidden_term)`` minus that
    of ``exp(visible log-weights)``; ``hidden_update``: the Markov prior then Bayes' rule."""
    cfg = BASE
    wp, bm, state, xy = _weight_inputs(sequence, cfg)
    motion = default_point_params().motion
    rc, inside = pb.window_pixels(bm, xy, cfg.window)
    z_pred = jnp.asarray([2100.0, 1900.0])
    prior_lw = jax.nn.log_softmax(jax.random.normal(jax.random.PRNGKey(3), (2, 48)), axis=1)
    lw_vis = np.asarray(jax.random.normal(jax.random.PRNGKey(4), (2, 48))) - 2.0
    lw_vis[0, :40] = -np.inf  # most of the first point's particles off the body
    lh = np.asarray(pf.hidden_term(wp, bm, rc, inside, z_pred))
    w = np.exp(np.asarray(prior_lw, np.float64))
    with np.errstate(divide="ignore"):
        want = np.log((w * np.exp(lh)).sum(1)) - np.log((w * np.exp(lw_vis)).sum(1))
    got = jax.jit(pf.hidden_evidence, static_argnums=0)(
        cfg, wp, bm, prior_lw, xy, jnp.asarray(lw_vis), z_pred
    )
    np.testing.assert_allclose(np.asarray(got), np.clip(want, -1e30, 1e30), rtol=1e-4, atol=1e-4)
    got_v = jax.vmap(pf.hidden_evidence, in_axes=(None, None, None, 0, 0, 0, None))(
        cfg, wp, bm, jnp.stack([prior_lw] * 2), jnp.stack([xy] * 2), jnp.stack([lw_vis] * 2), z_pred
    )
    np.testing.assert_allclose(np.asarray(got_v[1]), np.asarray(got), rtol=1e-6)
    prob, llr = np.array([0.0, 0.3, 0.9]), np.array([0.5, -1.0, 2.0])
    ph, ps = float(motion.p_hide), float(motion.p_show)
    prior = prob * (1 - ps) + (1 - prob) * ph
    post = prior * np.exp(llr) / (prior * np.exp(llr) + 1 - prior)
    got = jax.vmap(pf.hidden_update, in_axes=(None, 0, 0))(
        motion, jnp.asarray(prob)[:, None], jnp.asarray(llr)[:, None]
    )
    np.testing.assert_allclose(np.asarray(got)[:, 0], post, rtol=1e-5)


def test_hidden_term_and_reacquisition_match_their_references_under_jit_and_vmap(sequence):
    """``hidden_term``: the level where the surface is more than the margin in front of the
    predicted depth, ``-inf`` elsewhere; ``reacquire_logits`` against a loop over the window's
    pixels; ``point_reacquire`` draws only the particles that show again, each onto a pixel
    the logits allow, in proportion to their density."""
    cfg = BASE
    wp, bm, state, xy = _weight_inputs(sequence, cfg)
    params = default_point_params()
    rc, inside = pb.window_pixels(bm, xy, cfg.window)
    z_pred = jnp.asarray([2100.0, 1900.0])
    d = np.asarray(bm.depth)[np.asarray(rc[..., 0]), np.asarray(rc[..., 1])]
    front = (
        np.asarray(inside)
        & (d > 0)
        & (d < np.asarray(z_pred)[:, None] - float(wp.occlusion_margin))
    )
    want = np.where(front, float(wp.hidden_log_weight), -np.inf)
    got = jax.jit(pf.hidden_term)(wp, bm, rc, inside, z_pred)
    np.testing.assert_array_equal(np.asarray(got), want)
    assert 0 < front.mean() < 1
    got_v = jax.vmap(pf.hidden_term, in_axes=(None, None, 0, 0, None))(
        wp, bm, jnp.stack([rc, rc]), jnp.stack([inside, inside]), z_pred
    )
    np.testing.assert_array_equal(np.asarray(got_v[1]), want)

    prev = state.estimate
    logits = np.asarray(jax.jit(pf.reacquire_logits)(params, bm, state, prev))
    geo, valid = np.asarray(bm.geodesic), np.asarray(bm.spin_valid)
    o, s = np.asarray(bm.window.origin), float(bm.window.scale)
    ref = np.asarray(state.ref_geodesic)
    want = np.full(logits.shape, -np.inf)
    hw, ww = valid.shape
    for p in range(2):
        for r in range(hw):
            for c in range(ww):
                g = geo[:, r, c]
                if not valid[r, c] or not np.isfinite(g).all():
                    continue
                centre = o + s * (np.array([c, r]) + 0.5)
                dev = ((g - ref[p]) / float(params.weights.geo_sigma)) ** 2
                d2 = np.sum((centre - np.asarray(prev[p])) ** 2)
                spread = float(params.motion.reacquire_spread)
                want[p, r * ww + c] = -0.5 * dev.sum() - 0.5 * d2 / spread**2
    np.testing.assert_allclose(logits, want, rtol=1e-4, atol=1e-3)
    assert np.isfinite(want).mean() > 0.05

    n = 4000
    shown = jnp.zeros((2, n), bool).at[0, : n // 2].set(True)
    xy = jnp.zeros((2, n, 2))
    vel = jnp.ones((2, n, 2))
    reacq = jax.jit(pf.point_reacquire)
    new_xy, new_vel = (
        np.asarray(a) for a in reacq(params, jax.random.PRNGKey(1), bm, state, prev, xy, vel, shown)
    )
    np.testing.assert_array_equal(new_xy[0, n // 2 :], 0.0)
    np.testing.assert_array_equal(new_xy[1], 0.0)
    np.testing.assert_array_equal(new_vel[0, : n // 2], 0.0)
    np.testing.assert_array_equal(new_vel[0, n // 2 :], 1.0)
    ji = (new_xy[0, : n // 2] - o) / s
    flat = np.floor(ji[:, 1]).astype(int) * ww + np.floor(ji[:, 0]).astype(int)
    assert np.isfinite(want[0, flat]).all()
    # the drawn pixels follow the density: its most likely tenth of pixels gets its share
    prob = np.exp(want[0] - want[0].max())
    prob /= prob.sum()
    top = np.argsort(prob)[::-1][: max(1, np.isfinite(want[0]).sum() // 10)]
    assert abs(np.isin(flat, top).mean() - prob[top].sum()) < 0.05
    # vmapped over two keys, each as alone
    keys = jax.random.split(jax.random.PRNGKey(2), 2)
    both = jax.vmap(pf.point_reacquire, in_axes=(None, 0, None, None, None, None, None, None))(
        params, keys, bm, state, prev, xy, vel, shown
    )
    one = reacq(params, keys[1], bm, state, prev, xy, vel, shown)
    np.testing.assert_allclose(np.asarray(both[0][1]), np.asarray(one[0]), atol=1e-4)


def test_joined_components_keep_the_person_at_the_box_centre_not_the_one_beside():
    # A trunk at the window's centre, his arm 120 mm nearer beside it, and another person
    # 380 mm nearer at the side: with 160 mm joins the body is the trunk and the arm.
    d = np.full((20, 30), 3000.0, np.float32)
    d[2:18, 10:20] = 2000
    d[5:15, 20:23] = 1880
    d[2:18, 24:29] = 1500
    cfg = dataclasses.replace(BASE, min_component_fraction=0.05, joined_max_dz_mm=160.0)
    want = np.zeros(d.shape, bool)
    want[2:18, 10:20] = want[5:15, 20:23] = True
    ones = jnp.ones(d.shape, jnp.float32)
    got = jax.jit(lambda z, b: pb._joined_to_centre(cfg, z, b, ones))(jnp.asarray(d), d < 2500)
    np.testing.assert_array_equal(np.asarray(got), want)
    got_v = jax.vmap(lambda z, b: pb._joined_to_centre(cfg, z, b, ones))(
        jnp.stack([jnp.asarray(d)] * 2), jnp.stack([d < 2500] * 2)
    )
    np.testing.assert_array_equal(np.asarray(got_v[1]), want)
    with pytest.raises(ValueError, match="joined_max_dz_mm"):
        PointConfig(joined_max_dz_mm=0.0)


def test_anchor_term_is_the_box_relative_gaussian_under_jit_and_vmap():
    """``box_offsets``: offset from the box centre in box heights; ``anchor_term``: the
    Gaussian log-density (without its constant) of the offsets about each point's anchor,
    sigma across and down apart; a box twice as tall halves an offset's pixels' weight."""
    wp = default_point_params().weights._replace(
        anchor_sigma_x=jnp.asarray([0.2, 0.3]), anchor_sigma_y=jnp.float32(0.05)
    )
    box = jnp.asarray([40.0, 20.0, 50.0, 100.0])
    xy = 60.0 + 30.0 * jax.random.normal(jax.random.PRNGKey(0), (2, 16, 2))
    anchor = jnp.asarray([[0.0, 0.1], [-0.1, -0.3]])
    b = np.asarray(box, np.float64)
    off = (np.asarray(xy, np.float64) - (b[:2] + b[2:] / 2)) / b[3]
    np.testing.assert_allclose(np.asarray(jax.jit(pf.box_offsets)(box, xy)), off, rtol=1e-5)
    d = off - np.asarray(anchor)[:, None]
    sx = np.array([0.2, 0.3])[:, None]
    want = -0.5 * ((d[..., 0] / sx) ** 2 + (d[..., 1] / 0.05) ** 2)
    got = jax.jit(pf.anchor_term)(wp, box, anchor, xy)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-3)
    # vmapped over boxes: each box's own offsets
    boxes = jnp.stack([box, box.at[3].set(200.0)])
    got_v = jax.vmap(pf.anchor_term, in_axes=(None, 0, None, None))(wp, boxes, anchor, xy)
    np.testing.assert_allclose(np.asarray(got_v[0]), want, rtol=1e-4, atol=1e-3)
    assert not np.allclose(np.asarray(got_v[1]), want)
    # a particle at its point's anchor has the prior's maximum, 0
    at = (b[:2] + b[2:] / 2) + np.asarray(anchor) * b[3]
    top = pf.anchor_term(wp, box, anchor, jnp.asarray(at, jnp.float32)[:, None])
    np.testing.assert_allclose(np.asarray(top), 0.0, atol=1e-5)


def test_anchor_prior_keeps_the_start_offset_and_pulls_the_estimate_to_it(sequence):
    """``point_init`` stores each point's start offset in the box and ``step`` carries it;
    with ``anchor_prior`` and a narrow prior about an anchor moved down the box, the
    estimate moves down from the one without the prior (same key, same cloud)."""
    frames, inputs = sequence
    params = default_point_params()
    params = params._replace(
        weights=params.weights._replace(
            anchor_sigma_x=jnp.float32(0.01), anchor_sigma_y=jnp.float32(0.01)
        )
    )
    start, box0 = _start(frames), inputs.box[0]
    b = np.asarray(box0, np.float64)
    want = (np.asarray(start) - (b[:2] + b[2:] / 2)) / b[3]
    means = {}
    for prior in (False, True):
        filt = build_point_filter(dataclasses.replace(BASE, anchor_prior=prior))
        state = filt.init(
            params,
            jax.random.PRNGKey(0),
            PointFrame(inputs.depth[0], box0),
            box0,
            Context(points=start),
        )
        np.testing.assert_allclose(np.asarray(state.anchor), want, rtol=1e-5, atol=1e-6)
        state = state._replace(anchor=state.anchor + jnp.asarray([0.0, 0.1]))
        new, info = jax.jit(filt.step)(
            params, jax.random.PRNGKey(1), state, PointFrame(inputs.depth[1], inputs.box[1])
        )
        np.testing.assert_array_equal(np.asarray(new.anchor), np.asarray(state.anchor))
        means[prior] = np.asarray(info.mean)
    assert np.all(means[True][:, 1] > means[False][:, 1] + 0.3), means


def test_geodesic_reference_update_moves_visible_reached_points_under_jit_and_vmap(sequence):
    """``geodesic_reference_update``: ``ref + rate (g - ref)`` for a point reported visible
    whose estimate is on the body and reached, ``ref`` for a hidden one or one off the body
    (a plain loop over the points is the reference)."""
    cfg = BASE
    wp, bm, state, _ = _weight_inputs(sequence, cfg)
    wp = wp._replace(geo_rate=jnp.float32(0.25))
    body = np.argwhere(np.asarray(bm.body) & np.isfinite(np.asarray(bm.geodesic)).all(0))
    off = np.argwhere(~np.asarray(bm.body))
    rcs = np.stack([body[len(body) // 2], body[len(body) // 3], off[0]])  # [3, 2] (row, col)
    xy = pb.pixel_centre(bm, jnp.asarray(rcs))
    ref = jnp.asarray([[900.0], [1000.0], [1100.0]])
    visible = jnp.asarray([True, False, True])
    want = np.asarray(ref).copy()
    g = np.asarray(bm.geodesic)
    for i, (r, c) in enumerate(rcs):
        if bool(visible[i]) and bool(np.asarray(bm.body)[r, c]):
            want[i] += 0.25 * (g[:, r, c] - want[i])
    got = jax.jit(lambda b, r, x, v: pf.geodesic_reference_update(cfg, wp, b, r, x, v))(
        bm, ref, xy, visible
    )
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)
    assert want[0, 0] != 900.0 and want[1, 0] == 1000.0 and want[2, 0] == 1100.0
    got_v = jax.vmap(
        lambda r, v: pf.geodesic_reference_update(cfg, wp, bm, r, xy, v), in_axes=(0, 0)
    )(jnp.stack([ref, ref + 10.0]), jnp.stack([visible, ~visible]))
    np.testing.assert_allclose(np.asarray(got_v[0]), want, rtol=1e-5)
    assert float(got_v[1][0, 0]) == 910.0 and float(got_v[1][1, 0]) != 1010.0
