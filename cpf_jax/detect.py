"""Find a person to start tracking: the largest person-shaped foreground blob.

A live camera has no ground truth, and a recording may have none: ``cpf-track
--init auto`` starts the track on the first frame where this finds someone. It runs once
per frame until it does, on the host (NumPy and OpenCV), not inside the jitted filter.

Usage::

    background = median_background(colour_frames, depth_frames)  # an empty scene
    box = find_person(frame, background)        # [4] xywh float32, or None

Rules (:class:`DetectConfig`):

1. Foreground against the background model, as the RGB-D filter sees it
   (``kernels.background.foreground_mask``: nearer than the background by
   ``max(depth_abs, depth_rel * z)``, or a colour change where depth is missing).
2. A morphological opening (``open_px``) removes speckle; a closing (``close_px``)
   joins a body that a thin background gap split.
3. 8-connected components. Each is cut to its main depth: the pixels within
   ``max(depth_gap, depth_gap_rel * z)`` of its median depth, keeping the largest
   connected part, so two people side by side at different depths (or a person and the
   chair he touches) are not one blob; the rest is examined again as blobs of its own.
   Colour-only pixels (no depth) stay with the main part.
4. A person is at least ``min_area`` of the frame and ``min_height`` of its height,
   and no wider than ``max_aspect`` times his height (head and shoulders cut by the
   frame's edge are about as wide as tall; a row of desks is not).

The largest qualifying blob wins; its tight box is returned.

:func:`find_person_scored` also says how sure it is (:func:`person_confidence`): the
product of four shares in [0, 1], each 1 for an upright body seen whole, fill (the blob's
share of its box, full from 40 %), uprightness (height over width, full from 1.8), height
(of the frame's, full from 30 %) and 0.6 for each frame edge the box touches. A head in a
corner, head and shoulders cut by the frame, or a row of chairs score low.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import cv2
import jax
import numpy as np

from cpf_jax.kernels.background import Background, foreground_mask
from cpf_jax.kernels.blobs import confidence_shares, person_shaped
from cpf_jax.types import Frame

__all__ = [
    "DetectConfig",
    "Detection",
    "clean_mask",
    "find_person",
    "find_person_scored",
    "mask_person_boxes",
    "person_boxes",
    "person_confidence",
]


@dataclass(frozen=True)
class DetectConfig:
    """Thresholds of :func:`person_boxes` (module docstring)."""

    depth_abs: float = 150.0  # mm: foreground when nearer than the background by this ...
    depth_rel: float = 0.05  # ... or this fraction of the background depth
    colour_threshold: float = 40.0  # uint8 levels, where depth is missing
    open_px: int = 3
    close_px: int = 7
    depth_gap: float = 300.0  # mm: a blob is cut to its median depth +- this ...
    depth_gap_rel: float = 0.1  # ... or this fraction of it
    min_area: float = 0.004  # share of the frame's pixels
    min_height: float = 0.15  # share of the frame's height
    max_aspect: float = 1.3  # width / height

    def __post_init__(self) -> None:
        if self.open_px < 1 or self.close_px < 1:
            raise ValueError(
                f"open_px and close_px must be >= 1, got {self.open_px}, {self.close_px}"
            )
        if not (0 < self.min_area < 1 and 0 < self.min_height <= 1 and self.max_aspect > 0):
            raise ValueError(
                "min_area must be in (0, 1), min_height in (0, 1] and max_aspect > 0, got "
                f"{self.min_area}, {self.min_height}, {self.max_aspect}"
            )


@lru_cache(maxsize=8)
def _mask_fn(depth_abs: float, depth_rel: float, colour_threshold: float):
    return jax.jit(
        lambda c, d, bg: foreground_mask(
            c, d, bg, depth_abs=depth_abs, depth_rel=depth_rel, colour_threshold=colour_threshold
        )
    )


def _largest_component(mask: np.ndarray) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, bool)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k


def _foreground(colour: np.ndarray, depth: np.ndarray, background: Background, c: DetectConfig):
    """``[H, W] uint8`` foreground after the opening and the closing (rules 1 and 2)."""
    fg = np.asarray(
        _mask_fn(c.depth_abs, c.depth_rel, c.colour_threshold)(colour, depth, background)
    )
    return clean_mask(fg, c)


def clean_mask(mask: np.ndarray, config: DetectConfig = DetectConfig()) -> np.ndarray:
    """``[H, W] uint8`` foreground ``mask`` after the opening and the closing (rule 2)."""
    fg = np.asarray(mask).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((config.open_px, config.open_px), np.uint8))
    kernel = np.ones((config.close_px, config.close_px), np.uint8)
    return cv2.morphologyEx(fg, cv2.MORPH_CLOSE, kernel)


def _main_depth_part(blob: np.ndarray, z: np.ndarray, c: DetectConfig):
    """``(main, rest)``: the largest connected part of ``blob`` near its median depth (with
    its colour-only pixels), and what is left of the blob, or None when nothing is cut
    (rule 3). Each cut leaves a non-empty part, so cutting the rest again terminates."""
    measured = blob & (z > 0)
    if measured.sum() < 0.2 * blob.sum():
        return blob, None
    med = float(np.median(z[measured]))
    near = np.abs(z - med) <= max(c.depth_gap, c.depth_gap_rel * med)
    main = _largest_component(blob & (near | (z == 0)))
    if 0 < main.sum() < blob.sum():
        return main, blob & ~main
    return blob, None


def _person_box(blob: np.ndarray, c: DetectConfig):
    """The tight xywh box of ``blob`` if it is person-shaped (rule 4,
    ``kernels.blobs.person_shaped``), else None."""
    ys, xs = np.nonzero(blob)
    bx, by = xs.min(), ys.min()
    bw, bh = xs.max() - bx + 1, ys.max() - by + 1
    if not person_shaped(
        bw, bh, int(blob.sum()), blob.shape, c.min_area, c.min_height, c.max_aspect
    ):
        return None
    return bx, by, bw, bh


def _blobs(frame: Frame, background: Background, config: DetectConfig) -> list:
    """``[(area, (x, y, w, h))]`` of the person-shaped blobs, largest first."""
    colour = np.asarray(frame.colour)
    depth = np.asarray(frame.depth)
    if colour.ndim != 3 or colour.shape[:2] != depth.shape:
        raise ValueError(
            f"frame: colour {colour.shape} and depth {depth.shape} must be [H, W, 3] and [H, W]"
        )
    if tuple(np.shape(background.depth)) != depth.shape:
        raise ValueError(
            f"background is {np.shape(background.depth)} but the frame is {depth.shape}"
        )
    return _mask_blobs(_foreground(colour, depth, background, config).astype(bool), depth, config)


def _mask_blobs(mask: np.ndarray, depth: np.ndarray, config: DetectConfig) -> list:
    """``[(area, (x, y, w, h))]`` of the person-shaped blobs of a foreground ``mask``
    (rules 3 and 4), largest first."""
    h, w = depth.shape
    z = depth.astype(np.float32)
    min_px = config.min_area * h * w
    found = []
    queue = [mask]  # unexamined masks
    while queue:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(
            queue.pop().astype(np.uint8), connectivity=8
        )
        for k in range(1, n):
            if stats[k, cv2.CC_STAT_AREA] < min_px:
                continue
            blob, rest = _main_depth_part(labels == k, z, config)
            if rest is not None:
                queue.append(rest)
            box = _person_box(blob, config)
            if box is not None:
                found.append((int(blob.sum()), box))
    found.sort(key=lambda t: -t[0])
    return found


def mask_person_boxes(
    mask: np.ndarray, depth: np.ndarray, config: DetectConfig = DetectConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """``([K, 4] float32 xywh boxes, [K] int64 pixel counts)`` of the person-shaped blobs of
    a foreground ``mask [H, W]`` (already opened and closed, or as the caller wants it),
    largest first: rules 3 and 4 of the module docstring on a mask the caller made, e.g.
    the foreground that no tracked person claims (``cpf_jax.multi``)."""
    mask = np.asarray(mask, bool)
    depth = np.asarray(depth)
    if mask.shape != depth.shape:
        raise ValueError(f"mask {mask.shape} and depth {depth.shape} must both be [H, W]")
    found = _mask_blobs(mask, depth, config)
    boxes = np.asarray([b for _, b in found], np.float32).reshape(-1, 4)
    return boxes, np.asarray([a for a, _ in found], np.int64)


def person_boxes(
    frame: Frame, background: Background, config: DetectConfig = DetectConfig()
) -> np.ndarray:
    """``[K, 4]`` float32 xywh boxes of the person-shaped foreground blobs, largest first.

    ``frame``: one registered frame (``colour [H, W, 3] uint8``, ``depth [H, W] uint16``
    mm, zeros where missing); ``background``: its scene without people
    (``kernels.background.median_background``). Rules in the module docstring.
    """
    found = _blobs(frame, background, config)
    return np.asarray([b for _, b in found], np.float32).reshape(-1, 4)


class Detection(NamedTuple):
    """A person found by :func:`find_person_scored`."""

    box: np.ndarray  # [4] float32 xywh
    confidence: float  # in [0, 1] (person_confidence)
    doubts: tuple[str, ...]  # what lowered it, in words


def person_confidence(box, area: int, frame_hw: tuple[int, int]) -> tuple[float, tuple[str, ...]]:
    """``(confidence, doubts)`` that the blob of ``area`` pixels with tight ``box`` is a
    whole upright person (module docstring; the shares of
    ``kernels.blobs.confidence_shares``), and what lowered it, in words."""
    x, y, w, h = (float(v) for v in box)
    frame_h, frame_w = frame_hw
    shares = np.asarray(confidence_shares(np.float32([x, y, w, h]), area, frame_hw), np.float64)
    edges = [
        name
        for name, touches in (
            ("left", x <= 0),
            ("top", y <= 0),
            ("right", x + w >= frame_w),
            ("bottom", y + h >= frame_h),
        )
        if touches
    ]
    doubts = (
        f"it fills {100 * area / max(w * h, 1.0):.0f} % of its box",
        f"it is about as wide as tall (height / width {h / max(w, 1.0):.1f})",
        f"it is {100 * h / frame_h:.0f} % of the frame's height",
        f"the frame's {' and '.join(edges)} edge cuts it",
    )
    confidence = float(np.prod(shares))
    return confidence, tuple(why for why, share in zip(doubts, shares, strict=True) if share < 1)


def find_person_scored(
    frame: Frame, background: Background, config: DetectConfig = DetectConfig()
) -> Detection | None:
    """The largest person-shaped blob (:func:`find_person`) with its confidence, or None."""
    found = _blobs(frame, background, config)
    if not found:
        return None
    area, box = found[0]
    confidence, doubts = person_confidence(box, area, np.shape(frame.depth))
    return Detection(np.asarray(box, np.float32), confidence, doubts)


def find_person(
    frame: Frame, background: Background, config: DetectConfig = DetectConfig()
) -> np.ndarray | None:
    """``[4]`` float32 xywh box of the largest person-shaped blob, or None."""
    boxes = person_boxes(frame, background, config)
    return boxes[0] if len(boxes) else None
