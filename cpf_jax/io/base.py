"""The frame-source interface shared by every loader.

A *finite* source (:class:`FrameSource`: image folders, ``.npz``, video files,
synthetic scenarios) has ``len()``, random access ``read(i)`` / ``src[i]`` and
reads frames on demand, so a 1,000-frame folder is never held in memory at
once; :meth:`FrameSource.load_all` stacks a range of frames for a jitted
``lax.scan`` run. A *live* source (:class:`LiveSource`: cameras) is only
iterable and has no length.

Frames are :class:`cpf_jax.types.Frame` of NumPy arrays (the driver moves
them to the device): ``colour [H, W, 3] uint8`` RGB and ``depth [H, W]
uint16`` millimetres, 0 = missing; colour-only sources give zeros. Boxes are
``[T, 4] (x, y, w, h)`` top-left, 0-based float32 pixels in the colour image.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cpf_jax.errors import SourceError
from cpf_jax.types import Frame, Intrinsics

__all__ = ["Recording", "FrameSource", "LiveSource"]


class Recording(NamedTuple):
    """Stacked frames of a finite source (what :meth:`FrameSource.load_all` returns).

    colour ``[T, H, W, 3] uint8``; depth ``[T, H', W'] uint16`` (mm, 0 = missing);
    boxes ``[T, 4]`` xywh float32 or None; visible ``[T] bool`` or None.
    """

    colour: np.ndarray
    depth: np.ndarray
    boxes: np.ndarray | None
    visible: np.ndarray | None
    intrinsics: Intrinsics | None


class FrameSource:
    """A finite, random-access sequence of :class:`~cpf_jax.types.Frame`.

    Attributes every source sets (None when unknown):

    * ``kind``: ``"otb"``, ``"rgbd"``, ``"princeton"``, ``"tum"``, ``"npz"``,
      ``"video"``, ``"synthetic"`` ...
    * ``path``: where the data came from (a ``Path``, or None).
    * ``names``: one name per frame (the colour file name, or ``"<file>#<i>"``).
    * ``gt_boxes``: ``[T, 4]`` float32 xywh, 0-based; rows of frames where the
      target is not visible are ``0, 0, 0, 0``.
    * ``visible``: ``[T] bool``.
    * ``intrinsics``: :class:`~cpf_jax.types.Intrinsics` of the colour camera.
    * ``calibration``: a dict read from ``calibration.json`` (or similar).
    * ``depth_scale``: stored depth values per metre for sources that read depth files
      (folders, ``.npz``); None: the format's own or detected (see
      :func:`~cpf_jax.io.images.depth_millimetres`).

    Subclasses implement ``_read(i) -> Frame`` and set ``names``.
    """

    kind: str = "frames"
    depth_scale: float | None = None
    has_depth: bool = True  # False: a colour-only source, whose depth frames are zeros

    def __init__(
        self,
        names: list[str],
        *,
        path: Path | None = None,
        gt_boxes: np.ndarray | None = None,
        visible: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
        calibration: dict[str, Any] | None = None,
        init_box: np.ndarray | None = None,
    ) -> None:
        self.names = list(names)
        self.path = path
        self.gt_boxes = gt_boxes
        self.visible = visible
        self.intrinsics = intrinsics
        self.calibration = calibration
        self._init_box = init_box
        self._size: tuple[int, int] | None = None

    # -- sequence protocol -------------------------------------------------
    def __len__(self) -> int:
        return len(self.names)

    def _index(self, i: int) -> int:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an int, got {type(i).__name__}")
        j = int(i) + n if i < 0 else int(i)
        if not 0 <= j < n:
            raise IndexError(f"frame {i} out of range for {n} frames of {self.describe()}")
        return j

    def read(self, i: int) -> Frame:
        """Read frame ``i`` (negative counts from the end) from disk or memory."""
        return self._read(self._index(i))

    def __getitem__(self, i: int) -> Frame:
        return self.read(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._read(i)

    def _read(self, i: int) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- metadata ----------------------------------------------------------
    def describe(self) -> str:
        """A short human name: the path, or the kind."""
        return str(self.path) if self.path is not None else self.kind

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)`` of the colour images (reads frame 0 the first time)."""
        if self._size is None:
            if len(self) == 0:
                raise SourceError(f"{self.describe()}: no frames")
            h, w = self._read(0).colour.shape[:2]
            self._size = (int(w), int(h))
        return self._size

    def empty_background(self) -> Frame | None:
        """A frame of the empty scene (no person), when the source has one (a synthetic
        scenario's room); ``None`` otherwise. RGB-D models then use it as their
        background instead of a median over the recording's frames."""
        return None

    @property
    def first_visible(self) -> int | None:
        """Index of the first frame with a visible ground-truth box (or an init box: 0)."""
        if self.visible is not None and self.visible.any():
            return int(np.argmax(self.visible))
        return 0 if self._init_box is not None else None

    @property
    def init_box(self) -> np.ndarray | None:
        """``[4]`` xywh box to start tracking at :attr:`first_visible`, or None."""
        if self._init_box is not None:
            return np.asarray(self._init_box, np.float32)
        i = self.first_visible
        if i is None or self.gt_boxes is None:
            return None
        return self.gt_boxes[i].copy()

    def load_all(self, start: int = 0, stop: int | None = None) -> Recording:
        """Read frames ``start:stop`` and stack them (for one jitted ``lax.scan``)."""
        idx = range(len(self))[start:stop]
        if len(idx) == 0:
            raise SourceError(f"{self.describe()}: no frames in range {start}:{stop}")
        first = self._read(idx[0])
        colour = np.empty((len(idx), *first.colour.shape), np.uint8)
        depth = np.empty((len(idx), *first.depth.shape), np.uint16)
        colour[0], depth[0] = first.colour, first.depth
        for k, i in enumerate(idx[1:], start=1):
            f = self._read(i)
            colour[k], depth[k] = f.colour, f.depth
        sel = np.asarray(idx)
        boxes = None if self.gt_boxes is None else self.gt_boxes[sel]
        visible = None if self.visible is None else self.visible[sel]
        return Recording(colour, depth, boxes, visible, self.intrinsics)

    def close(self) -> None:
        """Release files or devices (no-op for most sources)."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        gt = "" if self.gt_boxes is None else ", with ground truth"
        return f"<{type(self).__name__} {self.kind} {self.describe()}: {len(self)} frames{gt}>"


class LiveSource:
    """An endless (or device-limited) stream of frames from a camera: iterable, no ``len()``.

    ``size`` and ``intrinsics`` are known once the device is open; there is no
    ground truth. Use as a context manager so the device is stopped.
    """

    kind: str = "live"
    has_depth = True
    names = None
    gt_boxes = None
    visible = None
    calibration: dict[str, Any] | None = None
    init_box = None
    first_visible = None
    intrinsics: Intrinsics | None = None
    size: tuple[int, int]

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        return self.kind

    def close(self) -> None:
        """Stop the device."""

    def __enter__(self) -> LiveSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
