"""Graph kernels against SciPy: connected components and geodesic distances (Dijkstra)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.csgraph as csg
from conftest import FIGURE_SEGMENTS, figure_joints
from hypothesis import given, settings
from hypothesis import strategies as st

from cpf_jax.kernels import graph as gk

FX = FY = 365.0


def render_figure(
    h: int = 96,
    w: int = 64,
    z0: float = 2000.0,
    noise: float = 1.0,
    seed: int = 0,
    arm: float = 0.4,
    k: float = 0.33,
):
    """A capsule figure (head, trunk, arms, legs; ``k`` x adult size) ray cast into a window.

    Returns ``(depth [h, w] float32 mm, 0 = background/missing, points [h, w, 3])``.
    The principal point is the window centre.
    """
    rng = np.random.default_rng(seed)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = np.stack([(u - cx) / FX, (v - cy) / FY, np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    j = figure_joints(arm)
    pts = {
        n: np.array([k * x, k * y, z0 + (40 * k if n == "lh" else 0)]) for n, (x, y) in j.items()
    }
    segs = FIGURE_SEGMENTS
    t = np.full((h, w), np.inf)
    for a, b, r in segs:
        pa, pb, r = pts[a], pts[b], r * k
        for s in np.linspace(0, 1, max(2, int(np.linalg.norm(pb - pa) / (0.25 * r)))):
            c = pa + s * (pb - pa)
            bb = d @ c
            disc = bb * bb - (c @ c - r * r)
            t = np.minimum(t, np.where(disc > 0, bb - np.sqrt(np.maximum(disc, 0)), np.inf))
    z = t * d[..., 2]
    z = np.where(np.isfinite(z), z + rng.normal(0, noise, z.shape), 0.0).astype(np.float32)
    p = np.stack([z * (u - cx) / FX, z * (v - cy) / FY, z], -1).astype(np.float32)
    return z, p


def scipy_graph(edges) -> sp.csr_matrix:
    i, j, w = gk.edge_list(edges)
    n = np.asarray(edges).shape[1] * np.asarray(edges).shape[2]
    return sp.coo_matrix((w, (i, j)), shape=(n, n)).tocsr()


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
    pairs = set(zip(a.tolist(), b.tolist(), strict=True))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def serpentine_mask(h: int, w: int) -> np.ndarray:
    """Vertical one-pixel corridors joined alternately at the bottom and the top.

    The shortest path from the top-left corner runs down, up, down, ... once
    per corridor, so row sweeps need about one sweep per corridor.
    """
    m = np.zeros((h, w), bool)
    m[:, 0:w:2] = True
    for k, c in enumerate(range(1, w - 1, 2)):
        m[h - 1 if k % 2 == 0 else 0, c] = True
    return m


# ---------------------------------------------------------------------------------------------


def test_pixel_graph_matches_loop():
    rng = np.random.default_rng(1)
    z = rng.uniform(1000, 1040, (7, 9)).astype(np.float32)
    valid = rng.random((7, 9)) > 0.2
    e = np.asarray(gk.pixel_graph(z, valid, 10.0))
    for k, (dr, dc) in enumerate(gk.FORWARD):
        for r in range(7):
            for c in range(9):
                r2, c2 = r + dr, c + dc
                inside = 0 <= r2 < 7 and 0 <= c2 < 9
                want = inside and valid[r, c] and valid[r2, c2] and abs(z[r, c] - z[r2, c2]) < 10
                assert e[k, r, c] == want


_cc = jax.jit(gk.connected_components)


@pytest.mark.parametrize("case", ["random", "serpentine", "figure"])
def test_connected_components_equal_scipy(case):
    if case == "random":
        rng = np.random.default_rng(0)
        z = np.round(rng.uniform(0, 3, (40, 48))).astype(np.float32) * 8.0
        edges = gk.pixel_graph(z, rng.random((40, 48)) > 0.3, 10.0)
    elif case == "serpentine":
        m = serpentine_mask(40, 48)
        edges = gk.pixel_graph(np.zeros((40, 48), np.float32), m, 1.0)
    else:
        z, _ = render_figure(40, 48, k=0.2, noise=3.0)
        edges = gk.pixel_graph(z, z > 0, 10.0)
    labels = np.asarray(_cc(edges))
    n, ref = csg.connected_components(scipy_graph(edges), directed=False)
    assert len(np.unique(labels)) == n
    assert same_partition(labels, ref)
    # labels are the smallest flat index of each component
    flat = np.arange(labels.size).reshape(labels.shape)
    for lab in np.unique(labels):
        assert lab == flat[labels == lab].min()


def test_connected_components_vmap_and_largest():
    rng = np.random.default_rng(3)
    zs = np.round(rng.uniform(0, 2, (3, 40, 48))).astype(np.float32) * 20.0
    valid = rng.random((3, 40, 48)) > 0.25
    edges = jax.vmap(lambda z, v: gk.pixel_graph(z, v, 10.0))(zs, valid)
    labels = np.asarray(jax.jit(jax.vmap(gk.connected_components))(edges))
    big = np.asarray(jax.vmap(gk.largest_component)(labels, valid))
    for b in range(3):
        n, ref = csg.connected_components(scipy_graph(edges[b]), directed=False)
        assert same_partition(labels[b], ref)
        sizes = np.bincount(ref.ravel()[valid[b].ravel()], minlength=n)
        assert big[b].sum() == sizes.max()
        assert len(np.unique(ref.ravel()[big[b].ravel()])) == 1
    empty = gk.largest_component(labels[0], np.zeros((40, 48), bool))
    assert not np.asarray(empty).any()
    # per-component means over valid pixels
    vals = rng.uniform(0, 100, (40, 48)).astype(np.float32)
    got = np.asarray(jax.jit(gk.component_mean)(labels[0], vals, valid[0]))
    for lab in np.unique(labels[0]):
        sel = labels[0] == lab
        want = vals[sel & valid[0]].mean() if (sel & valid[0]).any() else np.nan
        np.testing.assert_allclose(got[sel], want, rtol=1e-5)


def test_surface_graph_and_mesh_resolution():
    z, p = render_figure(40, 48, k=0.2)
    mask = z > 0
    w = np.asarray(gk.surface_graph(p, mask, 15.0))
    for k, (dr, dc) in enumerate(gk.FORWARD):
        for r in range(40):
            for c in range(48):
                r2, c2 = r + dr, c + dc
                if not (0 <= r2 < 40 and 0 <= c2 < 48) or not (mask[r, c] and mask[r2, c2]):
                    assert np.isinf(w[k, r, c])
                    continue
                dist = np.linalg.norm(p[r, c].astype(np.float64) - p[r2, c2])
                if dist <= 15.0 - 1e-3:
                    assert abs(w[k, r, c] - dist) <= 0.5 / gk.UNITS_PER_MM + 1e-5
                elif dist > 15.0 + 1e-3:
                    assert np.isinf(w[k, r, c])
    # weights sit on the fixed-point grid the relaxation uses
    fin = np.isfinite(w)
    assert np.all(w[fin] * gk.UNITS_PER_MM == np.round(w[fin] * gk.UNITS_PER_MM))
    assert abs(float(gk.mesh_resolution(w)) - w[fin].mean()) < 1e-3
    assert float(gk.mesh_resolution(np.full((4, 3, 3), np.inf, np.float32))) == 0.0


def _dijkstra(weights, sources):
    return csg.dijkstra(scipy_graph(weights), directed=False, indices=sources)


_geo = jax.jit(lambda w, s: gk.geodesic_distances(w, s, return_sweeps=True))


def _check_equal(d, ref):
    d = np.asarray(d).ravel()
    ref = np.asarray(ref).ravel()
    assert np.array_equal(np.isfinite(d), np.isfinite(ref))
    fin = np.isfinite(ref) & (ref > 0)
    if fin.any():
        assert np.max(np.abs(d[fin] - ref[fin]) / ref[fin]) <= 1e-4
    assert np.all(d[ref == 0] == 0)


def test_geodesic_equals_dijkstra_on_a_figure():
    z, p = render_figure(96, 64)
    w = gk.surface_graph(p, z > 0, 15.0)
    src = np.zeros(z.shape, bool)
    src[12, 32] = True  # the head
    d, sweeps = _geo(w, src)
    _check_equal(d, _dijkstra(w, 12 * 64 + 32))
    assert 2 <= int(sweeps) < 64
    # hands and feet are reached, across the whole figure
    assert np.isfinite(np.asarray(d)).sum() > 0.9 * (z > 0).sum() - 60


def test_geodesic_against_float64_graph_built_in_numpy():
    """Independent reference: float64 edge lengths computed here, not by ``surface_graph``."""
    z, p = render_figure(96, 64)
    mask = z > 0
    h, w = z.shape
    idx = np.arange(h * w).reshape(h, w)
    ii, jj, ww = [], [], []
    p64 = p.astype(np.float64)
    for dr, dc in gk.FORWARD:
        for r in range(h):
            for c in range(w):
                r2, c2 = r + dr, c + dc
                if 0 <= r2 < h and 0 <= c2 < w and mask[r, c] and mask[r2, c2]:
                    dist = np.linalg.norm(p64[r, c] - p64[r2, c2])
                    if dist <= 15.0:
                        ii.append(idx[r, c])
                        jj.append(idx[r2, c2])
                        ww.append(dist)
    g = sp.coo_matrix((ww, (ii, jj)), shape=(h * w, h * w)).tocsr()
    ref = csg.dijkstra(g, directed=False, indices=12 * 64 + 32)
    src = np.zeros(z.shape, bool)
    src[12, 32] = True
    d, _ = _geo(gk.surface_graph(p, mask, 15.0), src)
    d = np.asarray(d).ravel()
    fin = np.isfinite(ref) & (ref > 0) & np.isfinite(d)
    # Edges within 1e-3 mm of the threshold may fall on either side of it in float32.
    assert np.mean(np.isfinite(d) == np.isfinite(ref)) > 0.999
    assert np.max(np.abs(d[fin] - ref[fin]) / ref[fin]) <= 1e-4


def test_geodesic_serpentine_needs_many_sweeps_and_flags_non_convergence():
    m = serpentine_mask(40, 48)
    rng = np.random.default_rng(5)
    p = np.zeros((40, 48, 3), np.float32)
    p[..., 0], p[..., 1] = np.meshgrid(np.arange(48) * 2.0, np.arange(40) * 2.0)
    p[..., 2] = 3000 + rng.normal(0, 0.5, (40, 48))
    w = gk.surface_graph(p, m, 15.0)
    src = np.zeros((40, 48), bool)
    src[0, 0] = True
    d, sweeps = _geo(w, src)
    _check_equal(d, _dijkstra(w, 0))
    assert int(sweeps) >= 20  # one sweep per corridor
    two = jax.jit(lambda w, s: gk.geodesic_distances(w, s, max_sweeps=2, return_sweeps=True))
    short, k = two(w, src)
    assert int(k) == 2
    assert not np.array_equal(np.isfinite(np.asarray(short)), np.isfinite(np.asarray(d)))


def test_geodesic_beyond_max_distance_is_unreachable():
    m = np.ones((4, 200), bool)
    p = np.zeros((4, 200, 3), np.float32)
    p[..., 0] = np.arange(200) * 14.0  # a 2.8 m strip; paths up to ~2.8 m + detours
    p[..., 2] = 3000.0
    w = gk.surface_graph(p, m, 15.0)
    src = np.zeros((4, 200), bool)
    src[0, 0] = True
    d = np.asarray(_geo(w, src)[0])
    assert np.isfinite(d).all() and abs(d[0, -1] - 199 * 14.0) < 1e-2
    p[..., 0] = np.arange(200) * 24.0  # 4.8 m: the far end exceeds MAX_DISTANCE_MM
    w = gk.surface_graph(p, m, 30.0)
    d = np.asarray(_geo(w, src)[0])
    ref = _dijkstra(w, 0).reshape(4, 200)
    assert np.array_equal(np.isfinite(d), ref <= gk.MAX_DISTANCE_MM)
    with pytest.raises(ValueError):
        gk.geodesic_distances(np.full((4, 8, 251), np.inf, np.float32), np.zeros((8, 251), bool))


def test_geodesic_batched_sources_vmap_and_multi_source():
    z, p = render_figure(96, 64, seed=2)
    w = gk.surface_graph(p, z > 0, 15.0)
    pix = np.array([[12, 32], [50, 32], [90, 18], [0, 0]])  # the last one is off the body
    maps = np.asarray(jax.jit(gk.geodesic_from_pixels)(w, np.concatenate([pix, [[-3, 5]]])))
    refs = _dijkstra(w, pix[:, 0] * 64 + pix[:, 1])
    for k in range(len(pix)):
        _check_equal(maps[k], refs[k])
    assert np.isfinite(maps[3]).sum() == 1  # only the isolated source itself
    assert np.isinf(maps[4]).all()  # a source outside the window
    both = np.zeros(z.shape, bool)
    both[12, 32] = both[90, 18] = True
    d, _ = _geo(w, both)
    _check_equal(d, np.minimum(refs[0], refs[2]))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), density=st.floats(0.3, 0.95))
def test_geodesic_random_graphs(seed, density):
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.5, 20.0, (4, 16, 20)).astype(np.float32)
    w = np.where(rng.random((4, 16, 20)) < density, w, np.inf)
    w[0, :, -1] = np.inf  # no edges leave the window
    w[1:, -1, :] = np.inf
    w[2, :, -1] = np.inf
    w[3, :, 0] = np.inf
    w = np.asarray(gk.quantise_mm(w))
    src = np.zeros((16, 20), bool)
    r, c = rng.integers(0, 16), rng.integers(0, 20)
    src[r, c] = True
    d, _ = _geo(w, src)
    _check_equal(d, _dijkstra(w, r * 20 + c))


def _farthest_reference(weights, sources: np.ndarray, k: int):
    """The greedy farthest-point search with SciPy's Dijkstra: the distances of the
    chosen pixels, and per step the set of pixels tied at the maximum."""
    w = np.asarray(weights).shape[2]
    chosen = list(np.flatnonzero(sources.ravel()))
    dists, ties = [], []
    for _ in range(k):
        d = np.min(np.atleast_2d(_dijkstra(weights, chosen)), axis=0)
        score = np.where(np.isfinite(d), d, -1.0)
        best = score.max()
        dists.append(best)
        ties.append(set(np.flatnonzero(score >= best - 1e-3 * max(best, 1.0))))
        chosen.append(int(np.argmax(score)))
    return np.array(dists), ties, w


_far = jax.jit(gk.farthest_points, static_argnums=(2,))


@pytest.mark.parametrize("seed", [0, 3])
def test_farthest_points_equal_a_dijkstra_search_and_find_the_limbs(seed):
    z, p = render_figure(96, 64, seed=seed, arm=1.2)
    w = gk.surface_graph(p, z > 0, 15.0)
    src = np.zeros(z.shape, bool)
    src[12, 32] = src[50, 32] = True  # head and pelvis
    pix, dist = (np.asarray(a) for a in _far(w, src, 5))
    ref_d, ties, width = _farthest_reference(w, src, 5)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-4)
    for k in range(5):
        assert pix[k, 0] * width + pix[k, 1] in ties[k], (k, pix[k])
    # The first four are the hands and feet: each the nearest of them to one limb end
    # (the raised hand leaves the window: its end is clipped to the window's edge).
    joints = [figure_joints(1.2)[n] for n in ("lh", "rh", "lf", "rf")]
    ends = np.array([[47.5 + FY * 0.33 * y / 2000, 31.5 + FX * 0.33 * x / 2000] for x, y in joints])
    ends = np.clip(ends, 0, [95, 63])
    near = np.argmin(np.linalg.norm(pix[:4, None] - ends[None], axis=-1), axis=1)
    assert sorted(near) == [0, 1, 2, 3], (pix, ends)
    assert np.all(np.linalg.norm(pix[:4] - ends[near], axis=-1) < 8)
    assert np.all(np.diff(dist) <= 0) and dist[4] < 0.8 * dist[3]  # then the reach falls


def test_farthest_points_vmap_and_nothing_reachable():
    figs = [render_figure(96, 64, seed=s, arm=a)[1] for s, a in ((1, 0.4), (2, 1.2))]
    ws = np.stack([np.asarray(gk.surface_graph(p, p[..., 2] > 0, 15.0)) for p in figs])
    src = np.zeros((96, 64), bool)
    src[12, 32] = True
    pix, dist = jax.vmap(lambda w: gk.farthest_points(w, src, 3))(ws)
    for b in range(2):
        one_p, one_d = _far(ws[b], src, 3)
        np.testing.assert_array_equal(pix[b], one_p)
        np.testing.assert_allclose(dist[b], one_d, rtol=1e-6)
    off = np.zeros((96, 64), bool)
    off[0, 0] = True  # a source off the body, with no edges
    pix, dist = _far(ws[0], off, 2)
    np.testing.assert_array_equal(np.asarray(pix), [[0, 0], [0, 0]])
    np.testing.assert_array_equal(np.asarray(dist), [0.0, 0.0])
