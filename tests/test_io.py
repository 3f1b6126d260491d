"""Tests for cpf_jax.io: every loader on tiny folders made here, plus the shared recordings."""

from __future__ import annotations

import sys
import types
import warnings
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import pytest

from cpf_jax import io as cio
from cpf_jax.errors import CameraUnavailable, CpfJaxError, GroundTruthWarning, SourceError
from cpf_jax.io import cameras, folders
from cpf_jax.types import Frame, Intrinsics

SHARED = Path(__file__).parents[1] / ".." / "shared" / "data"
needs_shared = pytest.mark.skipif(
    not SHARED.is_dir(), reason=f"shared recordings not present at {SHARED.resolve()}"
)


# -- helpers that write tiny datasets ------------------------------------------


def rgb_image(i: int, h: int = 12, w: int = 16) -> np.ndarray:
    """A frame whose left half is pure red and whose green channel encodes ``i``."""
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : w // 2, 0] = 255
    img[:, w // 2 :, 1] = (10 * i) % 256
    return img


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rgb[..., ::-1])


def write_depth(path: Path, depth: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), depth)


def make_otb(root: Path, n: int = 5, gt: str | None = None, ext: str = ".png") -> Path:
    for i in range(n):
        write_rgb(root / "img" / f"{i + 1:04d}{ext}", rgb_image(i))
    if gt is None:
        gt = "".join(f"{i + 2},{i + 3},4,5\n" for i in range(n))
    (root / "groundtruth_rect.txt").write_text(gt)
    return root


def make_rgbd(root: Path, n: int = 4, rgb_name="images{:08d}.jpg", depth_name="images{:08d}.png"):
    for i in range(n):
        write_rgb(root / "rgb" / rgb_name.format(i + 1), rgb_image(i))
        write_depth(
            root / "depth" / depth_name.format(i + 1), np.full((12, 16), 1000 + i, np.uint16)
        )
    return root


# -- errors -------------------------------------------------------------------


def test_error_hierarchy():
    assert issubclass(SourceError, CpfJaxError)
    assert issubclass(CameraUnavailable, SourceError)


# -- OTB ------------------------------------------------------------------------


def test_otb_tmp_folder(tmp_path):
    gt = "2,3,4,5\n0,0,0,0\n7\t8\t9\t10\n11 12 13 14\n15;16;17;18\n\n"
    src = cio.open_source(str(make_otb(tmp_path, gt=gt)))
    assert isinstance(src, cio.ImageFolderSource) and src.kind == "otb"
    assert len(src) == 5 and src.names[0] == "0001.png"
    assert src.size == (16, 12)
    np.testing.assert_array_equal(
        src.gt_boxes,
        [[1, 2, 4, 5], [0, 0, 0, 0], [6, 7, 9, 10], [10, 11, 13, 14], [14, 15, 17, 18]],
    )
    assert src.gt_boxes.dtype == np.float32
    np.testing.assert_array_equal(src.visible, [True, False, True, True, True])
    frame = src[3]
    assert isinstance(frame, Frame)
    assert frame.colour.dtype == np.uint8 and frame.colour.shape == (12, 16, 3)
    np.testing.assert_array_equal(frame.colour, rgb_image(3))  # RGB order, PNG exact
    assert (
        frame.depth.dtype == np.uint16 and frame.depth.shape == (12, 16) and not frame.depth.any()
    )
    assert src[-1].colour[0, -1, 1] == 40
    assert [int(f.colour[0, -1, 1]) for f in src] == [0, 10, 20, 30, 40]
    assert src.first_visible == 0 and list(src.init_box) == [1, 2, 4, 5]
    assert src.intrinsics is None and src.calibration is None
    with pytest.raises(IndexError):
        src.read(5)


def test_first_visible_skips_invisible_frames(tmp_path):
    src = cio.open_otb(make_otb(tmp_path, n=3, gt="0,0,0,0\nNaN,NaN,NaN,NaN\n5,6,7,8\n"))
    assert src.first_visible == 2
    np.testing.assert_array_equal(src.init_box, [4, 5, 7, 8])
    assert not np.isnan(src.gt_boxes).any()


