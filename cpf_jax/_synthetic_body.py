"""Walking articulated figure and walking paths for the synthetic generator (private).

World frame (metres): ``x`` right, ``y`` up, ``z`` forward away from the camera, floor at
``y = 0``; a left-handed frame. The person's body frame: ``f`` forward (horizontal heading),
``u`` up, ``l = u x f`` lateral, which in this left-handed frame points to the person's
anatomical *right* (facing the camera, ``f = -z`` gives ``l = -x``, the image's left, where
the camera sees the person's right hand). The limbs on the ``+l`` side are the ``right_*``
ones. Gait is a sinusoidal approximation of normal walking
kinematics: hip flexion ``A sin(phase)``, knee flexion peaking in early swing, arms in
antiphase with the legs, forward trunk lean growing with speed; pelvis height is set so that
the lower foot touches the floor, which produces the vertical bob (about 2-5 cm) and lateral
sway. The gait phase advances with distance walked, so feet barely slide. Segment lengths
follow anthropometric ratios of stature (Winter, *Biomechanics and Motor Control of Human
Movement*, segment lengths as fractions of height), scaled by ``height / 1.75 m``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

JOINT_NAMES: tuple[str, ...] = (
    "head_top",
    "head",
    "neck",
    "torso",
    "pelvis",
    "left_shoulder",
    "left_elbow",
    "left_hand",
    "right_shoulder",
    "right_elbow",
    "right_hand",
    "left_hip",
    "left_knee",
    "left_ankle",
    "left_foot",
    "right_hip",
    "right_knee",
    "right_ankle",
    "right_foot",
)
J = {name: i for i, name in enumerate(JOINT_NAMES)}

# Body parts (primitives), each coloured by a clothing slot. A part's position is its
# primitive and material index, and the order breaks z-buffer ties, so it is part of the
# output; the right side (+l, module docstring) comes first.
PART_NAMES: tuple[str, ...] = (
    "face",
    "hair",
    "neck",
    "chest",
    "shoulders",
    "abdomen",
    "hips",
    "right_upper_arm",
    "right_forearm",
    "right_hand",
    "left_upper_arm",
    "left_forearm",
    "left_hand",
    "right_thigh",
    "right_shin",
    "right_foot",
    "left_thigh",
    "left_shin",
    "left_foot",
)
P = {name: i for i, name in enumerate(PART_NAMES)}

# Which parts count as "this joint is visible" when they are the nearest surface at the
# joint's pixel.
JOINT_PARTS: dict[str, tuple[str, ...]] = {
    "head_top": ("hair", "face"),
    "head": ("face", "hair"),
    "neck": ("neck",),
    "torso": ("chest", "abdomen"),
    "pelvis": ("hips", "abdomen"),
    "left_shoulder": ("shoulders", "chest", "left_upper_arm"),
    "left_elbow": ("left_upper_arm", "left_forearm"),
    "left_hand": ("left_hand",),
    "right_shoulder": ("shoulders", "chest", "right_upper_arm"),
    "right_elbow": ("right_upper_arm", "right_forearm"),
    "right_hand": ("right_hand",),
    "left_hip": ("hips", "left_thigh"),
    "left_knee": ("left_thigh", "left_shin"),
    "left_ankle": ("left_shin", "left_foot"),
    "left_foot": ("left_foot",),
    "right_hip": ("hips", "right_thigh"),
    "right_knee": ("right_thigh", "right_shin"),
    "right_ankle": ("right_shin", "right_foot"),
    "right_foot": ("right_foot",),
}

# Segment dimensions for a 1.75 m adult, metres.
THIGH, SHIN, ANKLE_H = 0.43, 0.42, 0.08
HIP_HALF = 0.09
UPPER_ARM, FOREARM, HAND_OFF = 0.29, 0.255, 0.085
SHOULDER_UP, SHOULDER_HALF, NECK_UP = 0.505, 0.185, 0.545
HEAD_RADII = (0.075, 0.115, 0.095)  # lateral, vertical, front-back
FOOT_RADII = (0.045, 0.04, 0.125)
FOOT_FWD, FOOT_DOWN = 0.055, 0.04


class Pose(NamedTuple):
    joints: np.ndarray  # [J, 3] world metres
    f: np.ndarray  # [3] forward
    l: np.ndarray  # [3] lateral: the person's right (module docstring)
    trunk_up: np.ndarray  # [3]
    ua_dir: np.ndarray  # [2, 3] upper-arm directions (right, left): side 0 is on +l
    fa_dir: np.ndarray  # [2, 3] forearm directions
    foot_fwd: np.ndarray  # [2, 3]
    foot_up: np.ndarray  # [2, 3]


def gait_parameters(speed: float) -> dict:
    """Speed-dependent gait amplitudes (radians, metres)."""
    v = float(np.clip(speed, 0.0, 2.0))
    # Step length ~0.5 m at 0.8 m/s (normal adult gait); box aspect ratios then stay
    # within ~0.25-0.5 as in real pedestrian ground truth (OTB Crossing: 0.26-0.44).
    step = float(np.clip(0.30 + 0.25 * v, 0.3, 0.7))
    return dict(
        step=step,
        hip=np.arcsin(min(step / (2 * (THIGH + SHIN)), 0.6)),
        knee_swing=np.radians(20 + 20 * min(v, 1.5)),
        knee_stance=np.radians(5.0),
        arm=np.radians(4 + 10 * v),
        elbow=np.radians(10 + 8 * v),
        lean=np.radians(1.5 + 3.0 * v),
        sway=0.012,
    )


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _leg_angles(g: dict, phase: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``[2]`` thigh, shank and foot-pitch angles (rad; right side first) at ``phase``.

    Thighs swing ``A sin(phase)`` forward of vertical in antiphase; a leg swings while
    ``cos(phase) > 0``, and its knee flexion peaks early in the swing.
    """
    sin_p = np.sin(phase)
    alpha = g["hip"] * np.array([sin_p, -sin_p])  # thigh angle from vertical, forward > 0
    swing = np.maximum(0.0, np.cos(np.array([phase, phase + np.pi]) + np.pi / 6)) ** 1.5
    knee = g["knee_stance"] + g["knee_swing"] * swing
    beta = alpha - knee  # shank angle from vertical
    rho = np.clip(0.6 * beta, -0.45, 0.45)  # foot pitch: toe down at push-off, up at strike
    return alpha, beta, rho


