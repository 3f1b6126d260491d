"""Depth pre-processing kernels against NumPy loops and closed forms, under jit and vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import depth as dk
from cpf_jax.kernels import graph as gk
from cpf_jax.types import KINECT_V2_DEPTH, Intrinsics


def fill_holes_loop(z: np.ndarray, region: np.ndarray) -> np.ndarray:
    h, w = z.shape
    out = np.where(region, z, 0.0).astype(np.float64)
    for r in range(h):
        for c in range(w):
            if not region[r, c] or z[r, c] > 0:
                continue
            vals = [
                z[r + dr, c + dc]
                for dr in (-1, 0, 1)
                for dc in (-1, 0, 1)
                if (dr or dc)
                and 0 <= r + dr < h
                and 0 <= c + dc < w
                and region[r + dr, c + dc]
                and z[r + dr, c + dc] > 0
            ]
            out[r, c] = np.median(vals) if vals else 0.0
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_fill_holes_matches_loop(seed):
    rng = np.random.default_rng(seed)
    z = rng.integers(500, 4000, (23, 31)).astype(np.float32)
    z[rng.random(z.shape) < 0.35] = 0  # many holes: every neighbour count 0..8 occurs
    z[5:9, 5:9] = 0  # a hole with no valid neighbour in its middle
    region = np.ones(z.shape, bool)
    region[:, 25:] = rng.random((23, 6)) > 0.3
    got = np.asarray(jax.jit(dk.fill_holes)(z, region))
    np.testing.assert_allclose(got, fill_holes_loop(z, region), rtol=0, atol=1e-3)
    assert got[6, 6] == 0  # one pass, as in the thesis
    everywhere = fill_holes_loop(z, np.ones_like(region))
    np.testing.assert_allclose(np.asarray(dk.fill_holes(z)), everywhere, atol=1e-3)


def test_fill_holes_vmap():
    rng = np.random.default_rng(2)
    z = rng.integers(500, 4000, (3, 12, 14)).astype(np.float32)
    z[rng.random(z.shape) < 0.3] = 0
    region = np.ones(z.shape, bool)
    got = np.asarray(jax.vmap(dk.fill_holes)(z, region))
    for b in range(3):
        np.testing.assert_allclose(got[b], fill_holes_loop(z[b], region[b]), atol=1e-3)


def test_window_exact_crop_and_resampling():
    rng = np.random.default_rng(0)
    frame = rng.integers(1, 5000, (424, 512)).astype(np.uint16)
    box = jnp.array([100.0, 50.0, 60.0, 150.0])  # fits a 256 x 192 window with margin 0.1
    d, win, rows, cols, roi = dk.crop_window(frame, box, (256, 192), margin=0.1)
    assert float(win.scale) == 1.0
    x0, y0 = (int(v) for v in np.asarray(win.origin))
    assert np.array_equal(np.asarray(rows), np.arange(y0, y0 + 256))
    assert np.array_equal(np.asarray(cols), np.arange(x0, x0 + 192))
    d, roi = np.asarray(d), np.asarray(roi)
    inside = roi & True
    sub = frame[np.clip(np.asarray(rows), 0, 423)][:, np.clip(np.asarray(cols), 0, 511)]
    assert np.array_equal(d[inside], sub[inside].astype(np.float32))
    assert np.all(d[~roi] == 0)
    # the ROI is the box enlarged by 10 % on every side (pixel centres inside it)
    yc = y0 + np.arange(256) + 0.5
    xc = x0 + np.arange(192) + 0.5
    want = ((yc >= 35) & (yc < 215))[:, None] & ((xc >= 94) & (xc < 166))[None, :]
    want &= ((np.asarray(rows) >= 0) & (np.asarray(rows) < 424))[:, None]
    assert np.array_equal(roi, want)
    # a box too large for the window is resampled with a common scale, nearest neighbour
    big = jnp.array([50.0, 10.0, 200.0, 400.0])
    d2, win2, rows2, cols2, roi2 = dk.crop_window(frame, big, (256, 192), margin=0.0)
    s = float(win2.scale)
    assert s == pytest.approx(400 / 256)
    o = np.asarray(win2.origin)
    want_rows = np.floor(o[1] + (np.arange(256) + 0.5) * s).astype(int)
    assert np.array_equal(np.asarray(rows2), want_rows)
    ok = np.asarray(roi2)
    r2 = np.clip(np.asarray(rows2), 0, 423)
    c2 = np.clip(np.asarray(cols2), 0, 511)
    assert np.array_equal(np.asarray(d2)[ok], frame[r2][:, c2][ok].astype(np.float32))
    # frame <-> window coordinates round trip
    xy = jnp.array([[123.4, 200.7], [60.0, 12.5]])
    back = dk.window_to_frame(win2, dk.frame_to_window(win2, xy))
    np.testing.assert_allclose(back, xy, atol=1e-4)


def test_back_project_and_project_round_trip():
    rows = jnp.arange(100, 110)
    cols = jnp.arange(300, 312)
    z = jnp.full((10, 12), 2500.0).at[3, 4].set(1234.0)
    p = np.asarray(dk.back_project(z, rows, cols, KINECT_V2_DEPTH))
    fx, fy, cx, cy = KINECT_V2_DEPTH
    assert p[3, 4, 0] == pytest.approx(1234.0 * (304 - cx) / fx)
    assert p[3, 4, 1] == pytest.approx(1234.0 * (103 - cy) / fy)
    uv = np.asarray(dk.project(p, KINECT_V2_DEPTH))
    uu, vv = np.meshgrid(np.arange(300, 312), np.arange(100, 110))
    np.testing.assert_allclose(uv[..., 0], uu, atol=1e-3)
    np.testing.assert_allclose(uv[..., 1], vv, atol=1e-3)
    other = Intrinsics(567.9, 568.9, 311.1, 241.6)
    q = np.asarray(dk.back_project(z, rows, cols, other))
    assert q[0, 0, 0] == pytest.approx(2500.0 * (300 - 311.1) / 567.9, rel=1e-5)


def _plane_points(h, w, normal, d0=2500.0, noise=0.0, seed=0):
    """Points of the plane n . X = -d0 seen by the Kinect, on an ``[h, w]`` window."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    fx, fy, cx, cy = KINECT_V2_DEPTH
    v, u = np.mgrid[200 : 200 + h, 250 : 250 + w].astype(np.float64)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    z = -d0 / (ray @ n)  # Z along the ray such that n . (Z ray) = -d0
    z = z + np.random.default_rng(seed).normal(0, noise, z.shape)
    return (z[..., None] * ray).astype(np.float32), n


