"""cpf_jax.detect: person-shaped foreground blobs against known boxes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cpf_jax.detect import DetectConfig, find_person, person_boxes
from cpf_jax.kernels.background import median_background
from cpf_jax.kernels.boxes import iou
from cpf_jax.types import Frame

H, W = 120, 160


def scene(people=(), depth=True):
    """A flat wall at 4 m with grey texture, and box-shaped 'people' ``(x, y, w, h, z_mm,
    rgb)`` in front of it. Returns (frame, background)."""
    rng = np.random.default_rng(0)
    colour = rng.integers(90, 110, (H, W, 3)).astype(np.uint8)
    z = np.full((H, W), 4000, np.uint16)
    bg = median_background(colour[None], (z if depth else 0 * z)[None])
    colour, z = colour.copy(), z.copy()
    for x, y, w, h, zz, rgb in people:
        colour[y : y + h, x : x + w] = rgb
        z[y : y + h, x : x + w] = zz
    return Frame(colour, z if depth else 0 * z), bg


def test_one_person_gives_his_exact_box():
    frame, bg = scene([(40, 20, 25, 70, 2500, (200, 30, 30))])
    np.testing.assert_array_equal(person_boxes(frame, bg), [[40, 20, 25, 70]])
    np.testing.assert_array_equal(find_person(frame, bg), [40, 20, 25, 70])


def test_empty_scene_and_non_person_shapes_give_nothing():
    frame, bg = scene()
    assert person_boxes(frame, bg).shape == (0, 4) and find_person(frame, bg) is None
    # a low wide object (a desk) and a speck
    frame, bg = scene([(20, 80, 100, 20, 3000, (50, 50, 50)), (140, 10, 2, 2, 1000, (0, 0, 0))])
    assert find_person(frame, bg) is None


def test_people_touching_at_different_depths_are_split_largest_first():
    near = (40, 20, 25, 80, 2000, (200, 30, 30))
    far = (65, 30, 20, 60, 3000, (30, 30, 200))  # touches the near one's right edge
    frame, bg = scene([far, near])
    np.testing.assert_array_equal(person_boxes(frame, bg), [[40, 20, 25, 80], [65, 30, 20, 60]])


def test_colour_only_frames_use_the_colour_change():
    frame, bg = scene([(40, 20, 25, 70, 0, (200, 30, 30))], depth=False)
    np.testing.assert_array_equal(find_person(frame, bg), [40, 20, 25, 70])


def test_synthetic_walkers_against_their_ground_truth():
    from cpf_jax.io import open_source

    for name in ("walk_across_medium", "walk_towards", "turn"):
        src = open_source(name)
        empty = src.empty_background()
        bg = median_background(empty.colour[None], empty.depth[None])
        for t in range(0, len(src), 15):
            box = find_person(src.read(t), bg)
            assert box is not None, (name, t)
            assert float(iou(box[None], src.gt_boxes[t : t + 1])[0]) > 0.6, (name, t, box)


def test_bad_input():
    frame, bg = scene()
    with pytest.raises(ValueError, match="background is"):
        person_boxes(Frame(frame.colour[:10], frame.depth[:10]), bg)
    with pytest.raises(ValueError, match="min_area"):
        DetectConfig(min_area=0.0)


def test_a_blob_with_no_pixel_near_its_median_depth_terminates():
    # Half the blob at 1 m, half at 3 m: the median (2 m) has no pixel within the
    # depth gap, so no cut is made (and the search does not loop): the blob stays whole.
    frame, bg = scene(
        [(40, 20, 10, 70, 1000, (200, 30, 30)), (50, 20, 10, 70, 3000, (200, 30, 30))]
    )
    cfg = DetectConfig(depth_gap=100.0, depth_gap_rel=0.01)
    np.testing.assert_array_equal(person_boxes(frame, bg, cfg), [[40, 20, 20, 70]])


VTEST = (
    Path(__file__).parents[1] / ".." / "shared" / "data" / "opencv_samples" / "vtest" / "vtest.avi"
)


@pytest.mark.skipif(not VTEST.is_file(), reason=f"shared recording not present: {VTEST}")
def test_finds_the_pedestrian_on_the_grass_in_a_real_video():
    # OpenCV's vtest.avi (colour only, no ground truth): against the median of 25 frames,
    # the largest person-shaped blob of frame 0 is the man on the grass at about
    # (254, 220, 30, 89), checked by eye; the walkers on the path are smaller.
    from cpf_jax.io import open_source

    src = open_source(str(VTEST))
    idx = np.linspace(0, len(src) - 1, 25).round().astype(int)
    frames = [src.read(int(i)) for i in idx]
    bg = median_background(
        np.stack([f.colour for f in frames]), np.stack([f.depth for f in frames])
    )
    box = find_person(src.read(0), bg)
    assert box is not None
    assert float(iou(box[None], np.array([[254.0, 220.0, 30.0, 89.0]]))[0]) > 0.7