def _hip_height(alpha: np.ndarray, beta: np.ndarray, rho: np.ndarray, k: float) -> float:
    """Height of the hip joints above the floor that puts the lower shoe on the floor."""
    th, sh = THIGH * k, SHIN * k
    fr = np.array(FOOT_RADII) * k
    knee_dy = -th * np.cos(alpha)
    ankle_dy = knee_dy - sh * np.cos(beta)
    foot_c_dy = ankle_dy + FOOT_FWD * k * np.sin(rho) - FOOT_DOWN * k * np.cos(rho)
    foot_bottom = foot_c_dy - np.sqrt((fr[2] * np.sin(rho)) ** 2 + (fr[1] * np.cos(rho)) ** 2)
    return -foot_bottom.min()


def _leg(joints, name: str, hip, f, u, alpha: float, beta: float, rho: float, k: float):
    """Write the leg joints of side ``name`` from its hip joint; returns the foot's
    forward and up directions."""
    kn = hip + THIGH * k * (np.sin(alpha) * f - np.cos(alpha) * u)
    an = kn + SHIN * k * (np.sin(beta) * f - np.cos(beta) * u)
    fd = np.cos(rho) * f + np.sin(rho) * u
    fu = -np.sin(rho) * f + np.cos(rho) * u
    joints[J[f"{name}_hip"]] = hip
    joints[J[f"{name}_knee"]] = kn
    joints[J[f"{name}_ankle"]] = an
    joints[J[f"{name}_foot"]] = an + fd * FOOT_FWD * k - fu * FOOT_DOWN * k
    return fd, fu


def _arm(joints, name: str, sgn: float, pelvis, tu, l, f, g: dict, sin_p: float, k: float):
    """Write the arm joints of side ``name`` (``sgn`` +1 on ``+l``); the arm swings in
    antiphase with the leg of its side, slightly abducted, the elbow bending more as the
    arm swings forward. Returns the upper-arm and forearm directions."""
    gamma = -sgn * g["arm"] * sin_p
    eps = g["elbow"] + np.radians(15) * max(0.0, np.sin(gamma) / max(np.sin(g["arm"]), 1e-6))
    abd = np.radians(7)
    sho = pelvis + tu * SHOULDER_UP * k + sgn * l * SHOULDER_HALF * k
    ua = np.cos(abd) * (np.sin(gamma) * f - np.cos(gamma) * tu) + sgn * np.sin(abd) * l
    fa = np.cos(abd) * (np.sin(gamma + eps) * f - np.cos(gamma + eps) * tu) + sgn * np.sin(abd) * l
    ua, fa = _unit(ua), _unit(fa)
    el = sho + ua * UPPER_ARM * k
    wr = el + fa * FOREARM * k
    joints[J[f"{name}_shoulder"]] = sho
    joints[J[f"{name}_elbow"]] = el
    joints[J[f"{name}_hand"]] = wr + fa * HAND_OFF * k
    return ua, fa


