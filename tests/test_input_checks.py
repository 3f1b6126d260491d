"""Inputs checked for meaning: each case is a plausible but wrong input, and what it now gives
(an error line that says what is wrong, or a warning that says what was done instead)."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import jax
import numpy as np
import pytest
from conftest import ROOT, shared_data

from cpf_jax.cli import build_parser, main
from cpf_jax.cli.inputs import open_inputs
from cpf_jax.errors import InputWarning, SourceError
from cpf_jax.io import NpzSource, depth_millimetres, open_source
from cpf_jax.synthetic import make_sequence, to_folder
from cpf_jax.types import (
    KINECT_V2_DEPTH,
    Frame,
    Intrinsics,
    check_frame,
    check_intrinsics,
    nominal_intrinsics,
)


@pytest.fixture(scope="module")
def seq():
    return make_sequence("walk_across_slow", seed=3, n_frames=4)


@pytest.fixture(scope="module")
def folder(seq, tmp_path_factory) -> Path:
    return Path(to_folder(seq, tmp_path_factory.mktemp("rec") / "walk"))


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("cpf-track: error: ")
    return err[0]


# ------------------------------------------------------------------------ depth where needed


def test_a_depth_model_on_colour_only_footage_is_an_error(seq, tmp_path, capsys):
    otb = tmp_path / "Walker"
    (otb / "img").mkdir(parents=True)
    for t in range(3):
        cv2.imwrite(str(otb / "img" / f"{t + 1:04d}.jpg"), seq.colour[t][..., ::-1])
    (otb / "groundtruth_rect.txt").write_text("101,81,60,180\n" * 3)
    assert main([str(otb), "--model", "grid-occlusion", "--no-progress"]) == 2
    line = _one_error_line(capsys)
    assert "--model grid-occlusion read depth" in line and "has no depth images" in line
    assert "--model rgb" in line


def test_a_folder_whose_depth_is_all_missing_is_an_error(seq, folder, tmp_path, capsys):
    blank = tmp_path / "blank"
    to_folder(seq, blank)
    for p in (blank / "depth").iterdir():
        cv2.imwrite(str(p), np.zeros(seq.depth.shape[1:], np.uint16))
    assert main([str(blank), "--model", "rgbd", "--background", "2", "--no-progress"]) == 2
    assert "every pixel is 0, i.e. missing" in _one_error_line(capsys)


def test_a_recording_whose_depth_starts_late_says_where(seq, tmp_path, capsys):
    late = tmp_path / "late"
    to_folder(seq, late)
    for p in sorted((late / "depth").iterdir())[:2]:  # a camera warming up
        cv2.imwrite(str(p), np.zeros(seq.depth.shape[1:], np.uint16))
    argv = [str(late), "--model", "rgbd", "--background", "2:4", "--start", "0"]
    assert main([*argv, "--no-progress"]) == 2
    assert "its depth starts at frame 2: start there with --start 2" in _one_error_line(capsys)


def test_a_blank_start_frame_says_where_the_picture_starts(seq, tmp_path, capsys):
    dark = tmp_path / "dark"
    to_folder(seq, dark)
    cv2.imwrite(str(sorted((dark / "rgb").iterdir())[0]), np.zeros(seq.colour.shape[1:], np.uint8))
    assert main([str(dark), "--start", "0", "--no-progress"]) == 2
    line = _one_error_line(capsys)
    assert "frame 0 is blank (every pixel RGB 0,0,0)" in line and "--start 1" in line


# ------------------------------------------------------------------------------ depth units


def test_depth_units_from_dtype_and_range():
    metres = np.array([[0.0, 1.5], [np.nan, 4.25]], np.float32)
    mm, note = depth_millimetres(metres, "f")
    np.testing.assert_array_equal(mm, [[0, 1500], [0, 4250]])
    assert mm.dtype == np.uint16 and "read as metres" in note
    mm, note = depth_millimetres(np.array([[900.4, 2500.0]], np.float64), "f")
    np.testing.assert_array_equal(mm, [[900, 2500]])
    assert "read as millimetres" in note
    mm, note = depth_millimetres(np.array([[1200, 0]], np.int32), "f")
    assert mm.dtype == np.uint16 and note is None
    raw = np.array([[1234, 0]], np.uint16)
    assert depth_millimetres(raw, "f")[0] is raw
    with pytest.raises(SourceError, match="f: the median depth is 12.5 m when read as mm"):
        depth_millimetres(np.full((2, 2), 12500, np.uint16), "f")  # TUM's 2.5 m
    with pytest.raises(SourceError, match="the median depth is 0.3 m .* --depth-scale N"):
        depth_millimetres(np.full((2, 2), 300, np.uint16), "f")  # a wall at 3 m in centimetres
    mm, note = depth_millimetres(np.full((2, 2), 12500, np.uint16), "f", per_metre=5000)
    np.testing.assert_array_equal(mm, 2500)
    assert note is None  # the units were given, not guessed
    with pytest.raises(SourceError, match="int16 depth from -3 to 900 does not fit"):
        depth_millimetres(np.array([[-3, 900]], np.int16), "f")  # uint16 saved as int16
    with pytest.raises(SourceError, match="does not fit 16-bit"):
        depth_millimetres(np.array([[70000]], np.int32), "f")
    with pytest.raises(SourceError, match="must be a number image"):
        depth_millimetres(np.ones((2, 2), bool), "f")


def test_an_npz_with_metres_is_converted_and_says_so(seq, tmp_path):
    path = tmp_path / "metres.npz"
    metres = seq.depth[:2].astype(np.float32) / 1000.0
    np.savez(path, colour=seq.colour[:2], depth=metres)
    with pytest.warns(InputWarning, match=r"metres.npz: 'depth': float32 depth read as metres"):
        frame = NpzSource(path).read(1)
    np.testing.assert_array_equal(frame.depth, seq.depth[1])


def test_an_npz_in_tum_units_is_refused(seq, tmp_path):
    path = tmp_path / "tum.npz"
    np.savez(path, colour=seq.colour[:2], depth=(seq.depth[:2] * 5).astype(np.uint16))
    with pytest.raises(SourceError, match="tum.npz: 'depth': the median depth is"):
        NpzSource(path).read(0)


def test_depth_in_another_unit_is_refused_then_read_at_the_scale_given(seq, tmp_path, capsys):
    path = Path(to_folder(seq, tmp_path / "tum_units"))
    for p in sorted((path / "depth").iterdir()):
        cv2.imwrite(str(p), (seq.depth[int(p.stem)].astype(np.uint32) * 5).astype(np.uint16))
    assert main([str(path), "--model", "rgbd", "--no-progress"]) == 2
    assert "--depth-scale N" in _one_error_line(capsys)
    source = open_source(str(path), depth_scale=5000)
    np.testing.assert_array_equal(source.read(3).depth, seq.depth[3])


@pytest.mark.parametrize(
    ("spec", "scale", "message"),
    [
        ("walk_towards", 1000, "not to a synthetic source, whose units are known"),
        ("walk_towards", -1, "finite number > 0"),
    ],
)
def test_a_depth_scale_where_it_cannot_apply_is_an_error(spec, scale, message):
    with pytest.raises(SourceError, match=message):
        open_source(spec, depth_scale=scale)


def test_a_folder_of_float_depth_images_is_read_in_millimetres(seq, tmp_path):
    path = Path(to_folder(seq, tmp_path / "f32"))
    for p in sorted((path / "depth").iterdir()):
        t = int(p.stem)
        cv2.imwrite(str(p.with_suffix(".tiff")), seq.depth[t].astype(np.float32) / 1000.0)
        p.unlink()
    source = open_source(str(path))
    with pytest.warns(InputWarning, match="float32 depth read as metres"):
        first = source.read(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)  # said once, for every image
        np.testing.assert_array_equal(source.read(2).depth, seq.depth[2])
    np.testing.assert_array_equal(first.depth, seq.depth[0])


def test_the_rgbd_filter_refuses_float_depth_under_jit(seq):
    from cpf_jax import RGBDConfig, build_rgbd_filter, default_rgbd_params

    frame = Frame(seq.colour[0], seq.depth[0].astype(np.float32) / 1000.0)
    with pytest.raises(ValueError, match="frame depth is float32.*depth_millimetres"):
        check_frame(frame, needs_depth=True)
    config = RGBDConfig(n_particles=8)
    filt = build_rgbd_filter(config)
    with pytest.raises(ValueError, match="frame depth is float32"):
        jax.jit(filt.init)(default_rgbd_params(config), jax.random.PRNGKey(0), frame, seq.boxes[0])


# ------------------------------------------------------------------------------- intrinsics


def test_intrinsics_of_another_frame_size_are_refused():
    check_intrinsics(KINECT_V2_DEPTH, (424, 512))
    with pytest.raises(ValueError, match=r"\(255, 205\) do not belong to 320x240 frames"):
        check_intrinsics(KINECT_V2_DEPTH, (240, 320))
    with pytest.raises(ValueError, match="640x480"):
        check_intrinsics(KINECT_V2_DEPTH, (480, 640))
    k = nominal_intrinsics(320, 240)
    assert k.fx == k.fy == pytest.approx(365.0 * 320 / 512) and (k.cx, k.cy) == (159.5, 119.5)
    check_intrinsics(k, (240, 320))
    assert nominal_intrinsics(512, 424) == KINECT_V2_DEPTH


def test_the_point_filter_refuses_intrinsics_that_do_not_fit_the_frame():
    from cpf_jax import Context, PointConfig, PointFrame, build_point_filter, default_point_params

    filt = build_point_filter(PointConfig(n_particles=8))  # Kinect v2 intrinsics by default
    frame = PointFrame(np.full((240, 320), 2000, np.uint16), np.ones((240, 320), bool))
    box = np.array([100, 40, 60, 150], np.float32)
    ctx = Context(points=np.array([[130.0, 60.0]], np.float32))
    with pytest.raises(ValueError, match="PointConfig.intrinsics: intrinsics with the principal"):
        filt.init(default_point_params(), jax.random.PRNGKey(0), frame, box, ctx)


# -------------------------------------------------------------------------------- alignment


def _shifted(depth: np.ndarray, dx: int) -> np.ndarray:
    """Depth moved ``dx`` px to the left (0 = missing where nothing lands)."""
    out = np.zeros_like(depth)
    out[..., : depth.shape[-1] - dx] = depth[..., dx:]
    return out


def test_depth_that_does_not_line_up_with_colour_is_found(seq):
    from cpf_jax.registration import check_alignment

    aligned = check_alignment(seq.colour[:2], seq.depth[:2])
    assert aligned.shift == (0, 0) and not aligned.misaligned
    off = check_alignment(seq.colour[:2], _shifted(seq.depth[:2], 8))
    assert off.shift == (8, 0) and off.misaligned, off
    assert "8 px left of the colour edges" in off.describe()
    assert not aligned.mirrored and not off.mirrored
    flipped = check_alignment(seq.colour[:2], seq.depth[:2, :, ::-1])
    assert flipped.mirrored and flipped.score_mirrored > 2 * flipped.score, flipped


def test_the_command_line_warns_when_depth_is_mirrored(seq, tmp_path):
    path = Path(to_folder(seq, tmp_path / "mirrored"))
    for p in (path / "depth").iterdir():
        cv2.imwrite(str(p), seq.depth[int(p.stem)][:, ::-1].copy())
    args = build_parser().parse_args([str(path), "--model", "rgbd", "--background", "2"])
    with pytest.warns(InputWarning, match="lines up with the colour only when flipped"):
        open_inputs(args, open_source(str(path)))


def test_the_real_recordings_depth_lies_beside_its_colour_without_the_fitted_offset():
    # The annotator fitted a 10-12 px shift by eye (images1/ANNOTATION.md); the check finds
    # it, and finds nothing once the calibration carries it.
    import json

    from cpf_jax.registration import calibration_from_dict, check_alignment, register_depth

    source = open_source(str(shared_data("ist_piv_rgbd", "images1")))
    frames = [source.read(i) for i in (1, 10, 20, 60, 80)]
    colour = np.stack([f.colour for f in frames])
    fitted = json.loads((ROOT / "experiments" / "calib" / "ist_piv.json").read_text())
    for offset, misaligned in (([0.0, 0.0], True), (fitted["offset_px"], False)):
        calib = calibration_from_dict({**fitted, "offset_px": offset})
        depth = np.stack([np.asarray(register_depth(f.depth, calib)) for f in frames])
        found = check_alignment(colour, depth)
        assert found.misaligned is misaligned and not found.mirrored, found
        if misaligned:
            assert 9 <= found.shift[0] <= 12 and abs(found.shift[1]) <= 3, found


def test_the_command_line_warns_when_depth_is_not_registered(seq, tmp_path):
    path = Path(to_folder(seq, tmp_path / "off"))
    for p in (path / "depth").iterdir():
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), _shifted(d, 10))
    args = build_parser().parse_args([str(path), "--model", "rgbd", "--background", "2"])
    with pytest.warns(InputWarning, match=r"depth edges lie 10 px left.*offset_px\": \[10, 0\]"):
        open_inputs(args, open_source(str(path)))
    # Without background frames (the default) the start frame and four spread over the
    # recording are checked.
    args = build_parser().parse_args([str(path), "--model", "rgbd"])
    with pytest.warns(InputWarning, match=r"depth edges lie 10 px left.* in 5 frames"):
        open_inputs(args, open_source(str(path)))
    args = build_parser().parse_args(["walk_across_slow", "--model", "rgbd"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)  # registered depth: no word
        open_inputs(args, open_source("walk_across_slow"))


# ---------------------------------------------------------------------- confidence of guesses


def test_person_confidence_is_high_for_a_walker_and_low_for_a_head_in_a_corner(seq):
    from cpf_jax.detect import find_person_scored, person_confidence
    from cpf_jax.io import SyntheticSource
    from cpf_jax.kernels.background import median_background

    empty = SyntheticSource(seq, "walk_across_slow").empty_background()
    background = median_background(empty.colour[None], empty.depth[None])
    found = find_person_scored(Frame(seq.colour[1], seq.depth[1]), background)
    assert found.confidence >= 0.5, found
    corner, doubts = person_confidence((0, 0, 60, 55), 2400, (424, 512))
    assert corner < 0.3
    assert any("left and top edge" in d for d in doubts)
    assert any("as wide as tall" in d for d in doubts)


def test_init_auto_refuses_a_blob_it_is_not_sure_of(seq, tmp_path, capsys):
    from cpf_jax.io import SyntheticSource

    empty = SyntheticSource(seq, "walk_across_slow").empty_background()
    path = tmp_path / "corner"
    (path / "rgb").mkdir(parents=True)
    (path / "depth").mkdir()
    for t in range(8):  # the empty room, then something head-sized in the top-left corner
        colour, depth = np.array(empty.colour), np.array(empty.depth)
        if t >= 5:
            colour[:70, :65] = (200, 170, 150)
            depth[:70, :65] = 1500
        cv2.imwrite(str(path / "rgb" / f"{t:03d}.png"), colour[..., ::-1])
        cv2.imwrite(str(path / "depth" / f"{t:03d}.png"), depth)
    argv = [str(path), "--init", "auto", "--model", "rgbd", "--background", "0:5"]
    assert main([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("--init auto: passed over a blob at 0,0,65,70 in frame 5")
    assert "no one found with confidence >= 0.5 in frames 0..7" in err[-1]
    assert "the frame's left and top edge cuts it" in err[-1]


def test_points_auto_refuses_a_box_without_the_whole_body(seq, folder, capsys):
    x, y, w, h = seq.boxes[1]
    upper = f"{x:.0f},{y:.0f},{w:.0f},{h / 3:.0f}"  # head and shoulders
    argv = [str(folder), "--model", "rgbd", "--init", upper, "--start", "1", "--background", "2"]
    assert main([*argv, "--points", "auto", "--no-progress"]) == 2
    warning, line = capsys.readouterr().err.strip().splitlines()
    # The folder has no calibration.json: the points' millimetres rest on a guess, said so.
    assert warning.startswith("cpf-track: warning: ") and "has no intrinsics; assuming" in warning
    assert line.startswith("cpf-track: error: --points auto: found head")
    assert "the farthest limb is" in line
    assert "give the points as x,y;x,y;..." in line


def test_body_points_confidence():
    from cpf_jax.cascade import body_points_confidence

    assert body_points_confidence([450, 520, 900, 1050]) == (1.0, ())
    low, doubts = body_points_confidence([380, 270, 600, 364])
    assert low == pytest.approx(0.25) and "the farthest limb is 600 mm" in doubts[0]


# ------------------------------------------------------------------ results that cannot mislead


def test_a_run_that_matches_nothing_prints_dashes_and_says_what_it_scored(folder, capsys):
    argv = [str(folder), "--init", "400,20,40,60", "--particles", "16", "--no-progress"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    header, _, row = out.splitlines()[1:4]
    names, values = ([c.strip() for c in line.split("|")] for line in (header, row))
    cells = dict(zip(names, values, strict=True))
    assert cells["matched"] == "0"
    assert cells["MOTP px"] == "-" and cells["SA px"] == "-"  # nothing matched to average
    assert "scored 4 of 4 tracked frames (0-3, the first being the start box)" in out
    assert "matched 0 (IoU >= 0.5)" in out
    # The compile is said, on stderr, as every note; stdout holds the results.
    assert "cpf-track: compiling init ... " in err
    assert "cpf-track: compiling step ... " in err
    assert "compiling" not in out and "note" not in out


def test_format_summary_prints_a_dash_for_a_mean_over_nothing():
    from cpf_jax.metrics import format_summary, summarise

    gt = np.array([[10, 10, 20, 40]] * 3, np.float32)
    s = summarise(gt + [200, 0, 0, 0], gt, lost=np.ones(3, bool))  # lost throughout
    assert s["boxed"] == 0 and s["lost"] == 3 and s["centre_error"] == 0.0
    row = format_summary(s).splitlines()[2].split("|")[1:-1]
    assert [c.strip() for c in row][-5:] == ["0.0", "-", "-", "0.0", "-"]  # P, CE, MOTP, MOTA, SA


# ------------------------------------------------------------------------------ compile cache


def test_one_call_keeps_compiled_programs_for_the_next_run(monkeypatch, tmp_path):
    import cpf_jax

    keys = ("jax_compilation_cache_dir", "jax_enable_compilation_cache")
    before = {k: getattr(jax.config, k) for k in keys}
    monkeypatch.setenv("CPF_JAX_COMPILE_CACHE", str(tmp_path / "cache"))
    try:
        assert cpf_jax.enable_compile_cache() == tmp_path / "cache"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache")
        assert jax.config.jax_enable_compilation_cache is True
    finally:
        for k, v in before.items():
            jax.config.update(k, v)


# ---------------------------------------------------------------------- ground truth, files


def _gt_warnings(boxes, size=(512, 424)) -> list[str]:
    from cpf_jax.io.groundtruth import check_groundtruth

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_groundtruth(np.asarray(boxes, np.float32), None, size, "gt")
    return [str(w.message) for w in caught]


def test_ground_truth_in_another_convention_is_named(seq):
    assert _gt_warnings(seq.boxes) == []
    corners = seq.boxes.copy()
    corners[:, 2:] += corners[:, :2]
    corners = np.concatenate([corners, corners + 1])  # 8 lines
    (said,) = _gt_warnings(corners)
    assert "every ground-truth box has w > x and h > y" in said
    (said,) = _gt_warnings(seq.boxes * 3.0)  # boxes of an image three times the size
    assert "lie more than half outside the 512x424 image" in said and "frame" in said


def test_a_polygon_ground_truth_names_itself(tmp_path):
    from cpf_jax.io.groundtruth import load_groundtruth

    (tmp_path / "gt.txt").write_text("10,20,50,20,50,90,10,90\n")
    with pytest.raises(SourceError, match=r"gt.txt:1: 8 numbers, a polygon"):
        load_groundtruth(tmp_path / "gt.txt")


def test_a_calibration_file_the_tracker_cannot_read_is_not_ignored_silently(seq, tmp_path):
    import json

    path = Path(to_folder(seq, tmp_path / "calib"))
    (path / "calibration.json").write_text(json.dumps({"depth_to_colour": [[1, 0], [0, 1]]}))
    args = build_parser().parse_args([str(path), "--background", "2"])
    with pytest.warns(InputWarning, match="calibration.json: neither a registration"):
        open_inputs(args, open_source(str(path)))


def test_python_m_cpf_jax_cli_is_the_command(tmp_path):
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-m", "cpf_jax.cli", str(tmp_path / "missing")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2 and "no such file or directory" in run.stderr, run.stderr


def test_a_background_longer_than_the_recording_is_announced(folder):
    args = build_parser().parse_args([str(folder), "--model", "rgbd", "--background", "0:40"])
    note = open_inputs(args, open_source(str(folder))).note
    assert (
        note == "background: --background 0:40 asks for 40 frames, the recording has 4; "
        "the median of frames 0-3"
    )


def test_an_npz_camera_matrix_is_read_as_intrinsics(seq, tmp_path):
    k = np.array([[365.0, 0, 255.0], [0, 366.0, 205.0], [0, 0, 1]])
    np.savez(tmp_path / "k.npz", colour=seq.colour[:2], intrinsics=k)
    assert NpzSource(tmp_path / "k.npz").intrinsics == Intrinsics(365.0, 366.0, 255.0, 205.0)


def test_a_box_left_of_the_frame_is_read_as_a_value_not_an_option(folder, capsys):
    assert main([str(folder), "--init", "-300,100,60,80", "--start", "0"]) == 2
    assert "initial box -300,100,60,80 lies outside" in _one_error_line(capsys)


# ----------------------------------------------------------------------------------- memory


def test_the_memory_a_filter_needs_grows_with_its_particles_and_is_checked():
    from cpf_jax import ColourConfig, build_colour_filter, default_colour_params
    from cpf_jax.errors import MemoryTooSmall
    from cpf_jax.memory import check_fits, needed_bytes

    frame = Frame(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16))
    box, key, params = np.array([10, 10, 8, 16], np.float32), jax.random.PRNGKey(0), None
    needs = []
    for n in (1_000, 100_000):
        filt = build_colour_filter(ColourConfig(n_particles=n))
        params = default_colour_params()
        state = jax.eval_shape(filt.init, params, key, frame, box, None)
        needs.append(needed_bytes(jax.jit(filt.step).lower(params, key, state, frame).compile()))
    assert needs[1] > 10 * needs[0] > 0  # the particles, not the frame, dominate at 100k
    check_fits(needs[1], "it", free=2 * needs[1])
    with pytest.raises(MemoryTooSmall, match=r"it needs about .* GB by XLA's estimate"):
        check_fits(needs[1], "it", free=needs[1])


def test_too_many_particles_for_the_memory_is_one_line_before_tracking(
    folder, tmp_path, monkeypatch, capsys
):
    import cpf_jax.memory

    monkeypatch.setattr(cpf_jax.memory, "free_bytes", lambda device=None: 10_000_000)
    out = str(tmp_path / "run.csv")
    assert main([str(folder), "--particles", "100000", "--out", out, "--no-progress"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("cpf-track: error: --particles 100000 on 512x424 needs about")
    assert "0.0 GB is free; about" in line and "particles fit" in line


def test_the_colour_folder_of_a_recording_is_named_for_what_it_is(folder):
    with pytest.warns(InputWarning, match=r"rgb is the colour folder of the RGB-D recording"):
        source = open_source(str(folder / "rgb"))
    assert source.kind == "otb" and not source.has_depth
