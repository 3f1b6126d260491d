"""Spin images against a plain NumPy loop over every point; similarity against NumPy formulas."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import depth as dk
from cpf_jax.kernels import graph as gk
from cpf_jax.kernels import spin as sk

FX = 365.0


def blob_surface(h=48, w=40, z0=1500.0, noise=1.0, seed=0):
    """Two bumps on a tilted plate (a small 'torso with an arm'), as window points and normals."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u - w / 2) * z0 / FX
    y = (v - h / 2) * z0 / FX
    z = z0 + 0.15 * y - 60 * np.exp(-((x - 20) ** 2 + (y + 15) ** 2) / 900.0)
    z = z - 35 * np.exp(-((x + 25) ** 2 + (y - 25) ** 2) / 300.0) + rng.normal(0, noise, (h, w))
    mask = ((u - w / 2) / (0.45 * w)) ** 2 + ((v - h / 2) / (0.48 * h)) ** 2 < 1
    p = np.stack([z * (u - w / 2) / FX, z * (v - h / 2) / FX, z], -1).astype(np.float32)
    wts = gk.surface_graph(p, mask, 15.0)
    nrm, ok = dk.vertex_normals(p, wts, smooth=1)
    return p, np.asarray(nrm), mask & np.asarray(ok), float(gk.mesh_resolution(wts))


def spin_loop(points, normals, valid, queries, bin_size, width=20, support_deg=60.0):
    """Plain loop: every valid point, eq. 4.4-4.5 with the thesis's in-image test."""
    pts = points[valid].astype(np.float64)
    nrm = normals[valid].astype(np.float64)
    cos_s = math.cos(math.radians(support_deg))
    out = np.zeros((len(queries), width, width))
    for k, (r, c) in enumerate(queries):
        if not valid[r, c]:
            continue
        p = points[r, c].astype(np.float64)
        n = normals[r, c].astype(np.float64)
        for x, nx in zip(pts, nrm, strict=True):
            d = x - p
            beta = d @ n
            alpha = math.sqrt(max(d @ d - beta * beta, 0.0))
            a = alpha / bin_size
            b = width / 2 - beta / bin_size
            if not (0 <= a < width - 1 and 0 <= b < width - 1) or nx @ n < cos_s:
                continue
            i, j = int(math.floor(b)), int(math.floor(a))
            fb, fa = b - i, a - j
            out[k, i, j] += (1 - fb) * (1 - fa)
            out[k, i, j + 1] += (1 - fb) * fa
            out[k, i + 1, j] += fb * (1 - fa)
            out[k, i + 1, j + 1] += fb * fa
    return out


@pytest.fixture(scope="module")
def surface():
    return blob_surface()


