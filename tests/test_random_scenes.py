"""Randomised scenes (cpf_jax.random_scenes) and the synthetic knobs they draw: the focal
scale, poles and signs, the virtual moving camera."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from cpf_jax.random_scenes import CameraMotion, draw_scene, make_random_sequence, move_camera
from cpf_jax.synthetic import make_sequence


def test_a_scene_is_a_function_of_its_seed():
    a, b, c = draw_scene(12), draw_scene(12), draw_scene(13)
    assert a == b
    assert (a.spec, a.motion) != (c.spec, c.motion)


def test_the_drawn_factors_cover_their_ranges():
    scenes = [draw_scene(s) for s in range(300)]
    heights = np.array([s.factors["target_height_px"] for s in scenes])
    assert 40 <= heights.min() < 50 and 350 < heights.max() <= 400
    assert all(0.55 <= s.spec.focal_scale <= 1.5 for s in scenes)
    seen = {f: {s.factors[f] for s in scenes} for f in scenes[0].factors if f != "target_height_px"}
    assert seen["view"] == {"eye", "high"}
    assert {"static", "pan", "follow", "shake"} <= {c.split("+")[0] for c in seen["camera"]}
    assert any(c.endswith("+zoom") for c in seen["camera"])
    assert seen["look_alikes"] == {"none", "behind", "in_front"}
    assert seen["lighting"] == {"none", "drift", "switch"}
    for flag in ("partial_occlusion", "dark_clothes"):
        assert seen[flag] == {"yes", "no"}
    assert seen["thin_clutter"] == {"none", "poles"}
    assert seen["size"] == {"small", "medium", "large"}


def test_the_focal_scale_sizes_the_walker():
    near = make_sequence("walk_towards", seed=2, n_frames=2)
    wide = make_sequence("walk_towards", seed=2, n_frames=2, focal_scale=0.6)
    ratio = wide.boxes[0, 3] / near.boxes[0, 3]
    assert ratio == pytest.approx(0.6, abs=0.03)
    assert wide.intrinsics.fx == pytest.approx(0.6 * near.intrinsics.fx)


def test_poles_stand_in_the_room_as_tall_thin_objects():
    plain = make_sequence("walk_across_medium", seed=5, n_frames=1)
    poles = make_sequence("walk_across_medium", seed=5, n_frames=1, poles=6)
    changed = (plain.meta["background_depth"] != poles.meta["background_depth"]).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(changed)
    tall_thin = [s for s in stats[1:] if s[3] > 5 * s[2] and s[4] > 200]
    assert tall_thin, "no pole-shaped change in the room's depth"


@pytest.fixture(scope="module")
def still():
    return make_sequence("walk_across_medium", seed=1, n_frames=12)


def test_a_still_camera_leaves_the_sequence_as_it_is(still):
    assert move_camera(still, CameraMotion(), seed=0) is still
    assert move_camera(still, CameraMotion(crop=0.8), seed=0) is still


def test_the_moved_camera_moves_pixels_and_ground_truth_together(still):
    motion = CameraMotion(crop=0.75, follow=0.8, pan_px=(2.0, 0.5), shake_px=3.0, zoom=0.1)
    moved = move_camera(still, motion, seed=3)
    crops, intr = moved.meta["crop_xywh"], moved.meta["intrinsics"]
    assert len(np.unique(np.round(crops[:, :2]), axis=0)) > 6  # it moves every frame
    assert np.all(crops[:, :2] >= 0)
    assert np.all(crops[:, 0] + crops[:, 2] <= 512 + 1e-3)
    assert np.all(crops[:, 1] + crops[:, 3] <= 424 + 1e-3)
    for t in (0, 5, 11):
        x0, y0, cw, ch = crops[t]
        s = 512 / cw
        # A pixel of the output is the rendered pixel under it.
        u, v = 300, 200
        src = (int(round(x0 + (u + 0.5) / s - 0.5)), int(round(y0 + (v + 0.5) * ch / 424 - 0.5)))
        assert moved.depth[t, v, u] == still.depth[t, src[1], src[0]]
        # The box is the original one through the same map (to the pixel grid).
        bx, by, bw, bh = still.boxes[t]
        expect = np.array([(bx - x0) * s, (by - y0) * s, bw * s, bh * s])
        np.testing.assert_allclose(moved.boxes[t], expect, atol=2.5)
        # The frame's intrinsics project the 3D joints onto the moved 2D joints.
        fx, fy, cx, cy = intr[t]
        j3 = still.joints3d[t]
        proj = np.stack([fx * j3[:, 0] / j3[:, 2] + cx, fy * j3[:, 1] / j3[:, 2] + cy], axis=1)
        np.testing.assert_allclose(moved.joints2d[t], proj, atol=0.05)


def test_a_random_sequence_carries_its_measured_size():
    seq = make_random_sequence(7)
    f = seq.meta["factors"]
    assert f["target_height_px"] == pytest.approx(np.median(seq.boxes[seq.visible, 3]))
    assert f["size"] == (
        "small"
        if f["target_height_px"] < 80
        else "medium"
        if f["target_height_px"] <= 200
        else "large"
    )
    assert seq.name == "random_7"


def test_a_random_sequence_starts_where_the_walker_is_clear():
    """Scene 5 opens with the walker behind a sign; it starts where his head and trunk
    show, inside the frame, and the frames before are dropped."""
    seq = make_random_sequence(5)
    start = seq.meta["start_frame"]
    assert start > 0 and len(seq.colour) == 100 - start
    seen = dict(zip(seq.joint_names, seq.meta["joint_visible"][0], strict=True))
    assert seen["head"] and seen["head_top"] and (seen["torso"] or seen["pelvis"])
    x, y, w, h = seq.boxes[0]
    assert x > 0 and y > 0 and x + w < 512 and y + h < 424
    assert len(seq.meta["visible_fraction"]) == len(seq.colour)


def _unseen():
    path = Path(__file__).resolve().parents[1] / "experiments" / "unseen.py"
    spec = importlib.util.spec_from_file_location("unseen", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_benchmark_splits_are_disjoint_and_its_table_groups_by_factor():
    unseen = _unseen()
    assert not set(unseen.TRAIN_SEEDS) & set(unseen.EVAL_SEEDS)
    assert len(unseen.EVAL_SEEDS) >= 60
    factors = dict.fromkeys(unseen.FACTORS, "a")
    rows = [
        {"factors": dict(factors, view="eye"), "runs": {"cpf_jax": {"sr": 80.0, "auc": 60.0}}},
        {"factors": dict(factors, view="high"), "runs": {"cpf_jax": {"sr": 20.0, "auc": 10.0}}},
        {"factors": dict(factors, view="high"), "runs": {"cpf_jax": {"sr": 40.0, "auc": 30.0}}},
    ]
    out = unseen.summary(rows)
    assert out["scenes"] == 3
    assert out["cpf_jax"] == {"sr": pytest.approx(140 / 3), "auc": pytest.approx(100 / 3)}
    assert out["csrt"] == {"sr": None, "auc": None}
    high = out["per_factor"]["view"]["high"]
    assert high["scenes"] == 2 and high["cpf_jax"] == {"sr": 30.0, "auc": 20.0}
