"""The hand annotations of IST images1 (experiments/annotations/): formats and consistency.

The checks on the project's own files run always; the comparison with the recording's
``groundtruth_rect.txt`` and the drawing of the check sheets need ../shared/data and are
marked ``shared_data``. Every check is a function that is also run on a corrupted copy of
the file, so each one is seen to fail.
"""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, shared_data

from cpf_jax.io.groundtruth import load_groundtruth
from cpf_jax.io.mot import read_mot

ANN = ROOT / "experiments" / "annotations"
PEOPLE = ANN / "ist_images1_people.txt"
POINTS = ANN / "ist_images1_points.csv"
WIDTH, HEIGHT = 640, 480
PARTS = ("head", "left_hand", "right_hand", "torso")
POINT_FRAMES = range(52, 91)  # 1-based
NEAR_BOX = 25  # px: a visible head or hand lies inside or this close to id 1's box


# -- checks (each raises AssertionError naming the first problem) -------------------------


def check_people(path: Path) -> np.ndarray:
    """MOTChallenge ground truth ``frame,id,x,y,w,h,1,1,visibility``: parses with
    ``read_mot``, ids unique per frame, boxes inside the frame; returns read_mot's rows."""
    rows = read_mot(path)  # 0-based frames and pixels
    raw = [line.split(",") for line in path.read_text(encoding="utf-8").splitlines()]
    assert len(rows) == len(raw) > 0, "every line is one box"
    for n, fields in enumerate(raw, start=1):
        assert len(fields) == 9, f"line {n}: 9 fields"
        assert fields[6:8] == ["1", "1"], f"line {n}: consider flag and class are 1"
        assert 0.0 <= float(fields[8]) <= 1.0, f"line {n}: visibility in [0, 1]"
    frame, pid = rows[:, 0].astype(int), rows[:, 1].astype(int)
    np.testing.assert_array_equal(rows[:, :6], np.round(rows[:, :6]), "whole pixels")
    assert frame.min() >= 0 and frame.max() < 108, "frames 1-108 of the recording"
    assert pid.min() >= 1, "ids from 1"
    keys = frame * 1000 + pid
    assert len(np.unique(keys)) == len(keys), "an id appears twice in one frame"
    x, y, w, h = rows[:, 2:6].T
    assert (w > 0).all() and (h > 0).all(), "empty box"
    inside = (x >= 0) & (y >= 0) & (x + w <= WIDTH) & (y + h <= HEIGHT)
    assert inside.all(), f"box outside the frame at line {np.flatnonzero(~inside)[0] + 1}"
    return rows


