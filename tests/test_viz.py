"""Tests for cpf_jax.viz: write a small .rrd and read it back with rerun.chunk.RrdReader."""

from __future__ import annotations

import warnings
from collections import defaultdict

import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from cpf_jax.types import Frame, Intrinsics
from cpf_jax.viz import RerunLogger, default_blueprint, weight_colours

T = 4


def read_rrd(path):
    """``{entity_path: {"frames": [...], "static": bool, "columns": set, "rows": [dict]}}``."""
    out = defaultdict(lambda: {"frames": [], "static": False, "columns": set(), "rows": []})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a missing footer warns: the file was not finished
        reader = RrdReader(path)
        for ch in reader.stream():
            data = ch.to_record_batch().to_pydict()
            e = out[ch.entity_path]
            e["static"] |= ch.is_static
            e["columns"] |= set(data)
            e["frames"] += data.get("frame", [])
            n = len(next(iter(data.values())))
            e["rows"] += [{k: v[r] for k, v in data.items()} for r in range(n)]
    return out


def frame(i: int, depth: bool = True) -> Frame:
    colour = np.zeros((6, 8, 3), np.uint8)
    colour[..., 0] = 10 * i
    d = np.full((6, 8), 1000 + i, np.uint16) if depth else np.zeros((6, 8), np.uint16)
    return Frame(colour, d)


def test_recording_round_trip(tmp_path):
    path = tmp_path / "run.rrd"
    k = Intrinsics(500.0, 501.0, 3.5, 2.5)
    rng = np.random.default_rng(0)
    with RerunLogger(path, raw=True) as log:
        for i in range(T):
            log.log_frame(i, frame(i), k)
            log.log_box(i, [1 + i, 2, 3, 4], label="cpf")
            log.log_gt_box(i, [1, 2, 3, 4] if i < T - 1 else [0, 0, 0, 0])
            log.log_particles(i, rng.uniform(0, 8, (10, 4)), rng.random(10), show_boxes=True)
            log.log_points2d(i, [[1, 1], [2, 3]], labels=["head", "hand"])
            log.log_points3d(i, [[0, 0, 1500], [np.nan, 0, 0]])
            log.log_scalar(i, "ess", 5.0 + i)
            log.log_scalar(i, "timing/step_ms", 3.0)
    rrd = read_rrd(path)
    per_frame = [
        "/world/camera/image",
        "/world/camera/depth",
        "/world/camera/tracker/box",
        "/world/camera/gt/box",
        "/world/camera/tracker/particles",
        "/world/camera/tracker/particles/boxes",
        "/world/camera/body/points",
        "/world/body/points3d",
        "/series/ess",
        "/series/timing/step_ms",
    ]
    for entity in per_frame:
        assert sorted(rrd[entity]["frames"]) == list(range(T)), entity
    assert (
        rrd["/world/camera"]["static"]
        and "Pinhole:image_from_camera" in rrd["/world/camera"]["columns"]
    )
    assert rrd["/world"]["static"]
    assert "DepthImage:meter" in rrd["/world/camera/depth"]["columns"]
    assert "Image:buffer" in rrd["/world/camera/image"]["columns"]  # raw=True
    assert "Boxes2D:labels" in rrd["/world/camera/tracker/box"]["columns"]
    ess = sorted((r["frame"], r["Scalars:scalars"]) for r in rrd["/series/ess"]["rows"])
    assert [v for _, v in ess] == [[5.0], [6.0], [7.0], [8.0]]
    # last GT box is "not visible": the entity is cleared, not given a zero box
    gt_rows = sorted(rrd["/world/camera/gt/box"]["rows"], key=lambda r: r["frame"])
    assert gt_rows[-1].get("Boxes2D:half_sizes") is None
    assert gt_rows[-1]["Clear:is_recursive"] == [False]
    pts3d = [r for r in rrd["/world/body/points3d"]["rows"] if r["frame"] == 0][0]
    np.testing.assert_allclose(
        pts3d["Points3D:positions"], [[0.0, 0.0, 1.5]]
    )  # mm -> m, NaN dropped
    particles = rrd["/world/camera/tracker/particles"]["rows"][0]
    assert len(particles["Points2D:positions"]) == 10 and len(particles["Points2D:colors"]) == 10


