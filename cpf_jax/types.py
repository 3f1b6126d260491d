"""Frames and cameras: one registered RGB-D frame, pinhole intrinsics, and the checks a
filter makes of a frame and of an initial box."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = [
    "Frame",
    "Intrinsics",
    "KINECT_V2_DEPTH",
    "check_box",
    "check_frame",
    "check_intrinsics",
    "nominal_intrinsics",
    "usable_box",
]


class Frame(NamedTuple):
    """One registered RGB-D frame.

    colour: ``[H, W, 3] uint8``, RGB order.
    depth: ``[H, W] uint16``, millimetres, 0 = missing. Colour-only sources
    give an all-zero depth of the same size.
    """

    colour: Array
    depth: Array


class Intrinsics(NamedTuple):
    """Pinhole intrinsics, 0-based pixel convention: ``u = fx * X / Z + cx``."""

    fx: float
    fy: float
    cx: float
    cy: float


# Kinect v2 depth camera, thesis Table 4.1 (512 x 424 depth image).
KINECT_V2_DEPTH = Intrinsics(fx=365.0, fy=365.0, cx=255.0, cy=205.0)
KINECT_V2_SIZE = (512, 424)  # width, height

# Principal points lie within this share of the frame's size of its centre.
_CENTRE_TOLERANCE = 0.1


def nominal_intrinsics(width: int, height: int) -> Intrinsics:
    """Intrinsics for frames of a camera nobody described: Kinect v2 depth's at its own
    512 x 424, else its horizontal field of view (70.1 degrees, ``fx = 365 * width / 512``)
    with square pixels and the principal point at the frame's centre. A guess, for 3D in
    millimetres that are roughly right; a caller says so (``cpf-track`` warns)."""
    if (width, height) == KINECT_V2_SIZE:
        return KINECT_V2_DEPTH
    f = KINECT_V2_DEPTH.fx * width / KINECT_V2_SIZE[0]
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def check_intrinsics(intrinsics: Intrinsics, frame_hw: tuple[int, int], where: str = "") -> None:
    """``ValueError`` when the principal point of ``intrinsics`` is not within 10 % of the
    size of the centre of a ``frame_hw = (height, width)`` frame: intrinsics of another
    camera or image size (the Kinect v2 default on 640 x 480 frames), which would put
    every 3D point in the wrong place without any other sign."""
    h, w = frame_hw
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if abs(cx - (w - 1) / 2) <= _CENTRE_TOLERANCE * w and abs(cy - (h - 1) / 2) <= (
        _CENTRE_TOLERANCE * h
    ):
        return
    lead = f"{where}: " if where else ""
    raise ValueError(
        f"{lead}intrinsics with the principal point at ({cx:g}, {cy:g}) do not belong to "
        f"{w}x{h} frames (its centre is ({(w - 1) / 2:g}, {(h - 1) / 2:g})); give the "
        "camera's own, or cpf_jax.types.nominal_intrinsics(width, height) as a rough guess"
    )


def check_box(box, frame_hw: tuple[int, int], where: str = "") -> np.ndarray:
    """``box`` (x, y, w, h) as ``float32 [4]`` if it can start a track, else ``ValueError``.

    A box that cannot: not four finite numbers, a side under 2 px, or less than 2 x 2 px
    of it inside the ``frame_hw = (height, width)`` frame. ``where`` (a file, a sequence)
    starts the message. The filters' ``init`` calls it when the box is a concrete value;
    under ``jit`` see :func:`usable_box`.
    """
    lead = f"{where}: " if where else ""
    b = np.asarray(box, np.float64).reshape(-1)
    if b.shape != (4,) or not np.all(np.isfinite(b)):
        raise ValueError(f"{lead}initial box must be four finite numbers x,y,w,h, got {box}")
    x, y, bw, bh = (float(v) for v in b)
    text = f"{x:g},{y:g},{bw:g},{bh:g}"
    if bw < 2 or bh < 2:
        raise ValueError(f"{lead}initial box {text} is smaller than 2x2 px")
    h, w = frame_hw
    if min(x + bw, w) - max(x, 0.0) < 2 or min(y + bh, h) - max(y, 0.0) < 2:
        raise ValueError(f"{lead}initial box {text} lies outside the {w}x{h} frame")
    return b.astype(np.float32)


def check_frame(frame: Frame, needs_depth: bool = False) -> None:
    """``ValueError`` unless ``frame.colour`` is ``[H, W, 3] uint8`` and, with ``needs_depth``
    (the models that read depth), ``frame.depth`` is ``[H, W]`` integer millimetres (float
    depth is most often metres, which would read as 1-5 mm). The colour layer never
    reads depth, so it takes raw depth of another size or ``None``. Shapes and dtypes are
    static, so the filters' ``init`` and ``step`` check them under ``jit`` too (once, while
    tracing): a float image in [0, 1] or an RGBA one would otherwise be binned as if it
    were 8-bit RGB.
    """
    colour = frame.colour if hasattr(frame.colour, "dtype") else np.asarray(frame.colour)
    shape = tuple(colour.shape)
    if len(shape) != 3 or shape[-1] != 3 or colour.dtype != np.uint8:
        raise ValueError(
            f"frame colour must be [H, W, 3] uint8 RGB, got {colour.dtype} of shape {shape}"
        )
    if not needs_depth:
        return
    if frame.depth is None:
        raise ValueError("frame depth is None: the RGB-D models need [H, W] depth in mm")
    depth_shape = tuple(np.shape(frame.depth))
    depth = frame.depth if hasattr(frame.depth, "dtype") else np.asarray(frame.depth)
    dtype = np.dtype(depth.dtype)
    if not np.issubdtype(dtype, np.integer):
        raise ValueError(
            f"frame depth is {dtype}: the RGB-D models read integer millimetres (uint16, "
            "0 = missing); convert metres with cpf_jax.io.depth_millimetres(depth, name)"
        )
    if depth_shape != shape[:2]:
        raise ValueError(
            f"frame depth must be [H, W] = {list(shape[:2])} like the colour, got shape "
            f"{list(depth_shape)}"
        )


def usable_box(box: Array, frame: Frame) -> tuple[Array, Array]:
    """``(box, ok)`` for a filter's ``init``: a concrete box is checked (``check_box``,
    ``ValueError``); under ``jit`` or ``vmap`` a box that is not finite or has a side
    under 1 px becomes the whole frame, with ``ok`` False (the colour filter's state then
    starts lost), so that no NaN reaches the estimates."""
    height, width = frame.colour.shape[:2]
    if not isinstance(box, jax.core.Tracer):
        check_box(box, (height, width))
    box = jnp.asarray(box, jnp.float32)
    ok = jnp.all(jnp.isfinite(box)) & (box[2] >= 1.0) & (box[3] >= 1.0)
    whole = jnp.array([0.0, 0.0, width, height], jnp.float32)
    return jnp.where(ok, box, whole), ok