@needs_shared
@pytest.mark.shared_data
def test_otb_crossing():
    src = cio.open_source(str(SHARED / "otb" / "Crossing"))
    assert src.kind == "otb" and len(src) == 120 and src.size == (360, 240)
    np.testing.assert_array_equal(src.gt_boxes[0], [204, 150, 17, 50])  # file says 205,151,17,50
    assert src.visible.all()
    f = src[0]
    assert f.colour.shape == (240, 360, 3) and f.depth.shape == (240, 360)


# -- recorded RGB-D --------------------------------------------------------------


def test_rgbd_folder_pairs_by_stem_and_loads_extras(tmp_path):
    root = make_rgbd(tmp_path)
    (root / "groundtruth_rect.txt").write_text("0,0,0,0\n3,3,5,5\n3,3,5,5\n0,0,0,0\n")
    (root / "occlusion.txt").write_text("full\npartial\nnone\nfull\n")
    (root / "calibration.json").write_text(
        '{"intrinsics": {"fx": 500, "fy": 501, "cx": 7.5, "cy": 5.5}}'
    )
    src = cio.open_source(root)
    assert src.kind == "rgbd" and src.has_depth
    assert [p.name for p in src.depth_paths] == [f"images{i:08d}.png" for i in range(1, 5)]
    assert src[2].depth[0, 0] == 1002 and src[2].depth.dtype == np.uint16
    assert src.occlusion == ["full", "partial", "none", "full"]
    assert src.calibration["intrinsics"]["fx"] == 500
    assert src.intrinsics == Intrinsics(500.0, 501.0, 7.5, 5.5)
    assert src.first_visible == 1


def test_rgbd_pairs_by_number_then_by_order(tmp_path):
    a = make_rgbd(tmp_path / "a", rgb_name="rgb_{}.jpg", depth_name="depth_{}.png")
    src = cio.open_rgbd_folder(a)
    assert [p.name for p in src.depth_paths] == [f"depth_{i}.png" for i in range(1, 5)]
    assert [int(f.depth[0, 0]) for f in src] == [1000, 1001, 1002, 1003]
    b = make_rgbd(tmp_path / "b", rgb_name="c{}.png", depth_name="x.d{}.png")
    assert [p.name for p in cio.open_rgbd_folder(b).depth_paths][0] == "x.d1.png"
    # no depth folder: colour only
    (tmp_path / "c" / "rgb").mkdir(parents=True)
    write_rgb(tmp_path / "c" / "rgb" / "f.png", rgb_image(0))
    c = cio.open_rgbd_folder(tmp_path / "c")
    assert not c.has_depth and not c[0].depth.any()


def test_rgbd_unpairable_depth_raises(tmp_path):
    root = make_rgbd(tmp_path, n=3)
    (root / "depth" / "images00000003.png").rename(root / "depth" / "other.png")
    write_depth(root / "depth" / "more.png", np.zeros((12, 16), np.uint16))
    with pytest.raises(SourceError, match=r"cannot pair 4 depth images with 3 colour"):
        cio.open_rgbd_folder(root)


@needs_shared
@pytest.mark.shared_data
def test_ist_rgbd_recording():
    src = cio.open_source(SHARED / "ist_piv_rgbd" / "images1")
    assert src.kind == "rgbd" and len(src) == 108 and src.size == (640, 480)
    assert src.depth_paths[0].name == "images00000001.png"
    assert src.first_visible == 50 and src.visible.sum() == 40
    assert len(src.occlusion) == 108 and src.occlusion[0] == "full"
    f = src[60]
    assert f.depth.dtype == np.uint16 and f.depth.shape == (480, 640) and f.depth.max() > 500


# -- Princeton and TUM ----------------------------------------------------------------


