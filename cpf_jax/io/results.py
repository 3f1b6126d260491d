"""Per-frame results as CSV, written and flushed row by row.

Columns: ``frame,x,y,w,h`` then any extra columns named when the writer is
made (``ess``, ``lost``, ``ms``, point coordinates ...). ``frame`` is the
0-based index in the source's sorted order; the box is top-left 0-based
pixels. Each row is flushed as it is written, so an interrupted run keeps
every finished frame.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from cpf_jax.errors import SourceError

__all__ = ["ResultsWriter", "read_results", "BOX_COLUMNS"]

BOX_COLUMNS = ("frame", "x", "y", "w", "h")


def _cell(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if value is None:
        return ""
    v = float(value)
    return "nan" if math.isnan(v) else f"{v:.7g}"


class ResultsWriter:
    """Append ``frame,x,y,w,h[,extras]`` rows to a CSV file, one flush per row.

    Args:
      path: the CSV file (parent folders are created; an existing file is replaced).
      extra_columns: names of extra columns, written in this order.

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: Path | str, extra_columns: Sequence[str] = ()) -> None:
        self.path = Path(path)
        self.extra_columns = tuple(extra_columns)
        clash = set(self.extra_columns) & set(BOX_COLUMNS)
        if clash or len(set(self.extra_columns)) != len(self.extra_columns):
            raise ValueError(f"extra columns must be unique and not {BOX_COLUMNS}: {extra_columns}")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[str] | None = open(self.path, "w", newline="", encoding="utf-8")  # noqa: SIM115
        except OSError as e:
            raise SourceError(f"{self.path}: cannot write results ({e.strerror or e})") from None
        self._csv = csv.writer(self._file)
        self._csv.writerow((*BOX_COLUMNS, *self.extra_columns))
        self._file.flush()
        self.rows = 0

    def write(self, frame: int, box: Sequence[float] | np.ndarray, **extras: Any) -> None:
        """Write one row: ``box`` is ``(x, y, w, h)``; missing extras are left empty."""
        if self._file is None:
            raise ValueError(f"{self.path}: writer is closed")
        unknown = set(extras) - set(self.extra_columns)
        if unknown:
            raise ValueError(
                f"unknown result columns {sorted(unknown)}; declared {self.extra_columns}"
            )
        b = np.asarray(box, np.float64).ravel()
        if b.shape != (4,):
            raise ValueError(f"box must have 4 numbers (x, y, w, h), got shape {b.shape}")
        row = [str(int(frame)), *(_cell(v) for v in b)]
        row += [_cell(extras.get(c)) for c in self.extra_columns]
        self._csv.writerow(row)
        self._file.flush()
        self.rows += 1

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> ResultsWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_results(path: Path | str) -> dict[str, np.ndarray]:
    """Read a results CSV back: ``{"frame": [N] int, "boxes": [N, 4] float32, <extra>: [N] float}``.

    Empty cells read as NaN; a last row cut short (the run was killed mid-write) is dropped.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise SourceError(f"{path}: cannot read results ({e.strerror or e})") from None
    if not rows or tuple(rows[0][:5]) != BOX_COLUMNS:
        raise SourceError(f"{path}: not a results file (header must start with frame,x,y,w,h)")
    header, body = rows[0], [r for r in rows[1:] if r]
    if body and len(body[-1]) != len(header):
        body.pop()  # a row cut short by an interrupted run
    try:
        cols = {
            name: np.array([float(r[k]) if r[k] else np.nan for r in body], np.float64)
            for k, name in enumerate(header)
        }
    except (ValueError, IndexError):
        raise SourceError(f"{path}: a row does not match the header {','.join(header)}") from None
    out: dict[str, np.ndarray] = {
        "frame": cols.pop("frame").astype(np.int64),
        "boxes": np.stack([cols.pop(c) for c in "xywh"], axis=-1).astype(np.float32),
    }
    out.update(cols)
    return out
