"""Z-buffer ray casting of simple primitives for the synthetic RGB-D generator (private).

Everything here is NumPy and lives in **camera coordinates, metres**: X right, Y down,
Z forward. The ray through pixel ``(row r, col c)`` is ``((c - cx)/fx, (r - cy)/fy, 1)``:
integer pixel coordinates are pixel centres, the convention of
``cpf_jax.types.Intrinsics`` (``u = fx X / Z + cx``) and of the depth layer's
back-projection ``X = Z (x - cx) / fx``. Because the ray has unit Z component, the ray
parameter ``t`` of a hit *is* its depth Z.

Arrays are laid out components-first (``[3, H, W]``): NumPy is slow on short last axes.

A scene is a list of :class:`Prim` (capsule, ellipsoid or oriented box). Each primitive
carries an ``object_id`` (0 = static background, 1 = the person, 2.. = occluders or other
people) and a ``material`` index, and :func:`raycast` writes a :class:`GBuffer` (depth,
primitive index, normal, surface coordinates) so that shading, masks and depth effects
are all per-pixel look-ups. Adding an object to a frame is appending primitives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CAPSULE, ELLIPSOID, BOX = 0, 1, 2


@dataclass(frozen=True, slots=True, eq=False)
class Prim:
    """One primitive in camera coordinates (metres).

    capsule:   ``p0``, ``p1`` segment end points, ``size[0]`` radius; ``rot[:, 0]`` is a
               reference direction perpendicular-ish to the axis (for texture angle).
    ellipsoid: ``p0`` centre, ``rot`` columns = local axes, ``size`` = radii.
    box:       ``p0`` centre, ``rot`` columns = local axes, ``size`` = half extents.
    """

    kind: int
    p0: np.ndarray
    p1: np.ndarray
    size: np.ndarray
    rot: np.ndarray
    object_id: int
    material: int
    part: int = -1


def capsule(a, b, radius, ref, object_id, material, part=-1) -> Prim:
    rot = np.zeros((3, 3))
    rot[:, 0] = ref
    return Prim(
        CAPSULE,
        np.asarray(a, float),
        np.asarray(b, float),
        np.array([radius, 0.0, 0.0]),
        rot,
        object_id,
        material,
        part,
    )


def ellipsoid(centre, axes, radii, object_id, material, part=-1) -> Prim:
    return Prim(
        ELLIPSOID,
        np.asarray(centre, float),
        np.zeros(3),
        np.asarray(radii, float),
        np.asarray(axes, float),
        object_id,
        material,
        part,
    )


def box(centre, axes, half, object_id, material, part=-1) -> Prim:
    return Prim(
        BOX,
        np.asarray(centre, float),
        np.zeros(3),
        np.asarray(half, float),
        np.asarray(axes, float),
        object_id,
        material,
        part,
    )


def pixel_rays(height: int, width: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``[2, H, W] float64`` X and Y components of the pixel rays (Z component is 1)."""
    rays = np.empty((2, height, width))
    rays[0] = ((np.arange(width, dtype=np.float64) - cx) / fx)[None, :]
    rays[1] = ((np.arange(height, dtype=np.float64) - cy) / fy)[:, None]
    return rays


class GBuffer:
    """Per-pixel render targets: depth ``z [H, W]`` (m, inf = nothing), primitive index
    ``pid [H, W]`` (-1 = nothing), unit ``normal [3, H, W]`` facing the camera, surface
    coordinates ``uv [2, H, W]`` (m). Components first: NumPy is slow on short last axes."""

    def __init__(self, height: int, width: int):
        self.z = np.full((height, width), np.inf)
        self.pid = np.full((height, width), -1, np.int32)
        self.normal = np.zeros((3, height, width), np.float32)
        self.uv = np.zeros((2, height, width), np.float32)

    @classmethod
    def over(cls, z: np.ndarray) -> GBuffer:
        """An empty buffer in front of the depths ``z`` (a copy is taken): only nearer
        surfaces are written; ``normal`` / ``uv`` are defined where ``pid >= 0``."""
        g = cls.__new__(cls)
        g.z = np.array(z, np.float64)
        g.pid = np.full(z.shape, -1, np.int32)
        g.normal = np.empty((3,) + z.shape, np.float32)
        g.uv = np.empty((2,) + z.shape, np.float32)
        return g


