"""Adapter from a synthetic scenario (``cpf_jax.synthetic.make_sequence``) to a frame source.

The generator returns a NamedTuple with ``colour [T, H, W, 3]``, ``depth [T, H, W]``,
``boxes [T, 4]`` xywh, ``visible [T]`` and ``intrinsics``; any extra fields
(3D body points, ...) stay reachable through :attr:`SyntheticSource.sequence`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cpf_jax.errors import SourceError
from cpf_jax.io.base import FrameSource, Recording
from cpf_jax.types import Frame, Intrinsics

__all__ = ["SyntheticSource", "open_synthetic"]


def _as_intrinsics(value: Any) -> Intrinsics | None:
    if value is None or isinstance(value, Intrinsics):
        return value
    if all(hasattr(value, k) for k in ("fx", "fy", "cx", "cy")):
        return Intrinsics(*(float(getattr(value, k)) for k in ("fx", "fy", "cx", "cy")))
    k = np.asarray(value, np.float64)
    if k.shape == (4,):
        return Intrinsics(*map(float, k))
    if k.shape == (3, 3):
        return Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    raise SourceError(f"synthetic intrinsics: cannot read {type(value).__name__} {k.shape}")


class SyntheticSource(FrameSource):
    """Frames of an in-memory synthetic sequence (arrays converted to NumPy once)."""

    kind = "synthetic"

    def __init__(self, sequence: Any, name: str = "synthetic") -> None:
        self.sequence = sequence
        self.name = name
        colour = np.asarray(sequence.colour)
        depth = np.asarray(sequence.depth) if getattr(sequence, "depth", None) is not None else None
        if colour.ndim != 4 or colour.shape[-1] != 3:
            raise SourceError(f"{name}: colour must be [T, H, W, 3], got shape {colour.shape}")
        if colour.dtype != np.uint8:
            # float colour in [0, 1] is scaled to 0..255; anything else is taken as 0..255.
            scale = (
                255.0 if colour.dtype.kind == "f" and colour.size and colour.max() <= 1.0 else 1.0
            )
            colour = np.clip(np.rint(colour * scale), 0, 255).astype(np.uint8)
        t = colour.shape[0]
        if depth is None:
            depth = np.zeros(colour.shape[:3], np.uint16)
        elif depth.ndim != 3 or depth.shape[0] != t:
            raise SourceError(f"{name}: depth must be [{t}, H, W], got shape {depth.shape}")
        elif depth.dtype != np.uint16:
            depth = np.clip(np.rint(depth), 0, 65535).astype(np.uint16)
        boxes = getattr(sequence, "boxes", None)
        boxes = None if boxes is None else np.asarray(boxes, np.float32)
        if boxes is not None and boxes.shape != (t, 4):
            raise SourceError(f"{name}: boxes must be [{t}, 4], got shape {boxes.shape}")
        visible = getattr(sequence, "visible", None)
        if visible is not None:
            visible = np.asarray(visible, bool)
        elif boxes is not None:
            visible = np.all(np.isfinite(boxes), 1) & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
        self._colour, self._depth = colour, depth
        super().__init__(
            [f"{name}#{i}" for i in range(t)],
            gt_boxes=boxes,
            visible=visible,
            intrinsics=_as_intrinsics(getattr(sequence, "intrinsics", None)),
        )
        self._size = (int(colour.shape[2]), int(colour.shape[1]))

    def describe(self) -> str:
        return self.name

    def _read(self, i: int) -> Frame:
        return Frame(self._colour[i], self._depth[i])

    def empty_background(self) -> Frame | None:
        meta = getattr(self.sequence, "meta", None) or {}
        colour, depth = meta.get("background_colour"), meta.get("background_depth")
        if colour is None or depth is None:
            return None
        return Frame(np.asarray(colour, np.uint8), np.asarray(depth, np.uint16))

    def load_all(self, start: int = 0, stop: int | None = None) -> Recording:
        sel = np.arange(len(self))[start:stop]
        if sel.size == 0:
            raise SourceError(f"{self.name}: no frames in range {start}:{stop}")
        boxes = None if self.gt_boxes is None else self.gt_boxes[sel]
        visible = None if self.visible is None else self.visible[sel]
        return Recording(self._colour[sel], self._depth[sel], boxes, visible, self.intrinsics)


def open_synthetic(name: str, **kwargs: Any) -> SyntheticSource:
    """Generate scenario ``name`` with ``cpf_jax.synthetic.make_sequence`` and wrap it."""
    try:
        from cpf_jax.synthetic import SCENARIOS, make_sequence
    except ImportError as e:
        raise SourceError(
            f"{name}: no such file or folder, and synthetic scenarios are unavailable ({e})"
        ) from None
    if name not in SCENARIOS:
        known = ", ".join(sorted(SCENARIOS))
        raise SourceError(
            f"{name}: no such file, folder, camera or synthetic scenario (scenarios: {known})"
        )
    return SyntheticSource(make_sequence(name, **kwargs), name=name)
