"""Image-folder sources: OTB, recorded RGB-D folders, Princeton RGB-D, TUM RGB-D.

All four read images lazily, one frame per :meth:`FrameSource.read`. Layouts:

* **OTB** (``kind="otb"``): ``img/*.jpg`` (or images directly in the folder) +
  optional ``groundtruth_rect.txt`` (or ``groundtruth_rect.1.txt``), 1-based
  ``x,y,w,h``. Colour only: depth is all zeros.
* **recorded RGB-D** (``kind="rgbd"``): ``rgb/`` (or ``color/``, ``colour/``)
  JPEG/PNG + optional ``depth/`` 16-bit PNG in millimetres + optional
  ``groundtruth_rect.txt`` (OTB format), ``occlusion.txt`` and
  ``calibration.json``. Depth is paired with colour by identical stems, else
  by the last number in the stem (``images00000001.jpg`` with
  ``images00000001.png``, ``rgb_7.jpg`` with ``depth_7.png``), else by sorted
  order when the counts agree. The depth is *not* registered to colour here.
* **Princeton** RGB-D tracking benchmark (``kind="princeton"``):
  ``rgb/r-<t>-<n>.png`` + ``depth/d-<t>-<n>.png`` (bit-rotated depth, see
  :func:`~cpf_jax.io.images.princeton_depth`), ``init.txt`` (the first box),
  optional ``<folder name>.txt`` full ground truth (NaN rows = not visible)
  and ``frames.json`` (kept as ``calibration``; its ``imageFrameID`` /
  ``depthFrameID`` lists pair the files when present, else files are paired
  by frame number, else by order).
* **TUM** RGB-D (``kind="tum"``): ``rgb.txt`` / ``depth.txt`` lists of
  ``timestamp path``; each colour image takes the depth image closest in time
  within 20 ms (as TUM's ``associate.py``), else zeros. Depth 5,000 per metre
  is converted to millimetres.

Ground-truth files must have exactly one line per image; otherwise opening
the folder raises :class:`~cpf_jax.errors.SourceError` with both counts.
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cpf_jax.errors import InputWarning, SourceError
from cpf_jax.io.base import FrameSource
from cpf_jax.io.groundtruth import load_groundtruth, load_occlusion
from cpf_jax.io.images import (
    TUM_PER_METRE,
    DepthDecoder,
    depth_millimetres,
    list_images,
    princeton_depth,
    read_colour,
    read_depth,
)
from cpf_jax.types import Frame, Intrinsics

__all__ = [
    "ImageFolderSource",
    "detect_folder_kind",
    "open_folder",
    "open_otb",
    "open_rgbd_folder",
    "open_princeton",
    "open_tum",
    "intrinsics_from_calibration",
]

_COLOUR_DIRS = ("rgb", "color", "colour")
_PRINCETON_RGB = re.compile(r"^r-(\d+)-(\d+)\.png$", re.IGNORECASE)
_PRINCETON_DEPTH = re.compile(r"^d-(\d+)-(\d+)\.png$", re.IGNORECASE)
_TUM_MAX_DT = 0.02  # seconds, TUM associate.py default


class ImageFolderSource(FrameSource):
    """Frames read lazily from lists of colour and (optional) depth image files.

    ``depth_paths[i] is None`` gives an all-zero depth for that frame. Every
    colour image must have the size of the first one read; a different size
    raises :class:`SourceError` naming the file. ``occlusion`` holds per-frame
    labels when the folder has ``occlusion.txt``.
    """

    def __init__(
        self,
        colour_paths: Sequence[Path],
        depth_paths: Sequence[Path | None] | None = None,
        *,
        kind: str,
        path: Path,
        depth_decoder: DepthDecoder | None = None,
        depth_scale: float | None = None,
        gt_boxes: np.ndarray | None = None,
        visible: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
        calibration: dict[str, Any] | None = None,
        init_box: np.ndarray | None = None,
        occlusion: list[str] | None = None,
    ) -> None:
        super().__init__(
            [p.name for p in colour_paths],
            path=path,
            gt_boxes=gt_boxes,
            visible=visible,
            intrinsics=intrinsics,
            calibration=calibration,
            init_box=init_box,
        )
        self.kind = kind
        self.colour_paths = list(colour_paths)
        self.depth_paths = None if depth_paths is None else list(depth_paths)
        self.depth_decoder = depth_decoder
        self.depth_scale = depth_scale
        self.occlusion = occlusion
        self._colour_shape: tuple[int, ...] | None = None
        self._depth_shape: tuple[int, ...] | None = None

    @property
    def has_depth(self) -> bool:
        return self.depth_paths is not None

    def _read(self, i: int) -> Frame:
        cpath = self.colour_paths[i]
        colour = read_colour(cpath)
        if self._colour_shape is None:
            self._colour_shape = colour.shape
        elif colour.shape != self._colour_shape:
            raise SourceError(
                f"{cpath}: image is {colour.shape[1]}x{colour.shape[0]}, but earlier frames "
                f"of {self.path} are {self._colour_shape[1]}x{self._colour_shape[0]}"
            )
        dpath = None if self.depth_paths is None else self.depth_paths[i]
        if dpath is None:
            shape = self._depth_shape or colour.shape[:2]
            return Frame(colour, np.zeros(shape, np.uint16))
        first = self._depth_shape is None
        raw = read_depth(dpath, self.depth_decoder)
        depth, note = depth_millimetres(raw, str(dpath), first, self.depth_scale)
        if note is not None and first:
            warnings.warn(f"{note} (and every depth image of {self.path})", InputWarning, 2)
        if first:
            self._depth_shape = depth.shape
        elif depth.shape != self._depth_shape:
            raise SourceError(
                f"{dpath}: depth is {depth.shape[1]}x{depth.shape[0]}, but earlier depth "
                f"images of {self.path} are {self._depth_shape[1]}x{self._depth_shape[0]}"
            )
        return Frame(colour, depth)


# -- helpers -----------------------------------------------------------------


def _require_dir(path: Path | str) -> Path:
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    if not path.is_dir():
        raise SourceError(f"{path}: not a directory")
    return path


def _images_in(folder: Path) -> list[Path]:
    images = list_images(folder)
    if not images:
        raise SourceError(f"{folder}: no images found (expected .jpg or .png files)")
    return images


def _last_number(name: str) -> int | None:
    nums = re.findall(r"\d+", Path(name).stem)
    return int(nums[-1]) if nums else None


def _check_gt_count(gt_path: Path, boxes: np.ndarray, n_images: int, image_dir: Path) -> None:
    if len(boxes) != n_images:
        raise SourceError(
            f"{gt_path}: {len(boxes)} boxes for {n_images} images in {image_dir} "
            "(need one line per image)"
        )


def _load_gt(
    gt_path: Path, n_images: int, image_dir: Path, one_based: bool = True
) -> tuple[np.ndarray | None, np.ndarray | None]:
    if not gt_path.is_file():
        return None, None
    boxes, visible = load_groundtruth(gt_path, one_based=one_based)
    _check_gt_count(gt_path, boxes, n_images, image_dir)
    return boxes, visible


def _load_json(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise SourceError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise SourceError(f"{path}: expected a JSON object at the top level")
    return data


def intrinsics_from_calibration(calibration: dict[str, Any] | None) -> Intrinsics | None:
    """Colour intrinsics from a calibration dict, when it has them (0-based pixels).

    Recognised: ``{"intrinsics": {"fx", "fy", "cx", "cy"}}`` or ``{"K": 3x3}``,
    at the top level or under ``"colour"`` / ``"color"`` / ``"rgb"``.
    """
    if not calibration:
        return None
    for node in (calibration, *(calibration.get(k) for k in ("colour", "color", "rgb"))):
        if not isinstance(node, dict):
            continue
        intr = node.get("intrinsics")
        if isinstance(intr, dict) and all(k in intr for k in ("fx", "fy", "cx", "cy")):
            return Intrinsics(*(float(intr[k]) for k in ("fx", "fy", "cx", "cy")))
        k = node.get("K")
        if k is not None:
            k = np.asarray(k, np.float64)
            if k.shape == (3, 3):
                return Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    return None


def _pair_depth(colour: list[Path], depth_dir: Path) -> list[Path]:
    """Pair each colour image with a depth image (same stem, same number, or same rank)."""
    depth = list_images(depth_dir)
    if not depth:
        raise SourceError(f"{depth_dir}: depth folder has no images")
    by_stem = {p.stem: p for p in depth}
    if all(c.stem in by_stem for c in colour):
        return [by_stem[c.stem] for c in colour]
    c_nums = [_last_number(c.name) for c in colour]
    d_nums = [_last_number(d.name) for d in depth]
    if None not in c_nums and None not in d_nums and len(set(d_nums)) == len(d_nums):
        by_num = dict(zip(d_nums, depth, strict=True))
        if len(set(c_nums)) == len(c_nums) and all(n in by_num for n in c_nums):
            return [by_num[n] for n in c_nums]
    if len(depth) == len(colour):
        return depth
    raise SourceError(
        f"{depth_dir}: cannot pair {len(depth)} depth images with {len(colour)} colour images "
        "(names do not match and the counts differ)"
    )


# -- loaders -----------------------------------------------------------------


def open_otb(path: Path | str, gt_file: str | None = None) -> ImageFolderSource:
    """OTB-style folder: ``img/`` (or images in ``path``) + ``groundtruth_rect.txt``."""
    path = _require_dir(path)
    img_dir = path / "img" if (path / "img").is_dir() else path
    images = _images_in(img_dir)
    if gt_file is None:
        candidates = [path / "groundtruth_rect.txt", path / "groundtruth_rect.1.txt"]
        gt_path = next((p for p in candidates if p.is_file()), candidates[0])
    else:
        gt_path = path / gt_file
        if not gt_path.is_file():
            raise SourceError(f"{gt_path}: no such ground-truth file")
    boxes, visible = _load_gt(gt_path, len(images), img_dir)
    return ImageFolderSource(images, None, kind="otb", path=path, gt_boxes=boxes, visible=visible)


def open_rgbd_folder(path: Path | str) -> ImageFolderSource:
    """Recorded RGB-D folder: ``rgb/`` + optional ``depth/``, ``groundtruth_rect.txt``, ..."""
    path = _require_dir(path)
    rgb_dir = next((path / d for d in _COLOUR_DIRS if (path / d).is_dir()), None)
    if rgb_dir is None:
        raise SourceError(f"{path}: no rgb/ folder")
    images = _images_in(rgb_dir)
    depth_dir = path / "depth"
    depth = _pair_depth(images, depth_dir) if depth_dir.is_dir() else None
    boxes, visible = _load_gt(path / "groundtruth_rect.txt", len(images), rgb_dir)
    occ_path = path / "occlusion.txt"
    occlusion = load_occlusion(occ_path) if occ_path.is_file() else None
    if occlusion is not None and len(occlusion) != len(images):
        raise SourceError(
            f"{occ_path}: {len(occlusion)} labels for {len(images)} images in {rgb_dir}"
        )
    calibration = _load_json(path / "calibration.json")
    return ImageFolderSource(
        images,
        depth,
        kind="rgbd",
        path=path,
        gt_boxes=boxes,
        visible=visible,
        intrinsics=intrinsics_from_calibration(calibration),
        calibration=calibration,
        occlusion=occlusion,
    )


def _princeton_files(folder: Path, pattern: re.Pattern[str]) -> dict[int, Path]:
    files: dict[int, Path] = {}
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m:
            files[int(m.group(2))] = p
    return files


def open_princeton(path: Path | str, one_based: bool = True) -> ImageFolderSource:
    """Princeton RGB-D tracking benchmark sequence folder (see the module docstring).

    ``one_based``: whether ``init.txt`` and the ground truth use 1-based corners
    (MATLAB, like OTB). Not checked against real PTB data, which is not stored here.
    """
    path = _require_dir(path)
    rgb = _princeton_files(_require_dir(path / "rgb"), _PRINCETON_RGB)
    if not rgb:
        raise SourceError(f"{path / 'rgb'}: no r-<time>-<frame>.png images")
    depth = _princeton_files(path / "depth", _PRINCETON_DEPTH) if (path / "depth").is_dir() else {}
    calibration = _load_json(path / "frames.json")
    c_ids = sorted(rgb)
    colour = [rgb[i] for i in c_ids]
    depth_paths: list[Path | None] | None = None
    if depth:
        ids = (calibration or {}).get("depthFrameID"), (calibration or {}).get("imageFrameID")
        if ids[0] is not None and ids[1] is not None and len(ids[0]) == len(ids[1]):
            by_image = dict(zip(map(int, ids[1]), map(int, ids[0]), strict=True))
            depth_paths = [depth.get(by_image.get(i, -1)) for i in c_ids]
        elif all(i in depth for i in c_ids):
            depth_paths = [depth[i] for i in c_ids]
        elif len(depth) == len(rgb):
            depth_paths = [depth[i] for i in sorted(depth)]
        else:
            raise SourceError(
                f"{path / 'depth'}: cannot pair {len(depth)} depth images with "
                f"{len(rgb)} colour images"
            )
    init_box = None
    if (path / "init.txt").is_file():
        boxes, vis = load_groundtruth(path / "init.txt", one_based=one_based)
        if len(boxes) < 1 or not vis[0]:
            raise SourceError(f"{path / 'init.txt'}: first line is not a visible box")
        init_box = boxes[0]
    gt, visible = _load_gt(path / f"{path.name}.txt", len(colour), path / "rgb", one_based)
    return ImageFolderSource(
        colour,
        depth_paths,
        kind="princeton",
        path=path,
        depth_decoder=princeton_depth,
        gt_boxes=gt,
        visible=visible,
        calibration=calibration,
        init_box=init_box,
    )


def _tum_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    stamps, files = [], []
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise SourceError(f"{path}: cannot read ({e.strerror or e})") from None
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            stamps.append(float(parts[0]))
            files.append(path.parent / parts[1])
        except (ValueError, IndexError):
            raise SourceError(f"{path}:{n}: expected 'timestamp filename', got {line!r}") from None
    return np.asarray(stamps, np.float64), files


def open_tum(path: Path | str) -> ImageFolderSource:
    """TUM RGB-D sequence folder with ``rgb.txt`` and ``depth.txt``."""
    path = _require_dir(path)
    c_t, colour = _tum_list(path / "rgb.txt")
    if not colour:
        raise SourceError(f"{path / 'rgb.txt'}: lists no images")
    depth_paths: list[Path | None] = [None] * len(colour)
    if (path / "depth.txt").is_file():
        d_t, depth = _tum_list(path / "depth.txt")
        if depth:
            order = np.argsort(d_t)
            d_t = d_t[order]
            depth = [depth[i] for i in order]
            for i, t in enumerate(c_t):
                j = int(np.searchsorted(d_t, t))
                near = [k for k in (j - 1, j) if 0 <= k < len(d_t)]
                k = min(near, key=lambda k: abs(d_t[k] - t))
                if abs(d_t[k] - t) <= _TUM_MAX_DT:
                    depth_paths[i] = depth[k]
    return ImageFolderSource(colour, depth_paths, kind="tum", path=path, depth_scale=TUM_PER_METRE)


def detect_folder_kind(path: Path | str) -> str:
    """``"tum"``, ``"princeton"``, ``"rgbd"`` or ``"otb"``, judged by the folder's content."""
    path = _require_dir(path)
    if (path / "rgb.txt").is_file():
        return "tum"
    if (path / "rgb").is_dir() and any(
        _PRINCETON_RGB.match(p.name) for p in (path / "rgb").iterdir()
    ):
        return "princeton"
    if any((path / d).is_dir() for d in _COLOUR_DIRS):
        return "rgbd"
    if (path / "img").is_dir() or list_images(path):
        return "otb"
    raise SourceError(
        f"{path}: no images found (expected img/, rgb/, rgb.txt or image files in the folder)"
    )


_OPENERS = {
    "tum": open_tum,
    "princeton": open_princeton,
    "rgbd": open_rgbd_folder,
    "otb": open_otb,
}


def open_folder(path: Path | str, kind: str | None = None) -> ImageFolderSource:
    """Open an image folder of ``kind``, or of the kind :func:`detect_folder_kind` finds."""
    kind = kind or detect_folder_kind(path)
    parent = Path(path).resolve().parent
    if kind == "otb" and Path(path).name.lower() in _COLOUR_DIRS and (parent / "depth").is_dir():
        warnings.warn(
            f"{path} is the colour folder of the RGB-D recording {parent}: read as colour "
            f"only, without its depth and ground truth; give {parent} for them",
            InputWarning,
            stacklevel=2,
        )
    try:
        opener = _OPENERS[kind]
    except KeyError:
        raise SourceError(f"unknown folder kind {kind!r} (one of {sorted(_OPENERS)})") from None
    return opener(path)