def normals_loop(p: np.ndarray, w: np.ndarray) -> np.ndarray:
    """MWA normals written out per pixel (same faces as the kernel)."""
    h, wd = p.shape[:2]
    ring = dk.RING
    fwd = {d: np.isfinite(w[k]) for k, d in enumerate(gk.FORWARD)}

    def edge(r, c, dr, dc):
        r2, c2 = r + dr, c + dc
        if not (0 <= r2 < h and 0 <= c2 < wd):
            return False
        if (dr, dc) in fwd:
            return bool(fwd[(dr, dc)][r, c])
        return bool(fwd[(-dr, -dc)][r2, c2])

    out = np.zeros((h, wd, 3))
    for r in range(h):
        for c in range(wd):
            s = [edge(r, c, dr, dc) for dr, dc in ring]
            faces = [(k, (k + 1) % 8) for k in range(8) if s[k] and s[(k + 1) % 8]]
            faces += [
                (k, k + 2 if k < 6 else 0)
                for k in (0, 2, 4, 6)
                if s[k] and s[(k + 2) % 8] and not s[k + 1]
            ]
            acc = np.zeros(3)
            for a, b in faces:
                va = p[r + ring[a][0], c + ring[a][1]].astype(np.float64) - p[r, c]
                vb = p[r + ring[b][0], c + ring[b][1]].astype(np.float64) - p[r, c]
                fn = np.cross(va, vb)
                if np.linalg.norm(fn) == 0:
                    continue
                fn /= np.linalg.norm(fn)
                if fn @ p[r, c] > 0:
                    fn = -fn
                ang = np.arccos(np.clip(va @ vb / np.linalg.norm(va) / np.linalg.norm(vb), -1, 1))
                acc += ang * fn
            out[r, c] = acc / np.linalg.norm(acc) if np.linalg.norm(acc) > 0 else np.nan
    return out


def test_vertex_normals_plane_and_loop():
    p, n = _plane_points(20, 24, [0.3, -0.2, -1.0])
    w = gk.surface_graph(p, np.ones((20, 24), bool), 30.0)
    nrm, ok = jax.jit(dk.vertex_normals)(p, w)
    nrm, ok = np.asarray(nrm), np.asarray(ok)
    assert ok.all()
    np.testing.assert_allclose(nrm, np.broadcast_to(n, nrm.shape), atol=2e-3)  # towards the sensor
    # a noisy curved surface, with holes, against the per-pixel loop
    p2, _ = _plane_points(16, 18, [0.1, 0.0, -1.0], noise=4.0, seed=3)
    mask = np.random.default_rng(4).random((16, 18)) > 0.15
    w2 = gk.surface_graph(p2, mask, 12.0)  # drops some diagonals: right-angle faces occur
    nrm2, ok2 = jax.jit(dk.vertex_normals)(p2, w2)
    ref = normals_loop(p2, np.asarray(w2))
    has = np.isfinite(ref[..., 0])
    assert np.array_equal(np.asarray(ok2), has)
    np.testing.assert_allclose(np.asarray(nrm2)[has], ref[has], atol=1e-4)
    # pixels without faces face the sensor
    far = ~has & mask
    if far.any():
        towards = -p2[far] / np.linalg.norm(p2[far], axis=-1, keepdims=True)
        np.testing.assert_allclose(np.asarray(nrm2)[far], towards, atol=1e-5)


