"""MOTChallenge text files: ``frame,id,x,y,w,h,conf,-1,-1,-1`` a line, one line per box.

MOTChallenge counts frames from 1 and puts the top-left pixel at ``1,1``; cpf_jax counts
both from 0, so reading subtracts 1 from the frame, ``x`` and ``y`` and writing adds it.
Rows in memory are ``[K, 7] (frame, id, x, y, w, h, conf)`` float64, the form
:func:`cpf_jax.metrics.mot_metrics` reads (it uses the first six columns).
"""

from __future__ import annotations

from pathlib import Path
from typing import IO

import numpy as np

from cpf_jax.errors import SourceError

__all__ = ["read_mot", "MotWriter"]


def read_mot(path: Path | str, truth: bool = False) -> np.ndarray:
    """``[K, 7]`` rows of a MOTChallenge file (0-based frames and pixels; ``conf`` 1 when the
    file has no seventh column); with ``truth``, ``[K, 9]`` rows of a ground-truth file
    ``(frame, id, x, y, w, h, active, class, visibility)``, each missing column 1.

    Raises:
      SourceError: naming the file and line of a line that is not 6 or more numbers.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise SourceError(f"{path}: cannot read ({e.strerror or e})") from None
    rows = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            fields = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            fields = []
        if len(fields) < 6:
            raise SourceError(f"{path}:{n}: expected 'frame,id,x,y,w,h[,conf,...]', got {line!r}")
        n = 9 if truth else 7
        rows.append([*fields[:n], *([1.0] * (n - len(fields[:n])))])
    out = np.asarray(rows, np.float64).reshape(-1, 9 if truth else 7)
    out[:, [0, 2, 3]] -= 1.0
    return out


class MotWriter:
    """Write boxes with identities as MOTChallenge lines, flushed frame by frame."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f: IO[str] | None = open(self.path, "w", encoding="utf-8")
        except OSError as e:
            raise SourceError(f"{self.path}: cannot write ({e.strerror or e})") from None

    def write(self, frame: int, ids, boxes, conf=None) -> None:
        """Frame ``frame`` (0-based): ``ids [K]``, ``boxes [K, 4]`` xywh 0-based, ``conf [K]``."""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        conf = np.ones(len(boxes)) if conf is None else np.asarray(conf, np.float64)
        for i, (x, y, w, h), c in zip(np.asarray(ids).ravel(), boxes, conf.ravel(), strict=True):
            self._f.write(
                f"{frame + 1},{int(i)},{x + 1:.2f},{y + 1:.2f},{w:.2f},{h:.2f},{c:.3f},-1,-1,-1\n"
            )
        self._f.flush()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> MotWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