def test_princeton_layout(tmp_path):
    mm = np.array([[500, 1234], [8000, 0]], np.uint16)

    def rotate(d):  # how PTB stores depth
        return ((d << np.uint16(3)) | (d >> np.uint16(13))).astype(np.uint16)

    for n, t in ((1, 100), (2, 133), (10, 400)):  # natural order 1, 2, 10
        write_rgb(tmp_path / "rgb" / f"r-{t}-{n}.png", rgb_image(n, 2, 2))
        write_depth(tmp_path / "depth" / f"d-{t + 5}-{n}.png", rotate(mm + np.uint16(n)))
    (tmp_path / "init.txt").write_text("11,21,31,41\n")
    assert cio.detect_folder_kind(tmp_path) == "princeton"
    src = cio.open_source(tmp_path)
    assert src.kind == "princeton" and src.names == ["r-100-1.png", "r-133-2.png", "r-400-10.png"]
    np.testing.assert_array_equal(src[2].depth, mm + 10)
    np.testing.assert_array_equal(src.init_box, [10, 20, 31, 41])
    assert src.first_visible == 0 and src.gt_boxes is None


def test_princeton_depth_decoder_matches_formula():
    raw = np.arange(0, 65536, 7, dtype=np.uint16)
    want = ((raw.astype(np.uint32) >> 3) | ((raw.astype(np.uint32) << 13) & 0xFFFF)).astype(
        np.uint16
    )
    np.testing.assert_array_equal(cio.princeton_depth(raw), want)


def test_tum_layout(tmp_path):
    for k, t in enumerate((1.00, 1.033, 1.066)):
        write_rgb(tmp_path / "rgb" / f"{t:.3f}.png", rgb_image(k))
    write_depth(tmp_path / "depth" / "a.png", np.full((12, 16), 5000, np.uint16))  # 1 m
    write_depth(tmp_path / "depth" / "b.png", np.full((12, 16), 7500, np.uint16))
    (tmp_path / "rgb.txt").write_text(
        "# colour\n1.000 rgb/1.000.png\n1.033 rgb/1.033.png\n1.066 rgb/1.066.png\n"
    )
    (tmp_path / "depth.txt").write_text("# depth\n1.035 depth/b.png\n1.005 depth/a.png\n")
    src = cio.open_source(tmp_path)
    assert src.kind == "tum" and len(src) == 3
    assert src[0].depth[0, 0] == 1000 and src[1].depth[0, 0] == 1500
    assert not src[2].depth.any()  # nearest depth is 31 ms away: none


# -- .npz, video, synthetic ------------------------------------------------------------------


def test_npz_source_and_load_all(tmp_path):
    colour = np.stack([rgb_image(i) for i in range(4)])
    depth = 1000 + np.arange(4 * 12 * 16, dtype=np.uint16).reshape(4, 12, 16)  # 1-1.8 m
    boxes = np.array([[1, 2, 3, 4], [0, 0, 0, 0], [1, 2, 3, 4], [1, 2, 3, 4]], np.float32)
    np.savez(tmp_path / "s.npz", colour=colour, depth=depth, boxes=boxes, intrinsics=[5, 6, 7, 8])
    src = cio.open_source(tmp_path / "s.npz")
    assert src.kind == "npz" and len(src) == 4 and src.size == (16, 12)
    np.testing.assert_array_equal(src[2].depth, depth[2])
    np.testing.assert_array_equal(src.visible, [True, False, True, True])
    assert src.intrinsics == Intrinsics(5.0, 6.0, 7.0, 8.0)
    rec = src.load_all(1, 3)
    assert isinstance(rec, cio.Recording)
    np.testing.assert_array_equal(rec.colour, colour[1:3])
    np.testing.assert_array_equal(rec.boxes, boxes[1:3])
    np.savez(tmp_path / "c.npz", rgb=colour)
    assert not cio.open_source(tmp_path / "c.npz")[0].depth.any()