def body_pose(
    root_xz: np.ndarray, heading_xz: np.ndarray, phase: float, speed: float, height: float = 1.75
) -> Pose:
    """Joints of the walking figure at one instant.

    root_xz: ``[2]`` ground point under the pelvis (x, z) in metres; heading_xz: ``[2]``
    walking direction; phase: gait phase (rad), the right thigh is ``A sin(phase)`` forward.
    The pelvis sways sideways with ``cos(phase)`` and the trunk leans forward with speed.
    """
    g = gait_parameters(speed)
    k = height / 1.75
    u = np.array([0.0, 1.0, 0.0])
    f = np.array([heading_xz[0], 0.0, heading_xz[1]])
    f = f / np.linalg.norm(f)
    l = np.cross(u, f)
    sin_p, cos_p = np.sin(phase), np.cos(phase)
    alpha, beta, rho = _leg_angles(g, phase)
    hip_y = _hip_height(alpha, beta, rho, k)
    pelvis = np.array([root_xz[0], hip_y, root_xz[1]]) + l * (-g["sway"] * cos_p)
    lean = g["lean"]
    tu = np.cos(lean) * u + np.sin(lean) * f

    joints = np.zeros((len(JOINT_NAMES), 3))
    joints[J["pelvis"]] = pelvis
    joints[J["torso"]] = pelvis + tu * 0.27 * k
    neck = pelvis + tu * NECK_UP * k
    head = neck + tu * 0.135 * k + f * 0.01 * k
    joints[J["neck"]] = neck
    joints[J["head"]] = head
    joints[J["head_top"]] = head + tu * (HEAD_RADII[1] + 0.02) * k

    limbs = []
    for side, sgn in ((0, 1.0), (1, -1.0)):
        name = "right" if side == 0 else "left"  # +l is the anatomical right (docstring)
        hip = pelvis + sgn * l * HIP_HALF * k
        foot = _leg(joints, name, hip, f, u, alpha[side], beta[side], rho[side], k)
        limbs.append((*_arm(joints, name, sgn, pelvis, tu, l, f, g, sin_p, k), *foot))
    ua, fa, ffwd, fup = (np.array(x) for x in zip(*limbs, strict=True))
    return Pose(joints, f, l, tu, ua, fa, ffwd, fup)


def _trunk_parts(pose: Pose, k: float) -> dict[str, tuple]:
    """Head, hair, neck, chest, shoulders, abdomen and hips."""
    jt, f, tu = pose.joints, pose.f, pose.trunk_up
    body_axes = np.stack([pose.l, tu, f], axis=1)  # lateral, up, forward
    pelvis, head = jt[J["pelvis"]], jt[J["head"]]
    hr = np.array(HEAD_RADII) * k
    return {
        "face": ("ellipsoid", head, body_axes, hr),
        "hair": (
            "ellipsoid",
            head + tu * 0.02 * k - f * 0.022 * k,
            body_axes,
            hr + np.array([0.008, 0.006, 0.004]) * k,
        ),
        "neck": ("capsule", jt[J["neck"]] - tu * 0.03 * k, head - tu * 0.06 * k, 0.05 * k, f),
        "chest": (
            "ellipsoid",
            pelvis + tu * 0.33 * k,
            body_axes,
            np.array([0.165, 0.21, 0.105]) * k,
        ),
        # From the +l side: textures run along the capsule.
        "shoulders": ("capsule", jt[J["right_shoulder"]], jt[J["left_shoulder"]], 0.06 * k, f),
        "abdomen": (
            "ellipsoid",
            pelvis + tu * 0.15 * k,
            body_axes,
            np.array([0.15, 0.14, 0.10]) * k,
        ),
        "hips": ("ellipsoid", pelvis + tu * 0.02 * k, body_axes, np.array([0.16, 0.12, 0.105]) * k),
    }