def read_points(path: Path) -> dict[tuple[int, str], tuple[float, float] | None]:
    """``{(frame 1-based, part): (x, y) 1-based, or None when hidden}``."""
    out: dict[tuple[int, str], tuple[float, float] | None] = {}
    with path.open(encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        assert reader.fieldnames == ["frame", "part", "x", "y", "visible"], "header"
        for row in reader:
            key = (int(row["frame"]), row["part"])
            assert key not in out, f"{key} twice"
            assert row["visible"] in ("0", "1"), f"{key}: visible is 0 or 1"
            if row["visible"] == "1":
                assert row["x"] and row["y"], f"{key}: visible without coordinates"
                out[key] = (float(row["x"]), float(row["y"]))
            else:
                assert not row["x"] and not row["y"], f"{key}: hidden with coordinates"
                out[key] = None
    return out


def check_points(path: Path, people: np.ndarray) -> None:
    """Every frame 52-90 and part once; visible heads and hands near id 1's box."""
    points = read_points(path)
    expected = {(f, p) for f in POINT_FRAMES for p in PARTS}
    assert set(points) == expected, f"missing or extra rows: {set(points) ^ expected}"
    for (f, part), xy in points.items():
        if xy is None:
            continue
        assert 1 <= xy[0] <= WIDTH and 1 <= xy[1] <= HEIGHT, f"{f} {part}: outside the frame"
        if part == "torso":
            continue
        box = people[(people[:, 0] == f - 1) & (people[:, 1] == 1)]
        assert len(box) == 1, f"frame {f}: a visible {part} but no id 1 box"
        x, y, w, h = box[0, 2:6] + [1, 1, 0, 0]  # 1-based, inclusive extent x .. x+w-1
        dx = max(x - xy[0], 0, xy[0] - (x + w - 1))
        dy = max(y - xy[1], 0, xy[1] - (y + h - 1))
        assert max(dx, dy) <= NEAR_BOX, f"frame {f}: {part} {xy} is {max(dx, dy)} px off box"


def check_target(people: np.ndarray, gt_path: Path) -> None:
    """id 1 is the recording's single-person ground truth: present exactly where it is
    non-zero, and the same box there within 1 px."""
    gt, visible = load_groundtruth(gt_path)  # 0-based xywh
    target = people[people[:, 1] == 1]
    frames = target[:, 0].astype(int)
    np.testing.assert_array_equal(frames, np.flatnonzero(visible), "id 1's frames")
    np.testing.assert_allclose(target[:, 2:6], gt[frames], atol=1.0, err_msg="id 1's boxes")


# -- the project's files -------------------------------------------------------------------


def test_people_file():
    rows = check_people(PEOPLE)
    assert set(rows[:, 1].astype(int)) == {1, 2, 3, 4, 5, 6}
    # read_mot counts from 0: the file's first line is frame 27, box x = 1.
    first = PEOPLE.read_text(encoding="utf-8").splitlines()[0].split(",")
    assert rows[0, 0] == int(first[0]) - 1 and rows[0, 2] == int(first[2]) - 1


def test_identities_are_contiguous_tracks():
    """Nobody leaves and comes back in this recording: each id is one run of frames."""
    rows = check_people(PEOPLE)
    for pid in np.unique(rows[:, 1]):
        frames = np.sort(rows[rows[:, 1] == pid, 0])
        np.testing.assert_array_equal(np.diff(frames), 1, f"id {int(pid)}")


def test_points_file():
    check_points(POINTS, check_people(PEOPLE))


# -- each check fails on a corrupted copy --------------------------------------------------


def corrupt(src: Path, dst: Path, line: int, edit) -> Path:
    lines = src.read_text(encoding="utf-8").splitlines()
    lines[line] = edit(lines[line])
    dst.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return dst


def people_line(edit):
    """Edit a line's fields: ``edit(fields) -> fields``."""
    return lambda text: ",".join(edit(text.split(",")))


@pytest.mark.parametrize(
    "line, edit, message",
    [
        (5, lambda f: f[:6], "9 fields"),
        (5, lambda f: [*f[:8], "1.5"], "visibility"),
        (5, lambda f: [f[0], "0", *f[2:]], "ids from 1"),
        (7, lambda f: [f[0], "2", *f[2:]], "twice in one frame"),  # frame 33: ids 2, 3
        (5, lambda f: [*f[:2], "600", *f[3:]], "outside the frame"),
        (5, lambda f: [*f[:4], "0", *f[5:]], "empty box"),
    ],
)
def test_check_people_fails_on_corruption(tmp_path, line, edit, message):
    bad = corrupt(PEOPLE, tmp_path / "people.txt", line, people_line(edit))
    with pytest.raises(AssertionError, match=message):
        check_people(bad)


@pytest.mark.parametrize(
    "line, edit, message",
    [
        (1, lambda t: "91,head,,,0", "missing or extra rows"),
        (1, lambda t: "52,head,,,1", "visible without coordinates"),
        (2, lambda t: "52,left_hand,10,10,0", "hidden with coordinates"),
        (1, lambda t: "52,head,300,100,1", "px off box"),
        (4, lambda t: "52,torso,700,100,1", "outside the frame"),
    ],
)
def test_check_points_fails_on_corruption(tmp_path, line, edit, message):
    bad = corrupt(POINTS, tmp_path / "points.csv", line, edit)
    with pytest.raises(AssertionError, match=message):
        check_points(bad, check_people(PEOPLE))


# -- against the recording -----------------------------------------------------------------


@pytest.mark.shared_data
def test_target_is_the_single_person_ground_truth():
    gt = shared_data("ist_piv_rgbd", "images1", "groundtruth_rect.txt")
    check_target(check_people(PEOPLE), gt)


@pytest.mark.shared_data
@pytest.mark.parametrize("shift, frame", [((2, 0, 0, 0), 60), ((0, 0, 0, 0), None)])
def test_check_target_fails_on_corruption(shift, frame):
    gt = shared_data("ist_piv_rgbd", "images1", "groundtruth_rect.txt")
    rows = check_people(PEOPLE).copy()
    target = np.flatnonzero(rows[:, 1] == 1)
    if frame is None:  # drop id 1's first box: a frame where the target is missing
        rows = np.delete(rows, target[0], axis=0)
    else:
        rows[target[rows[target, 0] == frame - 1], 2:6] += shift
    with pytest.raises(AssertionError):
        check_target(rows, gt)


@pytest.mark.shared_data
def test_check_sheets_draw(tmp_path):
    """The drawing script writes its six sheets, each under 1.5 MB."""
    data = shared_data("ist_piv_rgbd", "images1")
    spec = importlib.util.spec_from_file_location("draw_annotations", ANN / "draw_annotations.py")
    draw = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(draw)
    assert draw.main(["--data", str(data), "--out", str(tmp_path)]) == 0
    sheets = sorted(tmp_path.glob("ist_images1_annotations_*.png"))
    assert [p.name for p in sheets] == [
        *(f"ist_images1_annotations_people_{k}.png" for k in (1, 2, 3, 4)),
        *(f"ist_images1_annotations_points_{k}.png" for k in (1, 2)),
    ]
    assert all(p.stat().st_size < 1.5e6 for p in sheets)


def test_draw_script_skips_without_the_recording(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("draw_annotations", ANN / "draw_annotations.py")
    draw = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(draw)
    assert draw.main(["--data", str(tmp_path / "absent"), "--out", str(tmp_path)]) == 0
    assert "not available" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.png"))