@pytest.mark.parametrize(
    "arrays, message",
    [
        ({"depth": np.zeros((2, 3, 3), np.uint16)}, "no 'colour' array"),
        ({"colour": np.zeros((2, 3, 3), np.uint8)}, r"must be \[T, H, W, 3\]"),
        (
            {"colour": np.zeros((2, 3, 3, 3), np.uint8), "boxes": np.zeros((3, 4))},
            "'boxes' must be",
        ),
        (
            {"colour": np.zeros((2, 3, 3, 3), np.uint8), "depth": np.full((2, 3, 3), -5, np.int32)},
            "int32 depth from -5 to 0 does not fit 16-bit millimetres",
        ),
    ],
)
def test_npz_bad_arrays(tmp_path, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(SourceError, match=message) as err:
        cio.open_source(tmp_path / "bad.npz").read(0)
    assert "bad.npz" in str(err.value)


def test_video_source(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for i in range(6):
        writer.write(np.full((24, 32, 3), (0, 40 * i, 200), np.uint8))  # BGR
    writer.release()
    src = cio.open_source(str(path))
    assert src.kind == "video" and len(src) == 6 and src.size == (32, 24) and src.fps == 10
    f = src[0]
    assert f.colour.shape == (24, 32, 3) and abs(int(f.colour[5, 5, 0]) - 200) < 8  # R first
    assert abs(int(src[4].colour[5, 5, 1]) - 160) < 8  # seek
    assert abs(int(src[1].colour[5, 5, 1]) - 40) < 8  # seek backwards
    assert [abs(int(f.colour[5, 5, 1]) - 40 * i) < 8 for i, f in enumerate(src)] == [True] * 6
    src.close()


@needs_shared
@pytest.mark.shared_data
def test_video_vtest():
    src = cio.open_source(SHARED / "opencv_samples" / "vtest" / "vtest.avi")
    assert len(src) == 795 and src.size == (768, 576)
    assert src[0].colour.shape == (576, 768, 3)


class FakeScenario(NamedTuple):
    colour: np.ndarray
    depth: np.ndarray
    boxes: np.ndarray
    visible: np.ndarray
    intrinsics: tuple
    points3d: np.ndarray


def fake_scenario(t: int = 3) -> FakeScenario:
    import jax.numpy as jnp  # the generator returns JAX arrays

    return FakeScenario(
        colour=jnp.zeros((t, 6, 8, 3), jnp.uint8),
        depth=jnp.full((t, 6, 8), 2000.4, jnp.float32),
        boxes=jnp.tile(jnp.array([1.0, 1.0, 3.0, 4.0]), (t, 1)),
        visible=jnp.array([True] * (t - 1) + [False]),
        intrinsics=(365.0, 365.0, 3.5, 2.5),
        points3d=jnp.zeros((t, 5, 3)),
    )


def test_synthetic_adapter():
    src = cio.SyntheticSource(fake_scenario(), name="walk")
    assert src.kind == "synthetic" and len(src) == 3 and src.size == (8, 6)
    f = src[1]
    assert f.colour.dtype == np.uint8 and f.depth.dtype == np.uint16 and f.depth[0, 0] == 2000
    assert isinstance(src.gt_boxes, np.ndarray) and src.gt_boxes.dtype == np.float32
    np.testing.assert_array_equal(src.visible, [True, True, False])
    assert src.intrinsics == Intrinsics(365.0, 365.0, 3.5, 2.5)
    assert src.sequence.points3d.shape == (3, 5, 3)
    assert src.load_all().colour.shape == (3, 6, 8, 3)
    floats = fake_scenario()._replace(colour=np.full((3, 6, 8, 3), 0.5, np.float32))
    assert cio.SyntheticSource(floats)[0].colour[0, 0, 0] == 128


def test_open_source_dispatches_names_to_synthetic(monkeypatch):
    calls = []

    def make_sequence(name, **kw):
        calls.append(name)
        return fake_scenario()

    fake = types.ModuleType("cpf_jax.synthetic")
    fake.SCENARIOS = ("walk_across_medium", "walk_towards_slow")
    fake.make_sequence = make_sequence
    monkeypatch.setitem(sys.modules, "cpf_jax.synthetic", fake)
    src = cio.open_source("walk_across_medium")
    assert isinstance(src, cio.SyntheticSource) and calls == ["walk_across_medium"]
    with pytest.raises(SourceError, match="scenarios: walk_across_medium, walk_towards_slow"):
        cio.open_source("walk_sideways")


# -- cameras ---------------------------------------------------------------------------------


def test_missing_camera_libraries_give_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # makes the import fail
    monkeypatch.setitem(sys.modules, "pylibfreenect2", None)
    with pytest.raises(CameraUnavailable) as rs_err:
        cio.open_source("realsense")
    msg = str(rs_err.value)
    assert "pyrealsense2" in msg and "cpf_jax[realsense]" in msg and "libusb" in msg
    assert "\n" not in msg
    with pytest.raises(CameraUnavailable) as k_err:
        cio.open_source("kinect2")
    msg = str(k_err.value)
    assert "libfreenect2" in msg and "Debian does not package" in msg and "\n" not in msg


def test_broken_camera_library_reports_the_loader_reason(monkeypatch):
    def fail(name):
        raise ImportError("libusb-1.0.so.0: cannot open shared object file")

    monkeypatch.setattr(cameras.importlib, "import_module", fail)
    with pytest.raises(CameraUnavailable, match="libusb-1.0.so.0: cannot open"):
        cio.RealSenseSource()


def fake_realsense(n_frames: int, start_error: bool = False) -> types.ModuleType:
    """Just enough of pyrealsense2 to drive RealSenseSource without a camera."""
    rs = types.ModuleType("pyrealsense2")
    rs.stream = types.SimpleNamespace(depth="depth", color="color")
    rs.format = types.SimpleNamespace(z16="z16", rgb8="rgb8", bgr8="bgr8")
    ns = types.SimpleNamespace

    def data_frame(array, fmt):
        return ns(get_data=lambda: array, get_profile=lambda: ns(format=lambda: fmt))

    class Pipeline:
        def __init__(self):
            self.left, self.stopped = n_frames, False

        def start(self, config):
            if start_error:
                raise RuntimeError("No device connected")
            intr = ns(fx=600.0, fy=601.0, ppx=3.5, ppy=2.5, width=8, height=6)
            stream = ns(as_video_stream_profile=lambda: ns(get_intrinsics=lambda: intr))
            sensor = ns(get_depth_scale=lambda: 0.0001)  # 0.1 mm units
            device = ns(first_depth_sensor=lambda: sensor)
            return ns(get_device=lambda: device, get_stream=lambda s: stream)

        def try_wait_for_frames(self, timeout_ms):
            if self.left == 0:
                return False, None
            self.left -= 1
            bgr = np.zeros((6, 8, 3), np.uint8)
            bgr[..., 2] = 200
            return True, ns(
                get_color_frame=lambda: data_frame(bgr, "bgr8"),
                get_depth_frame=lambda: data_frame(np.full((6, 8), 12345, np.uint16), "z16"),
            )

        def stop(self):
            self.stopped = True

    rs.pipeline = Pipeline
    rs.config = lambda: ns(enable_stream=lambda *a: None, enable_device=lambda s: None)
    rs.align = lambda to: ns(process=lambda frames: frames)
    return rs


def test_realsense_source_with_a_fake_library(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake_realsense(3))
    src = cio.open_source("realsense")
    assert src.intrinsics == Intrinsics(600.0, 601.0, 3.5, 2.5) and src.size == (8, 6)
    with pytest.raises(TypeError):
        len(src)
    with src, pytest.raises(CameraUnavailable, match="no frame within"):
        frames = []
        for f in src:
            frames.append(f)
    assert len(frames) == 3
    assert frames[0].colour[0, 0, 0] == 200  # BGR converted to RGB
    assert frames[0].depth.dtype == np.uint16 and frames[0].depth[0, 0] == 1234  # 0.1 mm -> mm
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake_realsense(0, start_error=True))
    with pytest.raises(CameraUnavailable, match="cannot start streaming.*No device"):
        cio.open_source("realsense:1234")


def _real_realsense():
    """The installed pyrealsense2, or None (optional extra; its wheel needs libusb-1.0)."""
    try:
        import pyrealsense2
    except ImportError:
        return None
    return pyrealsense2 if hasattr(pyrealsense2, "software_device") else None


def write_realsense_recording(rs, path, colour, depth, k: Intrinsics) -> None:
    """Record ``colour [T, H, W, 3]`` / ``depth [T, H, W]`` (mm) as a RealSense
    recording with librealsense's own recorder, through a software device (no camera)."""
    t, h, w = depth.shape
    dev = rs.software_device()
    sensors = dev.add_sensor("Depth"), dev.add_sensor("Color")
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = w, h, k.fx, k.fy, k.cx, k.cy
    intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
    profiles = []
    for uid, (sensor, kind, fmt, bpp) in enumerate(
        zip(
            sensors,
            (rs.stream.depth, rs.stream.color),
            (rs.format.z16, rs.format.rgb8),
            (2, 3),
            strict=True,
        )
    ):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height = kind, 0, uid, w, h
        vs.fps, vs.bpp, vs.fmt, vs.intrinsics = 30, bpp, fmt, intr
        profiles.append(sensor.add_video_stream(vs))
    sensors[0].add_read_only_option(rs.option.depth_units, 0.001)
    same = rs.extrinsics()
    same.rotation, same.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    profiles[0].register_extrinsics_to(profiles[1], same)
    dev.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), dev)
    sync = rs.syncer()
    for sensor, prof in zip(sensors, profiles, strict=True):
        sensor.open(prof)
        sensor.start(sync)
    for i in range(t):
        for sensor, prof, arr, bpp in zip(
            sensors, profiles, (depth[i], colour[i]), (2, 3), strict=True
        ):
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = np.ascontiguousarray(arr), bpp, w * bpp
            f.timestamp, f.frame_number = i * 1000.0 / 30, i
            f.domain = rs.timestamp_domain.hardware_clock
            f.profile = prof.as_video_stream_profile()
            sensor.on_video_frame(f)
        sync.wait_for_frames(1000)
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    del recorder  # finishes the file


