"""Which target each pixel belongs to, and the depth image each slot's filter sees.

Before the slots step, every confirmed or tentative target claims the foreground pixels
of its predicted box (grown by ``claim.margin`` per side) within the depth tolerance of
its predicted depth (``rgbd.depth.depth_tolerance``); a pixel that several targets could
claim goes to the one it fits best, ``|z - z_k| / gate_k + |x - cx_k| / (w_k / 2)``. Depth
gates decide who occludes whom: a nearer target's pixels are never within a farther
target's gate, so they stay the nearer one's.

Each slot then sees the frame with the pixels claimed by the other targets at its own
depth or nearer turned into an occluder: their depth is set ``claim.fake_margins``
occluder margins nearer than the slot's target (or kept when already nearer). A target
hidden behind another has its cells explained by the person in front (the RGB-D filter's
occluded cells, paper eq. 1 with the depth-ordering rule), and a target beside a neighbour
at his depth cannot take the neighbour's pixels for its own: the neighbour is in front of
it as far as its filter can tell. Pixels of farther targets take the background's depth:
to a nearer target they are scene, and a slot whose search for its lost target widens its
depth gate cannot take a farther person for him.

Conventions: depth ``[H, W]`` uint16 mm (0: missing), boxes ``[K, 4]`` xywh top-left in
pixels (``cpf_jax.kernels.boxes``), target depths ``[K]`` mm (0: unknown).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.cells import histogram_quantile
from cpf_jax.kernels.histogram import box_histograms
from cpf_jax.rgbd.depth import depth_tolerance, mean_known_depth, occluder_margin

__all__ = [
    "Prediction",
    "predict_targets",
    "grow",
    "claim_owner",
    "slot_depths",
    "claimed_mask",
    "joined",
    "blob_reach",
    "evidence",
    "Visible",
    "visible_part",
    "same_place",
    "box_depths",
]


class Prediction(NamedTuple):
    box: Array  # [K, 4] xywh: the last estimate moved by the cloud's mean velocity
    depth: Array  # [K] mm: the depth templates' mean moved by their velocity (0: unknown)
    gate: Array  # [K] mm: the depth tolerance at that depth


def predict_targets(rgbd_params, slots) -> Prediction:
    """Where each slot's target is expected this frame, from its RGB-D state ``slots``
    (batched ``[K, ...]``): the last estimate moved by the weighted mean velocity of its
    particles, and its depth moved by the depth templates' velocity."""
    w = jnp.exp(slots.cloud.log_weights)  # [K, N]
    vel = jnp.einsum("kn,knd->kd", w, slots.cloud.particles[..., 2:4])
    box = slots.estimate.at[:, :2].add(vel)
    z0 = mean_known_depth(slots.depth.depth)
    z = jnp.where(z0 > 0, z0 + slots.depth.velocity, 0.0)
    return Prediction(box, z, depth_tolerance(rgbd_params, z))


def grow(boxes: Array, share: Array) -> Array:
    """``boxes [..., 4]`` xywh grown by ``share`` of their size on every side."""
    return jnp.concatenate(
        [boxes[..., :2] - share * boxes[..., 2:], boxes[..., 2:] * (1.0 + 2.0 * share)], axis=-1
    )


def _inside(boxes: Array, height: int, width: int) -> tuple[Array, Array]:
    """``([K, H] rows, [K, W] columns)`` whose pixel centres lie inside each box."""
    rect = box_ops.xywh_to_rect(boxes)  # [K, 4] (x0, y0, x1, y1)
    rows = jnp.arange(height, dtype=jnp.float32) + 0.5
    cols = jnp.arange(width, dtype=jnp.float32) + 0.5
    r = (rows[None] >= rect[:, 1:2]) & (rows[None] < rect[:, 3:4])
    c = (cols[None] >= rect[:, 0:1]) & (cols[None] < rect[:, 2:3])
    return r, c