def _bounding_corners(p: Prim) -> np.ndarray:
    if p.kind == CAPSULE:
        r = p.size[0]
        lo = np.minimum(p.p0, p.p1) - r
        hi = np.maximum(p.p0, p.p1) + r
    else:  # ellipsoid or box: axis-aligned bound of the rotated shape
        ext = np.abs(p.rot) @ p.size
        lo, hi = p.p0 - ext, p.p0 + ext
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def screen_rect(p: Prim, fx, fy, cx, cy):
    """Half-open pixel rect ``(r0, r1, c0, c1)`` (unclipped) containing the primitive's
    projection, or ``None`` when its bound straddles the camera plane."""
    corners = _bounding_corners(p)
    if corners[:, 2].min() <= 1e-3:
        return None
    u = fx * corners[:, 0] / corners[:, 2] + cx
    v = fy * corners[:, 1] / corners[:, 2] + cy
    return (
        int(np.floor(v.min())) - 1,
        int(np.ceil(v.max())) + 2,
        int(np.floor(u.min())) - 1,
        int(np.ceil(u.max())) + 2,
    )


def _sphere_t(x, y, dd, c, r):
    """Nearest positive hit depth of rays ``(x, y, 1)`` with a sphere; inf if none."""
    dc = x * c[0] + y * c[1] + c[2]
    disc = dc * dc - dd * (c @ c - r * r)
    t = (dc - np.sqrt(np.maximum(disc, 0.0))) / dd
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _local(R, x, y):
    """Components of the rays ``(x, y, 1)`` along the columns of ``R``."""
    return [R[0, k] * x + R[1, k] * y + R[2, k] for k in range(3)]