@pytest.mark.skipif(
    _real_realsense() is None,
    reason="pyrealsense2 not installed (optional extra 'realsense'; its wheel needs libusb-1.0-0)",
)
def test_realsense_recording_plays_back_the_recorded_frames(tmp_path):
    # The other RealSense tests use a fake library; this one records a synthetic sequence
    # with librealsense's recorder and plays it back through RealSenseSource.
    from cpf_jax.synthetic import make_sequence

    rs = _real_realsense()
    seq = make_sequence("walk_across_slow", seed=3, n_frames=6)
    colour, depth = np.asarray(seq.colour), np.asarray(seq.depth)
    path = tmp_path / "walk.db3"  # pyrealsense2 2.59 records only .db3
    write_realsense_recording(rs, path, colour, depth, seq.intrinsics)
    src = cio.open_source(str(path))
    assert isinstance(src, cameras.RealSenseSource) and src.size == (512, 424)
    assert src.intrinsics == seq.intrinsics
    with src:
        frames = list(src)  # ends with the recording
    assert len(frames) == 6
    for t, f in enumerate(frames):
        np.testing.assert_array_equal(f.colour, colour[t])
        # rs.align re-projects depth even onto identical intrinsics: about 6 % of the
        # pixels change (2 % become holes, edges move by a pixel); the rest is exact.
        assert f.depth.dtype == np.uint16 and np.mean(f.depth == depth[t]) > 0.9
    # cpf-track on the recording (a live source) = on the same colour frames from a file.
    from cpf_jax.cli import main
    from cpf_jax.io import read_results

    npz = tmp_path / "walk.npz"
    np.savez(npz, colour=colour, depth=depth)
    box = ",".join(f"{v:g}" for v in seq.boxes[0])
    argv = ["--init", box, "--particles", "64", "--no-progress", "--out"]
    assert main([str(path), *argv, str(tmp_path / "a.csv")]) == 0
    assert main([str(npz), *argv, str(tmp_path / "b.csv")]) == 0
    a, b = read_results(tmp_path / "a.csv"), read_results(tmp_path / "b.csv")
    np.testing.assert_array_equal(a["frame"], np.arange(6))
    np.testing.assert_allclose(a["boxes"], b["boxes"], atol=1e-3)


