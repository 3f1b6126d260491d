"""Pixel graphs on a depth window: connected components and geodesic distances.

The graph of a ``[H, W]`` window has one vertex per pixel and 8-neighbour edges
(thesis 4.1.2, 4.1.4). Edges are stored once, as four *forward* arrays::

    FORWARD = (E, S, SE, SW) = ((0, +1), (+1, 0), (+1, +1), (+1, -1))   # (d_row, d_col)

``edges[k, r, c]`` describes the edge from pixel ``(r, c)`` to
``(r + d_row, c + d_col)``; the reverse edge is the same edge (undirected
graphs). Boolean edge arrays (``[4, H, W] bool``) describe the segmentation
graph; weighted ones (``[4, H, W] float32``, ``inf`` = no edge) describe the
surface graph, weights in millimetres. Edges that would leave the window are
always absent.

Two kernels solve the two graph problems of the depth layer with the same
exact algorithm, a min-plus relaxation ordered as row sweeps:

* ``geodesic_distances``: shortest-path lengths from one or several source
  pixels (Dijkstra's answer, thesis 4.3 / Alg. 3).
* ``connected_components``: min-label propagation, which is the same
  relaxation with zero edge weights and every pixel a source labelled by its
  own flat index (thesis 4.1.2 finds the largest component with a DFS).

Row sweeps (why not plain Jacobi relaxation)
--------------------------------------------
Plain relaxation ``d = min(d, shift_k(d) + w_k)`` over the 8 directions moves
information one pixel per pass, so it needs as many passes as the longest
shortest path has hops (about 220 for a head-to-foot path in a 256-row
window). Here a *down sweep* visits the rows in
order inside one ``lax.scan``: row ``r`` first takes ``min`` with its three
upper neighbours (already final for this sweep), then is closed exactly along
its own row (every path that stays inside the row, both directions). An *up
sweep* does the same from the bottom. Every path that is monotone in the row
index is therefore resolved by one sweep whatever its number of hops, and a
body needs 3-6 alternating sweeps. The relaxation stops after the first sweep
that changes nothing once an opposite sweep has run: after an up sweep every
row is consistent with the row below it and with its own row, and a down
sweep without change adds consistency with the row above, so the result is a
fixed point of all 8-neighbour relaxations, i.e. exactly the shortest-path
distances (positive weights) or the component minima (zero weights).

The in-row closure is two prefix minima. With ``off_j`` the sum of the row's
edge weights left of ``j``, where every *missing* edge adds a constant ``K``
larger than any distance, ``min_{i<=j}(t_i - off_i) + off_j`` is the best
path that enters ``j`` from the left, and paths across a missing edge cost at
least ``K`` and are discarded. This needs exact integer arithmetic, so the
relaxation runs in int32 fixed point: distances and weights in units of
``1/2048`` mm. ``surface_graph`` rounds its weights to that grid, so the
relaxation is exact for the graph it returns (and differs from a float64
graph of the same points by at most ``0.5/2048`` mm per edge, a relative
``6e-5`` for 4 mm edges). Because the row prefix sums grow from left to
right, ``K`` only has to exceed the largest distance, and ``192 K`` plus a
row's total weight must fit in int32: distances are limited to
``MAX_DISTANCE_MM`` (4096 mm, far beyond any path on one person) and longer
paths are reported as unreachable; rows may be up to 250 columns wide.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array, lax

__all__ = [
    "FORWARD",
    "UNITS_PER_MM",
    "MAX_DISTANCE_MM",
    "neighbour",
    "pixel_graph",
    "surface_graph",
    "quantise_mm",
    "mesh_resolution",
    "connected_components",
    "largest_component",
    "component_mean",
    "geodesic_distances",
    "geodesic_from_pixels",
    "farthest_points",
    "edge_list",
]

FORWARD: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))

UNITS_PER_MM = 2048
_K = 2**23  # cost of crossing a missing in-row edge; larger than any distance
_INF = _K - 1  # "unreachable" in fixed point
_DMAX = _K - 2  # largest representable distance (about 4096 mm)
MAX_DISTANCE_MM = _DMAX / UNITS_PER_MM


def neighbour(a: Array, d_row: int, d_col: int, fill) -> Array:
    """``out[r, c] = a[r + d_row, c + d_col]`` over the two leading axes, ``fill`` outside."""
    h, w = a.shape[:2]
    pad = [(1, 1), (1, 1)] + [(0, 0)] * (a.ndim - 2)
    p = jnp.pad(a, pad, constant_values=fill)
    return lax.slice_in_dim(
        lax.slice_in_dim(p, 1 + d_row, 1 + d_row + h, axis=0), 1 + d_col, 1 + d_col + w, axis=1
    )


def pixel_graph(depth: Array, valid: Array, max_dz: float | Array) -> Array:
    """Segmentation graph (thesis 4.1.2): edges between valid pixels with ``|z1 - z2| < max_dz``.

    depth: ``[H, W]`` mm; valid: ``[H, W] bool``. Returns ``[4, H, W] bool`` (``FORWARD`` order).
    """
    z = jnp.asarray(depth, jnp.float32)
    valid = jnp.asarray(valid, bool)
    out = []
    for dr, dc in FORWARD:
        zn = neighbour(z, dr, dc, 0.0)
        vn = neighbour(valid, dr, dc, False)
        out.append(valid & vn & (jnp.abs(zn - z) < max_dz))
    return jnp.stack(out)


def quantise_mm(w: Array) -> Array:
    """Round mm weights to the ``1/UNITS_PER_MM`` grid of the exact relaxation (inf stays inf)."""
    w = jnp.asarray(w, jnp.float32)
    return jnp.round(w * UNITS_PER_MM) / UNITS_PER_MM


def surface_graph(points: Array, mask: Array, max_dist: float | Array) -> Array:
    """Surface graph (thesis 4.1.4): 8-neighbour edges of ``mask`` pixels, 3D length <= max_dist.

    points: ``[H, W, 3]`` mm camera coordinates; mask: ``[H, W] bool``.
    Returns weights ``[4, H, W] float32`` in mm, rounded to ``1/2048`` mm, ``inf`` where no edge.
    """
    p = jnp.asarray(points, jnp.float32)
    mask = jnp.asarray(mask, bool)
    planes = (p[..., 0], p[..., 1], p[..., 2])  # [H, W] planes vectorise better than [H, W, 3]
    out = []
    for dr, dc in FORWARD:
        d2 = sum((neighbour(c, dr, dc, 0.0) - c) ** 2 for c in planes)
        dist = jnp.sqrt(d2)
        ok = mask & neighbour(mask, dr, dc, False) & (dist <= max_dist)
        out.append(jnp.where(ok, quantise_mm(dist), jnp.inf))
    return jnp.stack(out)


def mesh_resolution(weights: Array) -> Array:
    """Mean edge length of a weighted graph (thesis 4.2.1), mm; 0 when it has no edge."""
    w = jnp.asarray(weights, jnp.float32)
    fin = jnp.isfinite(w)
    n = jnp.sum(fin)
    return jnp.where(n > 0, jnp.sum(jnp.where(fin, w, 0.0)) / jnp.maximum(n, 1), 0.0)


def edge_list(edges: Array):
    """NumPy helper for references: endpoints and weights ``(i, j, w)`` of every edge."""
    import numpy as np

    e = np.asarray(edges)
    h, w = e.shape[1:]
    idx = np.arange(h * w).reshape(h, w)
    ii, jj, ww = [], [], []
    for k, (dr, dc) in enumerate(FORWARD):
        has = np.isfinite(e[k]) if e.dtype != bool else e[k]
        r, c = np.nonzero(has)
        ii.append(idx[r, c])
        jj.append(idx[r + dr, c + dc])
        ww.append(np.ones(len(r)) if e.dtype == bool else e[k][r, c].astype(np.float64))
    return np.concatenate(ii), np.concatenate(jj), np.concatenate(ww)


# ----------------------------------------------------------------------------
# The exact row-sweep relaxation (int32 fixed point).


def _to_fixed(weights: Array) -> Array:
    """Float mm (inf = none) or bool (True = zero-weight edge) -> int32 units, _INF = none."""
    w = jnp.asarray(weights)
    if w.dtype == bool:
        return jnp.where(w, 0, _INF).astype(jnp.int32)
    w = w.astype(jnp.float32)
    fin = jnp.isfinite(w) & (w * UNITS_PER_MM < _DMAX)
    return jnp.where(fin, jnp.round(jnp.where(fin, w, 0.0) * UNITS_PER_MM), _INF).astype(jnp.int32)


def _row_offsets(w_east: Array) -> Array:
    """``off[r, c] = sum_{k < c}`` of the in-row edge ``k -> k+1`` weight (``_K`` if missing)."""
    inc = jnp.where(w_east < _INF, w_east, _K)  # [H, W]; last column's edge never exists

    def step(carry, col):
        return carry + col, carry

    _, off_t = lax.scan(step, jnp.zeros(inc.shape[0], jnp.int32), inc.T)
    return off_t.T


def _shift_right(v: Array) -> Array:  # out[c] = v[c - 1]
    return jnp.concatenate([jnp.full(v.shape[:-1] + (1,), _INF, v.dtype), v[..., :-1]], axis=-1)


def _shift_left(v: Array) -> Array:  # out[c] = v[c + 1]
    return jnp.concatenate([v[..., 1:], jnp.full(v.shape[:-1] + (1,), _INF, v.dtype)], axis=-1)


def _down_sweep(d: Array, off: Array, w_up: Array, w_upleft: Array, w_upright: Array) -> Array:
    """One sweep, first row to last: a row takes its upper neighbours, then in-row closure."""

    def step(prev, xs):
        row, o, a, b, c = xs
        t = jnp.minimum(row, prev + a)
        t = jnp.minimum(t, _shift_right(prev) + b)
        t = jnp.minimum(t, _shift_left(prev) + c)
        t = jnp.minimum(t, _INF)
        from_left = lax.cummin(t - o, axis=t.ndim - 1) + o
        from_right = lax.cummin(t + o, axis=t.ndim - 1, reverse=True) - o
        out = jnp.minimum(t, jnp.minimum(from_left, from_right))
        out = jnp.where(out > _DMAX, _INF, out)
        return out, out

    init = jnp.full(d.shape[1:], _INF, jnp.int32)
    _, out = lax.scan(step, init, (d, off, w_up, w_upleft, w_upright))
    return out


def _sweep_tables(wq: Array):
    """Per-row inputs of the down sweep and of the (row-flipped) up sweep."""
    e, s, se, sw = wq[0], wq[1], wq[2], wq[3]
    inf_row = jnp.full((1, e.shape[1]), _INF, jnp.int32)
    off = _row_offsets(e)
    # Down: row r from row r-1 (N: S-edge of (r-1, c); NW: SE-edge of (r-1, c-1);
    # NE: SW-edge of (r-1, c+1)).
    down = (
        jnp.concatenate([inf_row, s[:-1]], 0),
        jnp.concatenate([inf_row, _shift_right(se[:-1])], 0),
        jnp.concatenate([inf_row, _shift_left(sw[:-1])], 0),
    )
    # Up: row r from row r+1 (S: S-edge of (r, c); SW neighbour (r+1, c-1): SW-edge of (r, c);
    # SE neighbour (r+1, c+1): SE-edge of (r, c)); stored row-flipped.
    up = (s[::-1], sw[::-1], se[::-1])
    return off, down, up


def _relax(init: Array, wq: Array, max_sweeps: int) -> tuple[Array, Array]:
    """Alternate down / up sweeps from ``init`` (int32 units) until a sweep changes nothing.

    One loop iteration runs a down and an up sweep. It stops when the up sweep
    changed nothing, or when a down sweep after an up sweep changed nothing (the
    up sweep is then skipped). Returns the result and the number of sweeps run.
    """
    if wq.shape[-1] > 250:  # 192 K + a row's weight must fit in int32 (static check)
        raise ValueError(f"rows are limited to 250 pixels, got {wq.shape[-1]}; transpose or tile")
    off, down, up = _sweep_tables(wq)
    off_up = off[::-1]

    def cond(c):
        _, k, done = c
        return (~done) & (k < max_sweeps)

    def body(c):
        d, k, _ = c
        dd = _down_sweep(d, off, *down)
        settled = (k > 0) & jnp.all(dd == d)
        # Skip the up sweep once the down sweep changed nothing (unbatched: a real
        # saving; under vmap lax.cond runs both branches, which is still correct).
        du = lax.cond(settled, lambda x: x, lambda x: _down_sweep(x[::-1], off_up, *up)[::-1], dd)
        done = settled | jnp.all(du == dd)
        return du, k + 2 - settled.astype(jnp.int32), done

    d, k, _ = lax.while_loop(cond, body, (init, jnp.int32(0), jnp.bool_(False)))
    return d, k


def connected_components(edges: Array, max_sweeps: int = 256) -> Array:
    """Connected components of a ``[4, H, W] bool`` 8-neighbour graph by min-label propagation.

    Returns ``[H, W] int32``: every pixel carries the smallest flat index
    (``r * W + c``) of its component, so isolated pixels keep their own index.
    Exact (the same partition as ``scipy.sparse.csgraph.connected_components``)
    when the relaxation converges within ``max_sweeps`` sweeps (always, in practice).
    """
    edges = jnp.asarray(edges, bool)
    h, w = edges.shape[1:]
    init = jnp.arange(h * w, dtype=jnp.int32).reshape(h, w)
    labels, _ = _relax(init, _to_fixed(edges), max_sweeps)
    return labels


def largest_component(labels: Array, valid: Array) -> Array:
    """``[H, W] bool`` mask of the largest component among ``valid`` pixels (ties: smallest label).

    All False when no pixel is valid.
    """
    labels = jnp.asarray(labels, jnp.int32)
    valid = jnp.asarray(valid, bool)
    n = labels.size
    counts = jnp.zeros(n, jnp.int32).at[labels.reshape(-1)].add(valid.reshape(-1).astype(jnp.int32))
    best = jnp.argmax(counts)
    return valid & (labels == best) & (counts[best] > 0)


def component_mean(labels: Array, values: Array, valid: Array) -> Array:
    """Per pixel, the mean of ``values`` over the ``valid`` pixels of its component (``[H, W]``).

    Pixels of components without valid pixels get ``nan``.
    """
    labels = jnp.asarray(labels, jnp.int32).reshape(-1)
    valid = jnp.asarray(valid, bool).reshape(-1)
    values = jnp.asarray(values, jnp.float32)
    shape = values.shape
    n = labels.size
    w = valid.astype(jnp.float32)
    sums = jnp.zeros(n, jnp.float32).at[labels].add(jnp.where(valid, values.reshape(-1), 0.0))
    cnts = jnp.zeros(n, jnp.float32).at[labels].add(w)
    mean = jnp.where(cnts > 0, sums / jnp.maximum(cnts, 1.0), jnp.nan)
    return mean[labels].reshape(shape)


def geodesic_distances(
    weights: Array, sources: Array, max_sweeps: int = 64, return_sweeps: bool = False
):
    """Shortest-path lengths (mm) from a set of source pixels over a weighted pixel graph.

    weights: ``[4, H, W]`` float mm (``inf`` = no edge), e.g. from ``surface_graph``.
    sources: ``[H, W] bool``, distance 0 there (several sources give the distance to the nearest).
    Returns ``[H, W] float32``; ``inf`` where unreachable. Batch over sources with ``jax.vmap``.
    With ``return_sweeps`` also the number of sweeps run (``== max_sweeps`` means not converged).
    """
    wq = _to_fixed(weights)
    init = jnp.where(jnp.asarray(sources, bool), 0, _INF).astype(jnp.int32)
    d, k = _relax(init, wq, max_sweeps)
    dist = jnp.where(d >= _INF, jnp.inf, d.astype(jnp.float32) / UNITS_PER_MM)
    return (dist, k) if return_sweeps else dist


def geodesic_from_pixels(weights: Array, pixels: Array, max_sweeps: int = 64) -> Array:
    """Distance maps ``[S, H, W]`` from each of ``pixels: [S, 2] int (row, col)`` (vmapped sources).

    A source outside the window gives an all-``inf`` map.
    """
    weights = jnp.asarray(weights)
    h, w = weights.shape[1:]
    pixels = jnp.asarray(pixels, jnp.int32)
    rr = jnp.arange(h)[:, None]
    cc = jnp.arange(w)[None, :]

    def one(p):
        return geodesic_distances(weights, (rr == p[0]) & (cc == p[1]), max_sweeps)

    return jax.vmap(one)(pixels)


def farthest_points(
    weights: Array, sources: Array, k: int, max_sweeps: int = 64
) -> tuple[Array, Array]:
    """Greedy geodesic farthest-point search: ``k`` pixels ``[k, 2] int32 (row, col)``
    and their distances ``[k]`` mm.

    Pixel ``i`` is the one farthest (geodesically, over ``weights``) from the
    ``sources`` (``[H, W] bool``) and pixels ``0..i-1``; only pixels reachable
    from the sources count. On a body's surface graph, started from the torso
    and the head, these are its extremities: hands and feet, then elbows and
    knees (the AGEX interest points of Plagemann et al., ICRA 2010). The
    distances fall as the search runs out of extremities; a distance of 0
    means nothing reachable was left (the pixel is then a source, or (0, 0) when
    no source is reachable at all). Ties go to the first pixel in row-major order.
    """
    weights = jnp.asarray(weights)
    w = weights.shape[2]
    d = geodesic_distances(weights, sources, max_sweeps)
    pixels, dists = [], []
    for _ in range(k):  # k is small and static: unrolled
        score = jnp.where(jnp.isfinite(d), d, -1.0)
        i = jnp.argmax(score)
        pixels.append(jnp.stack([i // w, i % w]).astype(jnp.int32))
        dists.append(jnp.maximum(score.reshape(-1)[i], 0.0))
        d = jnp.minimum(d, geodesic_from_pixels(weights, pixels[-1][None], max_sweeps)[0])
    return jnp.stack(pixels), jnp.stack(dists)
