"""New people: the person detector on the foreground no target claims, and free slots for them.

The detector is the host's (:func:`host_candidates`: :mod:`cpf_jax.detect`'s opening and
closing, connected blobs cut to one depth, person-shaped; OpenCV), called from the jitted
step through ``jax.pure_callback``, or with ``MultiConfig.device_births`` the same rules in
JAX (``kernels.blobs.person_blobs``, :func:`device_candidates`: no host round trip, on
blocks of pixels, so blobs a few pixels apart can join), on the mask of foreground pixels
that no confirmed or tentative target explains (``claim.claimed_mask``). At most
``MultiConfig.max_births`` blobs, largest first, come back as fixed-size arrays. A blob
starts a tentative target when its confidence (``detect.person_confidence``) reaches
``life.birth_confidence``, it is at least ``life.birth_aspect`` as wide as tall (narrower:
a limb, or a sliver of someone at the frame's edge) and it is not part of a found target
(``part_of_found``); a blob that is part of one (within its box grown by
``claim.reanchor_margin``, at least ``claim.reanchor_aspect`` as wide as tall) and makes
its box larger starts that target again on the union (``reanchor``: he walked into view
legs first). Each new target takes a free slot, or the slot of the lost target closest to
being forgotten when none is free.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.detect import DetectConfig, clean_mask, mask_person_boxes, person_confidence
from cpf_jax.kernels.background import Background, behind_plane, side_scene
from cpf_jax.kernels.blobs import detector_block, person_blobs
from cpf_jax.multi.claim import same_place
from cpf_jax.multi.config import FREE, LOST, MultiConfig
from cpf_jax.rgbd.observe import no_background
from cpf_jax.types import Frame

__all__ = [
    "Candidates",
    "host_candidates",
    "callback_candidates",
    "detect_candidates",
    "device_candidates",
    "frame_scene",
    "part_of_found",
    "reanchor",
    "free_slot_order",
    "allocate",
]


class Candidates(NamedTuple):
    box: Array  # [D, 4] xywh of the person-shaped blobs, largest first (zeros: none)
    confidence: Array  # [D] detect.person_confidence (0: no blob)
    depth: Array  # [D] mm, median depth of the blob's pixels in its box (0: none)


def host_candidates(
    config: DetectConfig, n: int, mask: np.ndarray, depth: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Candidates`` fields (NumPy, ``n`` rows) of the person-shaped blobs of a foreground
    ``mask [H, W]`` over ``depth [H, W]`` mm: :func:`detect_candidates` on the host
    (``detect.clean_mask`` and ``detect.mask_person_boxes``), its reference."""
    mask = np.asarray(mask, bool)
    depth = np.asarray(depth)
    clean = clean_mask(mask, config).astype(bool)
    boxes, areas = mask_person_boxes(clean, depth, config)
    out = np.zeros((n, 4), np.float32)
    conf = np.zeros((n,), np.float32)
    z = np.zeros((n,), np.float32)
    for i, (box, area) in enumerate(zip(boxes[:n], areas[:n], strict=True)):
        out[i] = box
        conf[i], _ = person_confidence(box, int(area), depth.shape)
        x, y, w, h = (int(v) for v in box)
        patch = depth[y : y + h, x : x + w]
        pix = patch[clean[y : y + h, x : x + w] & (patch > 0)]
        z[i] = float(np.median(pix)) if pix.size else 0.0
    return out, conf, z


#: Rounds of the depth cut (``kernels.blobs.person_blobs``): a person, the chair he
#: touches and a second person behind both are three.
CUT_ROUNDS = 3


def callback_candidates(config: DetectConfig, n: int, mask: Array, depth: Array) -> Candidates:
    """:func:`host_candidates` from inside ``jit``, ``vmap`` (one host call per item) and
    ``lax.scan``; a mask with fewer pixels than the detector's least person (``min_area``)
    is not sent to the host."""
    shapes = (
        jax.ShapeDtypeStruct((n, 4), jnp.float32),
        jax.ShapeDtypeStruct((n,), jnp.float32),
        jax.ShapeDtypeStruct((n,), jnp.float32),
    )

    def call(mask, depth):
        return jax.pure_callback(
            functools.partial(host_candidates, config, n),
            shapes,
            mask,
            depth,
            vmap_method="sequential",
        )

    def nobody(mask, depth):
        return tuple(jnp.zeros(s.shape, s.dtype) for s in shapes)

    enough = jnp.sum(mask) >= config.min_area * mask.size
    return Candidates(*jax.lax.cond(enough, call, nobody, mask, depth))


def detect_candidates(
    config: DetectConfig, n: int, mask: Array, depth: Array, on_device: bool = False
) -> Candidates:
    """The ``n`` largest person-shaped blobs of ``mask [H, W] bool`` over ``depth [H, W]``
    mm (module docstring): :func:`device_candidates` with ``on_device``, else
    :func:`callback_candidates`."""
    if on_device:
        return device_candidates(config, n, mask, depth)
    return callback_candidates(config, n, mask, depth)


