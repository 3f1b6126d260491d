"""``open_source``: one entry point from a command-line string to a frame source."""

from __future__ import annotations

import math
from pathlib import Path

from cpf_jax.errors import SourceError
from cpf_jax.io.base import FrameSource, LiveSource
from cpf_jax.io.cameras import KinectV2Source, RealSenseSource
from cpf_jax.io.files import VIDEO_SUFFIXES, NpzSource, VideoSource
from cpf_jax.io.folders import ImageFolderSource, open_folder
from cpf_jax.io.synthetic import open_synthetic

__all__ = ["open_source", "CAMERA_NAMES", "REALSENSE_SUFFIXES"]

CAMERA_NAMES = ("realsense", "kinect2", "kinect")
# RealSense recordings: .bag (ROS1, older librealsense) and .db3 (ROS2; pyrealsense2
# 2.59's recorder writes only .db3).
REALSENSE_SUFFIXES = (".bag", ".db3")


def open_source(
    spec: str | Path, kind: str | None = None, depth_scale: float | None = None
) -> FrameSource | LiveSource:
    """Open frames from a path, a camera name or a synthetic scenario name.

    * a folder: its layout is detected from its content (``tum``, ``princeton``,
      ``rgbd``, ``otb``; see :mod:`cpf_jax.io.folders`), or forced with ``kind``;
    * a ``.npz`` file, a video file, or a RealSense recording (``.bag`` or ``.db3``);
    * ``realsense[:serial]`` or ``kinect2[:serial]``: a live camera;
    * any other name that is not an existing path: a synthetic scenario from
      ``cpf_jax.synthetic`` (an existing path with the same name wins).

    ``depth_scale`` (stored depth values per metre: 1000 for mm, 5000 for TUM, 1 for
    metres) overrides the units a folder or ``.npz`` source reads its depth in, which are
    otherwise its format's own or detected from the values.

    Raises:
      SourceError: one line naming what was asked for and what is wrong
      (:class:`~cpf_jax.errors.CameraUnavailable` for cameras).
    """
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise SourceError(f"depth scale must be a finite number > 0, got {depth_scale}")
    source = _open(str(spec), kind)
    if depth_scale is None:
        return source
    why = None
    if not isinstance(source, (ImageFolderSource, NpzSource)):
        why = (
            f"a depth scale applies to depth read from files (image folders, .npz), not to "
            f"a {source.kind} source, whose units are known"
        )
    elif not source.has_depth:
        why = "a depth scale given, but it has no depth"
    if why is not None:
        source.close()  # a camera opened for nothing is stopped
        raise SourceError(f"{source.describe()}: {why}")
    source.depth_scale = float(depth_scale)
    return source


def _open(text: str, kind: str | None) -> FrameSource | LiveSource:
    camera, _, serial = text.partition(":")
    if camera.lower() in CAMERA_NAMES and not Path(text).exists():
        if camera.lower() == "realsense":
            return RealSenseSource(serial or None)
        return KinectV2Source(serial or None)
    path = Path(text).expanduser()
    if path.is_dir():
        return open_folder(path, kind)
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix == ".npz":
            return NpzSource(path)
        if suffix in REALSENSE_SUFFIXES:
            return RealSenseSource(bag=path)
        if suffix in VIDEO_SUFFIXES:
            return VideoSource(path)
        raise SourceError(
            f"{path}: unsupported file type {suffix or '(none)'} "
            f"(expected a folder, .npz, .bag, .db3 or a video: {', '.join(VIDEO_SUFFIXES)})"
        )
    looks_like_path = "/" in text or "\\" in text or path.suffix != "" or text.startswith(".")
    if looks_like_path or not text:
        raise SourceError(f"{text}: no such file or directory")
    return open_synthetic(text)
