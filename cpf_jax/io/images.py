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
    "princeton_depth",
    "tum_depth",
    "natural_key",
    "list_images",
]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm", ".tif", ".tiff")

DepthDecoder = Callable[[np.ndarray], np.ndarray]


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
    """Read a 16-bit single-channel depth PNG as ``[H, W] uint16`` (then ``decode`` to mm).

    Raises:
      SourceError: when the file is missing or corrupt, or is not 16-bit single-channel.
    """
    path = Path(path)
    raw = _decode(path, cv2.IMREAD_UNCHANGED)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        raise SourceError(
            f"{path}: depth image must be 16-bit single-channel, "
            f"got {raw.dtype} with {channels} channel(s)"
        )
    return raw if decode is None else decode(raw)


def princeton_depth(raw: np.ndarray) -> np.ndarray:
    """Princeton RGB-D benchmark depth is stored bit-rotated: ``(raw >> 3) | (raw << 13)``."""
    raw = raw.astype(np.uint16, copy=False)
    return (raw >> np.uint16(3)) | (raw << np.uint16(13))


def tum_depth(raw: np.ndarray) -> np.ndarray:
    """TUM RGB-D depth: 5,000 per metre, i.e. 5 per millimetre; rounded to whole mm."""
    return np.round(raw.astype(np.float32) / 5.0).astype(np.uint16)
