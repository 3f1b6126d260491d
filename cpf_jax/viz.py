"""Logging a tracking run to Rerun 0.41 (an ``.rrd`` file headless, or a live viewer).

Entity layout (every 2D entity lives in the colour camera's image space, so
boxes and points are drawn over the image in one 2D view, and the depth
image is back-projected in the 3D view when intrinsics are known):

========================================  ==============================================
``world``                                 ``ViewCoordinates.RDF`` (static): camera frame
``world/camera``                          ``Pinhole`` (static, when intrinsics are known)
``world/camera/image``                    colour ``EncodedImage`` (JPEG; ``Image`` RGB raw)
``world/camera/depth``                    ``EncodedDepthImage`` (16-bit PNG, mm) every
                                          ``depth_every``-th frame (``DepthImage`` raw)
``world/camera/<path>``                   boxes (``tracker/box``, ``gt/box``, ``people``:
                                          one colour and label per identity), particles
                                          (``tracker/particles``), 2D body points
``world/<path>``                          3D points (``body/points3d``, ``surface``),
                                          metres in the camera frame (input in mm)
``series/<name>``                         ``Scalars`` time series (ESS, timings)
``events``                                ``TextLog``: births, losses, re-identifications
                                          and deaths of identities
========================================  ==============================================

A recording is compact by default, so that a live run can afford it: colour is JPEG at
quality ``JPEG_QUALITY`` (about 45 KB for 512 x 424 against 650 KB raw), depth a lossless
16-bit PNG (about 115 KB against 434 KB) on every ``DEPTH_EVERY``-th frame, which the viewer
shows until the next; ``raw=True`` logs every frame's pixels as they are.

Every call takes the frame index ``i`` and logs it on the ``frame``
sequence timeline. Log times are disabled (``set_log_time_enabled(False)``)
so recordings read back with ``rerun.chunk.RrdReader`` without pandas.
Nothing numeric happens here: arrays in, Rerun calls out.
"""

from __future__ import annotations

import socket
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cpf_jax.errors import OutputError, ViewerUnavailable
from cpf_jax.filter import cloud_boxes
from cpf_jax.types import Frame, Intrinsics

__all__ = [
    "RerunLogger",
    "identity_colour",
    "weight_colours",
    "default_blueprint",
    "IMAGE_SPACE",
    "check_viewer",
    "viewer_executable",
]

IMAGE_SPACE = "world/camera"
TIMELINE = "frame"
JPEG_QUALITY = 85  # colour: no visible blocking on the tracker's boxes and particles
DEPTH_EVERY = 3  # depth frames logged: 10 a second of a 30 Hz camera

# A short perceptual colour ramp (viridis key colours) for particle weights.
_RAMP = np.array(
    [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64
)


def weight_colours(weights: np.ndarray, log: bool = False) -> np.ndarray:
    """``[N]`` weights (or log-weights) -> ``[N, 3] uint8`` colours, dark = low, yellow = high.

    Weights are scaled by their maximum; non-finite or all-zero weights give the low colour.
    """
    w = np.asarray(weights, np.float64).ravel()
    if log:
        finite = np.isfinite(w)
        top = w[finite].max() if finite.any() else 0.0
        w = np.where(finite, np.exp(w - top), 0.0)
    w = np.where(np.isfinite(w), np.maximum(w, 0.0), 0.0)
    top = w.max() if w.size else 0.0
    t = w / top if top > 0 else np.zeros_like(w)
    pos = t * (len(_RAMP) - 1)
    lo = np.clip(np.floor(pos).astype(int), 0, len(_RAMP) - 2)
    frac = (pos - lo)[:, None]
    rgb = _RAMP[lo] * (1 - frac) + _RAMP[lo + 1] * frac
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def identity_colour(ident: int) -> tuple[int, int, int]:
    """A colour of its own for identity ``ident`` (hues a golden angle apart, so that
    identities born one after the other differ most), RGB 0-255."""
    import colorsys

    hue = (0.61803398875 * int(ident)) % 1.0
    return tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(hue, 0.85, 0.95))


