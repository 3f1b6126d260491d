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

TUM_PER_METRE = 5000.0  # TUM RGB-D's depth PNGs: 5,000 per metre

# Floating-point depth whose largest value is at most this is in metres (no room of people
# is 20 mm deep; no depth camera sees 20 m).
_METRES_MAX = 20.0
# Millimetres whose median is outside this range (0.4-8 m, where depth cameras see a room
# with people in it) are in another unit: TUM's 5,000 per metre puts a wall at 2 m at
# 10,000, centimetres put a wall nearer than 4 m under 400.
_MM_MEDIAN_MIN = 400.0
_MEDIAN_SAMPLES = 1_000_000  # evenly strided pixels the median is taken over, at most
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
    depth: np.ndarray, where: str, check_median: bool = True, per_metre: float | None = None
) -> tuple[np.ndarray, str | None]:
    """``(uint16 mm, note)``: depth in the units it came in, as the filters read it.

    ``per_metre`` (stored values per metre: 1000 for mm, 5000 for TUM, 1 for metres) scales
    any number type to millimetres. Without it the units are detected: ``uint16`` is
    millimetres already (note None); floating-point depth is metres when its largest finite
    value is at most 20, else millimetres; other integers are millimetres when they fit 16
    bits. NaN, inf and values <= 0 are missing (0); ``note`` says what was detected and
    converted (None when nothing was guessed).

    Raises:
      SourceError: naming ``where``, for depth that is not a number type, that does not
        fit 16-bit millimetres, or (``check_median``; a source checks its first frame)
        whose median (under 0.4 m or over 8 m) says another unit.
    """
    depth = np.asarray(depth)
    if not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise SourceError(f"{where}: depth must be a number image (mm or m), got {depth.dtype}")
    note = None
    if per_metre is not None:
        depth, _ = _scaled_mm(depth, where, 1000.0 / per_metre)
    elif np.issubdtype(depth.dtype, np.floating):
        valid = np.isfinite(depth) & (depth > 0)
        top = float(depth[valid].max()) if valid.any() else 0.0
        metres = top <= _METRES_MAX
        unit = "metres" if metres else "millimetres"
        note = f"{where}: {depth.dtype} depth read as {unit} (largest {top:g}), kept as uint16 mm"
        depth, _ = _scaled_mm(depth, where, 1000.0 if metres else 1.0)
    elif depth.dtype != np.uint16:
        depth, _ = _scaled_mm(depth, where, 1.0)
    if check_median:
        _check_median(depth, where, per_metre)
    return depth, note


def _scaled_mm(depth: np.ndarray, where: str, mm_per_value: float) -> tuple[np.ndarray, float]:
    """``depth * mm_per_value`` rounded to ``uint16`` mm (non-finite and <= 0 missing),
    and the largest stored value; depth beyond 65,535 mm, and negative integers (no
    integer format marks missing depth so), are refused, not wrapped."""
    valid = np.isfinite(depth) & (depth > 0)
    top = float(depth[valid].max()) if valid.any() else 0.0
    low = int(depth.min()) if np.issubdtype(depth.dtype, np.integer) and depth.size else 0
    if top * mm_per_value > np.iinfo(np.uint16).max or low < 0:
        raise SourceError(
            f"{where}: {depth.dtype} depth from {min(low, 0):g} to {top:g} does not fit "
            f"16-bit millimetres at {mm_per_value:g} mm per stored value"
        )
    mm = np.rint(np.where(valid, depth, 0).astype(np.float64) * mm_per_value)
    return mm.astype(np.uint16), top


def _check_median(depth_mm: np.ndarray, where: str, per_metre: float | None) -> None:
    """Refuse depth whose median valid value, read as mm, is nearer than a room with a
    person in it (0.4 m) or farther than a depth camera measures one (8 m): another unit."""
    flat = depth_mm.ravel()
    sample = flat[:: max(1, flat.size // _MEDIAN_SAMPLES)]  # a whole .npz need not be sorted
    valid = sample[sample > 0]
    if valid.size == 0:
        return
    median = float(np.median(valid))
    if _MM_MEDIAN_MIN <= median <= _MM_MEDIAN_MAX:
        return
    read = f"at {per_metre:g} per metre" if per_metre is not None else "as mm"
    raise SourceError(
        f"{where}: the median depth is {median / 1000:g} m when read {read}, outside "
        "0.4-8 m: the values are in another unit. Give the stored values per metre with "
        "--depth-scale N (open_source(..., depth_scale=N); TUM: 5000, metres: 1)"
    )


def princeton_depth(raw: np.ndarray) -> np.ndarray:
    """Princeton RGB-D benchmark depth is stored bit-rotated: ``(raw >> 3) | (raw << 13)``."""
    raw = raw.astype(np.uint16, copy=False)
    return (raw >> np.uint16(3)) | (raw << np.uint16(13))


def tum_depth(raw: np.ndarray) -> np.ndarray:
    """TUM RGB-D depth: 5,000 per metre, i.e. 5 per millimetre; rounded to whole mm."""
    return _scaled_mm(raw, "TUM depth", 1000.0 / TUM_PER_METRE)[0]