def _limb_parts(pose: Pose, side: int, name: str, k: float) -> dict[str, tuple]:
    """Upper arm, forearm, hand, thigh, shin and foot of one side (side 0 is on ``+l``)."""
    jt, f, l = pose.joints, pose.f, pose.l
    sho, el, hand = jt[J[f"{name}_shoulder"]], jt[J[f"{name}_elbow"]], jt[J[f"{name}_hand"]]
    wr = hand - pose.fa_dir[side] * HAND_OFF * k
    long_ax = pose.fa_dir[side]
    thick = l - (l @ long_ax) * long_ax
    thick /= np.linalg.norm(thick)
    width = np.cross(long_ax, thick)
    hip, kn, an = jt[J[f"{name}_hip"]], jt[J[f"{name}_knee"]], jt[J[f"{name}_ankle"]]
    foot_axes = np.stack([l, pose.foot_up[side], pose.foot_fwd[side]], axis=1)
    return {
        f"{name}_upper_arm": ("capsule", sho, el, 0.045 * k, f),
        f"{name}_forearm": ("capsule", el, wr, 0.037 * k, f),
        f"{name}_hand": (
            "ellipsoid",
            hand,
            np.stack([thick, long_ax, width], axis=1),
            np.array([0.022, 0.085, 0.045]) * k,
        ),
        f"{name}_thigh": ("capsule", hip, kn, 0.07 * k, f),
        f"{name}_shin": ("capsule", kn, an, 0.05 * k, f),
        f"{name}_foot": ("ellipsoid", jt[J[f"{name}_foot"]], foot_axes, np.array(FOOT_RADII) * k),
    }


def body_parts(pose: Pose, height: float = 1.75) -> list[tuple]:
    """Body primitives in **world** coordinates, one per entry of :data:`PART_NAMES`.

    Each entry is ``("capsule", a, b, radius, ref_dir)`` or ``("ellipsoid", centre, axes
    [3, 3] (columns), radii [3])``.
    """
    k = height / 1.75
    parts = _trunk_parts(pose, k)
    for side, name in ((0, "right"), (1, "left")):
        parts.update(_limb_parts(pose, side, name, k))
    return [parts[n] for n in PART_NAMES]


# ---------------------------------------------------------------------------------------------
# Paths: polylines on the floor with circular-arc corners, walked at constant speed.


class Path(NamedTuple):
    xz: np.ndarray  # [M, 2] dense points
    s: np.ndarray  # [M] arc length (m)

    @property
    def length(self) -> float:
        return float(self.s[-1])


def fillet_path(waypoints, radius: float, step: float = 0.005, extend: float = 50.0) -> Path:
    """Dense path through ``waypoints [K, 2]`` (x, z) with corners rounded by arcs.

    The last segment is extended by ``extend`` metres so that a sequence longer than the
    planned walk continues straight on (the walker may then leave the view).
    """
    w = np.asarray(waypoints, float)
    pieces = [w[:1]]
    cur = w[0]
    for i in range(1, len(w) - 1):
        d1 = _unit(w[i] - w[i - 1])
        d2 = _unit(w[i + 1] - w[i])
        cosang = np.clip(d1 @ d2, -1.0, 1.0)
        turn = np.arccos(cosang)
        if turn < 1e-6 or radius <= 0:
            pieces.append(_line(cur, w[i], step))
            cur = w[i]
            continue
        tlen = radius * np.tan(turn / 2)
        a = w[i] - d1 * tlen
        b = w[i] + d2 * tlen
        pieces.append(_line(cur, a, step))
        cross = d1[0] * d2[1] - d1[1] * d2[0]
        nrm = np.array([-d1[1], d1[0]]) * np.sign(cross)
        centre = a + nrm * radius
        a0 = np.arctan2(*(a - centre)[::-1])
        a1 = np.arctan2(*(b - centre)[::-1])
        da = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        n = max(int(np.ceil(abs(da) * radius / step)), 2)
        ang = a0 + da * np.linspace(0, 1, n)
        pieces.append(centre + radius * np.stack([np.cos(ang), np.sin(ang)], -1))
        cur = b
    end = w[-1] + _unit(w[-1] - w[-2]) * extend
    pieces.append(_line(cur, w[-1], step))
    pieces.append(_line(w[-1], end, 0.05))
    xz = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xz, axis=0), axis=1) > 1e-9])
    xz = xz[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
    return Path(xz, s)


def _line(a, b, step):
    n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
    return a + (b - a) * np.linspace(0, 1, n + 1)[1:, None]


def planned_length(waypoints, radius: float) -> float:
    """Arc length of the rounded path up to the last waypoint (without the extension)."""
    p = fillet_path(waypoints, radius, extend=0.0)
    return p.length


def sample_path(path: Path, s: np.ndarray):
    """Positions ``[T, 2]`` and unit headings ``[T, 2]`` at arc lengths ``s [T]``."""
    x = np.interp(s, path.s, path.xz[:, 0])
    z = np.interp(s, path.s, path.xz[:, 1])
    ds = 0.02
    x2 = np.interp(s + ds, path.s, path.xz[:, 0]) - np.interp(s - ds, path.s, path.xz[:, 0])
    z2 = np.interp(s + ds, path.s, path.xz[:, 1]) - np.interp(s - ds, path.s, path.xz[:, 1])
    head = np.stack([x2, z2], -1)
    return np.stack([x, z], -1), _unit(head)