def _hit_depth(p: Prim, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest positive hit depth of the rays ``(x, y, 1)`` (1-D arrays); inf = miss."""
    if p.kind == CAPSULE:
        a, b, r = p.p0, p.p1, p.size[0]
        length = float(np.linalg.norm(b - a))
        k = (b - a) / max(length, 1e-12)
        dd = x * x + y * y + 1.0
        # Infinite cylinder around the axis, kept within the segment; caps are spheres.
        dk = x * k[0] + y * k[1] + k[2]
        wk = -(a @ k)
        dw = -(x * a[0] + y * a[1] + a[2])
        A = dd - dk * dk
        B = dw - dk * wk
        disc = B * B - A * (a @ a - wk * wk - r * r)
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = (-B - np.sqrt(np.maximum(disc, 0.0))) / A
        s = wk + tc * dk
        tc = np.where((disc >= 0) & (A > 1e-15) & (tc > 0) & (s >= 0) & (s <= length), tc, np.inf)
        return np.minimum(tc, np.minimum(_sphere_t(x, y, dd, a, r), _sphere_t(x, y, dd, b, r)))
    if p.kind == ELLIPSOID:
        R, radii = p.rot, p.size
        o = (R.T @ (-p.p0)) / radii
        dl = [c / radii[i] for i, c in enumerate(_local(R, x, y))]
        A = dl[0] * dl[0] + dl[1] * dl[1] + dl[2] * dl[2]
        B = dl[0] * o[0] + dl[1] * o[1] + dl[2] * o[2]
        disc = B * B - A * (o @ o - 1.0)
        t = (-B - np.sqrt(np.maximum(disc, 0.0))) / A
        return np.where((disc >= 0) & (t > 0), t, np.inf)
    # Oriented box, slab method in local coordinates.
    tn, tf, _ = _box_slabs(p, x, y)
    return np.where((tn <= tf) & (tn > 0), tn, np.inf)


def _box_slabs(p: Prim, x, y):
    R, half = p.rot, p.size
    o = R.T @ (-p.p0)
    dl = [np.where(np.abs(c) < 1e-12, 1e-12, c) for c in _local(R, x, y)]
    tmin, tmax = [], []
    for i in range(3):
        t1 = (-half[i] - o[i]) / dl[i]
        t2 = (half[i] - o[i]) / dl[i]
        tmin.append(np.minimum(t1, t2))
        tmax.append(np.maximum(t1, t2))
    tn = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
    tf = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
    face = np.where(tmin[0] >= tn, 0, np.where(tmin[1] >= tn, 1, 2))
    return tn, tf, (face, dl, o)


def _surface(p: Prim, x: np.ndarray, y: np.ndarray, t: np.ndarray):
    """Unit normals ``[3, n]`` and surface coordinates ``[2, n]`` (m) at hits ``t`` (finite)."""
    if p.kind == CAPSULE:
        a, b, r = p.p0, p.p1, p.size[0]
        length = float(np.linalg.norm(b - a))
        k = (b - a) / max(length, 1e-12)
        px, py, pz = t * x - a[0], t * y - a[1], t - a[2]
        s = np.clip(px * k[0] + py * k[1] + pz * k[2], 0.0, length)
        n = np.stack([(px - s * k[0]) / r, (py - s * k[1]) / r, (pz - s * k[2]) / r])
        e1 = p.rot[:, 0] - (p.rot[:, 0] @ k) * k
        e1 /= max(np.linalg.norm(e1), 1e-12)
        e2 = np.cross(k, e1)
        ang = np.arctan2(e2 @ n, e1 @ n)
        return n, np.stack([s, ang * r])
    if p.kind == ELLIPSOID:
        R, radii = p.rot, p.size
        o = (R.T @ (-p.p0)) / radii
        dl = [c / radii[i] for i, c in enumerate(_local(R, x, y))]
        ps = [o[i] + t * dl[i] for i in range(3)]  # hit on the unit sphere
        n = R @ np.stack([ps[i] / radii[i] for i in range(3)])
        n /= np.maximum(np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 1e-12)
        uv = np.stack([np.arctan2(ps[0], ps[2]) * 0.5 * (radii[0] + radii[2]), ps[1] * radii[1]])
        return n, uv
    _, _, (face, dl, o) = _box_slabs(p, x, y)
    half = p.size
    n = p.rot[:, face] * -np.sign(np.choose(face, dl))  # [3, n]
    pl = [o[i] + t * dl[i] + half[i] for i in range(3)]  # local coordinates from a corner
    # The two in-face coordinates: (x, y) on z faces, (z, y) on x faces, (x, z) on y faces.
    uv = np.stack([np.where(face == 0, pl[2], pl[0]), np.where(face == 1, pl[2], pl[1])])
    return n, uv


def _intersect(p: Prim, x: np.ndarray, y: np.ndarray):
    """Depth ``t [n]`` (inf = miss), normals ``[3, n]`` and surface coords ``[2, n]``."""
    t = _hit_depth(p, x, y)
    n, uv = _surface(p, x, y, np.where(np.isfinite(t), t, 0.0))
    return t, n, uv


def raycast(
    prims, index_offset: int, gb: GBuffer, rays: np.ndarray, intr, origin: tuple[int, int] = (0, 0)
) -> None:
    """Render ``prims`` into ``gb`` in place (nearest hit wins); primitive ``i`` of the list
    is written as ``pid = index_offset + i``. ``gb`` and ``rays [2, h, w]`` may be a window
    of the image whose top-left pixel is ``origin = (row, col)``."""
    height, width = gb.z.shape
    fx, fy, cx, cy = intr
    for i, p in enumerate(prims):
        rect = screen_rect(p, fx, fy, cx, cy)
        if rect is None:
            r0, r1, c0, c1 = 0, height, 0, width
        else:
            r0 = max(rect[0] - origin[0], 0)
            r1 = min(rect[1] - origin[0], height)
            c0 = max(rect[2] - origin[1], 0)
            c1 = min(rect[3] - origin[1], width)
        if r1 <= r0 or c1 <= c0:
            continue
        sl = (slice(r0, r1), slice(c0, c1))
        x = rays[0][sl].ravel()
        y = rays[1][sl].ravel()
        t = _hit_depth(p, x, y)
        win = t < gb.z[sl].ravel()
        if not win.any():
            continue
        xw, yw, tw = x[win], y[win], t[win]
        nw, uvw = _surface(p, xw, yw, tw)
        win2 = win.reshape(r1 - r0, c1 - c0)
        gb.z[sl][win2] = tw
        gb.pid[sl][win2] = index_offset + i
        # Normals face the camera (for the eye ray d, n . d < 0).
        flip = (nw[0] * xw + nw[1] * yw + nw[2]) > 0
        nw[:, flip] *= -1
        for k in range(3):
            gb.normal[k][sl][win2] = nw[k]
        gb.uv[0][sl][win2] = uvw[0]
        gb.uv[1][sl][win2] = uvw[1]


# ---------------------------------------------------------------------------------------------
# Procedural textures (periodic, seeded).


def periodic_noise(rng: np.random.Generator, size: int = 256, beta: float = 2.0) -> np.ndarray:
    """``[size, size] float32`` tileable 1/f^beta noise, zero mean, unit std."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    spec = np.fft.fft2(white) / fr ** (beta / 2)
    spec[0, 0] = 0.0
    out = np.real(np.fft.ifft2(spec))
    out = (out - out.mean()) / out.std()
    return out.astype(np.float32)


def tile_lookup(tile: np.ndarray, u: np.ndarray, v: np.ndarray, scale: float) -> np.ndarray:
    """Nearest look-up of a periodic tile at surface coordinates (m); ``scale`` m per texel."""
    size = tile.shape[0]
    iu = np.floor(u / scale).astype(np.int64) % size
    iv = np.floor(v / scale).astype(np.int64) % size
    return tile[iv, iu]
