"""Ground-truth box files (OTB ``groundtruth_rect.txt`` and alike).

One line per frame, ``x, y, w, h`` separated by commas, whitespace, tabs or
semicolons. OTB stores 1-based top-left corners; they are converted to the
package's 0-based convention by subtracting 1 from ``x`` and ``y``. A line of
``0,0,0,0`` (OTB, LaSOT) or ``NaN,NaN,NaN,NaN`` (UAV123) means the target is not
visible; its row is returned as ``0, 0, 0, 0`` with ``visible = False``. Any
other line that cannot be a box (a zero or negative size, some fields NaN) is
read the same way, and a :class:`~cpf_jax.errors.GroundTruthWarning` names its
lines: such a line is more often a typo than a hidden target, and it drops its
frame from the metrics.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from cpf_jax.errors import GroundTruthWarning, SourceError

__all__ = ["load_groundtruth", "load_occlusion", "check_groundtruth"]

# Corner pairs x1,y1,x2,y2 read as x,y,w,h give w > x and h > y on every line; boxes of a
# target that moves about rarely do on this many lines.
_CORNER_LINES_MIN = 5

_SEP = re.compile(r"[,;\s]+")


def _parse_boxes(path: Path, lines: list[str]) -> tuple[np.ndarray, list[int]]:
    """``[T, 4] float32`` rows of the box lines as written, and their 1-based line numbers;
    ``#`` lines are skipped, any other line must hold 4 numbers."""
    rows, numbers = [], []
    for n, line in enumerate(lines, start=1):
        text = line.strip()
        if text.startswith("#"):
            continue
        fields = [f for f in _SEP.split(text) if f]
        try:
            if len(fields) == 8:
                raise SourceError(
                    f"{path}:{n}: 8 numbers, a polygon x1,y1,...,x4,y4 (as VOT writes): give "
                    "one axis-aligned box 'x,y,w,h' per line"
                )
            if len(fields) != 4:
                raise ValueError
            rows.append([float(f) for f in fields])
            numbers.append(n)
        except ValueError:
            raise SourceError(
                f"{path}:{n}: expected 4 numbers 'x,y,w,h', got {line.strip()!r}"
            ) from None
    return np.asarray(rows, np.float32).reshape(-1, 4), numbers


def load_groundtruth(path: Path | str, one_based: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read a box file: returns ``boxes [T, 4] float32`` (xywh, 0-based) and ``visible [T] bool``.

    Blank lines at the end and lines starting with ``#`` are skipped; a blank
    line in the middle is an error (it would shift every later frame).

    Raises:
      SourceError: naming the file and line when a line does not hold 4 numbers.

    Warns:
      GroundTruthWarning: naming the lines read as "not visible" that are neither
        ``0,0,0,0`` nor all NaN.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as e:
        raise SourceError(f"{path}: cannot read ground truth ({e.strerror or e})") from None
    while lines and not lines[-1].strip():
        lines.pop()
    boxes, numbers = _parse_boxes(path, lines)
    finite = np.all(np.isfinite(boxes), axis=1)
    visible = finite & (np.nan_to_num(boxes[:, 2]) > 0) & (np.nan_to_num(boxes[:, 3]) > 0)
    conventional = np.all(boxes == 0, axis=1) | np.all(np.isnan(boxes), axis=1)
    odd = np.flatnonzero(~visible & ~conventional)
    if odd.size:
        shown = ", ".join(f"line {numbers[i]} {lines[numbers[i] - 1].strip()!r}" for i in odd[:3])
        more = f" and {odd.size - 3} more" if odd.size > 3 else ""
        warnings.warn(
            GroundTruthWarning(
                f"{path}: {odd.size} line(s) read as 'target not visible' that are neither "
                f"0,0,0,0 nor all NaN (a zero or negative size, or a NaN field): {shown}{more}"
            ),
            stacklevel=2,
        )
    if one_based:
        boxes[:, :2] -= 1.0
    boxes[~visible] = 0.0
    return boxes, visible


def check_groundtruth(
    boxes: np.ndarray, visible: np.ndarray | None, size: tuple[int, int], where: str
) -> None:
    """Warn (:class:`~cpf_jax.errors.GroundTruthWarning`) about boxes that read as another
    convention: boxes more than half outside the ``size = (W, H)`` image (ground truth of
    another image size, or corners), and files whose every box has ``w > x`` and ``h > y``
    (corner pairs ``x1,y1,x2,y2``)."""
    b = np.asarray(boxes, np.float64)
    visible = (b[:, 2] > 0) & (b[:, 3] > 0) if visible is None else np.asarray(visible, bool)
    b = b[visible]
    if b.size == 0:
        return
    w, h = size
    inside_w = np.clip(b[:, 0] + b[:, 2], 0, w) - np.clip(b[:, 0], 0, w)
    inside_h = np.clip(b[:, 1] + b[:, 3], 0, h) - np.clip(b[:, 1], 0, h)
    outside = np.flatnonzero(inside_w * inside_h < 0.5 * b[:, 2] * b[:, 3])
    frames = np.flatnonzero(visible)
    if outside.size:
        i = outside[0]
        warnings.warn(
            GroundTruthWarning(
                f"{where}: {outside.size} of {len(b)} ground-truth boxes lie more than half "
                f"outside the {w}x{h} image (the first at frame {frames[i]}: "
                f"{','.join(f'{v:g}' for v in b[i])}): boxes for another image size, or "
                "corners x1,y1,x2,y2 rather than x,y,w,h?"
            ),
            stacklevel=2,
        )
    elif len(b) >= _CORNER_LINES_MIN and np.all((b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])):
        warnings.warn(
            GroundTruthWarning(
                f"{where}: every ground-truth box has w > x and h > y, as corners "
                "x1,y1,x2,y2 read as x,y,w,h do: if the file holds corners, write x,y,w,h "
                "(w = x2 - x1, h = y2 - y1)"
            ),
            stacklevel=2,
        )


def load_occlusion(path: Path | str) -> list[str]:
    """Per-frame occlusion labels (``none`` / ``partial`` / ``full``), one word a line."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").split()
    except OSError as e:
        raise SourceError(f"{path}: cannot read occlusion labels ({e.strerror or e})") from None
    return [w.strip().lower() for w in lines]
