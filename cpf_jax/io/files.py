"""Single-file sources: ``.npz`` arrays and video files.

* ``.npz`` (``kind="npz"``): ``colour`` (or ``color`` / ``rgb``) ``[T, H, W, 3]
  uint8`` RGB, optional ``depth [T, H', W']`` (``uint16`` mm,
  or floating-point metres or millimetres, converted by
  :func:`~cpf_jax.io.images.depth_millimetres` with a warning), ``boxes [T, 4]`` xywh
  0-based, ``visible [T] bool`` and ``intrinsics [4]`` (fx, fy, cx, cy; or a 3x3
  camera matrix). NumPy
  cannot memory-map arrays inside a zip, so each array is loaded whole on the
  first frame read.
* video (``kind="video"``): anything ``cv2.VideoCapture`` opens; colour only.
  Frames are decoded in order; reading out of order seeks.
"""

from __future__ import annotations

import warnings
import zipfile
from pathlib import Path

import cv2
import numpy as np

from cpf_jax.errors import InputWarning, SourceError
from cpf_jax.io.base import FrameSource, Recording
from cpf_jax.io.images import depth_millimetres
from cpf_jax.types import Frame, Intrinsics

__all__ = ["NpzSource", "VideoSource", "VIDEO_SUFFIXES"]

VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv")
_COLOUR_KEYS = ("colour", "color", "rgb")


class NpzSource(FrameSource):
    """Frames from a ``.npz`` file (see the module docstring for the keys)."""

    kind = "npz"

    def __init__(self, path: Path | str) -> None:
        path = Path(path)
        if not path.is_file():
            raise SourceError(f"{path}: no such file")
        try:
            npz = np.load(path, allow_pickle=False)
        except (OSError, ValueError, zipfile.BadZipFile) as e:
            raise SourceError(f"{path}: not a readable .npz file ({e})") from None
        key = next((k for k in _COLOUR_KEYS if k in npz.files), None)
        if key is None:
            raise SourceError(f"{path}: no 'colour' array (keys: {', '.join(npz.files)})")
        self._npz = npz
        self._colour_key = key
        shape = self._header_shape(key)
        if len(shape) != 4 or shape[-1] != 3:
            raise SourceError(f"{path}: '{key}' must be [T, H, W, 3], got shape {shape}")
        t = shape[0]
        self._colour: np.ndarray | None = None
        self._depth: np.ndarray | None = None
        if "depth" in npz.files:
            dshape = self._header_shape("depth")
            if len(dshape) != 3 or dshape[0] != t:
                raise SourceError(f"{path}: 'depth' must be [{t}, H, W], got shape {dshape}")
        boxes = visible = intrinsics = None
        if "boxes" in npz.files:
            boxes = np.asarray(npz["boxes"], np.float32)
            if boxes.shape != (t, 4):
                raise SourceError(f"{path}: 'boxes' must be [{t}, 4], got shape {boxes.shape}")
            if "visible" in npz.files:
                visible = np.asarray(npz["visible"], bool)
                if visible.shape != (t,):
                    raise SourceError(f"{path}: 'visible' must be [{t}], got {visible.shape}")
            else:
                visible = np.all(np.isfinite(boxes), 1) & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
        if "intrinsics" in npz.files:
            k = np.asarray(npz["intrinsics"], np.float64)
            if k.shape == (3, 3):  # a camera matrix K
                k = k[[0, 1, 0, 1], [0, 1, 2, 2]]
            if k.shape != (4,):
                raise SourceError(
                    f"{path}: 'intrinsics' must be [4] (fx, fy, cx, cy) or a 3x3 camera "
                    f"matrix, got shape {k.shape}"
                )
            intrinsics = Intrinsics(*map(float, k))
        super().__init__(
            [f"{path.name}#{i}" for i in range(t)],
            path=path,
            gt_boxes=boxes,
            visible=visible,
            intrinsics=intrinsics,
        )
        self._size = (int(shape[2]), int(shape[1]))

    @property
    def has_depth(self) -> bool:
        return "depth" in self._npz.files

    def _header_shape(self, key: str) -> tuple[int, ...]:
        # Read only the .npy header, not the data.
        fmt = np.lib.format
        with self._npz.zip.open(f"{key}.npy") as f:
            version = fmt.read_magic(f)
            if version == (1, 0):
                return tuple(fmt.read_array_header_1_0(f)[0])
            if version == (2, 0):
                return tuple(fmt.read_array_header_2_0(f)[0])
        return tuple(self._npz[key].shape)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray | None]:
        if self._colour is None:
            colour = self._npz[self._colour_key]
            if colour.dtype != np.uint8:
                raise SourceError(
                    f"{self.path}: '{self._colour_key}' must be uint8, got {colour.dtype}"
                )
            self._colour = colour
            if "depth" in self._npz.files:
                where = f"{self.path}: 'depth'"
                depth, note = depth_millimetres(self._npz["depth"], where, True, self.depth_scale)
                if note is not None:
                    warnings.warn(note, InputWarning, stacklevel=2)
                self._depth = depth
        return self._colour, self._depth

    def _read(self, i: int) -> Frame:
        colour, depth = self._arrays()
        d = depth[i] if depth is not None else np.zeros(colour.shape[1:3], np.uint16)
        return Frame(colour[i], d)

    def load_all(self, start: int = 0, stop: int | None = None) -> Recording:
        colour, depth = self._arrays()
        sel = np.arange(len(self))[start:stop]
        if sel.size == 0:
            raise SourceError(f"{self.describe()}: no frames in range {start}:{stop}")
        d = depth[sel] if depth is not None else np.zeros((sel.size, *colour.shape[1:3]), np.uint16)
        boxes = None if self.gt_boxes is None else self.gt_boxes[sel]
        visible = None if self.visible is None else self.visible[sel]
        return Recording(colour[sel], d, boxes, visible, self.intrinsics)

    def close(self) -> None:
        self._npz.close()


class VideoSource(FrameSource):
    """Colour frames of a video file through ``cv2.VideoCapture`` (depth is zeros).

    The length comes from the container's frame count; when the container
    does not say, the frames are counted once by grabbing them all.
    """

    kind = "video"
    has_depth = False

    def __init__(self, path: Path | str) -> None:
        path = Path(path)
        if not path.is_file():
            raise SourceError(f"{path}: no such file")
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            raise SourceError(
                f"{path}: OpenCV cannot open this video (unknown codec or not a video)"
            )
        n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if n <= 0:
            n = 0
            while self._cap.grab():
                n += 1
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        if n == 0:
            raise SourceError(f"{path}: video has no frames")
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS)) or None
        w = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        super().__init__([f"{path.name}#{i}" for i in range(n)], path=path)
        if w > 0 and h > 0:
            self._size = (w, h)
        self._next = 0

    def _read(self, i: int) -> Frame:
        if i != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, bgr = self._cap.read()
        if not ok or bgr is None:
            self._next = -1
            raise SourceError(f"{self.path}: cannot decode frame {i} of {len(self)}")
        self._next = i + 1
        colour = np.ascontiguousarray(bgr[..., ::-1])
        return Frame(colour, np.zeros(colour.shape[:2], np.uint16))

    def close(self) -> None:
        self._cap.release()
