"""Static-camera background model: temporal medians, foreground masks, running update (P 2.3).

Conventions (those of ``cpf_jax.types.Frame``):

* colour frames ``[..., H, W, 3] uint8`` RGB; depth ``[..., H, W] uint16``
  millimetres, 0 = missing;
* a :class:`Background` holds ``colour [H, W, 3] float32`` (0..255) and
  ``depth [H, W] float32`` mm, where ``0`` means "never measured";
* masks are ``[H, W] bool``, True = foreground.

The paper takes "the median value of each pixel in several frames" as the
background, in colour and in depth. Here:

* :func:`median_background` is that median over ``K`` frames, per pixel and
  channel. For depth the median is over the *measured* samples only (zeros
  are missing data, not a distance) and is 0 where no frame measured the
  pixel; with an even count it is the mean of the two middle samples, as
  ``np.median`` / ``np.nanmedian``.
* :func:`foreground_mask` decides per pixel. Depth first, because it is
  immune to shadows, lighting and clothes that match the wall: where the
  frame and the background both have depth, a pixel is foreground when it is
  nearer than the background by more than ``max(depth_abs, depth_rel * z_bg)``
  (only nearer: a farther reading is the background seen through a gap, or
  noise). Everywhere else (the frame or the background lacks depth: dark
  hair, a window, a far wall out of range) colour decides: the largest
  absolute channel difference to the background colour above
  ``colour_threshold``.
* :func:`foreground_shares` and :func:`quiet_frames` pick the frames to take the
  median over when nobody says which frames show the empty scene: those with the
  least foreground in front of the farthest surface the candidates see (a recording
  whose people come and go, e.g. IST images1: the empty frames at its start and
  end). The shares are computed on every ``stride``-th pixel of every ``stride``-th
  row, so that 150 full-HD candidates need about 1/16 of the memory of their
  full-resolution median.
* A pixel the model has never seen (colour ``< 0``, :data:`UNSEEN`) is unknown:
  :func:`behind_plane` gives the unknown pixels a surface (just behind the target: whatever
  is nearer is foreground, the wall behind it is not).
* :func:`side_scene` is a scene model of one frame alone, for a camera that moves or a
  scene never seen empty: behind a pixel lies the farthest surface found along its row
  at given distances to either side (wider than the target), so a person, narrower than
  those distances, stands in front of it, and a floor or a wall, which continues along
  the row, does not.
* :func:`update_background` is the optional running update: a blend
  ``(1 - rate) bg + rate frame`` on background pixels only (foreground never
  leaks into the model), depth only where the frame measured it; a pixel with
  no background depth takes the frame's depth outright.

All functions are pure, static-shaped, and work under ``jit`` and ``vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

__all__ = [
    "Background",
    "median_background",
    "masked_median",
    "foreground_mask",
    "foreground_shares",
    "masked_quantile",
    "quiet_frames",
    "update_background",
    "UNSEEN",
    "behind_plane",
    "side_scene",
]

#: Colour of a background pixel never seen: every frame's colour differs from it.
UNSEEN = -1000.0


class Background(NamedTuple):
    colour: Array  # [H, W, 3] float32, 0..255
    depth: Array  # [H, W] float32 mm, 0 = never measured


def masked_quantile(values: Array, valid: Array, q: float | Array, axis: int = 0) -> Array:
    """Quantile ``q`` in ``[0, 1]`` of ``values`` along ``axis`` over the entries where
    ``valid``; 0 if none.

    Equals ``np.nanquantile(..., method="linear")`` with the invalid entries set to NaN.
    ``float32`` result.
    """
    v = jnp.moveaxis(jnp.asarray(values, jnp.float32), axis, 0)
    ok = jnp.moveaxis(jnp.asarray(valid, bool), axis, 0)
    # Invalid samples sort to the end; the first n entries are the valid ones.
    s = jnp.sort(jnp.where(ok, v, jnp.inf), axis=0)
    n = jnp.sum(ok, axis=0)
    pos = q * jnp.maximum(n - 1, 0).astype(jnp.float32)
    lo = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, v.shape[0] - 1)
    hi = jnp.clip(jnp.ceil(pos).astype(jnp.int32), 0, v.shape[0] - 1)
    a = jnp.take_along_axis(s, lo[None], axis=0)[0]
    b = jnp.take_along_axis(s, hi[None], axis=0)[0]
    t = pos - lo
    # (1 - t) a + t b: at t = 1/2 bit for bit the mean of the two middle samples.
    return jnp.where(n > 0, (1.0 - t) * a + t * b, 0.0)


def masked_median(values: Array, valid: Array, axis: int = 0) -> Array:
    """Median of ``values`` along ``axis`` over the entries where ``valid``; 0 if none.

    Equals ``np.nanmedian`` with the invalid entries set to NaN (mean of the two
    middle samples for an even count). ``float32`` result.
    """
    return masked_quantile(values, valid, 0.5, axis)


def median_background(colour: Array, depth: Array) -> Background:
    """Per-pixel temporal median of ``colour [K, H, W, 3]`` and ``depth [K, H, W]``.

    Colour: the plain median of each channel (``np.median(colour, axis=0)``).
    Depth: the median of the measured (non-zero) samples, 0 where there is none.
    """
    colour = jnp.asarray(colour)
    depth = jnp.asarray(depth)
    col = jnp.median(colour.astype(jnp.float32), axis=0)
    dep = masked_median(depth, depth > 0, axis=0)
    return Background(col, dep)


def foreground_mask(
    colour: Array,
    depth: Array,
    background: Background,
    *,
    depth_abs: float | Array = 150.0,
    depth_rel: float | Array = 0.05,
    colour_threshold: float | Array = 40.0,
) -> Array:
    """``[H, W] bool`` foreground of one frame against ``background`` (rules in the module doc).

    colour: ``[H, W, 3] uint8``; depth: ``[H, W] uint16`` mm. Thresholds in mm,
    as a fraction of the background depth, and in uint8 levels.
    """
    z = jnp.asarray(depth).astype(jnp.float32)
    zb = background.depth
    have = z > 0
    have_bg = zb > 0
    nearer = (zb - z) > jnp.maximum(depth_abs, depth_rel * zb)
    diff = jnp.abs(jnp.asarray(colour).astype(jnp.float32) - background.colour)
    colour_fg = jnp.max(diff, axis=-1) > colour_threshold
    return jnp.where(have & have_bg, nearer, colour_fg)


def foreground_shares(
    colour: Array,
    depth: Array,
    *,
    stride: int = 4,
    far_quantile: float | Array = 0.8,
    depth_abs: float | Array = 150.0,
    depth_rel: float | Array = 0.05,
    colour_threshold: float | Array = 40.0,
) -> Array:
    """``[K]`` foreground share of each frame of ``colour [K, H, W, 3]`` / ``depth [K, H, W]``:
    how much of it stands in front of the empty scene.

    The empty scene's depth is the ``far_quantile`` of each pixel's measured depths
    over the ``K`` frames (:func:`masked_quantile`; the farthest surface seen in a fifth
    of them at 0.8), so that someone standing at a pixel in most frames does not become
    the scene. A pixel counts where the frame is nearer than that by more than
    ``max(depth_abs, depth_rel * z)``; where neither has depth, where its colour differs
    from the per-pixel colour median by more than ``colour_threshold`` (a recording
    without depth is judged by colour alone); where only one has depth, not at all.
    Everything on the pixel lattice of step ``stride`` (static).
    """
    if stride < 1:
        raise ValueError(f"foreground_shares: stride must be >= 1, got {stride}")
    c = jnp.asarray(colour)[:, ::stride, ::stride].astype(jnp.float32)
    z = jnp.asarray(depth)[:, ::stride, ::stride].astype(jnp.float32)
    scene = Background(jnp.median(c, axis=0), masked_quantile(z, z > 0, far_quantile, axis=0))
    # foreground_mask's rules (broadcast over the K frames), less the pixels where only
    # one of frame and scene has depth.
    fg = foreground_mask(
        c,
        z,
        scene,
        depth_abs=depth_abs,
        depth_rel=depth_rel,
        colour_threshold=colour_threshold,
    ) & ((z > 0) == (scene.depth > 0))
    return jnp.mean(fg.astype(jnp.float32), axis=(1, 2))


def quiet_frames(
    share: Array,
    n_max: int,
    n_min: int = 5,
    margin: float | Array = 0.01,
    factor: float | Array = 2.0,
) -> tuple[Array, Array]:
    """The frames in which the scene is emptiest, from their ``share [K]``
    (:func:`foreground_shares`): ``(indices [n_max] int32, count)``.

    Chosen: every frame whose share is at most ``factor`` times the smallest plus
    ``margin`` (a scene that is never empty keeps many frames for its median), and at
    least the ``n_min`` quietest, at most the ``n_max`` quietest (ties: the earlier
    frame). ``indices[:count]`` holds them in ascending order, the rest is -1.
    ``n_max`` / ``n_min`` are static; ``1 <= n_min <= n_max``.
    """
    k = share.shape[0]
    if not 1 <= n_min <= n_max:
        raise ValueError(f"quiet_frames: need 1 <= n_min <= n_max, got {n_min}, {n_max}")
    order = jnp.argsort(share, stable=True)
    rank = jnp.arange(k)
    sorted_share = share[order]
    near_best = sorted_share <= factor * sorted_share[0] + margin
    chosen = ((rank < n_min) | near_best) & (rank < n_max)
    picked = jnp.sort(jnp.where(chosen, order, k))
    picked = jnp.pad(picked, (0, max(n_max - k, 0)), constant_values=k)[:n_max]
    return jnp.where(picked < k, picked, -1).astype(jnp.int32), jnp.sum(chosen)


def update_background(
    background: Background,
    colour: Array,
    depth: Array,
    foreground: Array,
    rate: float | Array = 0.05,
) -> Background:
    """Running update: blend the frame into the model on background pixels only (an
    unseen pixel takes the frame's colour outright).

    ``colour [H, W, 3] uint8``, ``depth [H, W] uint16``, ``foreground [H, W] bool``;
    ``rate`` in ``[0, 1]`` (0: frozen model).
    """
    bg_pix = ~jnp.asarray(foreground, bool)
    col = jnp.asarray(colour).astype(jnp.float32)
    seen = background.colour >= 0
    blend = jnp.where(seen, (1.0 - rate) * background.colour + rate * col, col)
    new_col = jnp.where(bg_pix[..., None], blend, background.colour)
    z = jnp.asarray(depth).astype(jnp.float32)
    zb = background.depth
    blended = jnp.where(zb > 0, (1.0 - rate) * zb + rate * z, z)
    new_dep = jnp.where(bg_pix & (z > 0), blended, zb)
    return Background(new_col, new_dep)


def behind_plane(background: Background, z: Array) -> Background:
    """``background`` with its unseen pixels given depth ``z`` (mm, a scalar or ``[H, W]``;
    0 leaves them without depth, so that colour decides and every pixel there is
    foreground)."""
    unseen = background.colour[..., 0] < 0
    return background._replace(depth=jnp.where(unseen, z, background.depth))


def side_scene(depth: Array, offsets: Array) -> Array:
    """``[H, W] float32`` mm: each pixel's scene depth, the farthest measured depth among
    the pixels of its row at ``x - o`` and ``x + o`` for each ``o`` of ``offsets [K]``
    (pixels, rounded; samples outside the frame or without depth are skipped; 0 where
    none has depth).

    ``depth [H, W]`` mm, 0 = missing. The farthest sample is the scene because whatever
    stands between the camera and the scene at a side (another person, a pole) is nearer:
    one sample that reaches the scene is enough. A plane such as a level floor keeps its
    depth along a row, and a wall changes it slowly, so neither stands out from its own
    scene; an object narrower than the offsets does.
    """
    z = jnp.asarray(depth).astype(jnp.float32)
    height, width = z.shape
    # Zeros on either side stand for the samples outside the frame (no depth): shifted
    # copies are then slices, which XLA:CPU copies far faster than it gathers columns.
    padded = jnp.pad(z, ((0, 0), (width, width)))
    steps = jnp.clip(jnp.round(jnp.asarray(offsets, jnp.float32)).astype(jnp.int32), 0, width)
    scene = jnp.zeros_like(z)
    for k in range(steps.shape[0]):
        for start in (width - steps[k], width + steps[k]):
            scene = jnp.maximum(scene, jax.lax.dynamic_slice(padded, (0, start), (height, width)))
    return scene
