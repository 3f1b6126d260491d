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

# Body parts (primitives) and the clothing slot that colours them.
# (The right side's parts come first: their indices seed the textures, and the side they
# were first given to is the person's right; see the module docstring.)
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


def body_pose(
    root_xz: np.ndarray, heading_xz: np.ndarray, phase: float, speed: float, height: float = 1.75
) -> Pose:
    """Joints of the walking figure at one instant.

    root_xz: ``[2]`` ground point under the pelvis (x, z) in metres; heading_xz: ``[2]``
    walking direction; phase: gait phase (rad), the right thigh is ``A sin(phase)`` forward.
    """
    g = gait_parameters(speed)
    k = height / 1.75
    u = np.array([0.0, 1.0, 0.0])
    f = np.array([heading_xz[0], 0.0, heading_xz[1]])
    f = f / np.linalg.norm(f)
    l = np.cross(u, f)

    sin_p, cos_p = np.sin(phase), np.cos(phase)
    alpha = g["hip"] * np.array([sin_p, -sin_p])  # thigh angle from vertical, forward > 0
    # Swing (thigh moving forward) is cos(phase) > 0; knee flexion peaks early in swing.
    swing = np.maximum(0.0, np.cos(np.array([phase, phase + np.pi]) + np.pi / 6)) ** 1.5
    knee = g["knee_stance"] + g["knee_swing"] * swing
    beta = alpha - knee  # shank angle from vertical
    rho = np.clip(0.6 * beta, -0.45, 0.45)  # foot pitch: toe down at push-off, up at strike

    th, sh, ah = THIGH * k, SHIN * k, ANKLE_H * k
    fr = np.array(FOOT_RADII) * k
    # Heights relative to the hip joints; the lower foot decides the pelvis height.
    knee_dy = -th * np.cos(alpha)
    ankle_dy = knee_dy - sh * np.cos(beta)
    foot_c_dy = ankle_dy + FOOT_FWD * k * np.sin(rho) - FOOT_DOWN * k * np.cos(rho)
    foot_bottom = foot_c_dy - np.sqrt((fr[2] * np.sin(rho)) ** 2 + (fr[1] * np.cos(rho)) ** 2)
    hip_y = -foot_bottom.min()
    del ah

    sway = -g["sway"] * cos_p
    pelvis = np.array([root_xz[0], hip_y, root_xz[1]]) + l * sway
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

    ua_dirs, fa_dirs, ffwd, fup = [], [], [], []
    for side, sgn in ((0, 1.0), (1, -1.0)):
        name = "right" if side == 0 else "left"  # +l is the anatomical right (docstring)
        hip = pelvis + sgn * l * HIP_HALF * k
        kn = hip + th * (np.sin(alpha[side]) * f - np.cos(alpha[side]) * u)
        an = kn + sh * (np.sin(beta[side]) * f - np.cos(beta[side]) * u)
        fd = np.cos(rho[side]) * f + np.sin(rho[side]) * u
        fu = -np.sin(rho[side]) * f + np.cos(rho[side]) * u
        joints[J[f"{name}_hip"]] = hip
        joints[J[f"{name}_knee"]] = kn
        joints[J[f"{name}_ankle"]] = an
        joints[J[f"{name}_foot"]] = an + fd * FOOT_FWD * k - fu * FOOT_DOWN * k
        ffwd.append(fd)
        fup.append(fu)

        # Arms swing in antiphase with the leg of the same side.
        gamma = -sgn * g["arm"] * sin_p
        eps = g["elbow"] + np.radians(15) * max(0.0, np.sin(gamma) / max(np.sin(g["arm"]), 1e-6))
        abd = np.radians(7)
        sho = pelvis + tu * SHOULDER_UP * k + sgn * l * SHOULDER_HALF * k
        ua = np.cos(abd) * (np.sin(gamma) * f - np.cos(gamma) * tu) + sgn * np.sin(abd) * l
        fa = (
            np.cos(abd) * (np.sin(gamma + eps) * f - np.cos(gamma + eps) * tu)
            + sgn * np.sin(abd) * l
        )
        ua, fa = _unit(ua), _unit(fa)
        el = sho + ua * UPPER_ARM * k
        wr = el + fa * FOREARM * k
        joints[J[f"{name}_shoulder"]] = sho
        joints[J[f"{name}_elbow"]] = el
        joints[J[f"{name}_hand"]] = wr + fa * HAND_OFF * k
        ua_dirs.append(ua)
        fa_dirs.append(fa)
    return Pose(
        joints, f, l, tu, np.array(ua_dirs), np.array(fa_dirs), np.array(ffwd), np.array(fup)
    )


