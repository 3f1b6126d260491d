"""cpf-track end to end: a generated recorded folder, outputs written as the run goes, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cpf_jax.cli import main, open_inputs, parse_box
from cpf_jax.io import read_results
from cpf_jax.synthetic import make_sequence, to_folder

N_FRAMES = 12


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    seq = make_sequence("walk_across_slow", seed=3, n_frames=N_FRAMES)
    return Path(to_folder(seq, tmp_path_factory.mktemp("seq") / "walk"))


def test_tracks_folder_writes_csv_rrd_and_summary(folder, tmp_path, capsys):
    out, rrd, plot = tmp_path / "boxes.csv", tmp_path / "run.rrd", tmp_path / "p" / "run.png"
    argv = [str(folder), "--particles", "64", "--out", str(out), "--rrd", str(rrd)]
    code = main([*argv, "--plot", str(plot), "--no-progress"])
    assert code == 0
    # --plot: per-frame IoU and ESS panel, and the success plot (ground truth exists).
    img = cv2.imread(str(plot))
    assert img is not None and img.shape[0] > 2 * 360 and img.shape[1] == 640
    printed = capsys.readouterr().out
    assert "SR@0.5 %" in printed and f"tracked {N_FRAMES} frames" in printed
    assert "whole frame" not in printed  # every step counted in the histogram window
    res = read_results(out)
    np.testing.assert_array_equal(res["frame"], np.arange(N_FRAMES))
    boxes = res["boxes"]
    assert np.isfinite(boxes).all()
    gt = np.loadtxt(folder / "groundtruth_rect.txt", delimiter=",")
    np.testing.assert_allclose(boxes[0], gt[0] - [1, 1, 0, 0], atol=1e-3)  # 0-based init box
    # the run tracks: estimates stay on the person (a generous bound; accuracy is tested elsewhere)
    centre = boxes[:, :2] + boxes[:, 2:] / 2
    gt_centre = gt[:, :2] - 1 + gt[:, 2:] / 2
    assert np.median(np.linalg.norm(centre - gt_centre, axis=1)) < 25
    assert rrd.stat().st_size > 10_000
    from rerun.chunk import RrdReader

    paths = {str(ch.entity_path) for ch in RrdReader(str(rrd)).stream()}
    assert any("tracker/box" in p for p in paths) and any("series/ess" in p for p in paths)
    # The log colours the particles by their weights before resampling (after it they are
    # uniform), times the steps only (the first frame ran init) and carries its layout.
    rows = {}
    for ch in RrdReader(str(rrd)).stream():
        data = ch.to_record_batch().to_pydict()
        for r in range(len(data.get("frame", []))):
            row = {k: v[r] for k, v in data.items()}
            rows.setdefault(str(ch.entity_path), {})[data["frame"][r]] = row
    particles = rows["/world/camera/tracker/particles"]
    colours = np.asarray(particles[3]["Points2D:colors"])
    assert len(np.unique(colours)) > 1, "the particles are all one colour"
    assert min(rows["/series/ms_per_frame"]) == 1
    assert RrdReader(str(rrd)).blueprints()


def test_init_override_and_max_frames(folder, tmp_path):
    out = tmp_path / "b.csv"
    code = main(
        [
            str(folder),
            "--init",
            "100,80,60,190",
            "--max-frames",
            "3",
            "--out",
            str(out),
            "--particles",
            "64",
            "--no-progress",
        ]
    )
    assert code == 0
    res = read_results(out)
    assert len(res["frame"]) == 3
    np.testing.assert_allclose(res["boxes"][0], [100, 80, 60, 190])


def test_a_second_run_in_the_process_reuses_the_built_filter(folder, tmp_path):
    """The filter builders return the same ``Filter`` for equal configs
    (``filter.memoised_build``): a second ``main()`` with the same settings (a notebook,
    a script looping over recordings) jits the same step object, so JAX neither traces
    nor compiles it again, and it tracks the same; other settings build their own."""
    from cpf_jax import colour

    build = colour.build_colour_filter
    argv = [str(folder), "--particles", "64", "--max-frames", "4", "--no-progress"]
    out = [tmp_path / f"run{i}.csv" for i in range(3)]
    assert main([*argv, "--out", str(out[0])]) == 0
    before = build.cache_info()
    assert main([*argv, "--out", str(out[1])]) == 0
    after = build.cache_info()
    assert (after.hits, after.misses) == (before.hits + 1, before.misses)
    first, second = (read_results(p)["boxes"] for p in out[:2])
    np.testing.assert_array_equal(first, second)
    assert main([*argv, "--particles", "32", "--out", str(out[2])]) == 0
    assert build.cache_info().misses == after.misses + 1


def test_optional_colour_terms_from_the_command_line(folder, tmp_path, monkeypatch):
    out = tmp_path / "t.csv"
    argv = [str(folder), "--init", "100,80,60,190", "--max-frames", "3", "--out", str(out)]
    argv += ["--particles", "64", "--no-progress", "--contrast", "mixture", "--layout", "6x2"]
    assert main(argv) == 0
    res = read_results(out)
    assert len(res["frame"]) == 3 and np.isfinite(res["boxes"]).all()
    argv += ["--layout-feature", "gradient", "--layout-weight", "20", "--layout-mirror"]
    assert main(argv) == 0
    assert np.isfinite(read_results(out)["boxes"]).all()

    # --unseen reaches the filter's config (the linear contrast's prior on unseen colours)
    import cpf_jax.cascade as cascade

    configs, original = [], cascade.build_box_filter

    def build(config):
        configs.append(config)
        return original(config)

    monkeypatch.setattr(cascade, "build_box_filter", build)
    argv = argv[:10] + ["--layout", "6x2", "--layout-mirror", "--unseen", "neutral"]
    assert main(argv) == 0
    assert configs[-1].unseen == "neutral" and configs[-1].layout_mirror
    assert np.isfinite(read_results(out)["boxes"]).all()


def test_size_velocity_decay_and_size_hold_from_the_command_line(folder, tmp_path):
    import jax.numpy as jnp

    from cpf_jax.cli import build_parser, param_options
    from cpf_jax.colour import default_colour_params
    from cpf_jax.rgbd import RGBDConfig, default_rgbd_params

    # The option reaches both layers' parameters.
    args = build_parser().parse_args(["x", "--size-velocity-decay", "0.25", "--sigma", "0.3"])
    colour = param_options(args, default_colour_params())
    assert float(colour.motion.size_velocity_decay) == 0.25
    assert np.isclose(float(colour.histogram.sigma), 0.3)
    args.model = "grid-occlusion"
    rgbd = param_options(args, default_rgbd_params(RGBDConfig()))
    assert float(rgbd.motion.size_velocity_decay) == 0.25
    assert np.isclose(float(rgbd.colour.sigma), 0.3)
    assert float(default_colour_params().motion.size_velocity_decay) == np.float32(0.9)
    args = build_parser().parse_args(["x", "--dynamics", "ar1", "--size-hold", "0.25"])
    assert float(param_options(args, default_colour_params()).motion.size_hold) == 0.25
    assert float(default_colour_params().motion.size_hold) == 1.0

    # And changes the track: the first step starts from zero velocities (same boxes),
    # after it the size velocities differ (kept whole vs forgotten).
    tracks = []
    for decay in ("1", "0"):
        out = tmp_path / f"decay{decay}.csv"
        argv = [str(folder), "--max-frames", "6", "--particles", "64", "--no-progress"]
        argv += ["--dynamics", "ar1", "--size-velocity-decay", decay, "--out", str(out)]
        assert main(argv) == 0
        tracks.append(read_results(out)["boxes"])
    undamped, damped = tracks
    np.testing.assert_array_equal(undamped[:2], damped[:2])
    assert not np.allclose(undamped[2:], damped[2:], atol=1e-3)
    assert jnp.isfinite(jnp.asarray(damped)).all()


def test_histogram_only_model_from_the_command_line():
    """The default colour model has the layout term, the template update and neutral
    unseen colours; three options give ``ColourConfig.histogram_only()``."""
    from cpf_jax.cli import build_parser, model_options
    from cpf_jax.colour import ColourConfig

    default = ColourConfig()
    assert default.layout == (7, 3) and default.template_update
    assert default.unseen == "neutral"
    args = build_parser().parse_args(["x"])
    config_kw, colour_kw = model_options(args)
    assert ColourConfig(**config_kw, **colour_kw) == default
    argv = ["x", "--layout", "off", "--no-template-update", "--unseen", "background"]
    config_kw, colour_kw = model_options(build_parser().parse_args(argv))
    hist = ColourConfig(**config_kw, **colour_kw)
    assert hist == default.histogram_only() and hist != default
    assert hist.layout is None and not hist.template_update and hist.unseen == "background"
    # --contrast off: no centre-surround term (ColourConfig.contrast = None).
    config_kw, colour_kw = model_options(build_parser().parse_args(["x", "--contrast", "off"]))
    assert ColourConfig(**config_kw, **colour_kw).contrast is None


def test_the_learnt_terms_from_the_command_line():
    """--correlation and --follow-camera switch the correlation filter and the camera
    stage on or off whatever the defaults are."""
    from cpf_jax.cli import build_parser, model_options
    from cpf_jax.colour import ColourConfig, CorrelationConfig
    from cpf_jax.colour.camera import DOWNSCALE

    def config(*argv):
        config_kw, colour_kw = model_options(build_parser().parse_args(["x", *argv]))
        return ColourConfig(**config_kw, **colour_kw)

    on = config("--correlation", "--follow-camera")
    assert on.correlation == CorrelationConfig() and on.camera_motion == DOWNSCALE
    off = config("--no-correlation", "--no-follow-camera")
    assert off.correlation is None and off.camera_motion is None


@pytest.mark.parametrize(
    "args, needle",
    [
        (["/nonexistent/cpf_dir"], "nonexistent"),
        (["{folder}", "--init", "900,900,50,50"], "outside"),
        (["{folder}", "--init", "1,2,3"], "--init"),
        (["{folder}", "--particles", "0"], "--particles"),
        (["{folder}", "--bins", "8by8"], "--bins"),
        (["{folder}", "--layout", "12"], "--layout"),
        (["{folder}", "--layout", "0x3"], "--layout"),
        (["{folder}", "--layout", "6x2", "--layout-weight", "-1"], "--layout-weight"),
        (["{folder}", "--model", "grid", "--layout", "6x2", "--layout-weight", "5"], "--model rgb"),
        (["{folder}", "--layout", "off", "--layout-feature", "gradient"], "not --layout off"),
        (["{folder}", "--layout", "off", "--layout-mirror"], "not --layout off"),
        (["{folder}", "--model", "rgbd", "--no-template-update"], "--model rgb"),
        (["{folder}", "--model", "grid", "--correlation"], "--model rgb"),
        (["{folder}", "--model", "grid-occlusion", "--follow-camera"], "--model rgb"),
        (["{folder}", "--model", "rgbd", "--contrast", "mixture"], "--model rgb"),
        (["{folder}", "--model", "rgbd", "--unseen", "neutral"], "--model rgb"),
        (["{folder}", "--contrast", "mixture", "--unseen", "neutral"], "linear contrast"),
        (["{folder}", "--contrast", "off", "--unseen", "neutral"], "linear contrast"),
        (["{folder}", "--model", "rgbd", "--background", "empty"], "empty-scene"),
        (["{folder}", "--no-body-term"], "RGB-D models"),
        (["{folder}", "--plot", "run.jpg"], "--plot"),
        (["{folder}", "--dynamics", "ar1", "--size-velocity-decay", "1.5"], "in [0, 1]"),
        (["{folder}", "--size-velocity-decay", "0.5"], "not 'random_walk'"),
        (["{folder}", "--dynamics", "ar2_fixed", "--size-velocity-decay", "0.5"], "ar1|ar2"),
        (["{folder}", "--dynamics", "ar1", "--size-hold", "-0.5"], "in [0, 1]"),
        (["{folder}", "--size-hold", "0.5"], "--dynamics ar1"),
        (["{folder}", "--dynamics", "ar1", "--no-hierarchical", "--size-hold", "0"], "guided"),
        (["{folder}", "--model", "rgbd", "--dynamics", "ar1", "--size-hold", "0"], "RGB-D"),
        (["{folder}", "--rrd", "{folder}"], "is a directory, not an .rrd file"),
        (["{folder}", "--max-frames", "-1"], "--max-frames must be >= 1"),
        (["{folder}", "--sigma", "inf"], "--sigma must be a finite number"),
        (["{folder}", "--rrd", "{folder}/rgb/000000.png/run.rrd"], "cannot write the Rerun"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(folder, capsys, args, needle):
    argv = [a.format(folder=folder) for a in args] + ["--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cpf-track: error:") and needle in err
    assert len(err.splitlines()) == 1


def test_depth_of_another_size_without_calibration_names_the_frame(folder, tmp_path, capsys):
    """Depth that is not registered to the colour image (another size, no calibration) is
    one error line naming the frame for the models that read depth; the colour layer
    never reads depth and tracks."""
    import shutil

    bad = Path(shutil.copytree(folder, tmp_path / "raw_depth"))
    for p in sorted((bad / "depth").glob("*.png")):
        depth = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), depth[::2, ::2])
    argv = [str(bad), "--particles", "64", "--max-frames", "2", "--no-progress"]
    assert main([*argv, "--model", "rgbd"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "frame 0 (" in err, err
    assert "depth is 256x212 but colour is 512x424" in err and "--calib" in err, err
    assert main(argv) == 0


def test_corrupt_image_names_the_file(folder, tmp_path, capsys):
    bad = tmp_path / "bad"
    (bad / "rgb").mkdir(parents=True)
    for i, f in enumerate(sorted((folder / "rgb").iterdir())[:4]):
        (bad / "rgb" / f.name).write_bytes(f.read_bytes() if i != 2 else b"not a png")
    assert main([str(bad), "--init", "100,80,60,190", "--no-progress"]) == 2
    lines = capsys.readouterr().err.splitlines()
    errors = [e for e in lines if not e.startswith("cpf-track: compiling")]
    assert len(errors) == 1 and "000002.png" in errors[0]  # besides the compile lines


def test_ground_truth_that_never_shows_the_target_asks_for_init(folder, tmp_path, capsys):
    import shutil

    bad = Path(shutil.copytree(folder, tmp_path / "never"))
    (bad / "groundtruth_rect.txt").write_text("0,0,0,0\n" * (N_FRAMES - 1) + "5,5,-10,20\n")
    assert main([str(bad), "--no-progress"]) == 2
    warning, error = capsys.readouterr().err.splitlines()
    assert "shows the target in no frame; give --init" in error
    # The negative width counts as "not visible", and the run says which line it read so.
    assert warning.startswith("cpf-track: warning: ") and f"line {N_FRAMES} '5,5,-10,20'" in warning


def test_otb_style_folder_with_invisible_frames(tmp_path, capsys):
    """OTB layout: 1-based GT, 0,0,0,0 lines skipped; tracking starts at the first visible frame."""
    seq = make_sequence("walk_across_slow", seed=4, n_frames=8)
    (tmp_path / "img").mkdir()
    lines = []
    for t in range(8):
        cv2.imwrite(
            str(tmp_path / "img" / f"{t + 1:04d}.jpg"),
            cv2.cvtColor(seq.colour[t], cv2.COLOR_RGB2BGR),
        )
        x, y, w, h = seq.boxes[t]
        lines.append("0,0,0,0" if t < 2 else f"{x + 1:.0f},{y + 1:.0f},{w:.0f},{h:.0f}")
    (tmp_path / "groundtruth_rect.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.csv"
    assert main([str(tmp_path), "--out", str(out), "--particles", "64", "--no-progress"]) == 0
    res = read_results(out)
    np.testing.assert_array_equal(res["frame"], np.arange(2, 8))
    assert "visible" in capsys.readouterr().out


def test_rgbd_model_on_a_synthetic_scenario_with_its_empty_room(tmp_path, capsys):
    # occlusion_return's walker never uncovers the middle of the view: the median of its
    # frames would hold the walker, so the empty room is the background.
    out = tmp_path / "r.csv"
    argv = ["occlusion_return", "--model", "grid-occlusion", "--background", "empty"]
    argv += ["--max-frames", "4", "--particles", "64", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    res = read_results(out)
    assert len(res["frame"]) == 4
    # The walker is in full view in these frames: a box on him, not lost.
    seq = make_sequence("occlusion_return", seed=0)
    from cpf_jax.kernels.boxes import iou

    ious = np.asarray(iou(res["boxes"], seq.boxes[res["frame"]]))
    assert np.all(ious > 0.5), ious


def test_background_auto_is_the_recordings_empty_frames(tmp_path, capsys):
    # A recording of the empty room (frames 0-4), then occlusion_return's walker, who
    # never uncovers the middle of the view (10 frames): evenly spaced frames' median
    # would hold him; --background auto takes the empty frames.
    from cpf_jax.io.synthetic import SyntheticSource

    seq = make_sequence("occlusion_return", seed=0, n_frames=10)
    empty = SyntheticSource(seq, "occlusion_return").empty_background()
    colour = [np.asarray(empty.colour)] * 5 + list(seq.colour)
    depth = [np.asarray(empty.depth)] * 5 + list(seq.depth)
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    for t, (c, d) in enumerate(zip(colour, depth, strict=True)):
        cv2.imwrite(str(tmp_path / "rgb" / f"{t:06d}.png"), cv2.cvtColor(c, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(tmp_path / "depth" / f"{t:06d}.png"), d)
    lines = ["0,0,0,0"] * 5
    lines += [f"{x + 1:.0f},{y + 1:.0f},{w:.0f},{h:.0f}" for x, y, w, h in seq.boxes]
    (tmp_path / "groundtruth_rect.txt").write_text("\n".join(lines) + "\n")
    argv = [str(tmp_path), "--model", "rgbd", "--particles", "16", "--max-frames", "1"]
    assert main([*argv, "--background", "auto", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "note: background: median of the 5 of 15 frames with the least foreground (0-4;" in err
    assert main([*argv, "--background", "15", "--no-body-term", "--no-progress"]) == 0
    assert "background: median" not in capsys.readouterr().err


def test_background_option_forms():
    from cpf_jax.cli import AUTO_CANDIDATES, UsageError, parse_background, parse_live_background

    assert parse_background("auto", 40) == list(range(40))  # every frame of a short one
    assert len(parse_background("auto", 1000)) == AUTO_CANDIDATES
    assert parse_background("3", 9) == [0, 4, 8] and parse_background("2:5", 9) == [2, 3, 4]
    assert parse_live_background("auto") == (0, 25) and parse_live_background("7") == (0, 7)
    with pytest.raises(UsageError, match="--background expects none, auto, empty"):
        parse_background("often", 9)


def test_says_when_steps_left_the_histogram_window(capsys):
    # A small box given on a person walking towards the camera (the upper body, a quarter
    # of the person's area) outgrows the window sized for it and the grown windows
    # (window_ladder): the run says how many steps counted on the whole frame instead.
    # (The AR2 model's size trend carries particles past both: 5 of 29 steps here; the
    # default box on this scene stays inside the grown window.)
    argv = ["walk_towards", "--init", "224,102,30,77", "--particles", "64", "--dynamics", "ar2"]
    assert main([*argv, "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert "note" not in out  # stdout carries the results only
    note = [line for line in err.splitlines() if "whole frame" in line]
    assert len(note) == 1 and note[0].startswith("cpf-track: note: ")
    n_whole, n_steps = (int(v) for v in note[0].split()[2:5:2])
    assert 0 < n_whole < n_steps == 29


def test_parse_box():
    np.testing.assert_allclose(parse_box("1, 2,3.5,4"), [1, 2, 3.5, 4])


# ----------------------------------------------------------------------------- live sources
# A camera (RealSense, Kinect v2, a .bag playback) is a LiveSource: iterable once, no
# length, no ground truth. No device is attached here, so a fake camera replays frames.


class _FakeCamera:
    """A LiveSource replaying ``frames``; ``interrupt_after`` raises Ctrl-C mid-stream."""

    def __init__(self, frames, size, interrupt_after=None):
        from cpf_jax.io.base import LiveSource

        class Camera(LiveSource):
            kind = "fakecam"

            def __iter__(cam):
                for k, f in enumerate(frames):
                    if interrupt_after is not None and k == interrupt_after:
                        raise KeyboardInterrupt
                    cam.served += 1
                    yield f

            def close(cam):
                cam.closed = True

        self.camera = Camera()
        self.camera.size, self.camera.served, self.camera.closed = size, 0, False


@pytest.fixture
def camera(monkeypatch):
    """``make(frames, interrupt_after=None)``: ``open_source`` returns a fake camera."""
    import cpf_jax.io

    made = []

    def make(frames, interrupt_after=None):
        cam = _FakeCamera(
            frames, (frames[0].colour.shape[1], frames[0].colour.shape[0]), interrupt_after
        ).camera
        monkeypatch.setattr(
            cpf_jax.io, "open_source", lambda spec, kind=None, depth_scale=None: cam
        )
        made.append(cam)
        return cam

    return make


def test_live_stream_tracks_as_the_same_frames_recorded(folder, camera, tmp_path, capsys):
    from cpf_jax.io import open_source

    recorded = open_source(str(folder))
    frames = [recorded.read(i) for i in range(len(recorded))]
    box = ",".join(f"{v:g}" for v in recorded.init_box)
    argv = ["--init", box, "--particles", "64", "--no-progress", "--max-frames", "8"]
    ref = tmp_path / "ref.csv"
    assert main([str(folder), *argv, "--out", str(ref)]) == 0
    capsys.readouterr()
    cam = camera(frames)
    out = tmp_path / "live.csv"
    assert main(["realsense", *argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "tracked 8 frames of fakecam" in printed and "SR@0.5" not in printed  # no GT
    a, b = read_results(ref), read_results(out)
    np.testing.assert_array_equal(b["frame"], np.arange(8))
    np.testing.assert_allclose(b["boxes"], a["boxes"], atol=1e-3)  # same frames, same key
    assert cam.closed and cam.served == 8  # --max-frames stops reading the camera


def test_live_rgbd_learns_the_background_from_the_first_frames(camera, tmp_path):
    # The camera first sees the empty room (3 frames), then the walker: --background 3
    # takes those, and tracking starts at stream frame 3 with the --init box.
    from cpf_jax.io import open_source
    from cpf_jax.kernels.boxes import iou

    src = open_source("occlusion_return")
    frames = [src.empty_background()] * 3 + [src.read(i) for i in range(6)]
    box = ",".join(f"{v:g}" for v in src.gt_boxes[0])
    cam = camera(frames)
    out = tmp_path / "r.csv"
    argv = ["realsense", "--model", "grid-occlusion", "--background", "3", "--init", box]
    assert main([*argv, "--particles", "64", "--out", str(out), "--no-progress"]) == 0
    res = read_results(out)
    np.testing.assert_array_equal(res["frame"], np.arange(3, 9))  # the stream ran out
    ious = np.asarray(iou(res["boxes"], src.gt_boxes[res["frame"] - 3]))
    assert np.all(ious > 0.5), ious
    assert cam.closed


def test_live_interrupt_keeps_the_rows_so_far_and_stops_the_camera(folder, camera, tmp_path):
    from cpf_jax.io import open_source

    recorded = open_source(str(folder))
    cam = camera([recorded.read(i) for i in range(len(recorded))], interrupt_after=5)
    out, plot = tmp_path / "i.csv", tmp_path / "i.png"
    argv = ["kinect2", "--init", "100,80,60,190", "--particles", "64", "--out", str(out)]
    assert main([*argv, "--plot", str(plot), "--no-progress"]) == 130
    np.testing.assert_array_equal(read_results(out)["frame"], np.arange(5))
    assert cam.closed
    # The plot of the frames so far: one panel (a camera has no ground truth).
    img = cv2.imread(str(plot))
    assert img is not None and 360 < img.shape[0] < 2 * 360


def test_live_interrupt_is_not_hidden_by_a_viewer_error(
    folder, camera, monkeypatch, tmp_path, capsys
):
    # A streamed log whose viewer went away fails at close. After Ctrl-C that is one
    # warning line, and the run still ends as interrupted (130); without Ctrl-C the same
    # failure is the run's error (exit 2), reported after the run's own output.
    from cpf_jax import viz
    from cpf_jax.errors import ViewerUnavailable
    from cpf_jax.io import open_source

    real_close = viz.RerunLogger.close

    def close(logger):
        real_close(logger)
        raise ViewerUnavailable("Rerun viewer: the log could not be delivered (gone)")

    monkeypatch.setattr(viz.RerunLogger, "close", close)
    recorded = open_source(str(folder))
    frames = [recorded.read(i) for i in range(len(recorded))]
    argv = ["kinect2", "--init", "100,80,60,190", "--particles", "64", "--no-progress"]
    for interrupt, code in ((5, 130), (None, 2)):
        cam = camera(frames, interrupt_after=interrupt)
        assert main([*argv, "--max-frames", "6", "--rrd", str(tmp_path / "x.rrd")]) == code
        out, err = capsys.readouterr()
        assert "could not be delivered" in err and cam.closed
        if interrupt:
            assert "warning" in err and "interrupted" in err
        else:
            assert "tracked 6 frames" in out and "Rerun recording written" in err


@pytest.mark.parametrize(
    "args, needle",
    [
        ([], "give --init"),
        (["--init", "100,80,60,190", "--model", "rgbd", "--background", "empty"], "live stream"),
        (
            ["--init", "100,80,60,190", "--model", "rgbd", "--background", "3", "--start", "1"],
            "cannot go back",
        ),
        (["--init", "100,80,60,190", "--start", "40"], "stream ended after 12 frames"),
        (["--init", "900,900,50,50"], "outside"),
    ],
)
def test_live_bad_input_is_one_line_and_exit_2(folder, camera, capsys, args, needle):
    from cpf_jax.io import open_source

    recorded = open_source(str(folder))
    cam = camera([recorded.read(i) for i in range(len(recorded))])
    assert main(["realsense", *args, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cpf-track: error:") and needle in err, err
    assert len(err.splitlines()) == 1
    assert cam.closed


def test_viewer_errors_are_one_line_before_tracking(folder, monkeypatch, tmp_path, capsys):
    import socket
    import sys

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "v.csv"
    argv = [str(folder), "--no-progress", "--out", str(out)]
    assert main([*argv, "--connect", f"rerun+http://127.0.0.1:{port}/proxy"]) == 2
    err = capsys.readouterr().err.strip()
    assert "cannot connect" in err and len(err.splitlines()) == 1
    assert not out.exists()  # the check comes before tracking
    if sys.platform.startswith("linux"):
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        assert main([*argv, "--spawn"]) == 2
        err = capsys.readouterr().err.strip()
        assert "needs a display" in err and len(err.splitlines()) == 1


def test_init_auto_starts_on_the_first_frame_with_a_person(camera, tmp_path, capsys):
    from cpf_jax.io import open_source
    from cpf_jax.kernels.boxes import iou

    # A recording: the person is there from frame 0; the box is found, not given.
    out = tmp_path / "a.csv"
    argv = ["walk_across_slow", "--init", "auto", "--background", "empty", "--max-frames", "3"]
    assert main([*argv, "--particles", "64", "--out", str(out), "--no-progress"]) == 0
    res = read_results(out)
    gt = open_source("walk_across_slow").gt_boxes
    np.testing.assert_array_equal(res["frame"], np.arange(3))
    assert float(iou(res["boxes"][:1], gt[:1])[0]) > 0.8
    assert "--init auto: a person at" in capsys.readouterr().err
    # A camera: 3 background frames of the empty room, 2 more, then he walks in.
    src = open_source("walk_towards")
    empty = src.empty_background()
    cam = camera([empty] * 5 + [src.read(i) for i in range(4)])
    out = tmp_path / "b.csv"
    # (--model rgb: the colour filter ignores the background; the RGB-D live path is
    # tested above, and this keeps to one cheaper compile.)
    argv = ["realsense", "--init", "auto", "--background", "3"]
    assert main([*argv, "--particles", "64", "--out", str(out), "--no-progress"]) == 0
    res = read_results(out)
    np.testing.assert_array_equal(res["frame"], np.arange(5, 9))
    assert np.all(np.asarray(iou(res["boxes"], src.gt_boxes[:4])) > 0.5)
    assert cam.closed
    # Nobody comes: one error line.
    capsys.readouterr()
    camera([empty] * 6)
    assert main([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no person-shaped foreground in frames 3..5" in err[0]


def test_malloc_is_tuned_by_default_and_not_with_no_tune_malloc(tmp_path, monkeypatch, capsys):
    import cpf_jax.cli

    calls = []
    monkeypatch.setattr(cpf_jax.cli, "tune_process", lambda: calls.append(1) or True)
    missing = str(tmp_path / "nothing")
    assert main([missing, "--particles", "0"]) == 2  # refused after the switch, before JAX
    assert calls == [1]
    assert main([missing, "--particles", "0", "--no-tune-malloc"]) == 2
    assert calls == [1]
    assert "--particles must be >= 1" in capsys.readouterr().err


def test_log_thread_runs_jobs_in_order_and_hands_back_the_first_error():
    from cpf_jax.cli.run import LogThread

    done = []
    log = LogThread(depth=2)
    for k in range(10):
        log.submit(lambda k=k: done.append(k))
    log.close()
    assert done == list(range(10))

    def fails():
        raise OSError("disk full")

    log = LogThread()
    log.submit(fails)
    log.submit(lambda: done.append("after"))  # skipped: the log has failed
    with pytest.raises(OSError, match="disk full"):
        log.close()
    assert "after" not in done


def test_rows_hold_copies_not_views_of_the_steps_arrays():
    # A run keeps every row for its summary: a row that viewed a step's JAX array would keep
    # that array's device buffer alive too, and a long run's memory would grow with it.
    import jax.numpy as jnp

    from cpf_jax.cli.run import _step_row
    from cpf_jax.colour.filter import ColourInfo

    box = jnp.arange(4.0, dtype=jnp.float32)
    flag = jnp.asarray(False)
    info = ColourInfo(
        box, flag, jnp.float32(5), jnp.float32(0), box, flag, *(jnp.float32(0),) * 2, flag, flag
    )

    class Model:
        points = ()

    row = _step_row(Model(), info, 1.0)
    np.testing.assert_array_equal(row.box, [0, 1, 2, 3])
    assert row.box.flags.owndata and row.box.base is None
    assert row.points2d.shape == (0, 2) and row.points3d.shape == (0, 3)


def test_background_none_is_the_default_and_reads_no_background_frames(tmp_path, capsys):
    # --background none (the default): the RGB-D filter takes each frame's scene from the
    # frame (RGBDConfig.side_scene) and no frame is read for a background model.
    from cpf_jax.cli import build_parser
    from cpf_jax.io import open_source

    to_folder(make_sequence("walk_towards", seed=0, n_frames=6), tmp_path)
    for extra, frameless in (
        ([], True),
        (["--background", "none"], True),
        (["--background", "auto"], False),
    ):
        args = build_parser().parse_args([str(tmp_path), "--model", "rgbd", *extra])
        inputs = open_inputs(args, open_source(args.path))
        assert (inputs.background is None) == frameless, extra
    argv = [str(tmp_path), "--model", "grid-occlusion", "--particles", "16"]
    assert main([*argv, "--no-progress", "--out", str(tmp_path / "b.csv")]) == 0
    assert "background: median" not in capsys.readouterr().err