def default_blueprint(points: bool = True) -> rrb.Blueprint:
    """The viewer's layout for a run: the colour image with the boxes, the particles and
    the 2D body points; the depth image in a view of its own (drawn over the colour one
    it would tint it); the 3D body beside the camera (``points``); ESS and step time.

    Both image views share the colour camera's pinhole (``IMAGE_SPACE``), so they show
    the same pixel grid; the 3D view holds the camera and what lies under ``world/body``.
    """
    image = rrb.Spatial2DView(
        name="colour: tracker (green), ground truth (red)",
        origin=IMAGE_SPACE,
        contents=["$origin/**", "- $origin/depth"],
    )
    depth = rrb.Spatial2DView(name="depth", origin=IMAGE_SPACE, contents=["$origin/depth"])
    series = rrb.Vertical(
        rrb.TimeSeriesView(name="effective sample size", origin="series/ess"),
        rrb.TimeSeriesView(name="ms per step", origin="series/ms_per_frame"),
    )
    side = [depth]
    if points:
        body = rrb.Spatial3DView(
            name="body (3D)", origin="world", contents=["world/body/**", "world/camera"]
        )
        side.append(body)
    layout = rrb.Horizontal(image, rrb.Vertical(*side), series, column_shares=[3, 2, 2])
    return rrb.Blueprint(layout, collapse_panels=True)


def _np(x: Any) -> np.ndarray:
    return np.asarray(x)