def test_kinect_without_device(monkeypatch):
    fn2 = types.ModuleType("pylibfreenect2")
    fn2.CpuPacketPipeline = object
    fn2.Freenect2 = lambda: types.SimpleNamespace(enumerateDevices=lambda: 0)
    monkeypatch.setitem(sys.modules, "pylibfreenect2", fn2)
    with pytest.raises(CameraUnavailable, match="Kinect v2: no device found"):
        cio.open_source("kinect2")
    with pytest.raises(CameraUnavailable, match="pipeline 'cuda'"):
        cio.KinectV2Source(pipeline="cuda")


# -- bad input ---------------------------------------------------------------------------------


def test_nonexistent_path_and_empty_folder(tmp_path):
    with pytest.raises(SourceError, match="no such file or directory"):
        cio.open_source(str(tmp_path / "missing"))
    with pytest.raises(SourceError, match="no such file or directory"):
        cio.open_source("clip.npz")
    with pytest.raises(SourceError, match="no images found"):
        cio.open_source(tmp_path)
    (tmp_path / "img").mkdir()
    with pytest.raises(SourceError, match=r"img: no images found"):
        cio.open_otb(tmp_path)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(SourceError, match="unsupported file type .txt"):
        cio.open_source(tmp_path / "notes.txt")


