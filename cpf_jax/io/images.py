"""Reading colour and depth images from disk, with errors that name the file.

Colour comes back as ``[H, W, 3] uint8`` RGB, depth as ``[H, W] uint16``
millimetres (0 = missing). Depth decoders turn a dataset's stored values into
millimetres: Princeton's bit rotation, TUM's 5,000-per-metre scale.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from cpf_jax.errors import SourceError

__all__ = [
    "IMAGE_SUFFIXES",
    "read_colour",
    "read_depth",
    "depth_millimetres",
    "princeton_depth",
    "tum_depth",
    "natural_key",
    "list_images",
]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm", ".tif", ".tiff")

DepthDecoder = Callable[[np.ndarray], np.ndarray]

# Floating-point depth whose largest value is at most this is in metres (no room of people
# is 20 mm deep; no depth camera sees 20 m).
_METRES_MAX = 20.0
# Integer millimetres whose median is above this (8 m, beyond the range depth cameras
# measure people at) are in another unit (TUM's 5,000 per metre puts a wall at 2 m at 10,000).
_MM_MEDIAN_MAX = 8000.0


def natural_key(name: str) -> tuple:
    """Sort key that orders ``img2`` before ``img10`` (numbers compared as numbers)."""
    return tuple(int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name))


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, in natural order (hidden files skipped)."""
    files = [
        p
        for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


def _decode(path: Path, flags: int) -> np.ndarray:
    # imdecode on the bytes (not imread) so unreadable files raise here, without
    # OpenCV's own warning lines, and non-ASCII paths work.
    try:
        data = np.fromfile(str(path), np.uint8)
    except OSError as e:
        raise SourceError(f"{path}: cannot read file ({e.strerror or e})") from None
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise SourceError(f"{path}: not a readable image (corrupt, truncated or unknown format)")
    return image


def read_colour(path: Path | str) -> np.ndarray:
    """Read a colour image as ``[H, W, 3] uint8`` RGB (grey images are expanded to 3 channels)."""
    path = Path(path)
    bgr = _decode(path, cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[..., ::-1])


def read_depth(path: Path | str, decode: DepthDecoder | None = None) -> np.ndarray:
    """Read a single-channel depth image: a 16-bit PNG as ``[H, W] uint16`` (then
    ``decode`` to mm), or a floating-point one (32-bit TIFF) as it is stored, for
    :func:`depth_millimetres` to convert.

    Raises:
      SourceError: when the file is missing or corrupt, or is not 16-bit or floating-point
        single-channel.
    """
    path = Path(path)
    raw = _decode(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim == 2 and np.issubdtype(raw.dtype, np.floating):
        return raw
    if raw.dtype != np.uint16 or raw.ndim != 2:
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        raise SourceError(
            f"{path}: depth image must be 16-bit (mm) or floating-point (m or mm) "
            f"single-channel, got {raw.dtype} with {channels} channel(s)"
        )
    return raw if decode is None else decode(raw)


def depth_millimetres(
    depth: np.ndarray, where: str, check_median: bool = True
) -> tuple[np.ndarray, str | None]:
    """``(uint16 mm, note)``: depth in the units it came in, as the filters read it.

    ``uint16`` is millimetres already (note None); floating-point depth is metres when its
    largest finite value is at most 20, else millimetres, rounded, with NaN and inf as
    missing (0); other integers are millimetres when they fit 16 bits. ``note`` says what
    was converted.

    Raises:
      SourceError: naming ``where``, for depth that is not a number type, that does not
        fit 16-bit millimetres, or (``check_median``; a source checks its first frame)
        whose median (over 8 m) says another unit.
    """
    depth = np.asarray(depth)
    note = None
    if np.issubdtype(depth.dtype, np.floating):
        finite = np.isfinite(depth)
        valid = finite & (depth > 0)
        top = float(depth[valid].max()) if valid.any() else 0.0
        metres = top <= _METRES_MAX
        scale = 1000.0 if metres else 1.0
        if top * scale > np.iinfo(np.uint16).max:
            raise SourceError(
                f"{where}: depth up to {top:g} does not fit 16-bit millimetres (expected "
                "metres up to 20 or millimetres up to 65535)"
            )
        unit = "metres" if metres else "millimetres"
        note = f"{where}: {depth.dtype} depth read as {unit} (largest {top:g}), kept as uint16 mm"
        depth = np.where(valid, np.rint(np.where(finite, depth, 0.0) * scale), 0).astype(np.uint16)
    elif np.issubdtype(depth.dtype, np.integer) and depth.dtype != np.uint16:
        lo, hi = (int(depth.min()), int(depth.max())) if depth.size else (0, 0)
        if lo < 0 or hi > np.iinfo(np.uint16).max:
            raise SourceError(
                f"{where}: {depth.dtype} depth from {lo} to {hi} does not fit 16-bit millimetres"
            )
        depth = depth.astype(np.uint16)
    elif depth.dtype != np.uint16:
        raise SourceError(f"{where}: depth must be a number image (mm or m), got {depth.dtype}")
    valid = depth[depth > 0] if check_median else depth[:0]
    median = float(np.median(valid)) if valid.size else 0.0
    if median > _MM_MEDIAN_MAX:
        raise SourceError(
            f"{where}: the median depth is {median:g}, i.e. {median / 1000:g} m if millimetres: "
            "the values are in another unit (TUM stores 5,000 per metre: give the folder its "
            "rgb.txt and depth.txt to be read as TUM); convert them to millimetres"
        )
    return depth, note


def princeton_depth(raw: np.ndarray) -> np.ndarray:
    """Princeton RGB-D benchmark depth is stored bit-rotated: ``(raw >> 3) | (raw << 13)``."""
    raw = raw.astype(np.uint16, copy=False)
    return (raw >> np.uint16(3)) | (raw << np.uint16(13))


def tum_depth(raw: np.ndarray) -> np.ndarray:
    """TUM RGB-D depth: 5,000 per metre, i.e. 5 per millimetre; rounded to whole mm."""
    return np.round(raw.astype(np.float32) / 5.0).astype(np.uint16)