def test_compact_logging_encodes_colour_and_thins_depth_losslessly(tmp_path):
    from cpf_jax.synthetic import make_sequence

    seq = make_sequence("walk_towards", n_frames=6)
    sizes = {}
    for raw in (False, True):
        path = tmp_path / f"raw{raw}.rrd"
        with RerunLogger(path, raw=raw) as log:
            for i in range(6):
                log.log_frame(i, Frame(seq.colour[i], seq.depth[i]))
        sizes[raw] = path.stat().st_size / 6
    assert sizes[False] < 150_000 and sizes[True] > 5 * sizes[False], sizes  # bytes a frame
    rrd = read_rrd(tmp_path / "rawFalse.rrd")
    image, depth = rrd["/world/camera/image"], rrd["/world/camera/depth"]
    assert sorted(image["frames"]) == list(range(6)) and sorted(depth["frames"]) == [0, 3]
    assert image["rows"][0]["EncodedImage:media_type"] == ["image/jpeg"]
    blob = sorted(depth["rows"], key=lambda r: r["frame"])[1]["EncodedDepthImage:blob"][0]
    decoded = cv2.imdecode(np.asarray(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded, seq.depth[3])  # lossless mm


def test_colour_only_frames_skip_depth_and_pinhole(tmp_path):
    path = tmp_path / "c.rrd"
    log = RerunLogger(path)
    for i in range(2):
        log.log_frame(i, frame(i, depth=False))
    log.close()
    log.close()  # idempotent
    rrd = read_rrd(path)
    assert sorted(rrd["/world/camera/image"]["frames"]) == [0, 1]
    assert "/world/camera/depth" not in rrd
    assert "/world/camera" not in rrd


def read_blueprint(path):
    """``{view name: (origin, [content queries])}`` of the blueprint stored with a recording."""
    reader = RrdReader(str(path))
    (store,) = reader.blueprints()
    rows = defaultdict(dict)
    for ch in reader.stream(store=store):
        data = ch.to_record_batch().to_pydict()
        entity = str(ch.entity_path)
        for k, v in data.items():
            rows[entity.removesuffix("/ViewContents")][k] = v[-1]
    views = {}
    for row in rows.values():
        if "ViewBlueprint:display_name" in row:
            views[row["ViewBlueprint:display_name"][0]] = (
                row["ViewBlueprint:space_origin"][0],
                list(row.get("ViewContents:query") or []),
            )
    return views


@pytest.mark.parametrize("points", [True, False])
def test_the_recording_carries_its_viewer_layout(tmp_path, points):
    path = tmp_path / "b.rrd"
    with RerunLogger(path, blueprint=default_blueprint(points=points)) as log:
        log.log_frame(0, frame(0))
    views = read_blueprint(path)
    colour = [v for name, v in views.items() if name.startswith("colour")]
    # The colour view shows the boxes and particles but not the depth, which has its own.
    assert colour == [("world/camera", ["$origin/**", "- $origin/depth"])]
    assert views["depth"] == ("world/camera", ["$origin/depth"])
    assert views["effective sample size"][0] == "series/ess"
    assert views["ms per step"][0] == "series/ms_per_frame"
    assert ("body (3D)" in views) == points
    with RerunLogger(tmp_path / "none.rrd", blueprint=None) as log:
        log.log_frame(0, frame(0))
    assert RrdReader(str(tmp_path / "none.rrd")).blueprints() == []


def test_weight_colours():
    c = weight_colours(np.array([0.0, 0.5, 1.0, np.nan]))
    assert c.dtype == np.uint8 and c.shape == (4, 3)
    assert tuple(c[0]) == (68, 1, 84) and tuple(c[2]) == (253, 231, 37)
    assert tuple(c[3]) == tuple(c[0])
    np.testing.assert_array_equal(
        weight_colours(np.log([0.1, 1.0]), log=True), weight_colours([0.1, 1.0])
    )
    assert (weight_colours(np.zeros(3)) == c[0]).all()  # all-zero weights: no NaN


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="rrd path"):
        RerunLogger()
    with RerunLogger(tmp_path / "x.rrd") as log:
        with pytest.raises(ValueError, match=r"\[N, 2\]"):
            log.log_particles(0, np.zeros((3, 3)), np.ones(3))
        with pytest.raises(ValueError, match="3 particles but 2 weights"):
            log.log_particles(0, np.zeros((3, 2)), np.ones(2))


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_streams_to_a_running_viewer(tmp_path):
    # `rerun --save FILE --port P` is a headless stand-in for a viewer: it listens for
    # the SDK's gRPC stream and writes what arrives to FILE.
    import subprocess
    import sys
    import time

    port, saved = _free_port(), tmp_path / "received.rrd"
    server = subprocess.Popen(
        [sys.executable, "-m", "rerun", "--save", str(saved), "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # `python -m rerun` runs the viewer binary as a child
    )
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    try:
        from cpf_jax.errors import ViewerUnavailable
        from cpf_jax.viz import check_viewer

        for _ in range(100):  # the server needs a moment to listen
            try:
                check_viewer(url, timeout=0.5)
                break
            except ViewerUnavailable:
                time.sleep(0.1)
        with RerunLogger(connect=url) as log:
            for i in range(T):
                log.log_box(i, np.array([1.0, 2.0, 3.0, 4.0]))
                log.log_scalar(i, "ess", 10.0 + i)
        want, found = {"/series/ess", "/world/camera/tracker/box"}, set()
        for _ in range(150):  # the server writes as it receives
            try:
                found = _entities(saved)
            # Not there yet, its last message half written, or (ValueError) the file
            # exists but holds no recording store yet: a race seen once in CI-like runs.
            except (OSError, RuntimeError, ValueError):
                found = set()
            if want <= found:
                break
            time.sleep(0.1)
    finally:
        import os
        import signal

        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)
    assert want <= found, found


def _entities(path) -> set[str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the server's file has no footer until it stops
        return {str(ch.entity_path) for ch in RrdReader(str(path)).stream()}


@pytest.mark.parametrize(
    "url, needle",
    [
        ("rerun+http://127.0.0.1:{port}/proxy", "cannot connect"),
        ("127.0.0.1:9876", r"expected rerun\+http"),
    ],
)
def test_unreachable_viewer_is_one_clear_error_before_logging(url, needle):
    from cpf_jax.errors import ViewerUnavailable

    with pytest.raises(ViewerUnavailable, match=needle):
        RerunLogger(connect=url.format(port=_free_port()))