def test_vertex_normals_smoothing_and_vmap():
    p, n = _plane_points(30, 30, [0.0, 0.4, -1.0], noise=3.0, seed=1)
    w = gk.surface_graph(p, np.ones((30, 30), bool), 40.0)
    normals = jax.jit(dk.vertex_normals, static_argnums=2)
    raw, _ = normals(p, w, 0)
    smooth, _ = normals(p, w, 3)
    err_raw = np.degrees(np.arccos(np.clip(np.asarray(raw)[5:-5, 5:-5] @ n, -1, 1))).mean()
    err_s = np.degrees(np.arccos(np.clip(np.asarray(smooth)[5:-5, 5:-5] @ n, -1, 1))).mean()
    assert err_s < 0.5 * err_raw
    both = jax.jit(jax.vmap(dk.vertex_normals))(jnp.stack([p, p[::-1]]), jnp.stack([w, w]))
    np.testing.assert_allclose(np.asarray(both[0][0]), np.asarray(raw), atol=1e-6)


def _silhouette(h=120, w=60, neck=(30, 34), head_w=16, neck_w=6, body_w=40):
    m = np.zeros((h, w), bool)
    c = w // 2
    for r in range(10, h - 5):
        if r < neck[0]:  # head: a disc-like profile, widest in the middle
            half = int(head_w / 2 * np.sqrt(max(0.0, 1 - ((r - 20) / 11) ** 2))) + 1
        elif r < neck[1]:
            half = neck_w // 2
        else:
            half = body_w // 2
        m[r, c - half : c + half] = True
    return m


def test_silhouette_widths_and_head_neck_split():
    m = _silhouette()
    widths = np.asarray(dk.silhouette_widths(m))
    ref = [np.ptp(np.nonzero(row)[0]) + 1 if row.any() else 0 for row in m]
    assert np.array_equal(widths, ref)
    split = jax.jit(dk.head_neck_split)(m)
    assert 30 <= int(split.neck_row) < 34  # inside the neck, not the crown of the head
    assert int(split.top) == 10
    head = np.asarray(split.head)
    assert head.sum() == m[: int(split.neck_row)].sum()
    cr, cc = np.asarray(split.head_centre)
    assert abs(cr - np.nonzero(head)[0].mean()) < 1e-3 and abs(cc - 29.5) < 1.0
    # batched, and an empty mask
    out = jax.vmap(dk.head_neck_split)(np.stack([m, np.zeros_like(m)]))
    assert int(out.neck_row[0]) == int(split.neck_row) and int(out.neck_row[1]) == -1
    assert not np.asarray(out.head[1]).any()


def test_nearest_true_brute_force():
    rng = np.random.default_rng(7)
    m = rng.random((30, 40)) > 0.97
    q = rng.uniform(-5, 45, (25, 2)).astype(np.float32)
    pix, found = dk.nearest_true(m, q)
    rr, cc = np.nonzero(m)
    for k in range(25):
        d2 = (rr - q[k, 0]) ** 2 + (cc - q[k, 1]) ** 2
        got = (pix[k, 0] - q[k, 0]) ** 2 + (pix[k, 1] - q[k, 1]) ** 2
        assert m[pix[k, 0], pix[k, 1]] and got == pytest.approx(d2.min(), abs=1e-3)
    assert np.asarray(found).all()
    _, f2 = dk.nearest_true(np.zeros((5, 5), bool), q[:3])
    assert not np.asarray(f2).any()


def test_erode_matches_loop():
    rng = np.random.default_rng(8)
    m = rng.random((15, 17)) > 0.2
    got = np.asarray(dk.erode(m))
    for r in range(15):
        for c in range(17):
            win = [
                m[r + a, c + b] if 0 <= r + a < 15 and 0 <= c + b < 17 else False
                for a in (-1, 0, 1)
                for b in (-1, 0, 1)
            ]
            assert got[r, c] == all(win)


def test_foreground_mask():
    z = np.array([[1000, 2900, 0, 1500], [3000, 2000, 2500, 0]], np.float32)
    bg = np.array([[3000, 3000, 3000, 0], [3000, 3000, 2560, 0]], np.float32)
    fg = np.asarray(dk.foreground_mask(z, bg, 100.0, 0.03))
    assert fg.tolist() == [[True, False, False, True], [False, True, False, False]]