def test_corrupt_image_names_the_file_when_read(tmp_path):
    root = make_otb(tmp_path, n=4, ext=".jpg")
    (root / "img" / "0003.jpg").write_bytes(b"not a jpeg at all")
    src = cio.open_otb(root)  # opening is lazy: no error yet
    src.read(1)
    with pytest.raises(SourceError, match=r"0003\.jpg: not a readable image"):
        src.read(2)
    (root / "img" / "0004.jpg").write_bytes(b"")
    with pytest.raises(SourceError, match=r"0004\.jpg"):
        src.read(3)


def test_groundtruth_parse_error_names_file_and_line(tmp_path):
    root = make_otb(tmp_path, n=3, gt="1,2,3,4\n1,2,three,4\n1,2,3,4\n")
    with pytest.raises(SourceError, match=r"groundtruth_rect\.txt:2: expected 4 numbers") as err:
        cio.open_otb(root)
    assert "three" in str(err.value) and "\n" not in str(err.value)
    (root / "groundtruth_rect.txt").write_text("1,2,3,4\n1,2,3\n1,2,3,4\n")
    with pytest.raises(SourceError, match=r":2: "):
        cio.open_otb(root)
    (root / "groundtruth_rect.txt").write_text("1,2,3,4\n\n1,2,3,4\n")
    with pytest.raises(SourceError, match=r":2: "):
        cio.open_otb(root)


