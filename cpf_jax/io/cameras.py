"""Live camera sources: Intel RealSense (pyrealsense2) and Kinect v2 (pylibfreenect2).

Both are optional extras. When the library is missing, or no device answers,
opening the source raises :class:`~cpf_jax.errors.CameraUnavailable` with one
line that says what to install or check. The libraries are imported when a
source is opened, never at module import.

Frames are registered to one image: RealSense depth is aligned to the colour
stream (``rs.align``); Kinect v2 colour is mapped onto the 512x424 depth image
by libfreenect2's ``Registration`` (the thesis's set-up, T 5.1), so
``intrinsics`` are those of the depth camera there.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from cpf_jax.errors import CameraUnavailable, SourceError
from cpf_jax.io.base import LiveSource
from cpf_jax.types import Frame, Intrinsics

__all__ = ["RealSenseSource", "KinectV2Source", "REALSENSE_HINT", "KINECT_HINT"]

REALSENSE_HINT = (
    "RealSense source needs pyrealsense2: pip install 'cpf_jax[realsense]' "
    "(and Debian's libusb-1.0-0)"
)
KINECT_HINT = (
    "Kinect v2 source needs pylibfreenect2, which needs libfreenect2, and Debian does not "
    "package libfreenect2: build it from https://github.com/OpenKinect/libfreenect2 "
    "(cmake, make install), then LIBFREENECT2_INSTALL_PREFIX=<prefix> "
    "pip install 'cpf_jax[kinect]'"
)


def _import(module: str, hint: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as e:
        # A missing module gets the hint alone; a broken install (e.g. a missing
        # shared library) also gets the loader's reason.
        missing = isinstance(e, ModuleNotFoundError) and e.name == module
        detail = "" if missing or e.msg is None else f" (import failed: {e.msg})"
        raise CameraUnavailable(hint + detail) from None


class RealSenseSource(LiveSource):
    """Intel RealSense colour + depth aligned to colour, or playback of a recording.

    Args:
      serial: which camera (default: the first found).
      bag: play a recording instead of a live camera (ends with the file): ``.bag``
        (older librealsense) or ``.db3`` (pyrealsense2 2.59 records only ``.db3``).
      width, height, fps: stream settings for a live camera.
      timeout_ms: how long to wait for a frame before giving up.
    """

    kind = "realsense"

    def __init__(
        self,
        serial: str | None = None,
        *,
        bag: Path | str | None = None,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        timeout_ms: int = 5000,
    ) -> None:
        rs = _import("pyrealsense2", REALSENSE_HINT)
        self._rs = rs
        self.bag = None if bag is None else Path(bag)
        self.timeout_ms = timeout_ms
        if self.bag is not None and not self.bag.is_file():
            raise SourceError(f"{self.bag}: no such RealSense recording")
        self._pipeline = rs.pipeline()
        config = rs.config()
        if self.bag is not None:
            config.enable_device_from_file(str(self.bag), repeat_playback=False)
        else:
            if serial:
                config.enable_device(serial)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as e:
            what = str(self.bag) if self.bag else f"RealSense camera {serial or ''}".strip()
            raise CameraUnavailable(f"{what}: cannot start streaming ({e})") from None
        device = profile.get_device()
        self._playback = None
        if self.bag is not None:
            self._playback = self._rewind(device.as_playback())
        self._mm_per_unit = float(device.first_depth_sensor().get_depth_scale()) * 1000.0
        self._align = rs.align(rs.stream.color)
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self.intrinsics = Intrinsics(
            float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy)
        )
        self.size = (int(intr.width), int(intr.height))
        self._running = True

    def _rewind(self, playback: Any) -> Any:
        """Pause a recording at its start, as fast as it can be read (not real time).

        Playback starts with the pipeline, in real time, so the first frame can go out
        before ``set_real_time(False)`` and be lost. Paused, rewound and drained here, it
        is resumed by :meth:`__iter__`, so every recorded frame arrives, in order.
        """
        from datetime import timedelta

        playback.pause()
        playback.set_real_time(False)
        playback.seek(timedelta(0))
        ok, _ = self._pipeline.try_wait_for_frames(50)
        while ok:  # frames delivered before the pause (they come again after the seek)
            ok, _ = self._pipeline.try_wait_for_frames(50)
        return playback

    def describe(self) -> str:
        return str(self.bag) if self.bag else "realsense"

    def __iter__(self) -> Iterator[Frame]:
        rs = self._rs
        if self._playback is not None:
            self._playback.resume()
        while self._running:
            ok, frames = self._pipeline.try_wait_for_frames(self.timeout_ms)
            if not ok:
                if self.bag is not None:
                    return  # end of the recording
                raise CameraUnavailable(f"RealSense: no frame within {self.timeout_ms} ms")
            aligned = self._align.process(frames)
            c, d = aligned.get_color_frame(), aligned.get_depth_frame()
            if not c or not d:
                continue
            colour = np.asanyarray(c.get_data()).copy()
            if c.get_profile().format() == rs.format.bgr8:
                colour = np.ascontiguousarray(colour[..., ::-1])
            depth = np.asanyarray(d.get_data())
            if abs(self._mm_per_unit - 1.0) > 1e-6:
                depth = np.clip(np.rint(depth * self._mm_per_unit), 0, 65535)
            yield Frame(colour, depth.astype(np.uint16))

    def close(self) -> None:
        if self._running:
            self._running = False
            self._pipeline.stop()


class KinectV2Source(LiveSource):
    """Kinect v2 through libfreenect2: colour registered onto the 512x424 depth image.

    Args:
      serial: which device (default: the first found).
      pipeline: libfreenect2 packet pipeline, ``"cpu"``, ``"opengl"``, ``"opencl"`` or ``"cuda"``.
    """

    kind = "kinect2"

    def __init__(self, serial: str | None = None, *, pipeline: str = "cpu") -> None:
        fn2 = _import("pylibfreenect2", KINECT_HINT)
        names = {
            "cpu": "CpuPacketPipeline",
            "opengl": "OpenGLPacketPipeline",
            "opencl": "OpenCLPacketPipeline",
            "cuda": "CudaPacketPipeline",
        }
        if pipeline not in names or not hasattr(fn2, names[pipeline]):
            raise CameraUnavailable(f"Kinect v2: packet pipeline {pipeline!r} is not available")
        self._fn2 = fn2
        self._freenect = fn2.Freenect2()
        if self._freenect.enumerateDevices() == 0:
            raise CameraUnavailable("Kinect v2: no device found (check USB 3 and power)")
        serial = serial or self._freenect.getDeviceSerialNumber(0)
        device = self._freenect.openDevice(serial, pipeline=getattr(fn2, names[pipeline])())
        if device is None:
            raise CameraUnavailable(f"Kinect v2 {serial}: cannot open device")
        self._device = device
        types = fn2.FrameType.Color | fn2.FrameType.Ir | fn2.FrameType.Depth
        self._listener = fn2.SyncMultiFrameListener(types)
        device.setColorFrameListener(self._listener)
        device.setIrAndDepthFrameListener(self._listener)
        device.start()
        ir = device.getIrCameraParams()
        self._registration = fn2.Registration(ir, device.getColorCameraParams())
        self.intrinsics = Intrinsics(float(ir.fx), float(ir.fy), float(ir.cx), float(ir.cy))
        self.size = (512, 424)
        self._undistorted = fn2.Frame(512, 424, 4)
        self._registered = fn2.Frame(512, 424, 4)
        self._running = True

    def __iter__(self) -> Iterator[Frame]:
        while self._running:
            frames: Any = self._listener.waitForNewFrame()
            try:
                self._registration.apply(
                    frames["color"], frames["depth"], self._undistorted, self._registered
                )
                bgrx = self._registered.asarray(np.uint8)
                colour = np.ascontiguousarray(bgrx[..., 2::-1])
                depth_mm = self._undistorted.asarray(np.float32)
                depth_mm = np.where(np.isfinite(depth_mm), depth_mm, 0.0)
                depth = np.clip(np.rint(depth_mm), 0, 65535).astype(np.uint16)
            finally:
                self._listener.release(frames)
            yield Frame(colour, depth)

    def close(self) -> None:
        if self._running:
            self._running = False
            self._device.stop()
            self._device.close()