def device_candidates(config: DetectConfig, n: int, mask: Array, depth: Array) -> Candidates:
    """The ``n`` largest person-shaped blobs of ``mask [H, W] bool`` over ``depth [H, W]``
    mm (module docstring), pure JAX (``jit``, ``vmap``, ``lax.scan``); on blocks of
    ``kernels.blobs.detector_block(W)`` pixels. A mask with fewer pixels than the
    detector's least person (``min_area``) is not examined."""
    block = detector_block(mask.shape[-1])

    def examine(mask, depth):
        box, _, z, confidence = person_blobs(
            mask,
            depth,
            n,
            open_px=config.open_px,
            close_px=config.close_px,
            depth_gap=config.depth_gap,
            depth_gap_rel=config.depth_gap_rel,
            min_area=config.min_area,
            min_height=config.min_height,
            max_aspect=config.max_aspect,
            block=block,
            rounds=CUT_ROUNDS,
        )
        return Candidates(box, confidence, z)

    def nobody(mask, depth):
        return Candidates(
            jnp.zeros((n, 4), jnp.float32),
            jnp.zeros((n,), jnp.float32),
            jnp.zeros((n,), jnp.float32),
        )

    # Fewer foreground pixels than the least person: nobody (unbatched, not examined).
    enough = jnp.sum(mask) >= config.min_area * mask.size
    return jax.lax.cond(enough, examine, nobody, mask, depth)


def frame_scene(config: MultiConfig, frame: Frame) -> Background:
    """The scene without people read in ``frame`` itself, for a tracker without a
    background model (``config.scene_width`` set): every pixel unseen (``no_background``,
    so each slot's RGB-D filter reads its own scene, ``rgbd.filter.unseen_scene``), its
    depth the row's scene at ``config.rgbd.side_scene`` times a person's width
    (``kernels.background.side_scene``): what stands out from it, nearer, is someone."""
    offsets = jnp.asarray(config.rgbd.side_scene, jnp.float32) * config.scene_width
    return behind_plane(no_background(frame), side_scene(frame.depth, offsets))


def part_of_found(
    cand: Candidates, boxes: Array, z: Array, gate: Array, found: Array, share: Array
) -> Array:
    """``[D] bool``: candidates that share at least ``share`` of the narrower box's columns
    with the box ``[K, 4]`` of a ``found [K]`` target whose depth ``z [K]`` is within ``gate
    [K]`` of theirs: a part of someone tracked (his legs below a box that holds his trunk),
    since two people at one depth do not stand in one place."""
    gate_c = jnp.zeros_like(cand.depth)
    near = same_place(cand.box, cand.depth, gate_c, boxes, z, gate, share)
    return jnp.any(near & found[None], axis=1)


def reanchor(
    cand: Candidates,
    ok: Array,
    boxes: Array,
    grown: Array,
    z: Array,
    gate: Array,
    found: Array,
    share: Array,
    growth: Array,
) -> tuple[Array, Array]:
    """``([K] bool, [K, 4])``: found targets to start again on a larger box, and the box. A
    candidate ``ok [D]`` that is part of a found target (``part_of_found``: the rest of a
    person whose box holds only his legs, as when he walks into view; tested against the
    ``grown`` boxes) widens the target's box ``[K, 4]`` to the union of the two when that
    is at least ``growth`` times its area; each target takes the first such candidate."""
    gate_c = jnp.zeros_like(cand.depth)
    part = same_place(cand.box, cand.depth, gate_c, grown, z, gate, share)
    part = part & ok[:, None] & found[None]  # [D, K]
    first = jnp.argmax(part, axis=0)  # [K]
    has = jnp.any(part, axis=0)
    c = cand.box[first]
    x0 = jnp.minimum(c[:, 0], boxes[:, 0])
    y0 = jnp.minimum(c[:, 1], boxes[:, 1])
    x1 = jnp.maximum(c[:, 0] + c[:, 2], boxes[:, 0] + boxes[:, 2])
    y1 = jnp.maximum(c[:, 1] + c[:, 3], boxes[:, 1] + boxes[:, 3])
    union = jnp.stack([x0, y0, x1 - x0, y1 - y0], axis=-1)
    area = jnp.maximum(boxes[:, 2] * boxes[:, 3], 1.0)
    grows = has & (union[:, 2] * union[:, 3] >= growth * area)
    return grows, union


def free_slot_order(status: Array, missed: Array, forget_after: Array) -> tuple[Array, Array]:
    """``([K] slot indices, [K] bool usable)`` in the order births take them: free slots
    first, then lost ones, those closest to being forgotten first."""
    key = jnp.where(
        status == FREE,
        -1.0,
        jnp.where(status == LOST, forget_after - missed.astype(jnp.float32), jnp.inf),
    )
    order = jnp.argsort(key).astype(jnp.int32)
    return order, jnp.isfinite(key[order])


def allocate(ok: Array, status: Array, missed: Array, forget_after: Array) -> Array:
    """``[K] int32``: the candidate (index into ``ok [D]``) each slot takes this frame, -1
    for none: the ``r``-th accepted candidate takes the ``r``-th slot of
    :func:`free_slot_order`."""
    k = status.shape[0]
    order, usable = free_slot_order(status, missed, forget_after)
    rank = jnp.cumsum(ok.astype(jnp.int32)) - 1  # [D]
    take = ok & (rank < k)
    target = jnp.where(take, order[jnp.clip(rank, 0, k - 1)], k)
    target = jnp.where(take & usable[jnp.clip(rank, 0, k - 1)], target, k)
    d = jnp.arange(ok.shape[0], dtype=jnp.int32)
    return jnp.full((k,), -1, jnp.int32).at[target].set(d, mode="drop")