class RerunLogger:
    """Log frames, boxes, particles, points and scalars of a run to Rerun.

    Args:
      rrd: write the recording to this ``.rrd`` file (headless).
      spawn: start a Rerun viewer and stream to it (needs a display).
      connect: stream to a running viewer at this gRPC URL
        (e.g. ``rerun+http://127.0.0.1:9876/proxy``).
      application_id: Rerun application id.
      recording_id: optional id, e.g. to merge runs in one viewer.
      raw: log colour and depth pixels as they are, every frame (default: JPEG colour,
        PNG depth every ``depth_every``-th frame; see the module docstring).
      depth_every: log the depth image of every this many frames (compact logging).
      blueprint: the viewer's layout, sent with the recording (default
        :func:`default_blueprint`; None: Rerun's own heuristics).

    Any combination of the three sinks works; at least one is required.
    Call :meth:`close` (or use ``with``) so the ``.rrd`` file is finished.
    """

    def __init__(
        self,
        rrd: Path | str | None = None,
        *,
        spawn: bool = False,
        connect: str | None = None,
        application_id: str = "cpf_jax",
        recording_id: str | None = None,
        raw: bool = False,
        depth_every: int = DEPTH_EVERY,
        blueprint: rrb.Blueprint | Literal["default"] | None = "default",
    ) -> None:
        if rrd is None and not spawn and connect is None:
            raise ValueError("RerunLogger needs an .rrd path, spawn=True or a connect URL")
        if depth_every < 1:
            raise ValueError(f"depth_every must be >= 1, got {depth_every}")
        self.raw, self.depth_every = raw, 1 if raw else int(depth_every)
        self._depth_logged = -1
        self.rrd = None if rrd is None else Path(rrd)
        self.viewer = connect if connect is not None else ("spawned viewer" if spawn else None)
        if connect is not None:
            check_viewer(connect)
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self.rec.set_log_time_enabled(False)
        if spawn:
            _spawn_viewer(self.rec)
        sinks: list[Any] = []
        if self.rrd is not None:
            if self.rrd.is_dir():
                raise OutputError(f"{self.rrd}: is a directory, not an .rrd file to write")
            try:
                self.rrd.parent.mkdir(parents=True, exist_ok=True)
                sinks.append(rr.FileSink(str(self.rrd)))
            except (OSError, RuntimeError) as e:
                raise OutputError(f"{self.rrd}: cannot write the Rerun recording ({e})") from None
        if spawn or connect is not None:
            sinks.append(rr.GrpcSink(connect))
        try:
            self.rec.set_sinks(*sinks)
        except RuntimeError as e:  # the file sink opens its file here
            if self.rrd is None:
                raise
            raise OutputError(f"{self.rrd}: cannot write the Rerun recording ({e})") from None
        if isinstance(blueprint, str):
            if blueprint != "default":
                raise ValueError(f"blueprint must be a Blueprint, 'default' or None: {blueprint!r}")
            blueprint = default_blueprint()
        if blueprint is not None:
            self.rec.send_blueprint(blueprint)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self._pinhole: tuple[Intrinsics, int, int] | None = None
        self._closed = False

    # -- helpers -------------------------------------------------------------
    def _at(self, i: int) -> None:
        self.rec.set_time(TIMELINE, sequence=int(i))

    @staticmethod
    def _image_path(path: str) -> str:
        return f"{IMAGE_SPACE}/{path.strip('/')}"

    # -- frames ----------------------------------------------------------------
    def log_pinhole(self, intrinsics: Intrinsics, width: int, height: int) -> None:
        """Log the colour camera's pinhole model (static; again only if it changes)."""
        key = (Intrinsics(*map(float, intrinsics)), int(width), int(height))
        if key == self._pinhole:
            return
        self._pinhole = key
        k = key[0]
        self.rec.log(
            IMAGE_SPACE,
            rr.Pinhole(
                focal_length=[k.fx, k.fy],
                principal_point=[k.cx, k.cy],
                width=key[1],
                height=key[2],
                camera_xyz=rr.ViewCoordinates.RDF,
            ),
            static=True,
        )

    def log_frame(
        self,
        i: int,
        frame: Frame,
        intrinsics: Intrinsics | None = None,
        *,
        depth: bool | None = None,
    ) -> None:
        """Log the colour image and depth image of frame ``i`` (and the pinhole, once).

        ``depth=None`` logs the depth image unless it is all zeros (colour-only sources);
        compact logging logs it only every ``depth_every`` frames.
        """
        colour = _np(frame.colour)
        h, w = colour.shape[:2]
        if intrinsics is not None:
            self.log_pinhole(intrinsics, w, h)
        self._at(i)
        self.rec.log(f"{IMAGE_SPACE}/image", self._colour(colour))
        d = _np(frame.depth)
        due = self._depth_logged < 0 or i - self._depth_logged >= self.depth_every
        if due and (depth or (depth is None and d.any())):
            self.rec.log(f"{IMAGE_SPACE}/depth", self._depth(d.astype(np.uint16)))
            self._depth_logged = i

    def _colour(self, colour: np.ndarray) -> Any:
        if self.raw:
            return rr.Image(colour, color_model="RGB")
        bgr = np.ascontiguousarray(colour[..., ::-1])
        _, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        return rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg")

    def _depth(self, depth_mm: np.ndarray) -> Any:
        if self.raw:
            return rr.DepthImage(depth_mm, meter=1000.0)
        _, png = cv2.imencode(".png", depth_mm)  # 16-bit, lossless; integer depth is mm
        return rr.EncodedDepthImage(blob=png.tobytes(), media_type="image/png")

    # -- boxes -------------------------------------------------------------------
    def log_box(
        self,
        i: int,
        box_xywh: Any,
        path: str = "tracker/box",
        label: str | None = None,
        colour: Sequence[int] = (0, 200, 0),
    ) -> None:
        """Log one or more ``[..., 4]`` xywh boxes (top-left, pixels) at ``world/camera/<path>``.

        Non-finite or empty boxes (a lost tracker, an invisible target) clear the entity.
        """
        boxes = _np(box_xywh).astype(np.float32).reshape(-1, 4)
        ok = np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
        self._at(i)
        entity = self._image_path(path)
        if not ok.any():
            self.rec.log(entity, rr.Clear(recursive=False))
            return
        boxes = boxes[ok]
        labels = None if label is None else [label] * len(boxes)
        self.rec.log(
            entity,
            rr.Boxes2D(mins=boxes[:, :2], sizes=boxes[:, 2:], labels=labels, colors=[colour]),
        )

    def log_gt_box(self, i: int, box_xywh: Any, label: str | None = "GT") -> None:
        """Log the ground-truth box at ``world/camera/gt/box`` (red)."""
        self.log_box(i, box_xywh, path="gt/box", label=label, colour=(220, 40, 40))

    def log_people(self, i: int, ids: Any, boxes_xywh: Any, path: str = "people") -> None:
        """Log the boxes ``[K, 4]`` (xywh) of people ``ids [K]`` at ``world/camera/<path>``,
        each in its identity's colour (:func:`identity_colour`) with its id as label; no
        people clears the entity."""
        ids = _np(ids).astype(np.int64).reshape(-1)
        boxes = _np(boxes_xywh).astype(np.float32).reshape(-1, 4)
        self._at(i)
        entity = self._image_path(path)
        if not len(ids):
            self.rec.log(entity, rr.Clear(recursive=False))
            return
        self.rec.log(
            entity,
            rr.Boxes2D(
                mins=boxes[:, :2],
                sizes=boxes[:, 2:],
                labels=[f"id {n}" for n in ids],
                colors=[identity_colour(n) for n in ids],
                class_ids=ids,
                show_labels=True,
            ),
        )

    def log_event(self, i: int, text: str, level: str = "INFO") -> None:
        """Log one line of text (a birth, a loss, a death) at ``events``."""
        self._at(i)
        self.rec.log("events", rr.TextLog(text, level=level))

    # -- particles and points ----------------------------------------------------
    def log_particles(
        self,
        i: int,
        boxes_or_centres: Any,
        weights: Any,
        path: str = "tracker/particles",
        *,
        log_weights: bool = False,
        show_boxes: bool = False,
        radius: float = 2.0,
    ) -> None:
        """Log particles as points coloured by weight (``[N, 4]`` xywh boxes or ``[N, 2]`` points).

        Box particles are drawn at their centres; ``show_boxes`` also draws the
        boxes at ``<path>/boxes``. ``log_weights`` says the weights are logs.
        """
        p = _np(boxes_or_centres).astype(np.float32)
        if p.ndim != 2 or p.shape[1] not in (2, 4):
            raise ValueError(f"particles must be [N, 2] points or [N, 4] boxes, got {p.shape}")
        colours = weight_colours(_np(weights), log=log_weights)
        if len(colours) != len(p):
            raise ValueError(f"{len(p)} particles but {len(colours)} weights")
        centres = p if p.shape[1] == 2 else p[:, :2] + p[:, 2:] / 2
        self._at(i)
        entity = self._image_path(path)
        self.rec.log(entity, rr.Points2D(centres, colors=colours, radii=radius))
        if show_boxes and p.shape[1] == 4:
            self.rec.log(
                f"{entity}/boxes", rr.Boxes2D(mins=p[:, :2], sizes=p[:, 2:], colors=colours)
            )

    def log_points2d(
        self,
        i: int,
        points: Any,
        path: str = "body/points",
        *,
        labels: Sequence[str] | None = None,
        colours: Any = None,
        radius: float = 4.0,
    ) -> None:
        """Log ``[K, 2]`` image points (pixels) at ``world/camera/<path>``."""
        pts = _np(points).astype(np.float32).reshape(-1, 2)
        self._at(i)
        self.rec.log(
            self._image_path(path),
            rr.Points2D(pts, labels=labels, colors=colours, radii=radius),
        )

    def log_points3d(
        self,
        i: int,
        points_mm: Any,
        path: str = "body/points3d",
        *,
        labels: Sequence[str] | None = None,
        colours: Any = None,
        radius: float = 0.01,
    ) -> None:
        """Log ``[K, 3]`` camera-frame points in mm (shown in metres) at ``world/<path>``."""
        pts = _np(points_mm).astype(np.float32).reshape(-1, 3) / 1000.0
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        self._at(i)
        self.rec.log(
            f"world/{path.strip('/')}",
            rr.Points3D(pts, labels=labels, colors=colours, radii=radius),
        )

    def log_cloud(
        self, i: int, state: Any, path: str = "tracker/particles", *, weighed: Any = None
    ) -> None:
        """The particles of any box filter's state (``state.cloud``), coloured by weight, or
        those of ``weighed`` (an info's ``weighed_cloud``: the weights before resampling,
        which after it are uniform)."""
        boxes, log_weights = cloud_boxes(state.cloud if weighed is None else weighed)
        self.log_particles(i, np.asarray(boxes), np.asarray(log_weights), path, log_weights=True)

    # -- scalars -----------------------------------------------------------------
    def log_scalar(self, i: int, name: str, value: float) -> None:
        """Log one value of the time series ``series/<name>`` (ESS, ms per step, ...)."""
        self._at(i)
        self.rec.log(f"series/{name.strip('/')}", rr.Scalars(float(value)))

    # -- lifetime -------------------------------------------------------------------
    def close(self) -> None:
        """Flush and close the sinks; the ``.rrd`` file is complete after this."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rec.flush()
        except RuntimeError as e:  # the gRPC sink lost (or never had) its viewer
            self.rec.disconnect()
            raise ViewerUnavailable(
                f"Rerun {self.viewer}: the log could not be delivered ({str(e).splitlines()[0]})"
            ) from None
        self.rec.disconnect()

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def viewer_executable() -> str | None:
    """The ``rerun`` viewer executable that ships with rerun-sdk (``rerun_cli``), found
    even when the virtual environment's ``bin`` is not on ``PATH``; else the one on
    ``PATH``, else None."""
    import shutil

    try:
        import rerun_cli

        bundled = Path(rerun_cli.__file__).parent / "rerun"
        if bundled.is_file():
            return str(bundled)
    except ImportError:
        pass
    return shutil.which("rerun")


def _spawn_viewer(rec: rr.RecordingStream) -> None:
    """Start a Rerun viewer for ``rec`` to stream to (port 9876), or raise one clear
    :class:`~cpf_jax.errors.ViewerUnavailable`.

    The viewer is :func:`viewer_executable`. On Linux a viewer window needs ``DISPLAY``
    or ``WAYLAND_DISPLAY``; without one the run would only fail when the log is flushed
    at its end.
    """
    import os
    import sys

    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise ViewerUnavailable(
            "a Rerun viewer needs a display (DISPLAY / WAYLAND_DISPLAY unset): write --rrd FILE "
            "and open it elsewhere, or --connect to a viewer on another machine"
        )
    try:
        rr.spawn(connect=False, executable_path=viewer_executable(), recording=rec)
    except RuntimeError as e:
        raise ViewerUnavailable(f"cannot start a Rerun viewer: {str(e).splitlines()[0]}") from None


def check_viewer(url: str, timeout: float = 2.0) -> None:
    """Raise :class:`~cpf_jax.errors.ViewerUnavailable` unless something listens at the
    host and port of the Rerun gRPC ``url`` (``rerun+http://host:port/proxy``).

    Rerun's gRPC sink connects in the background and only fails when the recording is
    flushed, after the whole run: this check makes a mistyped URL or a viewer that is
    not running a one-line error before tracking starts.
    """
    parts = urlsplit(url.removeprefix("rerun+"))
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ViewerUnavailable(f"Rerun viewer URL {url!r}: expected rerun+http://host:port/proxy")
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        with socket.create_connection((parts.hostname, port), timeout=timeout):
            pass
    except OSError as e:
        raise ViewerUnavailable(
            f"Rerun viewer at {url}: cannot connect ({e.strerror or e}); start one with "
            "`rerun` or leave out --connect"
        ) from None