def test_spin_coordinates_closed_form():
    p = jnp.array([0.0, 0.0, 1000.0])
    n = jnp.array([0.0, 0.0, -1.0])
    x = jnp.array([[3.0, 4.0, 990.0], [0.0, 0.0, 1000.0], [0.0, 0.0, 1010.0]])
    alpha, beta = sk.spin_coordinates(x, p, n)
    np.testing.assert_allclose(alpha, [5.0, 0.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(beta, [10.0, 0.0, -10.0], atol=1e-4)


def test_spin_images_equal_loop_over_all_points(surface):
    p, n, valid, mres = surface
    rng = np.random.default_rng(0)
    vr, vc = np.nonzero(valid)
    pick = rng.choice(len(vr), 12, replace=False)
    q = np.stack([vr[pick], vc[pick]], -1)
    q = np.concatenate([q, [[0, 0]]])  # an invalid query pixel: empty image
    b = 1.5 * mres
    f = jax.jit(lambda qq, bb: sk.spin_images(p, n, valid, qq, bb, patch_radius=40, batch_size=5))
    imgs, complete = f(q, b)
    ref = spin_loop(p, n, valid, q, b)
    assert np.asarray(complete).all()  # a 81 x 81 patch covers the 48 x 40 window
    np.testing.assert_allclose(np.asarray(imgs), ref, atol=2e-3, rtol=1e-4)
    assert ref[:-1].sum(axis=(1, 2)).min() > 50  # the images are not trivially empty
    assert np.all(np.asarray(imgs)[-1] == 0)
    # the batch size does not change the result
    imgs2, _ = sk.spin_images(p, n, valid, q, b, patch_radius=40, batch_size=13)
    np.testing.assert_allclose(np.asarray(imgs2), np.asarray(imgs), atol=1e-5)


def test_spin_images_support_angle_and_batched_shapes(surface):
    p, n, valid, mres = surface
    q = np.array([[[20, 20], [30, 12]], [[10, 25], [35, 30]]])
    imgs, _ = sk.spin_images(p, n, valid, q, mres, support_angle_deg=20.0, patch_radius=40)
    assert imgs.shape == (2, 2, 20, 20)
    ref = spin_loop(p, n, valid, q.reshape(-1, 2), mres, support_deg=20.0)
    np.testing.assert_allclose(np.asarray(imgs).reshape(4, 20, 20), ref, atol=2e-3, rtol=1e-4)
    wide, _ = sk.spin_images(p, n, valid, q, mres, support_angle_deg=90.0, patch_radius=40)
    assert float(wide.sum()) > float(imgs.sum())


def test_spin_images_vmap_over_surfaces(surface):
    p, n, valid, mres = surface
    p2, n2, valid2, mres2 = blob_surface(seed=1, z0=1400.0)
    q = np.array([[24, 20], [15, 25]])
    f = jax.vmap(lambda a, b, c, d: sk.spin_images(a, b, c, q, d, patch_radius=40)[0])
    out = np.asarray(
        f(np.stack([p, p2]), np.stack([n, n2]), np.stack([valid, valid2]), jnp.array([mres, mres2]))
    )
    np.testing.assert_allclose(out[0], spin_loop(p, n, valid, q, mres), atol=2e-3, rtol=1e-4)
    np.testing.assert_allclose(out[1], spin_loop(p2, n2, valid2, q, mres2), atol=2e-3, rtol=1e-4)


def test_only_needed_queries_are_computed(surface):
    # Queries not needed get an empty image and complete False; under jit the needed ones
    # equal, bit for bit, the images computed without the mask, and under vmap the loop.
    p, n, valid, mres = surface
    q = np.array([[24, 20], [15, 25], [30, 12], [10, 18], [30, 12], [5, 5]])
    needs = np.array([[1, 0, 1, 0, 1, 0], [0, 0, 0, 1, 0, 0]], bool)

    def spin(m):
        return sk.spin_images(p, n, valid, q, mres, patch_radius=40, batch_size=2, needed=m)

    full, full_complete = (np.asarray(x) for x in jax.jit(lambda: spin(None))())
    ref = spin_loop(p, n, valid, q, mres)
    for batch in (
        [jax.jit(spin)(m) for m in needs],
        list(zip(*jax.jit(jax.vmap(spin))(needs), strict=True)),
    ):
        for (got, ok), need in zip(batch, needs, strict=True):
            got, ok = np.asarray(got), np.asarray(ok)
            np.testing.assert_allclose(got[need], ref[need], atol=2e-3, rtol=1e-4)
            assert np.all(got[~need] == 0)
            np.testing.assert_array_equal(ok, full_complete & need)
    for m in needs:
        np.testing.assert_array_equal(np.asarray(jax.jit(spin)(m)[0])[m], full[m])
    assert full[3].sum() > 0
    none, _ = spin(np.zeros(6, bool))  # nothing needed: every image empty
    assert np.all(np.asarray(none) == 0)


def test_shared_query_pixels_are_computed_once_and_read_by_each_query(surface):
    # Particles share pixels: each distinct pixel's image is computed once and every query
    # on it reads that image. Against the loop, with repeats in any order and a clipped
    # out-of-window query, under jit and vmap (two clouds with different repeats).
    p, n, valid, mres = surface
    distinct = np.array([[24, 20], [15, 25], [30, 12], [10, 18]])
    picks = [np.array([2, 0, 2, 2, 1, 0, 3, 2, 0]), np.array([1, 1, 1, 1, 1, 1, 1, 1, 3])]
    clouds = np.stack([distinct[i] for i in picks])
    clouds[0, -1] = [60, 50]  # outside the 48 x 40 window: clipped to (47, 39)
    f = jax.jit(
        jax.vmap(lambda qq: sk.spin_images(p, n, valid, qq, mres, patch_radius=40, batch_size=2))
    )
    imgs, complete = f(clouds)
    for got, qq in zip(np.asarray(imgs), clouds, strict=True):
        clipped = np.minimum(qq, [47, 39])
        ref = spin_loop(p, n, valid, clipped, mres)
        np.testing.assert_allclose(got, ref, atol=2e-3, rtol=1e-4)
        for i, j in zip(*np.nonzero((clipped[:, None] == clipped[None]).all(-1)), strict=True):
            np.testing.assert_array_equal(got[i], got[j])
    assert np.asarray(complete).all()
    assert float(np.asarray(imgs)[1].sum()) > 0


def test_small_patch_is_flagged_incomplete(surface):
    p, n, valid, mres = surface
    q = np.array([[24, 20], [20, 15]])
    imgs, complete = sk.spin_images(p, n, valid, q, 2.0 * mres, patch_radius=6)
    ref = spin_loop(p, n, valid, q, 2.0 * mres)
    assert not np.asarray(complete).any()
    assert np.abs(np.asarray(imgs) - ref).max() > 1.0
    # where the flag says complete, the patch result is the full one
    imgs, complete = sk.spin_images(p, n, valid, q, 0.3 * mres, patch_radius=12)
    assert np.asarray(complete).all()
    np.testing.assert_allclose(np.asarray(imgs), spin_loop(p, n, valid, q, 0.3 * mres), atol=2e-3)


def test_support_patch_radius_holds_the_whole_support(surface):
    p, n, valid, mres = surface
    bin_size = 0.5 * mres
    z_near = float(p[..., 2][valid].min())
    r = sk.support_patch_radius(bin_size, 20, z_near, FX)
    q = np.array([[24, 20], [20, 15], [30, 25]])
    imgs, complete = sk.spin_images(p, n, valid, q, bin_size, patch_radius=r)
    assert np.asarray(complete).all()
    np.testing.assert_allclose(np.asarray(imgs), spin_loop(p, n, valid, q, bin_size), atol=2e-3)
    # A third of it cuts the support short (the bound is not vacuous).
    _, complete = sk.spin_images(p, n, valid, q, bin_size, patch_radius=r // 3)
    assert not np.asarray(complete).any()


def test_correlation_and_similarity_match_numpy():
    rng = np.random.default_rng(3)
    a = np.where(rng.random((4, 20, 20)) > 0.5, rng.uniform(0, 5, (4, 20, 20)), 0)
    a = a.astype(np.float32)
    b = np.where(rng.random((4, 20, 20)) > 0.5, a + rng.normal(0, 1, a.shape), 0).astype(np.float32)
    b = np.maximum(b, 0)
    r, nb = sk.spin_correlation(a, b)
    for k in range(4):
        both = (a[k] > 0) & (b[k] > 0)
        assert int(nb[k]) == both.sum() == int(sk.overlap_count(a[k], b[k]))
        assert float(r[k]) == pytest.approx(np.corrcoef(a[k][both], b[k][both])[0, 1], abs=1e-4)
    lam = float(sk.johnson_lambda(nb))
    assert lam == pytest.approx(0.5 * np.median(np.asarray(nb)))
    c = np.asarray(sk.spin_similarity(a, b, lam))
    want = np.arctanh(np.clip(np.asarray(r), 0, 0.999)) ** 2 - lam / (np.asarray(nb) - 3)
    np.testing.assert_allclose(c, want, rtol=1e-4, atol=1e-5)
    # identical images score higher than unrelated ones; <= 3 overlapping bins: no match
    assert float(sk.spin_similarity(a[0], a[0], lam)) > c.max()
    tiny = np.zeros((20, 20), np.float32)
    tiny[0, :3] = [1, 2, 3]
    assert float(sk.spin_similarity(tiny, tiny, lam)) == -np.inf
    # anti-correlated overlap earns nothing beyond the variance penalty
    anti = np.where(a[1] > 0, 6.0 - a[1], 0).astype(np.float32)
    nn = float(sk.overlap_count(a[1], anti))
    assert float(sk.spin_similarity(a[1], anti, lam)) == pytest.approx(-lam / (nn - 3), rel=1e-5)


def test_spin_similarity_peaks_at_the_same_point(surface):
    """The image of a point matches itself on a re-noised copy of the surface best nearby."""
    p, n, valid, mres = surface
    p2, n2, valid2, _ = blob_surface(seed=9)
    ref, _ = sk.spin_images(p, n, valid, np.array([[14, 26]]), 1.5 * mres, patch_radius=40)
    rr, cc = np.mgrid[6:23:2, 18:35:2]
    q = np.stack([rr.ravel(), cc.ravel()], -1)
    imgs, _ = sk.spin_images(p2, n2, valid2, q, 1.5 * mres, patch_radius=40)
    ov = sk.overlap_count(imgs, ref[0])
    c = np.asarray(sk.spin_similarity(imgs, ref[0], sk.johnson_lambda(ov)))
    best = q[np.argmax(c)]
    assert np.hypot(*(best - [14, 26])) <= 3.0