def claim_owner(depth: Array, boxes: Array, z: Array, gate: Array, claiming: Array) -> Array:
    """``[H, W] int32``: the slot that claims each pixel, -1 for none (module docstring).

    ``boxes [K, 4]`` the (grown) boxes, ``z [K]`` and ``gate [K]`` the targets' depths and
    tolerances, ``claiming [K] bool`` the slots that claim (others and unknown depths
    claim nothing). Pixels without depth are nobody's."""
    height, width = depth.shape
    d = depth.astype(jnp.float32)
    rows, cols = _inside(boxes, height, width)
    off = jnp.abs(d[None] - z[:, None, None])  # [K, H, W]
    ok = claiming & (z > 0)
    cand = rows[:, :, None] & cols[:, None, :] & (off < gate[:, None, None]) & (d > 0)
    cand = cand & ok[:, None, None]
    cx = boxes[:, 0] + 0.5 * boxes[:, 2]
    x = jnp.arange(width, dtype=jnp.float32) + 0.5
    lateral = jnp.abs(x[None] - cx[:, None]) / jnp.maximum(0.5 * boxes[:, 2:3], 1.0)  # [K, W]
    cost = off / jnp.maximum(gate, 1.0)[:, None, None] + lateral[:, None, :]
    cost = jnp.where(cand, cost, jnp.inf)
    best = jnp.argmin(cost, axis=0).astype(jnp.int32)
    return jnp.where(jnp.any(cand, axis=0), best, -1)


def slot_depths(
    rgbd_params, depth: Array, owner: Array, z: Array, gate: Array, margins, scene: Array
) -> Array:
    """``[K, H, W]`` uint16: the depth image each slot's filter sees (module docstring):
    the pixels another target claims are put ``margins`` occluder margins nearer than the
    slot's target (``claim.fake_margins``; kept when nearer already) when that target is
    at its depth or nearer, else given the depth of the scene behind, ``scene [H, W]`` mm
    (the background model's; 0 where it has none): for a nearer target a farther person is
    part of the background, and a slot searching for its lost target cannot take him."""
    d = depth.astype(jnp.float32)
    z_owner = jnp.where(owner >= 0, z[jnp.maximum(owner, 0)], 0.0)  # [H, W]
    fake = jnp.maximum(z - margins * occluder_margin(rgbd_params, z), 1.0)  # [K]
    k = jnp.arange(z.shape[0])
    other = (owner[None] >= 0) & (owner[None] != k[:, None, None]) & (z > 0)[:, None, None]
    in_front = z_owner[None] < (z + gate)[:, None, None]
    occluder = jnp.minimum(d[None], fake[:, None, None])
    out = jnp.where(other, jnp.where(in_front, occluder, scene[None]), d[None])
    return jnp.round(out).astype(depth.dtype)


def claimed_mask(depth: Array, boxes: Array, z: Array, gate: Array, claiming: Array) -> Array:
    """``[H, W] bool``: the pixels that the ``claiming [K]`` targets explain, for the
    detector of new people: inside a (grown) box with depth within its target's tolerance,
    or without depth (a dark head, a window behind him: nobody can tell)."""
    height, width = depth.shape
    d = depth.astype(jnp.float32)
    rows, cols = _inside(boxes, height, width)
    near = (jnp.abs(d[None] - z[:, None, None]) < gate[:, None, None]) | (d[None] <= 0)
    mine = rows[:, :, None] & cols[:, None, :] & near & (claiming & (z > 0))[:, None, None]
    return jnp.any(mine, axis=0)


def _fill_runs(mask: Array, reached: Array) -> Array:
    """``reached`` grown to every ``mask`` pixel of a run (along the last axis) that holds a
    reached pixel: a run's pixels carry its index, and a pixel is reached when the nearest
    reached pixel on its left or on its right carries its own."""
    start = mask & ~jnp.pad(mask, [(0, 0)] * (mask.ndim - 1) + [(1, 0)])[..., :-1]
    run = jnp.cumsum(start, axis=-1, dtype=jnp.int32)
    seed = mask & reached
    left = jax.lax.cummax(jnp.where(seed, run, -1), axis=mask.ndim - 1)
    big = jnp.iinfo(jnp.int32).max
    right = jax.lax.cummin(jnp.where(seed, run, big), axis=mask.ndim - 1, reverse=True)
    return mask & ((left == run) | (right == run))


