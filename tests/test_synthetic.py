"""Synthetic RGB-D generator: determinism, ground-truth geometry, depth model, scenarios."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cpf_jax.kernels.boxes import xywh_to_rect
from cpf_jax.synthetic import (
    SCENARIOS,
    Clothing,
    Occluder,
    SyntheticSequence,
    iter_frames,
    kinect_v2_axial_sigma_mm,
    make_sequence,
    stacked_frames,
    to_folder,
)
from cpf_jax.types import KINECT_V2_DEPTH, Frame

H, W = 424, 512
REQUIRED_JOINTS = ("head", "left_hand", "right_hand", "left_foot", "right_foot", "torso")


@pytest.fixture(scope="module")
def medium() -> SyntheticSequence:
    return make_sequence("walk_across_medium", seed=0, n_frames=40)


def _j(seq: SyntheticSequence, name: str) -> int:
    return seq.joint_names.index(name)


def _to_world_mm(seq: SyntheticSequence, pts_cam: np.ndarray) -> np.ndarray:
    m = seq.meta["world_to_camera_mm"]
    return (pts_cam - m[:3, 3]) @ m[:3, :3]  # R^T (p - t), R orthonormal


def _hsv(seq: SyntheticSequence) -> np.ndarray:
    return np.stack([cv2.cvtColor(c, cv2.COLOR_RGB2HSV) for c in seq.colour])


# -- API, shapes, determinism ---------------------------------------------------------------


def test_shapes_and_dtypes(medium):
    s = medium
    T, J = 40, len(s.joint_names)
    assert s.colour.shape == (T, H, W, 3) and s.colour.dtype == np.uint8
    assert s.depth.shape == (T, H, W) and s.depth.dtype == np.uint16
    assert s.boxes.shape == (T, 4) and s.boxes.dtype == np.float32
    assert s.visible.shape == (T,) and s.visible.dtype == bool
    assert s.joints3d.shape == (T, J, 3) and s.joints3d.dtype == np.float32
    assert s.joints2d.shape == (T, J, 2) and s.joints2d.dtype == np.float32
    assert s.mask.shape == (T, H, W) and s.mask.dtype == bool
    assert set(REQUIRED_JOINTS) <= set(s.joint_names)
    assert s.intrinsics == KINECT_V2_DEPTH and s.fps == 10.0 and s.name == "walk_across_medium"
    assert s.meta["joint_visible"].shape == (T, J)


def test_deterministic_per_seed_and_prefix_stable():
    a = make_sequence("walk_across_fast", seed=3, n_frames=6)
    b = make_sequence("walk_across_fast", seed=3, n_frames=6)
    for f in ("colour", "depth", "boxes", "joints3d", "mask"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    c = make_sequence("walk_across_fast", seed=4, n_frames=6)
    assert not np.array_equal(a.colour, c.colour)
    assert not np.array_equal(a.joints3d, c.joints3d)
    # Frame t of a seed does not depend on the sequence length.
    d = make_sequence("walk_across_fast", seed=3, n_frames=3)
    for f in ("colour", "depth", "boxes", "joints3d", "mask"):
        np.testing.assert_array_equal(getattr(d, f), getattr(a, f)[:3], err_msg=f)


def test_overrides_are_checked_and_applied():
    with pytest.raises(TypeError, match="unknown ScenarioSpec field"):
        make_sequence("walk_across_medium", n_frames=2, partikles=3)
    with pytest.raises(KeyError, match="unknown scenario"):
        make_sequence("walk_sideways", n_frames=2)
    # Halving fps doubles the motion per frame; the speed in m/s is unchanged.
    steps = []
    for fps in (10.0, 5.0):
        s = make_sequence("walk_across_medium", n_frames=8, fps=fps)
        assert s.fps == fps and s.meta["spec"].fps == fps
        tor = s.joints3d[:, _j(s, "torso")].astype(np.float64)
        steps.append(np.median(np.linalg.norm(np.diff(tor[:, [0, 2]], axis=0), axis=1)))
    assert steps[1] / steps[0] == pytest.approx(2.0, rel=0.03)


def test_frame_iteration(medium):
    frames = list(iter_frames(medium))
    assert len(frames) == 40 and all(isinstance(f, Frame) for f in frames)
    np.testing.assert_array_equal(frames[7].depth, medium.depth[7])
    st = stacked_frames(medium)
    assert st.colour.shape == (40, H, W, 3) and st.depth.shape == (40, H, W)


# -- ground-truth geometry ------------------------------------------------------------------


def test_box_is_the_tight_box_of_the_mask(medium):
    s = medium
    assert s.visible.all()
    for t in range(len(s.boxes)):
        x0, y0, x1, y1 = np.asarray(xywh_to_rect(s.boxes[t]))
        inside = np.zeros((H, W), bool)
        inside[y0:y1, x0:x1] = True
        m = s.mask[t]
        assert m.any() and not (m & ~inside).any(), t  # contains every person pixel
        # ... and tightly: every edge row / column of the rect holds a person pixel.
        assert m[y0, x0:x1].any() and m[y1 - 1, x0:x1].any(), t
        assert m[y0:y1, x0].any() and m[y0:y1, x1 - 1].any(), t


def test_box_agrees_with_the_body_joints(medium):
    s = medium
    x, y, w, h = s.boxes.T
    u, v = s.joints2d[..., 0] + 0.5, s.joints2d[..., 1] + 0.5  # pixel centres in box coordinates
    assert (u >= x[:, None] - 1).all() and (u <= (x + w)[:, None] + 1).all()
    assert (v >= y[:, None] - 1).all() and (v <= (y + h)[:, None] + 1).all()
    # The box top is the top of the hair (head_top joint), within a few pixels.
    np.testing.assert_allclose(v[:, _j(s, "head_top")], y, atol=4)
    # A 1.75 m person: box height ~ f * 1.75 m / Z (Z of the torso; feet/head at +-0.3 m).
    z_torso = s.joints3d[:, _j(s, "torso"), 2] / 1000.0
    ratio = h / (KINECT_V2_DEPTH.fy * 1.75 / z_torso)
    assert np.all((ratio > 0.9) & (ratio < 1.15)), ratio


def test_joints2d_are_projections_of_joints3d(medium):
    fx, fy, cx, cy = medium.intrinsics
    X, Y, Z = np.moveaxis(medium.joints3d.astype(np.float64), -1, 0)
    np.testing.assert_allclose(medium.joints2d[..., 0], fx * X / Z + cx, atol=1e-3)
    np.testing.assert_allclose(medium.joints2d[..., 1], fy * Y / Z + cy, atol=1e-3)
    # Walking lanes at 3.0 +- 0.3 m (+- 0.1 m seed jitter).
    z_torso = medium.joints3d[:, _j(medium, "torso"), 2]
    assert z_torso.min() > 2500 and z_torso.max() < 3500


def test_depth_at_head_pixel_is_the_head_surface(medium):
    s = medium
    h = _j(s, "head")
    uv = np.rint(s.joints2d[:, h]).astype(int)
    d = s.depth[np.arange(len(uv)), uv[:, 1], uv[:, 0]].astype(np.float64)
    z = s.joints3d[:, h, 2]
    ok = d > 0
    assert ok.mean() > 0.5
    # The ray through the head centre meets face or hair 75-100 mm in front of the centre.
    gap = z[ok] - d[ok]
    assert np.all((gap > 55) & (gap < 120)), gap
    # Back-projected with X = Z (x - cx) / fx, that pixel is a head-radius from the joint.
    fx, fy, cx, cy = s.intrinsics
    p = np.stack([d[ok] * (uv[ok, 0] - cx) / fx, d[ok] * (uv[ok, 1] - cy) / fy, d[ok]], -1)
    dist = np.linalg.norm(p - s.joints3d[ok, h], axis=-1)
    assert np.all((dist > 55) & (dist < 125)), dist
    assert s.meta["joint_visible"][:, h].all()


def test_person_depths_lie_on_the_body(medium):
    s = medium
    z_torso = s.joints3d[:, _j(s, "torso"), 2]
    for t in range(0, 40, 5):
        d = s.depth[t][s.mask[t]].astype(np.float64)
        d = d[d > 0]
        assert np.all(np.abs(d - z_torso[t]) < 700), t
        # Background pixels behind the person are far (>= 0.4 m) behind it.
        ring = cv2.dilate(s.mask[t].astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        ring &= ~cv2.dilate(s.mask[t].astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        bgd = s.depth[t][ring].astype(np.float64)
        bgd = bgd[(bgd > 0)]
        assert np.median(bgd) > z_torso[t] + 400


# -- depth model ----------------------------------------------------------------------------


def test_missing_pixels_plausible(medium):
    s = medium
    missing = s.depth == 0
    assert 0.003 < missing.mean() < 0.2
    m = s.mask
    assert 0.02 < missing[m].mean() < 0.3
    # Silhouette pixels (grazing incidence) drop out far more than the interior.
    interior = np.stack([cv2.erode(x.astype(np.uint8), np.ones((5, 5), np.uint8)) for x in m])
    interior = interior.astype(bool)
    eroded = [cv2.erode(x.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) for x in m]
    rim = m & ~np.stack(eroded)
    assert missing[rim].mean() > 5 * missing[interior].mean()

    # Depth discontinuities: the background pixels right next to the person (far side of
    # the jump, facing the camera) are removed like flying pixels; a few pixels out they are not.
    def ring(r0, r1):
        grow = lambda r: np.stack(  # noqa: E731
            [cv2.dilate(x.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) for x in m]
        ).astype(bool)
        return grow(r1) & ~grow(r0) if r0 > 0 else grow(r1) & ~m

    assert missing[ring(0, 1)].mean() > 0.4
    assert missing[ring(3, 6)].mean() < 0.1
    # Dark surfaces (black hair, shoes) drop out more than bright ones (shirt, skin).
    v = _hsv(s)[..., 2]
    dark = interior & (v < 50)
    bright = interior & (v > 100)
    assert dark.sum() > 1000 and bright.sum() > 10000
    assert missing[dark].mean() > 3 * missing[bright].mean()
    assert missing[dark].mean() > 0.1


def test_range_limit():
    s = make_sequence("walk_towards", n_frames=4, max_range_mm=3000.0)
    d = s.depth.astype(np.float64)
    # Only noise can push a surface just inside the range above it.
    assert (d > 3000).mean() < 0.005 and d.max() < 3200
    # The person starts at 4.2 m: nearly all of their pixels are beyond range.
    assert (s.depth[0][s.mask[0]] == 0).mean() > 0.9


def test_depth_noise_follows_the_kinect_v2_model():
    s = make_sequence("walk_across_slow", n_frames=30)
    d = s.depth.astype(np.float64)
    valid = (d > 0).all(0) & ~s.mask.any(0)
    mean, std = d.mean(0), d.std(0, ddof=1)
    fx, fy, cx, cy = s.intrinsics
    v, u = np.mgrid[0:H, 0:W]
    p_cam = np.stack([mean * (u - cx) / fx, mean * (v - cy) / fy, mean], -1)
    p_world = _to_world_mm(s, p_cam)
    # Static back-wall pixels (world z = room depth), above the furniture.
    wall_z = s.meta["spec"].room_depth_m * 1000.0
    wall = valid & (np.abs(p_world[..., 2] - wall_z) < 25) & (p_world[..., 1] > 1200)
    assert wall.sum() > 5000
    r = s.meta["world_to_camera_mm"][:3, :3]
    n = r @ np.array([0.0, 0.0, -1.0])
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(mean)], -1)
    cos = np.abs(ray @ n) / np.linalg.norm(ray, axis=-1)
    model = kinect_v2_axial_sigma_mm(mean / 1000.0, np.arccos(cos))
    assert np.median(std[wall] / model[wall]) == pytest.approx(1.0, abs=0.1)
    # Fankhauser et al. 2015 at 3 m facing the sensor: 1.5 - 1.5 + 2.7 = 2.7 mm.
    assert float(kinect_v2_axial_sigma_mm(3.0, 0.0)) == pytest.approx(2.7, abs=1e-5)


# -- motion ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, speed",
    [("walk_across_slow", 0.4), ("walk_across_medium", 0.8), ("walk_across_fast", 1.2)],
)
def test_torso_horizontal_speed_matches_scenario(name, speed):
    s = make_sequence(name, n_frames=20)
    tor = _to_world_mm(s, s.joints3d[:, _j(s, "torso")].astype(np.float64))
    step = np.linalg.norm(np.diff(tor[:, [0, 2]], axis=0), axis=1) * s.fps / 1000.0
    assert np.median(step) == pytest.approx(speed, rel=0.02)
    # Walking across: the motion is mostly along the image x axis.
    du = np.abs(np.diff(s.joints2d[:, _j(s, "torso"), 0]))
    assert np.median(du) > 0.8 * KINECT_V2_DEPTH.fx * speed / s.fps / 3.4


def test_walk_towards_grows_and_walk_away_shrinks_the_box():
    tw = make_sequence("walk_towards")
    aw = make_sequence("walk_away")
    assert tw.visible.all() and aw.visible.all()
    zt = tw.joints3d[:, _j(tw, "torso"), 2]
    za = aw.joints3d[:, _j(aw, "torso"), 2]
    assert np.all(np.diff(zt) < 0) and zt[0] > 3900 and zt[-1] < 2200
    assert np.all(np.diff(za) > 0) and za[0] < 2200 and za[-1] > 3900
    ht, ha = tw.boxes[:, 3], aw.boxes[:, 3]
    assert ht[-1] > 1.8 * ht[0] and ha[0] > 1.8 * ha[-1]
    assert np.corrcoef(np.arange(len(ht)), ht)[0, 1] > 0.95
    assert np.corrcoef(np.arange(len(ha)), ha)[0, 1] < -0.95


@pytest.mark.parametrize("name, sign", [("walk_towards", 1.0), ("walk_away", -1.0)])
def test_left_is_the_persons_anatomical_left(name, sign):
    # Facing the camera a person's left shoulder, hip, hand and foot are on the image's
    # right; seen from behind, on its left. (The generator's world frame is left-handed:
    # u x f points to the person's right.)
    s = make_sequence(name, seed=0, n_frames=10)
    u = s.joints2d[..., 0]
    for part in ("shoulder", "hip", "hand", "foot"):
        d = sign * (u[:, _j(s, f"left_{part}")] - u[:, _j(s, f"right_{part}")])
        assert np.all(d > 0) if part in ("shoulder", "hip") else np.median(d) > 0, (part, d)


def test_gait_limbs_swing_in_antiphase():
    s = make_sequence("walk_across_medium", n_frames=60, fps=30.0)
    world = _to_world_mm(s, s.joints3d.astype(np.float64))
    head = s.meta["heading_xz"]
    fwd = lambda j: (  # noqa: E731 - forward offset of a joint from the pelvis
        (world[:, _j(s, j), 0] - world[:, _j(s, "pelvis"), 0]) * head[:, 0]
        + (world[:, _j(s, j), 2] - world[:, _j(s, "pelvis"), 2]) * head[:, 1]
    )
    lf, rf, lh, rh = fwd("left_foot"), fwd("right_foot"), fwd("left_hand"), fwd("right_hand")
    assert np.corrcoef(lf, rf)[0, 1] < -0.8
    assert np.corrcoef(lh, rh)[0, 1] < -0.8
    assert np.corrcoef(lf, lh)[0, 1] < -0.5  # arm swings against the leg of the same side
    assert np.ptp(lf) > 400  # about one stride
    bob = world[:, _j(s, "torso"), 1]
    assert 10 < np.ptp(bob) < 80  # vertical bob of a walking trunk, mm


# -- scenarios ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(n for n, sp in SCENARIOS.items() if not sp.occluders))
def test_person_stays_fully_in_view(name):
    # Sample the default duration at 3 frames/s to keep the test fast.
    spec = SCENARIOS[name]
    fps = 3.0
    n = int(spec.n_frames * fps / spec.fps) if spec.path == "pace" else None
    s = make_sequence(name, seed=1, fps=fps, n_frames=n)
    assert len(s.boxes) >= 5 and s.visible.all()
    x, y, w, h = s.boxes.T
    assert x.min() >= 1 and y.min() >= 1
    assert (x + w).max() <= W - 1 and (y + h).max() <= H - 1
    assert (s.meta["occlusion"] == 0).all()


def test_single_pass_default_length_is_clipped_to_the_walk():
    s = make_sequence("walk_towards")
    walked = s.meta["walk_length_m"]
    assert len(s.colour) == int(walked / s.meta["spec"].speed_mps * s.fps) + 1
    longer = make_sequence("walk_towards", n_frames=len(s.colour) + 5, colour_noise=0.0)
    z = longer.joints3d[:, _j(longer, "torso"), 2]
    assert z[-1] < z[len(s.colour) - 1]  # keeps walking past the planned end


def _shirt_hue_fraction(seq: SyntheticSequence) -> float:
    h0 = int(
        cv2.cvtColor(np.uint8([[seq.meta["spec"].clothing.shirt]]), cv2.COLOR_RGB2HSV)[0, 0, 0]
    )
    hsv = _hsv(seq)
    dh = np.abs(hsv[..., 0].astype(int) - h0)
    dh = np.minimum(dh, 180 - dh)
    sel = (dh <= 6) & (hsv[..., 1] > 80) & (hsv[..., 2] > 40) & ~seq.mask
    return float(sel.mean())


def test_distractor_shares_the_shirt_hue():
    near = make_sequence("distractor_pass", n_frames=4)
    far = make_sequence("distractor_pass", n_frames=4, distractor_similarity=0.0)
    assert near.meta["spec"].distractor
    f_near, f_far = _shirt_hue_fraction(near), _shirt_hue_fraction(far)
    assert f_near > 0.05 and f_near > 3 * f_far


def test_dark_clothes_match_the_background():
    """The jacket's near-black is common in dark_clothes' background (matched clutter),
    rare in the plain room with the same clothes; the beige trousers match the wall."""

    def share(seq, rgb):
        c, bg = seq.colour[0].astype(int), ~seq.mask[0]
        return float((np.abs(c - np.array(rgb)).max(-1)[bg] < 30).mean())

    spec = SCENARIOS["dark_clothes"]
    jacket, trousers = spec.clothing.shirt, spec.clothing.trousers
    dark = [make_sequence("dark_clothes", seed=s, n_frames=2) for s in range(4)]
    plain = [
        make_sequence("walk_across_medium", seed=s, n_frames=2, clothing=spec.clothing)
        for s in range(4)
    ]
    assert np.mean([share(q, jacket) for q in dark]) > 2 * np.mean(
        [share(q, jacket) for q in plain]
    )
    assert np.mean([share(q, trousers) for q in dark]) > 0.2
    assert all(q.boxes[0, 3] < 180 for q in dark)  # a far walker: a small box


def test_illumination_switch_and_constant_light():
    on = make_sequence("light_switch", n_frames=12)
    off = make_sequence("walk_across_medium", n_frames=12)
    lum = lambda s: np.array([s.colour[t][~s.mask[t]].mean() for t in range(12)])  # noqa: E731
    a, b = lum(on), lum(off)
    assert a[6:].mean() < 0.75 * a[:6].mean()
    assert np.ptp(a[:6]) < 2 and np.ptp(a[6:]) < 2
    assert np.ptp(b) < 2
    drift = make_sequence("walk_across_medium", n_frames=12, illumination="drift")
    assert np.ptp(lum(drift)) > 10


def test_occluder_hook_reports_partial_and_full_occlusion():
    # A 1 m wide panel slides across between the camera and the walker, overtaking them
    # at about 1.6 m/s relative (in the walker's plane), so that each of its edges takes
    # 3 frames to pass over the walker (partial), with full occlusion in between; a faster
    # panel would cross the walker's width within one frame and leave no partial frame.
    wall = Occluder(
        size_m=(1.0, 2.4, 0.1), start_xz=(-1.3, 1.5), end_xz=(0.55, 1.5), t0_s=0.0, t1_s=2.0
    )
    s = make_sequence("walk_across_slow", n_frames=21, occluders=(wall,))
    occ = s.meta["occlusion"]
    frac = s.meta["visible_fraction"]
    assert occ[0] == 0 and occ[-1] == 0
    assert (occ == 1).sum() >= 4 and (occ == 2).any()
    full = occ == 2
    assert not s.visible[full].any() and (s.boxes[full] == 0).all()
    assert frac[~full].min() < 0.9 and (frac[occ == 0] > 0.97).all()
    # The occluder is nearer than the person wherever it covers them.
    t = int(np.nonzero(occ == 1)[0][0])
    z_torso = s.joints3d[t, _j(s, "torso"), 2]
    unmasked = s.depth[t][~s.mask[t]].astype(np.float64)
    assert (np.abs(unmasked - 1500) < 150).mean() > 0.05 and z_torso > 2500


def test_person_occluder_hides_the_walker_and_is_not_in_the_mask():
    # A second person walks quickly across, close to the camera, in front of the walker.
    other = Occluder(
        size_m=(0.5, 1.8, 0.3),
        start_xz=(-2.0, 1.6),
        end_xz=(2.0, 1.6),
        t0_s=0.0,
        t1_s=1.4,
        kind="person",
        clothing=Clothing(shirt=(30, 150, 60)),
    )
    s = make_sequence("walk_across_slow", n_frames=15, occluders=(other,))
    occ, frac = s.meta["occlusion"], s.meta["visible_fraction"]
    assert (occ == 1).any() and (frac < 0.8).any()
    t = int(np.argmin(frac))
    # The occluder's pixels (green top) are nearer than the walker and not in the mask.
    hsv = cv2.cvtColor(s.colour[t], cv2.COLOR_RGB2HSV)
    green = (np.abs(hsv[..., 0].astype(int) - 68) < 12) & (hsv[..., 1] > 120) & (s.depth[t] > 0)
    assert green.sum() > 500 and not (green & s.mask[t]).any()
    z_torso = s.joints3d[t, _j(s, "torso"), 2]
    assert np.median(s.depth[t][green]) < z_torso - 800
    with pytest.raises(ValueError, match="occluder kind"):
        make_sequence("walk_across_slow", n_frames=1, occluders=(Occluder(kind="ghost"),))


def test_occluder_mirror_x_follows_the_walkers_direction():
    # The occluder starts on the side the walker walks away from, for either direction.
    oc = Occluder(size_m=(0.5, 2.0, 0.3), start_xz=(-1.2, 1.8), end_xz=(-1.2, 1.8), mirror_x=True)
    sides = []
    for seed in range(6):
        s = make_sequence("walk_across_slow", seed=seed, n_frames=2, occluders=(oc,))
        walk = np.sign(s.joints3d[1, _j(s, "torso"), 0] - s.joints3d[0, _j(s, "torso"), 0])
        near = (s.depth[0] > 0) & (s.depth[0] < 2100)
        near[300:] = False  # ignore the floor in front of the camera
        cols = np.nonzero(near.any(axis=0))[0]
        sides.append(np.sign(np.mean(cols) - W / 2) * walk)
    assert set(sides) == {-1.0}


@pytest.mark.parametrize(
    "name, states",
    [("occlusion_box", [0, 1, 2]), ("occlusion_person", [0, 1])],  # the box hides all of him
)
def test_occlusion_scenarios(name, states):
    s = make_sequence(name, seed=0, n_frames=66)
    occ = s.meta["occlusion"]
    assert occ[0] == 0 and np.unique(occ).tolist() == states
    # The person is visible exactly in the frames that are not fully occluded.
    np.testing.assert_array_equal(s.visible, occ < 2)


def _chest_green_minus_red(s: SyntheticSequence, t: int) -> float:
    """Median G - R of the person pixels around the torso joint of frame ``t``."""
    u, v = np.rint(s.joints2d[t, _j(s, "torso")]).astype(int)
    window = (slice(v - 8, v + 9), slice(u - 5, u + 6))
    chest = s.colour[t][window][s.mask[t][window]].astype(int)
    return float(np.median(chest[:, 1] - chest[:, 0]))


def test_appearance_change_turns_the_red_top_green_at_frame_50():
    spec = SCENARIOS["appearance_change"]
    assert spec.shirt_change[0] == 50 and not spec.occluders
    s = make_sequence("appearance_change", seed=0, n_frames=52)
    before = [_chest_green_minus_red(s, t) for t in (48, 49)]
    after = [_chest_green_minus_red(s, t) for t in (50, 51)]
    assert max(before) < -50 and min(after) > 30


def test_occlusion_return_reverses_in_depth_while_occluded():
    s = make_sequence("occlusion_return", seed=0)
    z = s.joints3d[:, _j(s, "torso"), 2]
    turn = int(np.argmax(z))
    # Walks away (about 1.7 m), turns round and comes back nearly as far.
    assert 10 < turn < len(z) - 10
    assert z[turn] - z[0] > 1500 and z[turn] - z[-1] > 1200
    # The crossing person hides part of the walker around the turn, not at the ends.
    occ = s.meta["occlusion"]
    assert (occ[turn - 3 : turn + 4] > 0).all()
    assert (occ[:5] == 0).all() and (occ[-5:] == 0).all()
    # The empty-room background: what a background model of an empty room would hold.
    bg_depth = s.meta["background_depth"]
    assert bg_depth.shape == s.depth.shape[1:] and bg_depth.dtype == np.uint16
    far = (s.depth[0] > 0) & (bg_depth > 0) & ~s.mask[0]
    diff = np.abs(s.depth[0][far].astype(float) - bg_depth[far])
    assert np.median(diff) < 20  # the room where the walker is not
    person = s.mask[0] & (s.depth[0] > 0) & (bg_depth > 0)
    assert np.median(bg_depth[person].astype(float) - s.depth[0][person]) > 500


def test_shirt_colour_change():
    s = make_sequence("walk_across_medium", n_frames=8, shirt_change=(4, (40, 80, 200)))
    tor = np.rint(s.joints2d[:, _j(s, "torso")]).astype(int)
    blue_minus_red = []
    for t in range(8):
        u, v = tor[t]
        chest = s.colour[t][v - 8 : v + 9, u - 5 : u + 6][s.mask[t][v - 8 : v + 9, u - 5 : u + 6]]
        blue_minus_red.append(np.median(chest[:, 2].astype(int) - chest[:, 0]))
    assert max(blue_minus_red[:4]) < -50 and min(blue_minus_red[4:]) > 50


# -- export ---------------------------------------------------------------------------------


def test_to_folder_roundtrip(tmp_path):
    cover = Occluder(
        size_m=(4.0, 3.0, 0.1), start_xz=(0.0, 1.2), end_xz=(0.0, 1.2), t0_s=0.0, t1_s=0.05
    )
    s = make_sequence("walk_across_medium", n_frames=3)
    hidden = make_sequence("walk_across_medium", n_frames=1, occluders=(cover,))
    assert not hidden.visible[0]
    seq = s._replace(
        boxes=np.concatenate([s.boxes, hidden.boxes]),
        visible=np.concatenate([s.visible, hidden.visible]),
        colour=np.concatenate([s.colour, hidden.colour]),
        depth=np.concatenate([s.depth, hidden.depth]),
    )
    to_folder(seq, tmp_path / "seq")
    for t in range(4):
        rgb = cv2.imread(str(tmp_path / "seq" / "rgb" / f"{t:06d}.png"), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB), seq.colour[t])
        dep = cv2.imread(str(tmp_path / "seq" / "depth" / f"{t:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert dep.dtype == np.uint16
        np.testing.assert_array_equal(dep, seq.depth[t])
    rows = (tmp_path / "seq" / "groundtruth_rect.txt").read_text().strip().splitlines()
    gt = np.array([[float(v) for v in r.split(",")] for r in rows])
    np.testing.assert_array_equal(gt[:3], s.boxes + np.array([1, 1, 0, 0]))
    np.testing.assert_array_equal(gt[3], [0, 0, 0, 0])