def body_parts(pose: Pose, height: float = 1.75) -> list[tuple]:
    """Body primitives in **world** coordinates, one per entry of :data:`PART_NAMES`.

    Each entry is ``("capsule", a, b, radius, ref_dir)`` or ``("ellipsoid", centre, axes
    [3, 3] (columns), radii [3])``.
    """
    k = height / 1.75
    jt = pose.joints
    f, l, tu = pose.f, pose.l, pose.trunk_up
    body_axes = np.stack([l, tu, f], axis=1)  # lateral, up, forward
    pelvis = jt[J["pelvis"]]
    head = jt[J["head"]]
    hr = np.array(HEAD_RADII) * k
    parts: list[tuple] = [None] * len(PART_NAMES)
    parts[P["face"]] = ("ellipsoid", head, body_axes, hr)
    parts[P["hair"]] = (
        "ellipsoid",
        head + tu * 0.02 * k - f * 0.022 * k,
        body_axes,
        hr + np.array([0.008, 0.006, 0.004]) * k,
    )
    parts[P["neck"]] = ("capsule", jt[J["neck"]] - tu * 0.03 * k, head - tu * 0.06 * k, 0.05 * k, f)
    parts[P["chest"]] = (
        "ellipsoid",
        pelvis + tu * 0.33 * k,
        body_axes,
        np.array([0.165, 0.21, 0.105]) * k,
    )
    parts[P["shoulders"]] = (
        "capsule",
        jt[J["right_shoulder"]],  # from the +l side (textures run along the capsule)
        jt[J["left_shoulder"]],
        0.06 * k,
        f,
    )
    parts[P["abdomen"]] = (
        "ellipsoid",
        pelvis + tu * 0.15 * k,
        body_axes,
        np.array([0.15, 0.14, 0.10]) * k,
    )
    parts[P["hips"]] = (
        "ellipsoid",
        pelvis + tu * 0.02 * k,
        body_axes,
        np.array([0.16, 0.12, 0.105]) * k,
    )
    for side, name in ((0, "right"), (1, "left")):  # side 0 is on +l (Pose)
        sho, el, hand = jt[J[f"{name}_shoulder"]], jt[J[f"{name}_elbow"]], jt[J[f"{name}_hand"]]
        wr = hand - pose.fa_dir[side] * HAND_OFF * k
        parts[P[f"{name}_upper_arm"]] = ("capsule", sho, el, 0.045 * k, f)
        parts[P[f"{name}_forearm"]] = ("capsule", el, wr, 0.037 * k, f)
        long_ax = pose.fa_dir[side]
        thick = l - (l @ long_ax) * long_ax
        thick /= np.linalg.norm(thick)
        width = np.cross(long_ax, thick)
        parts[P[f"{name}_hand"]] = (
            "ellipsoid",
            hand,
            np.stack([thick, long_ax, width], axis=1),
            np.array([0.022, 0.085, 0.045]) * k,
        )
        hip, kn, an = jt[J[f"{name}_hip"]], jt[J[f"{name}_knee"]], jt[J[f"{name}_ankle"]]
        parts[P[f"{name}_thigh"]] = ("capsule", hip, kn, 0.07 * k, f)
        parts[P[f"{name}_shin"]] = ("capsule", kn, an, 0.05 * k, f)
        foot_axes = np.stack([l, pose.foot_up[side], pose.foot_fwd[side]], axis=1)
        parts[P[f"{name}_foot"]] = (
            "ellipsoid",
            jt[J[f"{name}_foot"]],
            foot_axes,
            np.array(FOOT_RADII) * k,
        )
    return parts


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