def test_groundtruth_lines_that_cannot_be_boxes_are_named(tmp_path):
    """0,0,0,0 and all-NaN lines are the two "not visible" conventions and pass in
    silence; any other line read as not visible (a typo, most likely) is named."""
    gt = tmp_path / "gt.txt"
    gt.write_text("# x,y,w,h\n0,0,0,0\nNaN,NaN,NaN,NaN\n5,6,7,8\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        boxes, visible = cio.load_groundtruth(gt)
    assert visible.tolist() == [False, False, True]
    gt.write_text("5,6,7,8\n5,6,-7,8\n0,0,0,0\n5,nan,7,8\n5,6,7,0\n1,1,0,0\n1,1,-2,-2\n")
    with pytest.warns(GroundTruthWarning) as record:
        boxes, visible = cio.load_groundtruth(gt)
    assert visible.tolist() == [True] + [False] * 6
    np.testing.assert_array_equal(boxes[1:], 0.0)
    (message,) = [str(r.message) for r in record]
    assert "\n" not in message and str(gt) in message
    assert "5 line(s)" in message and "and 2 more" in message
    assert "line 2 '5,6,-7,8'" in message and "line 4 '5,nan,7,8'" in message
    assert "line 3" not in message  # 0,0,0,0: the convention


def test_groundtruth_count_mismatch(tmp_path):
    root = make_otb(tmp_path, n=3, gt="1,2,3,4\n1,2,3,4\n")
    with pytest.raises(SourceError, match=r"2 boxes for 3 images"):
        cio.open_otb(root)


@pytest.mark.parametrize(
    "image, what",
    [
        (np.zeros((12, 16), np.uint8), "uint8 with 1 channel"),
        (np.zeros((12, 16, 3), np.uint16), "3 channel"),
    ],
)
def test_depth_png_must_be_16_bit_single_channel(tmp_path, image, what):
    root = make_rgbd(tmp_path, n=2)
    assert cv2.imwrite(str(root / "depth" / "images00000002.png"), image)
    src = cio.open_rgbd_folder(root)
    src.read(0)
    with pytest.raises(
        SourceError, match=rf"images00000002\.png: depth image must be 16-bit.*{what}"
    ):
        src.read(1)


def test_image_size_change_is_reported(tmp_path):
    root = make_otb(tmp_path, n=3)
    write_rgb(root / "img" / "0002.png", rgb_image(1, h=10))
    src = cio.open_otb(root)
    src.read(0)
    with pytest.raises(
        SourceError, match=r"0002\.png: image is 16x10, but earlier frames .* 16x12"
    ):
        src.read(1)


def test_reading_is_lazy(tmp_path, monkeypatch):
    root = make_otb(tmp_path, n=50)
    reads = []
    real = folders.read_colour
    monkeypatch.setattr(folders, "read_colour", lambda p: reads.append(Path(p).name) or real(p))
    src = cio.open_source(root)
    assert len(src) == 50 and reads == []
    src.read(37)
    assert reads == ["0038.png"]
    rec = src.load_all(10, 14)
    assert rec.colour.shape == (4, 12, 16, 3) and rec.depth.shape == (4, 12, 16)
    assert rec.colour.dtype == np.uint8 and rec.depth.dtype == np.uint16
    np.testing.assert_array_equal(rec.boxes, src.gt_boxes[10:14])
    assert reads[1:] == ["0011.png", "0012.png", "0013.png", "0014.png"]


# -- results writer -----------------------------------------------------------------------------


def test_results_writer_flushes_each_row(tmp_path):
    path = tmp_path / "out" / "boxes.csv"
    writer = cio.ResultsWriter(path, extra_columns=("ess", "lost", "ms"))
    writer.write(0, np.array([1.5, 2.0, 30.0, 40.25]), ess=812.5, lost=False, ms=4.2)
    writer.write(1, [np.nan] * 4, lost=True)
    # read while the writer is still open, as after a crash
    lines = path.read_text().splitlines()
    assert lines == [
        "frame,x,y,w,h,ess,lost,ms",
        "0,1.5,2,30,40.25,812.5,0,4.2",
        "1,nan,nan,nan,nan,,1,",
    ]
    with pytest.raises(ValueError, match="unknown result columns"):
        writer.write(2, [0, 0, 1, 1], speed=3)
    with pytest.raises(ValueError, match="4 numbers"):
        writer.write(2, [0, 0, 1])
    writer.close()
    res = cio.read_results(path)
    np.testing.assert_array_equal(res["frame"], [0, 1])
    np.testing.assert_allclose(res["boxes"][0], [1.5, 2.0, 30.0, 40.25])
    assert np.isnan(res["boxes"][1]).all() and np.isnan(res["ess"][1]) and res["lost"][1] == 1


def test_read_results_drops_a_row_cut_short(tmp_path):
    path = tmp_path / "r.csv"
    with cio.ResultsWriter(path) as w:
        for i in range(3):
            w.write(i, [i, i, 5, 5])
    path.write_text(path.read_text() + "3,3,3")
    res = cio.read_results(path)
    assert res["boxes"].shape == (3, 4)
    path.write_text("a,b\n")
    with pytest.raises(SourceError, match="not a results file"):
        cio.read_results(path)


def test_synthetic_source_empty_background():
    from cpf_jax.io import open_synthetic

    src = open_synthetic("occlusion_return")
    bg = src.empty_background()
    assert bg.colour.shape == (424, 512, 3) and bg.colour.dtype == np.uint8
    assert bg.depth.shape == (424, 512) and bg.depth.dtype == np.uint16
    # The empty room lies behind the walker of frame 0.
    f0 = src.read(0)
    person = src.sequence.mask[0] & (f0.depth > 0) & (bg.depth > 0)
    assert np.median(bg.depth[person].astype(float) - f0.depth[person]) > 500