def joined(mask: Array, seeds: Array, max_rounds: int = 16) -> Array:
    """``[..., H, W] bool``: the ``mask`` pixels 4-connected within ``mask`` to a ``seeds``
    pixel (seeds off the mask join nothing). Row runs and column runs are filled in turn
    until nothing changes (at most ``max_rounds`` rounds of both; a blob reached in fewer
    turns of its outline is exact)."""

    def fill(reached):
        rows = _fill_runs(mask, reached)
        return jnp.swapaxes(
            _fill_runs(jnp.swapaxes(mask, -1, -2), jnp.swapaxes(rows, -1, -2)), -1, -2
        )

    def cond(c):
        reached, last, n = c
        return jnp.any(reached != last) & (n < max_rounds)

    def body(c):
        reached, _, n = c
        return fill(reached), reached, n + 1

    first = mask & seeds
    reached, _, _ = jax.lax.while_loop(cond, body, (fill(first), first, jnp.int32(1)))
    return reached


def blob_reach(foreground: Array, depth: Array, owner: Array, z: Array, gate: Array) -> Array:
    """``[K, H, W] bool``: for each target, the ``foreground [H, W]`` pixels within ``gate
    [K]`` of its depth ``z [K]`` (mm) joined at that depth to the pixels it owns (``owner
    [H, W]``, ``claim_owner``): one depth-connected blob is one person, so the part of a
    person that a narrow box leaves unclaimed is still his."""
    d = depth.astype(jnp.float32)
    k = jnp.arange(z.shape[0])
    near = jnp.abs(d[None] - z[:, None, None]) < gate[:, None, None]
    mask = (foreground & (d > 0))[None] & near & (z > 0)[:, None, None]
    return joined(mask, owner[None] == k[:, None, None])


def _own_pixels(foreground, depth, owner, z, gate, reach):
    """``[K, H, W] bool``: each target's own pixels (``evidence``'s docstring)."""
    d = depth.astype(jnp.float32)
    k = jnp.arange(z.shape[0])
    near = jnp.abs(d[None] - z[:, None, None]) < gate[:, None, None]
    free = (owner[None] < 0) | (owner[None] == k[:, None, None])
    if reach is not None:
        n_reach = jnp.sum(reach, axis=0, dtype=jnp.int32)  # [H, W]
        others = n_reach[None] - reach.astype(jnp.int32)
        free = free & ((others == 0) | reach)
    return (foreground & (d > 0))[None] & near & free & (z > 0)[:, None, None]


def _count_inside(rows: Array, mask: Array, cols: Array) -> Array:
    """``[K]``: the ``mask [K, H, W]`` pixels inside each box (``rows [K, H]``, ``cols [K, W]``)."""
    f = jnp.float32
    return jnp.einsum("kh,khw,kw->k", rows.astype(f), mask.astype(f), cols.astype(f))


def evidence(
    foreground: Array,
    depth: Array,
    owner: Array,
    boxes: Array,
    z: Array,
    gate: Array,
    reach: Array | None = None,
) -> Array:
    """``[K]``: the share of each box ``[K, 4]`` (xywh) that its own target explains: the
    ``foreground [H, W]`` pixels within ``gate [K]`` of its depth ``z [K]`` (mm) that no
    other target owns (``owner [H, W]``, ``claim_owner``) nor, given ``reach [K, H, W]``
    (``blob_reach``), joins at its depth without the target joining them too. A target
    whose box holds little of it is not seen, whatever its filter reports: the pixels a
    nearer target claims are that target's, the rest of a claimed person's blob is his,
    and the floor or a farther person left in the box are not him."""
    rows, cols = _inside(boxes, *depth.shape)
    own = _own_pixels(foreground, depth, owner, z, gate, reach)
    return _count_inside(rows, own, cols) / jnp.maximum(boxes[:, 2] * boxes[:, 3], 1.0)


class Visible(NamedTuple):
    hidden: Array  # [K] share of the box that nearer targets claim
    evidence: Array  # [K] share of the rest of the box that the target's own pixels fill
    box: Array  # [K, 4] xywh, the tight box of its own pixels in the box (zeros: none)


def visible_part(
    foreground: Array,
    depth: Array,
    owner: Array,
    boxes: Array,
    z: Array,
    gate: Array,
    reach: Array | None = None,
) -> Visible:
    """What of each target shows in its box ``[K, 4]`` (xywh, e.g. the predicted one) under
    depth-ordered occlusion: the share of the box that the pixels of nearer targets
    (``owner [H, W]`` at a depth under ``z [K]``) cover, the share of the rest that its own
    pixels fill (``evidence``'s, with ``reach``), and their tight box. A target behind a
    nearer one is seen when the part of his box left in view is his: his head above the
    other's shoulder explains his box as well as his whole body would without her."""
    height, width = depth.shape
    rows, cols = _inside(boxes, height, width)
    own = _own_pixels(foreground, depth, owner, z, gate, reach)
    own = own & rows[:, :, None] & cols[:, None, :]
    z_owner = jnp.where(owner >= 0, z[jnp.maximum(owner, 0)], jnp.inf)  # [H, W]
    k = jnp.arange(z.shape[0])
    front = (owner[None] >= 0) & (owner[None] != k[:, None, None])
    front = front & (z_owner[None] < z[:, None, None])
    area = jnp.maximum(boxes[:, 2] * boxes[:, 3], 1.0)
    # At most 1: a box a few pixels across can hold more pixel centres than its area.
    hidden = jnp.minimum(_count_inside(rows, front, cols) / area, 1.0)
    n_own = jnp.sum(own, axis=(1, 2), dtype=jnp.float32)
    shown = n_own / jnp.maximum(area * (1.0 - hidden), 1.0)
    r = jnp.any(own, axis=2)  # [K, H]
    c = jnp.any(own, axis=1)  # [K, W]
    y0 = jnp.argmax(r, axis=1)
    y1 = height - jnp.argmax(r[:, ::-1], axis=1)
    x0 = jnp.argmax(c, axis=1)
    x1 = width - jnp.argmax(c[:, ::-1], axis=1)
    box = jnp.stack([x0, y0, x1 - x0, y1 - y0], axis=-1).astype(jnp.float32)
    box = jnp.where((n_own > 0)[:, None], box, 0.0)
    return Visible(hidden, shown, box)


def same_place(
    a: Array, za: Array, ga: Array, b: Array, zb: Array, gb: Array, share: Array
) -> Array:
    """``[A, B] bool``: boxes ``a [A, 4]`` and ``b [B, 4]`` (xywh) at known depths ``za
    [A]`` and ``zb [B]`` (mm) within the larger of their gates ``ga [A]``, ``gb [B]`` of
    each other whose column spans overlap by at least ``share`` of the narrower one: one
    person, since two people at one depth do not stand in one place (one box may hold his
    trunk and the other his legs)."""
    x0 = jnp.maximum(a[:, None, 0], b[None, :, 0])
    x1 = jnp.minimum(a[:, None, 0] + a[:, None, 2], b[None, :, 0] + b[None, :, 2])
    narrower = jnp.maximum(jnp.minimum(a[:, None, 2], b[None, :, 2]), 1.0)
    known = (za[:, None] > 0) & (zb[None] > 0)
    near = jnp.abs(za[:, None] - zb[None]) < jnp.maximum(ga[:, None], gb[None])
    return (jnp.maximum(x1 - x0, 0.0) / narrower >= share) & known & near


def box_depths(config, obs, boxes: Array) -> Array:
    """``[K]`` mm: the median depth of the foreground in each box ``[K, 4]`` of one
    observation (``rgbd.observe.observe``; 0 where there is none), from its log-spaced depth
    bins. Two boxes on one person measure one depth here, whatever each slot's templates
    have learnt."""
    rects = box_ops.xywh_to_rect(boxes)
    counts = box_histograms(obs.depth_bins, rects, config.depth_bins)
    return histogram_quantile(counts, config.depth_bins, *config.depth_range)[0]
