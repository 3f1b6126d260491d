"""Synthetic Kinect-v2-like RGB-D sequences of a walking person, with ground truth.

``make_sequence(name, seed=0, n_frames=None, **overrides)`` renders one of
:data:`SCENARIOS` (or a variation of it: any :class:`ScenarioSpec` field can be overridden)
and returns a :class:`SyntheticSequence`. Pure NumPy (+ OpenCV for a blur and PNG I/O),
deterministic per seed.

Camera and images
-----------------
* Colour is rendered from the depth camera's viewpoint, i.e. already registered to the
  512 x 424 depth image: ``colour [T, 424, 512, 3] uint8`` RGB and ``depth [T, 424, 512]
  uint16`` millimetres, 0 = missing. Intrinsics are :data:`cpf_jax.types.KINECT_V2_DEPTH`.
* Camera coordinates are millimetres, X right, Y down, Z forward, and integer pixel
  coordinates are pixel centres: ``u = fx X / Z + cx``, ``v = fy Y / Z + cy``; the depth at
  pixel ``(row r, col c)`` back-projects to ``X = Z (c - cx) / fx, Y = Z (r - cy) / fy``
  (thesis T 4.2). The camera stands ``camera_height_m`` above the floor, pitched down by
  ``camera_pitch_deg``.

Ground truth
------------
* ``boxes [T, 4] float32`` (x, y, w, h), top-left, in the convention of
  ``cpf_jax.kernels.boxes`` (pixel ``c`` covers ``[c, c + 1)``): the **tight box of the
  visible person pixels** (``mask``), i.e. ``(c_min, r_min, c_max - c_min + 1, r_max -
  r_min + 1)``; ``xywh_to_rect`` of it gives exactly the mask's extent. ``(0, 0, 0, 0)``
  when the person is not visible. Note the half-pixel offset to ``joints2d``: a joint at
  ``(u, v)`` lies in pixel ``(round(v), round(u))``, whose box-convention centre is
  ``(round(u) + 0.5, round(v) + 0.5)``.
* ``visible [T] bool``: at least one person pixel.
* ``mask [T, H, W] bool``: pixels whose nearest surface is the person (occluders excluded).
* ``joints3d [T, J, 3] float32`` mm camera coordinates and ``joints2d [T, J, 2] float32``
  ``(u, v)`` projections, names in ``joint_names``. Joints are anatomical centres (inside
  the body): ``head`` is the centre of the head, ``head_top`` the top of the hair,
  ``torso`` the trunk centroid (the thesis's body-centroid reference point),
  ``left_hand`` / ``right_hand`` the hand centres, ``left_foot`` / ``right_foot`` the shoe
  centres; ``left`` is the person's anatomical left (facing the camera, the left hand is
  on the image's right).
* ``meta``: the spec, the camera pose, ``up`` (world up in camera coordinates),
  ``joint_visible [T, J]`` (the joint's own body part is the nearest surface at its
  pixel), ``visible_fraction`` and ``occlusion`` (0 none, 1 partial, 2 full) per frame,
  per-frame ``gain`` of the illumination, the walked path, ``background_colour`` and
  ``background_depth``: the empty room without noise (a clean background model).

Depth model
-----------
* Axial noise: Gaussian with the Kinect v2 model of Fankhauser et al., "Kinect v2 for
  mobile robot navigation: evaluation and modeling", ICAR 2015:
  ``sigma_z(z, theta) = 1.5 - 0.5 z + 0.3 z^2 + 0.1 z^1.5 theta^2 / (pi/2 - theta)^2`` mm
  with ``z`` in metres and ``theta`` the angle between the ray and the surface normal
  (coefficients as recalled from that paper, ~2.7 mm at 3 m, ~5 mm at 4.4 m facing the
  camera); the structured-light Kinect v1 model of Nguyen et al. (3DIMPVT 2012) has the
  same ``a + b (z - c)^2`` shape. ``depth_noise_scale`` multiplies it.
* Missing pixels (0): beyond ``max_range_mm`` (4.5 m, the Kinect v2 SDK's reliable range)
  or nearer than 0.5 m; at grazing incidence (> 83 deg); on the far (p=0.7) and near (p=0.3)
  side of depth discontinuities between different surfaces, where a time-of-flight camera
  produces flying pixels that the driver's edge filter removes (libfreenect2 does this);
  and on surfaces with a weak infrared return, with probability ``sigmoid((A0 - A)/s)`` of
  the return amplitude ``A = ir_reflectivity * cos(theta) / z^2`` (black hair and dark
  shoes drop out partially at 3 m, skin and bright fabric never).
* Colour: Lambert shading plus ambient from a fixed light, procedural textures (wood floor,
  plaster walls, bookshelves, fabric), a light blur, Gaussian sensor noise
  ``colour_noise`` (uint8 units) and optional global illumination change.

Extending
---------
Every frame is a list of primitives (``cpf_jax._synthetic_render.Prim``) with an object id
(0 background, 1 person, 2.. occluders) ray cast into one z-buffer with a primitive-id
buffer, so adding objects means appending primitives: ``occluders`` (boxes moving on the
floor) already use this, and ``shirt_change`` switches the shirt colour at a frame.
"""

from __future__ import annotations

import colorsys
import dataclasses
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import cv2
import numpy as np

from cpf_jax import _synthetic_body as body
from cpf_jax import _synthetic_render as rnd
from cpf_jax.types import KINECT_V2_DEPTH, Frame, Intrinsics

__all__ = [
    "Clothing",
    "Occluder",
    "ScenarioSpec",
    "SCENARIOS",
    "SyntheticSequence",
    "make_sequence",
    "iter_frames",
    "stacked_frames",
    "to_folder",
    "contact_sheet",
    "kinect_v2_axial_sigma_mm",
]

RGB = tuple[int, int, int]
HEIGHT, WIDTH = 424, 512


@dataclass(frozen=True)
class Clothing:
    """Colours (sRGB 0-255) of the walking person."""

    shirt: RGB = (170, 35, 45)
    trousers: RGB = (45, 60, 95)
    skin: RGB = (205, 150, 120)
    hair: RGB = (40, 30, 25)
    shoes: RGB = (35, 33, 35)
    long_sleeves: bool = True


@dataclass(frozen=True)
class Occluder:
    """A box standing on the floor, or a second person, moving in a straight line (world
    metres, seconds).

    ``start_xz`` / ``end_xz`` are floor positions of its centre (x right, z away from the
    camera); it moves between them during ``[t0_s, t1_s]`` and rests outside that interval.

    ``kind="box"``: a box of ``size_m`` and ``colour``. ``kind="person"``: another walking
    figure of height ``size_m[1]`` dressed in ``clothing`` (default: grey top, dark
    trousers), facing and walking from ``start_xz`` to ``end_xz`` with the gait of its
    speed (standing still outside ``[t0_s, t1_s]``). Occluders are objects ``2, 3, ...``
    in the z-buffer: they hide the target (``mask``, ``visible_fraction``, ``occlusion``)
    but are never part of its ground truth.
    """

    size_m: tuple[float, float, float] = (0.6, 1.9, 0.4)  # width (x), height, depth (z)
    start_xz: tuple[float, float] = (-2.5, 2.0)
    end_xz: tuple[float, float] = (2.5, 2.0)
    t0_s: float = 0.0
    t1_s: float = 5.0
    colour: RGB = (90, 90, 95)
    kind: str = "box"
    clothing: Clothing | None = None
    # True: the x coordinates are given for a walker who starts walking towards +x and are
    # mirrored when this seed's walker starts towards -x, so that the occluder meets the
    # walker in the same way for every seed.
    mirror_x: bool = False
    # Who this is in multi-person ground truth (``meta["occluder_boxes"]``): occluders
    # that share an identity are one person seen on several walks (one who leaves and comes
    # back); None: its own, ``2 + k`` for occluder ``k`` (the walker is 1).
    identity: int | None = None


@dataclass(frozen=True)
class ScenarioSpec:
    """Everything that defines a scenario; every field can be overridden in
    :func:`make_sequence`. Lengths in metres, speeds in m/s, angles in degrees.

    ``path``: ``"pace"`` walks across the view in a stadium-shaped loop (two lanes
    ``lane_gap_m`` apart around ``distance_m``, U-turns at the sides, as many crossings
    as the sequence needs); ``"towards"`` / ``"away"`` walk between ``far_m`` and
    ``near_m``; ``"turn"`` walks across at ``far_m - 0.4`` then turns 90 degrees towards
    the camera (L-shaped); ``"away_back"`` walks away from ``near_m`` to ``far_m``, makes a
    U-turn (radius 0.3 m) and walks back towards the camera. Single-pass paths clip the
    default ``n_frames`` so the person stays in view; an explicit longer ``n_frames`` lets
    them walk on (and out of view).

    Difficulty knobs: ``fps`` (frame spacing; motion per frame is ``speed / fps``),
    ``clutter`` (number of furniture objects), ``clutter_match`` (fraction of them coloured
    like the clothing), ``distractor_similarity`` (0 = unrelated hue .. 1 = identical
    colour, used for matched clutter and the distractor panel), ``distractor`` (a large
    shirt-coloured panel just behind the walking lane), ``colour_noise``, ``illumination``
    (``"none"``, ``"drift"`` slow gain and colour-temperature drift, ``"switch"`` a light
    goes off half-way) with ``illumination_strength``, ``distance_m``, ``backdrop``
    (``"low"``: behind the walking path only furniture up to ``backdrop_height_m`` and no
    posters or wall shelves, so the upper body passes in front of the wall; ``"full"``:
    clutter anywhere, as in ``distractor_pass``), ``poles`` (thin clutter: posts 5-12 cm
    thick, about half of them carrying a sign, standing anywhere in view, also between the
    camera and the walk), ``focal_scale`` (the Kinect v2 focal length times this: below 1 a
    wider view in which a far walker is small, above 1 a zoomed one).
    """

    path: str = "pace"
    speed_mps: float = 0.8
    fps: float = 10.0
    n_frames: int = 150
    distance_m: float = 3.0
    lane_gap_m: float = 0.6
    near_m: float = 1.9
    far_m: float = 4.2
    height_m: float = 1.75
    clothing: Clothing = field(default_factory=Clothing)
    clutter: int = 8
    clutter_match: float = 0.25
    distractor_similarity: float = 0.8
    distractor: bool = False
    colour_noise: float = 3.0
    colour_blur: float = 0.6
    colour_holes: bool = False
    illumination: str = "none"
    illumination_strength: float = 0.35
    camera_height_m: float = 1.1
    camera_pitch_deg: float = 7.0
    room_depth_m: float = 4.4
    room_half_width_m: float = 3.2
    depth_noise_scale: float = 1.0
    max_range_mm: float = 4500.0
    backdrop: str = "low"
    backdrop_height_m: float = 0.9
    occluders: tuple[Occluder, ...] = ()
    shirt_change: tuple[int, RGB] | None = None
    poles: int = 0
    focal_scale: float = 1.0


SCENARIOS: dict[str, ScenarioSpec] = {
    "walk_across_slow": ScenarioSpec(speed_mps=0.4),
    "walk_across_medium": ScenarioSpec(speed_mps=0.8),
    "walk_across_fast": ScenarioSpec(speed_mps=1.2),
    "walk_towards": ScenarioSpec(
        path="towards",
        room_depth_m=4.9,
        clothing=Clothing(shirt=(45, 120, 75), trousers=(60, 55, 50)),
    ),
    "walk_away": ScenarioSpec(
        path="away", room_depth_m=4.9, clothing=Clothing(shirt=(45, 120, 75), trousers=(60, 55, 50))
    ),
    "turn": ScenarioSpec(
        path="turn",
        room_depth_m=4.6,
        clothing=Clothing(shirt=(215, 150, 40), trousers=(50, 50, 60)),
    ),
    "distractor_pass": ScenarioSpec(
        distractor=True,
        clutter=10,
        clutter_match=0.4,
        distractor_similarity=0.9,
        backdrop="full",
    ),
    "light_switch": ScenarioSpec(illumination="switch"),
    # Clothes coloured like the background (OTB Crossing's problem: a dark jacket on
    # dark asphalt, light trousers on white road markings): a far walker in a black
    # jacket and beige trousers paces in front of clutter half of which is black or
    # beige (a dark cabinet, light boxes) at similarity 0.9.
    "dark_clothes": ScenarioSpec(
        distance_m=3.6,
        room_depth_m=4.9,
        clutter=10,
        clutter_match=0.5,
        distractor_similarity=0.9,
        backdrop="full",
        clothing=Clothing(shirt=(38, 38, 42), trousers=(165, 155, 135), hair=(30, 25, 22)),
    ),
    # Occlusion scenarios (paper Table 2): something nearer than the walker crosses the
    # whole view slowly (0.64 m/s) while the walker paces behind it, so the two pass each
    # other going the same way (long occlusions, up to ~60 frames) and opposite ways
    # (short ones, ~10 frames), partially and fully. meta["occlusion"] has the state.
    "occlusion_box": ScenarioSpec(
        n_frames=150,
        occluders=(
            Occluder(
                size_m=(0.8, 2.0, 0.4),
                start_xz=(-2.2, 1.7),
                end_xz=(2.3, 1.7),
                t0_s=0.0,
                t1_s=15.0,
                colour=(95, 95, 100),
                mirror_x=True,
            ),
        ),
    ),
    # A second person in a similar outfit (red top, dark-blue trousers) walks across in
    # front of the walker: colour alone cannot tell the two apart, depth can.
    "occlusion_person": ScenarioSpec(
        n_frames=150,
        occluders=(
            Occluder(
                size_m=(0.5, 1.8, 0.3),
                start_xz=(-2.2, 1.6),
                end_xz=(2.3, 1.6),
                t0_s=0.0,
                t1_s=15.0,
                kind="person",
                mirror_x=True,
                clothing=Clothing(shirt=(155, 40, 55), trousers=(40, 48, 80), hair=(60, 45, 35)),
            ),
        ),
    ),
    # The walker walks away, turns round while a second person (another outfit) crosses
    # in front, and comes back towards the camera: a target that reverses its motion in
    # depth while hidden (like the IST recording's second occlusion). The crossing is
    # timed to hide part of the walker around the turn (about frames 13-37, partially).
    "occlusion_return": ScenarioSpec(
        path="away_back",
        near_m=2.1,
        far_m=3.9,
        room_depth_m=4.9,
        clothing=Clothing(shirt=(45, 120, 75), trousers=(60, 55, 50)),
        occluders=(
            Occluder(
                size_m=(0.5, 1.8, 0.3),
                start_xz=(-0.8, 1.6),
                end_xz=(2.0, 1.6),
                t0_s=0.0,
                t1_s=8.0,
                kind="person",
                clothing=Clothing(shirt=(120, 110, 150), trousers=(70, 60, 50), hair=(40, 30, 25)),
            ),
        ),
    ),
    # Abrupt appearance change (paper Table 1's "appearance changed drastically"): at
    # frame 50 the walker's top turns from red to a green jacket.
    "appearance_change": ScenarioSpec(n_frames=110, shirt_change=(50, (40, 125, 70))),
}


class SyntheticSequence(NamedTuple):
    colour: np.ndarray  # [T, H, W, 3] uint8 RGB
    depth: np.ndarray  # [T, H, W] uint16 mm, 0 = missing
    boxes: np.ndarray  # [T, 4] float32 xywh, tight box of the visible person pixels
    visible: np.ndarray  # [T] bool
    joints3d: np.ndarray  # [T, J, 3] float32 mm, camera coordinates
    joints2d: np.ndarray  # [T, J, 2] float32 (u, v) pixels
    joint_names: tuple[str, ...]
    mask: np.ndarray  # [T, H, W] bool person pixels
    intrinsics: Intrinsics
    fps: float
    name: str
    meta: dict[str, Any]


def kinect_v2_axial_sigma_mm(z_m: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Axial depth noise std (mm) of Kinect v2 at depth ``z_m`` (m), incidence ``theta`` (rad)."""
    z = np.asarray(z_m, np.float32)
    th = np.minimum(np.asarray(theta, np.float32), np.float32(1.45))
    return (
        1.5 - 0.5 * z + 0.3 * z * z + 0.1 * z**1.5 * th * th / (np.float32(np.pi / 2) - th) ** 2
    ).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Materials and textures.


@dataclass(frozen=True)
class _Material:
    rgb: tuple[float, float, float]
    ir: float  # near-infrared reflectivity (0..1) for the time-of-flight amplitude
    texture: str = "plain"
    scale: float = 0.01
    strength: float = 0.05
    palette: tuple = ()
    emissive: bool = False


def _lum(rgb) -> float:
    return (0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]) / 255.0


def _ir(rgb, base=0.25, gain=0.6) -> float:
    return base + gain * _lum(rgb)


def _alike(rgb, target, hue_deg: float = 30.0) -> bool:
    """Whether two colours fall in nearby hue-saturation histogram cells (greys match
    greys of similar brightness)."""
    h1, s1, v1 = colorsys.rgb_to_hsv(*(np.asarray(rgb, float) / 255.0))
    h2, s2, v2 = colorsys.rgb_to_hsv(*(np.asarray(target, float) / 255.0))
    if s1 < 0.2 or s2 < 0.2:
        return s1 < 0.2 and s2 < 0.2 and abs(v1 - v2) < 0.25
    dh = abs(h1 - h2) * 360.0
    return min(dh, 360.0 - dh) < hue_deg and abs(s1 - s2) < 0.4


def _similar_colour(rng: np.random.Generator, rgb, similarity: float) -> tuple:
    """A colour whose hue/saturation/value differ from ``rgb`` by ``(1 - similarity)``-scaled
    random amounts (similarity 1: the same colour; 0: up to 90 degrees of hue away)."""
    h, s, v = colorsys.rgb_to_hsv(*(np.asarray(rgb, float) / 255.0))
    d = 1.0 - float(np.clip(similarity, 0.0, 1.0))
    h = (h + rng.choice([-1, 1]) * d * rng.uniform(0.6, 1.0) * 0.25) % 1.0
    s = float(np.clip(s * (1 + d * rng.uniform(-0.5, 0.3)), 0, 1))
    v = float(np.clip(v * (1 + d * rng.uniform(-0.4, 0.4) + rng.uniform(-0.05, 0.05)), 0.05, 1))
    return tuple(255.0 * np.array(colorsys.hsv_to_rgb(h, s, v)))


_FURNITURE_COLOURS = (
    (150, 110, 70),
    (110, 75, 45),
    (200, 165, 120),
    (225, 225, 220),
    (180, 180, 185),
    (95, 98, 102),
    (40, 40, 44),
    (55, 85, 150),
    (70, 125, 80),
    (160, 50, 45),
    (205, 175, 70),
    (120, 140, 160),
    (190, 120, 60),
)
_BOOK_COLOURS = (
    (160, 40, 40),
    (40, 70, 140),
    (40, 110, 60),
    (200, 170, 60),
    (220, 220, 210),
    (30, 30, 35),
    (150, 90, 40),
    (110, 50, 110),
    (60, 140, 150),
    (200, 110, 40),
    (90, 90, 90),
    (180, 60, 90),
)


class _Tex(NamedTuple):
    smooth: np.ndarray  # [256, 256] float32 tileable 1/f^2.2 noise
    rough: np.ndarray  # [256, 256] float32 tileable 1/f^0.8 noise
    hash: np.ndarray  # [4096] uniform(0, 1)


def _make_tex(rng: np.random.Generator) -> _Tex:
    return _Tex(
        rnd.periodic_noise(rng, 256, 2.2),
        rnd.periodic_noise(rng, 256, 0.8),
        rng.uniform(size=4096).astype(np.float32),
    )


def _aniso(tile, u, v, su, sv):
    """Nearest look-up of a periodic tile with ``su`` x ``sv`` metres per texel."""
    size = tile.shape[0]
    return tile[np.floor(v / sv).astype(np.int64) % size, np.floor(u / su).astype(np.int64) % size]


def _base(mat: _Material) -> np.ndarray:
    return np.asarray(mat.rgb, np.float32)[None, :]


def _fabric_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Fine weave plus a slow mottle."""
    st = mat.strength
    f = (
        1
        + st * _aniso(tex.rough, u, v, 0.0035, 0.0035)
        + 0.7 * st * _aniso(tex.smooth, u, v, 0.04, 0.04)
    )
    return _base(mat) * f[:, None]


def _hair_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Strands: noise stretched along ``v``."""
    f = 1 + mat.strength * _aniso(tex.rough, u, v, 0.0015, 0.02)
    return _base(mat) * f[:, None]


def _planks_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """14 cm floor boards in 1.3 m lengths, each with its own shade and grain, dark joints."""
    st, hsh = mat.strength, tex.hash
    w = 0.14
    idx = np.floor(u / w).astype(np.int64)
    seg = np.floor((v + hsh[idx % 4096] * 2.0) / 1.3).astype(np.int64)
    shade = 0.85 + 0.3 * hsh[(idx * 7 + seg * 131) % 4096]
    grain = (
        1
        + st * _aniso(tex.rough, u, v, 0.0015, 0.05)
        + 0.5 * st * _aniso(tex.smooth, u, v, 0.01, 0.2)
    )
    gap = (np.mod(u, w) < 0.004) | (np.mod(v + hsh[idx % 4096] * 2.0, 1.3) < 0.004)
    f = np.where(gap, 0.55, shade * grain)
    return _base(mat) * f[:, None]


def _tiles_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Square tiles of side ``mat.scale`` with grout lines."""
    st, sc, hsh = mat.strength, mat.scale, tex.hash
    fu, fv = np.mod(u, sc), np.mod(v, sc)
    idx = (np.floor(u / sc).astype(np.int64) * 31 + np.floor(v / sc).astype(np.int64) * 17) % 4096
    f = (0.95 + 0.1 * hsh[idx]) * (1 + st * _aniso(tex.rough, u, v, 0.004, 0.004))
    f = np.where((fu < 0.008) | (fv < 0.008), 0.75, f)
    return _base(mat) * f[:, None]


def _books_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Shelves 38 cm apart holding 3.5 cm book spines of palette colours and random heights."""
    hsh, base = tex.hash, _base(mat)
    pal = np.asarray(mat.palette, np.float32)
    shelf_h = 0.38
    sv = np.mod(v, shelf_h)
    shelf = np.floor(v / shelf_h).astype(np.int64)
    bu = u + hsh[(shelf * 13) % 4096]
    bi = np.floor(bu / 0.035).astype(np.int64) + shelf * 1000
    hb = hsh[bi % 4096]
    col = pal[(hb * len(pal)).astype(np.int64) % len(pal)]
    top = 0.2 + 0.12 * hsh[(bi * 7) % 4096]
    out = np.where(((sv > 0.03) & (sv < 0.03 + top))[:, None], col, base * 0.35)
    out = np.where((sv <= 0.03)[:, None], base, out)
    return out * (1 + 0.5 * mat.strength * _aniso(tex.rough, u, v, 0.004, 0.004))[:, None]


def _stripes_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Horizontal bands ``mat.scale`` high, cycling through the palette."""
    pal = np.asarray(mat.palette, np.float32)
    col = pal[np.floor(v / mat.scale).astype(np.int64) % len(pal)]
    return col * (1 + mat.strength * _aniso(tex.rough, u, v, 0.004, 0.004))[:, None]


def _blotches_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Palette colours by level of the smooth noise: irregular patches."""
    pal = np.asarray(mat.palette, np.float32)
    q = _aniso(tex.smooth, u, v, mat.scale, mat.scale)
    k = np.clip(((q + 2.0) / 4.0 * len(pal)).astype(np.int64), 0, len(pal) - 1)
    return pal[k] * (1 + mat.strength * _aniso(tex.rough, u, v, 0.004, 0.004))[:, None]


def _plain_albedo(mat: _Material, u, v, tex: _Tex) -> np.ndarray:
    """Plain, wall and skin: fine noise at ``mat.scale`` plus a 20x coarser one."""
    st, sc = mat.strength, mat.scale
    f = (
        1
        + st * _aniso(tex.rough, u, v, sc, sc)
        + 0.5 * st * _aniso(tex.smooth, u, v, sc * 20, sc * 20)
    )
    return _base(mat) * f[:, None]


_TEXTURES = {
    "fabric": _fabric_albedo,
    "hair": _hair_albedo,
    "planks": _planks_albedo,
    "tiles": _tiles_albedo,
    "books": _books_albedo,
    "stripes": _stripes_albedo,
    "blotches": _blotches_albedo,
}


def _albedo(mat: _Material, uv: np.ndarray, tex: _Tex) -> np.ndarray:
    """``[n, 3] float32`` albedo (0-255 scale) of ``mat`` at surface coordinates ``uv [2, n]``
    (m); any texture name without a pattern of its own is plain."""
    u = uv[0].astype(np.float64)
    v = uv[1].astype(np.float64)
    return _TEXTURES.get(mat.texture, _plain_albedo)(mat, u, v, tex)


# ---------------------------------------------------------------------------------------------
# Camera.


class _Camera(NamedTuple):
    R: np.ndarray  # [3, 3] world -> camera rotation (rows: right, down, forward)
    C: np.ndarray  # [3] camera centre in world (m)

    def to_cam(self, p):
        return (np.asarray(p) - self.C) @ self.R.T

    def dir_to_cam(self, d):
        return np.asarray(d) @ self.R.T


def _camera(height_m: float, pitch_deg: float) -> _Camera:
    th = np.radians(pitch_deg)
    R = np.array([[1.0, 0.0, 0.0], [0.0, -np.cos(th), -np.sin(th)], [0.0, -np.sin(th), np.cos(th)]])
    return _Camera(R, np.array([0.0, height_m, 0.0]))


# ---------------------------------------------------------------------------------------------
# Paths.


def _intrinsics(spec: ScenarioSpec) -> Intrinsics:
    """The Kinect v2 depth camera's intrinsics with the focal length times ``focal_scale``."""
    k, f = KINECT_V2_DEPTH, float(spec.focal_scale)
    if f == 1.0:
        return k
    return Intrinsics(k.fx * f, k.fy * f, k.cx, k.cy)


def _tan_half_fov(spec: ScenarioSpec) -> float:
    """Tangent of the narrower half of the horizontal field of view."""
    k = _intrinsics(spec)
    return min(k.cx, WIDTH - 1 - k.cx) / k.fx


class _PathPlan(NamedTuple):
    waypoints: np.ndarray  # [K, 2] (x, z) floor points, m
    radius: float  # corner radius, m
    s0: float  # arc length walked before frame 0, m
    walk_length: float  # in-view walk length, m; inf: the pace loop repeats
    extent_length: float  # arc length that covers every place the walk visits, m


def _pace_path(spec: ScenarioSpec, rng, duration_s: float, mirror: float) -> _PathPlan:
    """Stadium loop of two lanes around ``distance_m``, repeated as often as the sequence
    needs; it starts at a random point of the far lane."""
    r = spec.lane_gap_m / 2
    d = spec.distance_m + rng.uniform(-0.1, 0.1)
    zf, zn = d + r, d - r
    span = max(zn * _tan_half_fov(spec) - 0.6, 0.4)
    loop = [(-span, zf), (span, zf), (span, zn), (-span, zn)]
    need = spec.speed_mps * duration_s + 4 * span
    n_loops = int(np.ceil(need / (4 * span + 2 * np.pi * r))) + 1
    wps = [loop[i % 4] for i in range(4 * n_loops + 1)]
    wps = np.array(wps) * np.array([mirror, 1.0])
    s0 = rng.uniform(0.0, 0.5 * span)
    return _PathPlan(wps, r, s0, np.inf, s0 + body.planned_length(wps[:6], r))


def _straight_path(spec: ScenarioSpec, rng, duration_s: float, mirror: float) -> _PathPlan:
    """``towards``: from ``far_m`` to ``near_m`` with a little sideways drift; ``away``: back."""
    x0 = rng.uniform(-0.4, 0.4)
    x1 = x0 + rng.uniform(-0.4, 0.4)
    wps = np.array([(x0, spec.far_m), (x1, spec.near_m)])
    if spec.path == "away":
        wps = wps[::-1]
    length = body.planned_length(wps, 0.0)
    return _PathPlan(wps, 0.0, 0.0, length, length)


def _turn_path(spec: ScenarioSpec, rng, duration_s: float, mirror: float) -> _PathPlan:
    """Across the view at ``far_m - 0.4``, then a 90 degree turn towards the camera."""
    z_across = spec.far_m - 0.4
    xs = -(z_across * _tan_half_fov(spec) - 0.8)
    xc = rng.uniform(0.1, 0.5)
    wps = np.array([(xs, z_across), (xc, z_across), (xc, spec.near_m + 0.2)])
    wps = wps * np.array([mirror, 1.0])
    length = body.planned_length(wps, 0.5)
    return _PathPlan(wps, 0.5, 0.0, length, length)


def _away_back_path(spec: ScenarioSpec, rng, duration_s: float, mirror: float) -> _PathPlan:
    """Away from ``near_m`` to ``far_m``, a U-turn of radius 0.3 m, and back."""
    r = 0.3
    x0 = rng.uniform(-0.2, 0.0)
    wps = np.array(
        [
            (x0, spec.near_m),
            (x0, spec.far_m),
            (x0 + 2 * r, spec.far_m),
            (x0 + 2 * r, spec.near_m),
        ]
    )
    length = body.planned_length(wps, r)
    return _PathPlan(wps, r, 0.0, length, length)


_PATHS = {
    "pace": _pace_path,
    "towards": _straight_path,
    "away": _straight_path,
    "turn": _turn_path,
    "away_back": _away_back_path,
}


def _plan_path(spec: ScenarioSpec, rng: np.random.Generator, duration_s: float) -> _PathPlan:
    """The walk of ``spec.path`` for a sequence of ``duration_s``. The mirror draw comes
    first for every path, so each path consumes the layout stream the same way."""
    mirror = rng.choice([-1.0, 1.0])
    if spec.path not in _PATHS:
        raise ValueError(
            f"unknown path {spec.path!r}; expected 'pace', 'towards', 'away', 'turn' or 'away_back'"
        )
    return _PATHS[spec.path](spec, rng, duration_s, mirror)


class _KeepOut(NamedTuple):
    """The walker's floor region and angular range, which furniture must neither enter
    nor hide: ``x0..x1``, ``z0..z1`` in metres and ``amin..amax`` in ``x / z``."""

    x0: float
    x1: float
    z0: float
    z1: float
    amin: float
    amax: float


def _keep_out(path: body.Path, extent_length: float) -> _KeepOut:
    """Keep-out region of the planned walk; it does not depend on the sequence length, so
    frame ``t`` of a seed never depends on ``n_frames``."""
    walked = path.xz[path.s <= extent_length + 0.1]
    xs, zs = walked[:, 0], walked[:, 1]
    # The body reaches ~0.45 m from the path (stride, arm swing) and ~0.6 m sideways in view.
    amin = float(np.min((xs - 0.6) / zs))
    amax = float(np.max((xs + 0.6) / zs))
    return _KeepOut(xs.min() - 0.45, xs.max() + 0.45, zs.min() - 0.45, zs.max() + 0.45, amin, amax)


class _Walk(NamedTuple):
    n_frames: int
    t_s: np.ndarray  # [T] frame times, s
    root_xz: np.ndarray  # [T, 2] floor point under the pelvis, m
    heading_xz: np.ndarray  # [T, 2] unit walking direction
    phase: np.ndarray  # [T] gait phase, rad
    plan: _PathPlan
    keep_out: _KeepOut


def _walk(spec: ScenarioSpec, rng: np.random.Generator, n_frames: int | None, fps: float) -> _Walk:
    """Plan the path, clip the default length of a single pass to the walk, and sample the
    walker's position, heading and gait phase at every frame."""
    n_req = int(n_frames) if n_frames is not None else int(spec.n_frames)
    plan = _plan_path(spec, rng, n_req / fps)
    if n_frames is None and np.isfinite(plan.walk_length):
        n_req = min(n_req, int(np.floor(plan.walk_length / spec.speed_mps * fps)) + 1)
    T = max(n_req, 1)
    path = body.fillet_path(plan.waypoints, plan.radius)
    t_s = np.arange(T) / fps
    s = plan.s0 + spec.speed_mps * t_s
    root_xz, heading_xz = body.sample_path(path, s)
    step = body.gait_parameters(spec.speed_mps)["step"]
    phase0 = rng.uniform(0, 2 * np.pi)
    phase = phase0 + np.pi * (s - plan.s0) / step
    return _Walk(T, t_s, root_xz, heading_xz, phase, plan, _keep_out(path, plan.extent_length))


# ---------------------------------------------------------------------------------------------
# Static scene.


class _Scene(NamedTuple):
    prims: list
    materials: list
    floor_index: int


class _SceneBuilder:
    """Collects the static boxes (object 0) and their materials; boxes are placed by world
    centre and size (m) and stored in camera coordinates."""

    def __init__(self, cam: _Camera) -> None:
        self.cam = cam
        self.prims: list[rnd.Prim] = []
        self.materials: list[_Material] = []

    def material(self, m: _Material) -> int:
        self.materials.append(m)
        return len(self.materials) - 1

    def box(self, centre, size, material: int) -> None:
        cam = self.cam
        self.prims.append(rnd.box(cam.to_cam(centre), cam.R, np.asarray(size) / 2, 0, material))


_CEILING_M = 2.7
_TILE_GREY = (150, 150, 145)


def _room(b: _SceneBuilder, spec: ScenarioSpec, rng: np.random.Generator) -> int:
    """Floor (planks or tiles), back and side walls, ceiling, lamps and a skirting board;
    returns the floor's primitive index."""
    D, W2, CEIL = spec.room_depth_m, spec.room_half_width_m, _CEILING_M
    floor_rgb = _FURNITURE_COLOURS[rng.choice([0, 2])] if rng.uniform() < 0.6 else _TILE_GREY
    floor_tex = "planks" if floor_rgb != _TILE_GREY else "tiles"
    m_floor = b.material(_Material(floor_rgb, _ir(floor_rgb), floor_tex, 0.45, 0.12))
    b.box((0, -0.05, D / 2), (2 * W2 + 1, 0.1, D + 1), m_floor)
    floor_index = len(b.prims) - 1
    wall_rgb = tuple(
        int(c) for c in rng.choice([(225, 222, 210), (205, 210, 200), (215, 205, 185)])
    )
    m_wall = b.material(_Material(wall_rgb, _ir(wall_rgb), "wall", 0.006, 0.04))
    b.box((0, CEIL / 2, D + 0.05), (2 * W2 + 1, CEIL + 0.2, 0.1), m_wall)
    side_rgb = tuple(int(0.93 * c) for c in wall_rgb)
    m_side = b.material(_Material(side_rgb, _ir(side_rgb), "wall", 0.006, 0.04))
    b.box((-W2 - 0.05, CEIL / 2, D / 2), (0.1, CEIL + 0.2, D + 1), m_side)
    b.box((W2 + 0.05, CEIL / 2, D / 2), (0.1, CEIL + 0.2, D + 1), m_side)
    m_ceil = b.material(_Material((235, 235, 235), 0.7, "wall", 0.006, 0.03))
    b.box((0, CEIL + 0.05, D / 2), (2 * W2 + 1, 0.1, D + 1), m_ceil)
    m_lamp = b.material(_Material((255, 252, 240), 0.7, "plain", 0.01, 0.0, emissive=True))
    for lz in np.arange(1.5, D, 1.6):
        b.box((0, CEIL - 0.02, lz), (1.2, 0.04, 0.3), m_lamp)
    m_skirt = b.material(_Material((245, 245, 240), 0.7, "plain", 0.01, 0.02))
    b.box((0, 0.05, D - 0.01), (2 * W2, 0.1, 0.02), m_skirt)
    return floor_index


def _clutter_palettes(cl: Clothing) -> tuple[list, tuple]:
    """Furniture and book colours unlike the clothing, so that ``clutter_match`` alone
    decides how much of the scene resembles the person."""
    clothes = (cl.shirt, cl.trousers)
    furniture = [c for c in _FURNITURE_COLOURS if not any(_alike(c, k) for k in clothes)]
    books = tuple(c for c in _BOOK_COLOURS if not any(_alike(c, k) for k in clothes))
    furniture = furniture or list(_FURNITURE_COLOURS)
    books = books if len(books) >= 4 else tuple(_BOOK_COLOURS)
    return furniture, books


def _clutter_colour(rng: np.random.Generator, spec: ScenarioSpec, furniture: list):
    """``(rgb, matched)``: with probability ``clutter_match`` a colour similar to the shirt
    (or, less often, the trousers), else a plain furniture colour. Every draw is made
    whatever the knobs, so the layout does not depend on them."""
    cl = spec.clothing
    matched = rng.uniform() < spec.clutter_match
    target = cl.shirt if rng.uniform() < 0.7 else cl.trousers
    similar = _similar_colour(rng, target, spec.distractor_similarity)
    plain = furniture[rng.integers(len(furniture))]
    return (similar if matched else plain), matched


def _behind_path(keep: _KeepOut, a_lo: float, a_hi: float, za: float) -> bool:
    """Whether something at depth ``za`` spanning ``a_lo..a_hi`` (x / z) is seen right
    behind the walking path."""
    return za >= keep.z1 - 0.1 and a_hi > keep.amin and a_lo < keep.amax


def _placement_allowed(
    spec: ScenarioSpec, keep: _KeepOut, cx: float, cz: float, w: float, d: float, top: float
) -> bool:
    """Whether a ``w x d`` footprint centred at ``(cx, cz)`` reaching up to ``top`` fits in
    the room, is in view, and neither stands on the walk nor hides the walker."""
    D, W2 = spec.room_depth_m, spec.room_half_width_m
    xa, xb, za, zb = cx - w / 2, cx + w / 2, cz - d / 2, cz + d / 2
    if xa < -W2 or xb > W2 or zb > D or za < 0.8:
        return False
    if xb > keep.x0 and xa < keep.x1 and zb > keep.z0 and za < keep.z1:
        return False  # on the walking area
    corners_a = [xa / za, xb / za, xa / zb, xb / zb]
    a_lo, a_hi = min(corners_a), max(corners_a)
    tan_fov = _tan_half_fov(spec)
    if a_hi < -tan_fov or a_lo > tan_fov:
        return False  # out of view: pointless
    if za < keep.z1 + 0.1 and a_hi > keep.amin and a_lo < keep.amax:
        return False  # would hide the person
    if (
        spec.backdrop == "low"
        and top > spec.backdrop_height_m
        and _behind_path(keep, a_lo, a_hi, za)
    ):
        return False  # tall clutter right behind the walking path
    return True


def _posters(
    b: _SceneBuilder, spec: ScenarioSpec, rng: np.random.Generator, keep: _KeepOut, books: tuple
) -> None:
    """Striped or blotchy posters on the back wall (1.2 cm thick: no depth of their own);
    with ``backdrop="low"`` none behind the walking path."""
    D, W2 = spec.room_depth_m, spec.room_half_width_m
    palette_pool = list(books)
    for _ in range(1 + spec.clutter // 3):
        w, h = rng.uniform(0.4, 1.0), rng.uniform(0.5, 1.0)
        cx = rng.uniform(-W2 + w, W2 - w)
        if spec.backdrop == "low":
            for _attempt in range(30):
                if not _behind_path(keep, (cx - w / 2) / D, (cx + w / 2) / D, D):
                    break
                cx = rng.uniform(-W2 + w, W2 - w)
            else:
                continue
        pal = tuple(palette_pool[i] for i in rng.choice(len(palette_pool), 4, replace=False))
        similar = _similar_colour(rng, spec.clothing.shirt, spec.distractor_similarity)
        if rng.uniform() < spec.clutter_match:
            pal = (similar,) + pal[1:]
        kind = "stripes" if rng.uniform() < 0.4 else "blotches"
        m = b.material(_Material(pal[0], 0.5, kind, rng.uniform(0.04, 0.12), 0.05, pal))
        b.box((cx, rng.uniform(1.1, 1.8), D - 0.006), (w, h, 0.012), m)


def _furniture_size(rng: np.random.Generator, kind: str) -> tuple[float, float, float]:
    """Width (x), height and depth (z) of one piece of furniture, metres."""
    if kind == "shelf":
        return rng.uniform(0.6, 1.2), rng.uniform(1.2, 2.0), rng.uniform(0.3, 0.4)
    if kind == "cabinet":
        return rng.uniform(0.5, 1.2), rng.uniform(0.7, 1.3), rng.uniform(0.4, 0.6)
    if kind == "table":
        return rng.uniform(0.8, 1.6), rng.uniform(0.7, 0.78), rng.uniform(0.6, 0.9)
    if kind == "wall_shelf":
        return rng.uniform(0.6, 1.4), rng.uniform(0.35, 0.8), 0.25
    if kind == "crate":
        return rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6)
    return 0.45, 0.9, 0.45  # chair


def _place_furniture(rng: np.random.Generator, spec: ScenarioSpec, keep: _KeepOut, kind: str):
    """``(w, h, d, cx, cz)`` of a piece of ``kind`` at an allowed place, drawn afresh up to
    60 times; None when no draw is allowed. Shelves and cabinets mostly stand against the
    back wall, wall shelves always hang there."""
    D, W2 = spec.room_depth_m, spec.room_half_width_m
    for _attempt in range(60):
        w, h, d = _furniture_size(rng, kind)
        against_wall = kind == "wall_shelf" or (
            kind in ("shelf", "cabinet") and rng.uniform() < 0.7
        )
        cz = D - d / 2 - 0.01 if against_wall else rng.uniform(1.0, D - d / 2)
        cx = rng.uniform(-W2 + w / 2, W2 - w / 2)
        top = 2.5 if kind == "wall_shelf" else h
        if _placement_allowed(spec, keep, cx, cz, w, d, top):
            return w, h, d, cx, cz
    return None


def _add_table_or_chair(b: _SceneBuilder, rng, kind: str, placed, rgb) -> None:
    """A 4 cm top on four legs; a chair has a 46 cm seat and a backrest."""
    w, h, d, cx, cz = placed
    top = 0.04
    m = b.material(_Material(rgb, _ir(rgb), "plain", 0.004, 0.06))
    leg_rgb = (60, 60, 62) if rng.uniform() < 0.5 else rgb
    m_leg = b.material(_Material(leg_rgb, _ir(leg_rgb), "plain", 0.004, 0.03))
    seat_h = h if kind == "table" else 0.46
    b.box((cx, seat_h - top / 2, cz), (w, top, d), m)
    for sx in (-1, 1):
        for sz in (-1, 1):
            b.box(
                (cx + sx * (w / 2 - 0.04), (seat_h - top) / 2, cz + sz * (d / 2 - 0.04)),
                (0.04, seat_h - top, 0.04),
                m_leg,
            )
    if kind == "chair":
        b.box((cx, seat_h + 0.22, cz + d / 2 - 0.02), (w, 0.44, 0.03), m)


def _add_furniture(b: _SceneBuilder, rng, kind: str, placed, rgb, matched: bool, books) -> None:
    """Boxes of one piece: a bookshelf (matched ones hold books of its colour too), a
    cabinet, a crate, or a table or chair."""
    w, h, d, cx, cz = placed
    if kind in ("shelf", "wall_shelf"):
        pal = books + ((rgb, rgb) if matched else ())
        frame_rgb = rgb if matched else _FURNITURE_COLOURS[rng.choice([0, 1, 3, 6])]
        m_frame = b.material(_Material(frame_rgb, _ir(frame_rgb), "books", 0.01, 0.06, pal))
        y0 = rng.uniform(1.1, 2.5 - h) if kind == "wall_shelf" else 0.0
        b.box((cx, y0 + h / 2, cz), (w, h, d), m_frame)
    elif kind == "cabinet":
        m = b.material(_Material(rgb, _ir(rgb), "plain", 0.005, 0.05))
        b.box((cx, h / 2, cz), (w, h, d), m)
    elif kind == "crate":
        m = b.material(_Material(rgb, _ir(rgb), "plain", 0.004, 0.08))
        b.box((cx, h / 2, cz), (w, h, d), m)
    else:
        _add_table_or_chair(b, rng, kind, placed, rgb)


def _furniture(
    b: _SceneBuilder,
    spec: ScenarioSpec,
    rng: np.random.Generator,
    keep: _KeepOut,
    furniture: list,
    books: tuple,
) -> None:
    """``spec.clutter`` pieces of furniture; a piece that finds no allowed place is left out."""
    for _ in range(spec.clutter):
        kind = rng.choice(
            ["shelf", "cabinet", "table", "crate", "chair", "wall_shelf"],
            p=[0.2, 0.2, 0.15, 0.15, 0.1, 0.2],
        )
        placed = _place_furniture(rng, spec, keep, kind)
        if placed is None:
            continue
        rgb, matched = _clutter_colour(rng, spec, furniture)
        _add_furniture(b, rng, kind, placed, rgb, matched, books)


def _distractor_panel(
    b: _SceneBuilder, spec: ScenarioSpec, rng: np.random.Generator, keep: _KeepOut
) -> None:
    """A large shirt-coloured panel standing just behind the far lane, centred on the walk."""
    rgb = _similar_colour(rng, spec.clothing.shirt, spec.distractor_similarity)
    m = b.material(_Material(rgb, _ir(rgb), "plain", 0.004, 0.06))
    zc = min(keep.z1 + 0.1, spec.room_depth_m - 0.05)
    b.box((0.5 * (keep.x0 + keep.x1) + rng.uniform(-0.2, 0.2), 0.85, zc), (1.2, 1.7, 0.04), m)


def _scene(spec: ScenarioSpec, cam: _Camera, rng: np.random.Generator, keep: _KeepOut) -> _Scene:
    """Room, posters, furniture and the optional distractor, kept clear of the walk."""
    b = _SceneBuilder(cam)
    floor_index = _room(b, spec, rng)
    furniture, books = _clutter_palettes(spec.clothing)
    _posters(b, spec, rng, keep, books)
    _furniture(b, spec, rng, keep, furniture, books)
    if spec.distractor:
        _distractor_panel(b, spec, rng, keep)
    _poles(b, spec, rng, keep, furniture)
    return _Scene(b.prims, b.materials, floor_index)


_POLE_COLOURS = ((70, 70, 72), (150, 150, 155), (40, 40, 44), (185, 170, 60))


def _poles(b: _SceneBuilder, spec: ScenarioSpec, rng, keep: _KeepOut, furniture: list) -> None:
    """``spec.poles`` thin posts in view, off the walking area but free to stand between it
    and the camera; a sign on about half of them, coloured like the clutter."""
    D, W2 = spec.room_depth_m, spec.room_half_width_m
    tan_fov = _tan_half_fov(spec)
    for _ in range(spec.poles):
        for _attempt in range(60):
            t = rng.uniform(0.05, 0.12)
            cz = rng.uniform(max(1.5, 0.3 * D), D - 0.3)
            cx = rng.uniform(-1.0, 1.0) * min(cz * tan_fov, W2 - 0.2)
            if not (keep.x0 - t < cx < keep.x1 + t and keep.z0 - t < cz < keep.z1 + t):
                break
        else:
            continue
        rgb = _POLE_COLOURS[rng.integers(len(_POLE_COLOURS))]
        height = rng.uniform(2.0, _CEILING_M - 0.05)
        b.box((cx, height / 2, cz), (t, height, t), b.material(_Material(rgb, _ir(rgb))))
        if rng.uniform() < 0.5:
            w, h = rng.uniform(0.3, 0.7), rng.uniform(0.25, 0.6)
            sign, _ = _clutter_colour(rng, spec, furniture)
            m = b.material(_Material(tuple(sign), _ir(sign), "plain", 0.004, 0.05))
            b.box((cx, height - h / 2 - 0.05, cz - t / 2 - 0.01), (w, h, 0.02), m)


# ---------------------------------------------------------------------------------------------
# Person.


def _person_materials(cl: Clothing, shirt: RGB) -> list[_Material]:
    """Materials of the body parts, indexed like ``body.PART_NAMES``."""
    shirt_m = _Material(tuple(shirt), _ir(shirt), "fabric", 0.004, 0.07)
    trousers_m = _Material(cl.trousers, _ir(cl.trousers), "fabric", 0.004, 0.08)
    skin_m = _Material(cl.skin, 0.55, "plain", 0.003, 0.03)
    # Dark hair and shoes reflect little near-infrared: ToF holes (about half the hair at 3 m).
    hair_m = _Material(cl.hair, 0.02 + 0.3 * _lum(cl.hair), "hair", 0.002, 0.12)
    shoes_m = _Material(cl.shoes, 0.03 + 0.4 * _lum(cl.shoes), "plain", 0.004, 0.05)
    slot = {
        "face": skin_m,
        "hair": hair_m,
        "neck": skin_m,
        "chest": shirt_m,
        "shoulders": shirt_m,
        "abdomen": shirt_m,
        "hips": trousers_m,
        "left_upper_arm": shirt_m,
        "right_upper_arm": shirt_m,
        "left_forearm": shirt_m if cl.long_sleeves else skin_m,
        "right_forearm": shirt_m if cl.long_sleeves else skin_m,
        "left_hand": skin_m,
        "right_hand": skin_m,
        "left_thigh": trousers_m,
        "right_thigh": trousers_m,
        "left_shin": trousers_m,
        "right_shin": trousers_m,
        "left_foot": shoes_m,
        "right_foot": shoes_m,
    }
    return [slot[n] for n in body.PART_NAMES]


def _person_prims(
    pose: body.Pose, height: float, cam: _Camera, mat_offset: int, object_id: int
) -> list[rnd.Prim]:
    prims = []
    for i, part in enumerate(body.body_parts(pose, height)):
        if part[0] == "capsule":
            _, a, b, r, ref = part
            prims.append(
                rnd.capsule(
                    cam.to_cam(a),
                    cam.to_cam(b),
                    r,
                    cam.dir_to_cam(ref),
                    object_id,
                    mat_offset + i,
                    i,
                )
            )
        else:
            _, c, axes, radii = part
            prims.append(
                rnd.ellipsoid(cam.to_cam(c), cam.R @ axes, radii, object_id, mat_offset + i, i)
            )
    return prims


# A second person's default outfit: grey top, dark trousers.
_OCCLUDER_CLOTHING = Clothing(shirt=(120, 120, 125), trousers=(40, 40, 45), hair=(70, 55, 40))


def _occluder_person(
    oc: Occluder,
    xz,
    a: float,
    phase0: float,
    height: float,
    cam: _Camera,
    mat_offset: int,
    object_id: int,
) -> list[rnd.Prim]:
    """Primitives of a person occluder at floor point ``xz``, ``a`` of the way along its walk."""
    delta = np.asarray(oc.end_xz, float) - np.asarray(oc.start_xz, float)
    dist = float(np.linalg.norm(delta))
    heading = delta / dist if dist > 1e-9 else np.array([1.0, 0.0])
    duration = max(oc.t1_s - oc.t0_s, 1e-9)
    moving = 0.0 < a < 1.0
    speed = dist / duration if moving else 0.0
    step = body.gait_parameters(max(dist / duration, 1e-3))["step"]
    phase = phase0 + np.pi * a * dist / step
    pose = body.body_pose(np.asarray(xz, float), heading, phase, speed, height)
    return _person_prims(pose, height, cam, mat_offset, object_id)


# ---------------------------------------------------------------------------------------------
# Depth effects.

_P_EDGE_FAR, _P_EDGE_NEAR = 0.7, 0.3
_AMP0, _AMP_S = 0.0045, 0.0012
_COS_GRAZING = np.cos(np.radians(83.0))


def _edge_flags(z: np.ndarray, key: np.ndarray):
    """Far / near side of depth discontinuities between different surfaces (4-neighbours)."""
    zp = np.pad(z, 1, mode="edge")
    kp = np.pad(key, 1, mode="edge")
    thr = np.maximum(0.05, 0.03 * np.where(np.isfinite(z), z, 10.0))
    far = np.zeros(z.shape, bool)
    near = np.zeros(z.shape, bool)
    h, w = z.shape
    for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
        zn = zp[dr : dr + h, dc : dc + w]
        diff = kp[dr : dr + h, dc : dc + w] != key
        with np.errstate(invalid="ignore"):
            far |= diff & (z - zn > thr)
            near |= diff & (zn - z > thr)
    return far, near


def _edge_prob(far: np.ndarray, near: np.ndarray) -> np.ndarray:
    return np.where(
        far, np.float32(_P_EDGE_FAR), np.where(near, np.float32(_P_EDGE_NEAR), 0)
    ).astype(np.float32)


def _static_missing(zmm: np.ndarray, cos: np.ndarray, max_range_mm: float) -> np.ndarray:
    """Deterministic dropouts: no surface, out of range, grazing incidence."""
    return (zmm > max_range_mm) | (zmm < 500.0) | (cos < _COS_GRAZING)


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img.copy()


def _dynamic_window(prims, root_xz, cam: _Camera, intr, H: int, W: int):
    """Pixel window ``(r0, r1, c0, c1)`` that holds every dynamic primitive and the
    person's floor shadow, with a 4 px margin (so that no dynamic pixel touches its
    border), ``None`` when nothing is in view; and the floor-shadow rect (unclipped)."""
    rects = [rnd.screen_rect(p, *intr) for p in prims]
    floor = np.array(
        [(root_xz[0] + dx, 0.0, root_xz[1] + dz) for dx in (-0.8, 0.8) for dz in (-0.8, 0.8)]
    )
    fc = cam.to_cam(floor)
    shadow = None
    if fc[:, 2].min() > 0.05:
        u = intr.fx * fc[:, 0] / fc[:, 2] + intr.cx
        v = intr.fy * fc[:, 1] / fc[:, 2] + intr.cy
        shadow = (
            int(np.floor(v.min())),
            int(np.ceil(v.max())) + 1,
            int(np.floor(u.min())),
            int(np.ceil(u.max())) + 1,
        )
        rects.append(shadow)
    if any(r is None for r in rects):
        return (0, H, 0, W), shadow
    r = np.array(rects)
    r0, r1 = max(r[:, 0].min() - 4, 0), min(r[:, 1].max() + 4, H)
    c0, c1 = max(r[:, 2].min() - 4, 0), min(r[:, 3].max() + 4, W)
    if r1 <= r0 or c1 <= c0:
        return None, None
    return (int(r0), int(r1), int(c0), int(c1)), shadow


def _dropout_prob(ir: np.ndarray, cos: np.ndarray, z: np.ndarray) -> np.ndarray:
    amp = ir * cos / np.maximum(z * z, 1e-6)
    return (1.0 / (1.0 + np.exp(np.clip((amp - _AMP0) / _AMP_S, -50, 50)))).astype(np.float32)


def _shade(albedo, normal, light, emissive=None):
    """Ambient + Lambert; ``albedo [n, 3]``, ``normal [3, n]``."""
    lam = np.maximum(light @ normal, 0.0)
    f = 0.55 + 0.5 * lam
    if emissive is not None:
        f = np.where(emissive, 1.0, f)
    return albedo * f[:, None]


def _illumination_gain(spec: ScenarioSpec, n: int, fps: float) -> np.ndarray:
    """``[T, 3]`` per-frame RGB gain."""
    g = np.ones((n, 3), np.float32)
    a = spec.illumination_strength
    t = np.arange(n) / fps
    if spec.illumination == "drift":
        period = max(n / fps, 1.0)
        s = np.sin(2 * np.pi * t / period)
        c = np.sin(np.pi * t / period)
        g *= (1 + 0.5 * a * s)[:, None]
        g *= np.stack([1 + 0.25 * a * c, np.ones_like(c), 1 - 0.25 * a * c], -1)
    elif spec.illumination == "switch":
        k = n // 2
        off = np.array([1 - a, 1 - 1.15 * a, 1 - 1.4 * a], np.float32).clip(0.2, 1)
        g[k:] = off
    elif spec.illumination != "none":
        raise ValueError(f"unknown illumination {spec.illumination!r}")
    return g


# ---------------------------------------------------------------------------------------------
# The fixed stage: rays, light, the empty room rendered once, noise banks.


class _Rays(NamedTuple):
    xy: np.ndarray  # [2, H, W] float64 X and Y of the pixel rays (Z = 1)
    rx: np.ndarray  # [H, W] float32 X
    ry: np.ndarray  # [H, W] float32 Y
    norm: np.ndarray  # [H, W] float32 ray length


def _rays(intr: Intrinsics) -> _Rays:
    rays = rnd.pixel_rays(HEIGHT, WIDTH, intr.fx, intr.fy, intr.cx, intr.cy)
    rx, ry = rays[0].astype(np.float32), rays[1].astype(np.float32)
    return _Rays(rays, rx, ry, np.sqrt(rx * rx + ry * ry + 1))


def _light(cam: _Camera) -> np.ndarray:
    """``[3] float32`` unit direction towards the light (above, left, behind the camera)."""
    light = cam.dir_to_cam(np.array([-0.35, 1.0, -0.6]) / np.linalg.norm([-0.35, 1.0, -0.6]))
    return light.astype(np.float32)


class _Background(NamedTuple):
    """The empty room without sensor noise, per pixel ``[H, W]``."""

    gbuf: rnd.GBuffer  # ray-cast buffers (z in m, inf = nothing)
    lin: np.ndarray  # [H, W, 3] float32 shaded colour, 0-255 scale
    blur: np.ndarray  # [H, W, 3] float32 ``lin`` after the lens blur
    u8: np.ndarray  # [H, W, 3] uint8 ``blur`` rounded
    z_m: np.ndarray  # float32 depth, m, 0 = no surface
    z_mm: np.ndarray  # float32 depth, mm
    cos: np.ndarray  # cosine between ray and surface normal
    sigma: np.ndarray  # float32 axial noise std, mm
    missing: np.ndarray  # bool deterministic dropouts
    p_amp: np.ndarray  # float32 dropout probability of a weak infrared return
    cand_r: np.ndarray  # [n] rows of the pixels that may drop out at random
    cand_c: np.ndarray  # [n] their columns
    cand_amp: np.ndarray  # [n] their weak-return dropout probabilities
    cand_edge: np.ndarray  # [n] their depth-edge dropout probabilities


def _shade_room(scene: _Scene, tex: _Tex, light: np.ndarray, bg: rnd.GBuffer):
    """``([H, W, 3] float32 shaded colour, [H, W] float32 infrared reflectivity)``."""
    bg_mat = np.array([p.material for p in scene.prims])
    lin = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    ir = np.zeros((HEIGHT, WIDTH), np.float32)
    for i in np.unique(bg.pid[bg.pid >= 0]):
        sel = bg.pid == i
        m = scene.materials[bg_mat[i]]
        alb = _albedo(m, bg.uv[:, sel], tex)
        lin[sel] = _shade(alb, bg.normal[:, sel], light, np.full(len(alb), m.emissive))
        ir[sel] = m.ir
    return lin, ir


def _render_background(
    spec: ScenarioSpec, scene: _Scene, tex: _Tex, rays: _Rays, light: np.ndarray, intr
) -> _Background:
    """Ray cast and shade the empty room once, with its depth-noise and dropout model."""
    bg = rnd.GBuffer(HEIGHT, WIDTH)
    rnd.raycast(scene.prims, 0, bg, rays.xy, intr)
    lin, ir = _shade_room(scene, tex, light, bg)
    z_m = np.where(np.isfinite(bg.z), bg.z, 0.0).astype(np.float32)
    cos = np.abs(bg.normal[0] * rays.rx + bg.normal[1] * rays.ry + bg.normal[2]) / rays.norm
    blur = _blur(lin, spec.colour_blur)
    noise_scale = np.float32(spec.depth_noise_scale)
    sigma = kinect_v2_axial_sigma_mm(z_m, np.arccos(np.clip(cos, 0, 1))) * noise_scale
    z_mm = z_m * np.float32(1000.0)
    missing = _static_missing(z_mm, cos, spec.max_range_mm)
    p_amp = _dropout_prob(ir, cos, z_m)
    p_edge = _edge_prob(*_edge_flags(z_m, bg.pid))
    cand_r, cand_c = np.nonzero(((p_amp > 1e-4) | (p_edge > 0)) & ~missing)
    u8 = np.clip(np.rint(blur), 0, 255).astype(np.uint8)
    return _Background(
        bg,
        lin,
        blur,
        u8,
        z_m,
        z_mm,
        cos,
        sigma,
        missing,
        p_amp,
        cand_r,
        cand_c,
        p_amp[cand_r, cand_c],
        p_edge[cand_r, cand_c],
    )


# Pre-drawn noise: each frame reads a randomly offset window of one of _BANKS fields, which
# is statistically white noise again and much cheaper than drawing fresh fields per frame.
_BANKS, _PAD = 3, 32


class _NoiseBanks(NamedTuple):
    colour: np.ndarray  # [K, H + PAD, W + PAD, 3] int16 colour noise, uint8 levels
    depth: np.ndarray  # [K, H + PAD, W + PAD] float32 standard normal
    uniform: np.ndarray  # [K, H + PAD, W + PAD] float32 U(0, 1) for edge dropouts
    block: np.ndarray  # [K, H + PAD, W + PAD] float32 U(0, 1) in 2 x 2 blocks, weak returns


def _noise_banks(seed: int, colour_noise: float) -> _NoiseBanks:
    H, W, K, PAD = HEIGHT, WIDTH, _BANKS, _PAD
    rng = np.random.default_rng([seed, 2])
    col = np.rint(
        rng.standard_normal((K, H + PAD, W + PAD, 3), dtype=np.float32) * np.float32(colour_noise)
    ).astype(np.int16)
    dep = rng.standard_normal((K, H + PAD, W + PAD), dtype=np.float32)
    uni = rng.random((K, H + PAD, W + PAD), dtype=np.float32)
    blk = rng.random((K, (H + PAD) // 2 + 1, (W + PAD) // 2 + 1), dtype=np.float32)
    blk = np.repeat(np.repeat(blk, 2, axis=1), 2, axis=2)[:, : H + PAD, : W + PAD]
    return _NoiseBanks(col, dep, uni, blk)


class _FrameNoise(NamedTuple):
    colour: np.ndarray  # [H, W, 3] int16
    depth: np.ndarray  # [H, W] float32 standard normal
    edge: np.ndarray  # [H, W] float32 U(0, 1)
    amp: np.ndarray  # [H, W] float32 U(0, 1), 2 x 2 blocks


def _frame_noise(banks: _NoiseBanks, seed: int, t: int) -> _FrameNoise:
    """Frame ``t``'s windows of the banks, from a stream of its own (``[seed, 1, t]``), so
    that frame ``t`` does not depend on the sequence length."""
    H, W = HEIGHT, WIDTH
    rng = np.random.default_rng([seed, 1, t])
    kc, kd, ku = rng.integers(_BANKS, size=3)
    off = rng.integers(_PAD + 1, size=(3, 2))
    return _FrameNoise(
        banks.colour[kc, off[0, 0] : off[0, 0] + H, off[0, 1] : off[0, 1] + W],
        banks.depth[kd, off[1, 0] : off[1, 0] + H, off[1, 1] : off[1, 1] + W],
        banks.uniform[ku, off[2, 0] : off[2, 0] + H, off[2, 1] : off[2, 1] + W],
        # The same bank slot as ``edge`` with the offsets swapped: an independent window.
        banks.block[ku, off[2, 1] : off[2, 1] + H, off[2, 0] : off[2, 0] + W],
    )


class _Stage(NamedTuple):
    """What every frame is rendered against."""

    spec: ScenarioSpec
    intr: Intrinsics
    cam: _Camera
    rays: _Rays
    light: np.ndarray
    tex: _Tex
    bg: _Background
    floor_index: int
    gain: np.ndarray  # [T, 3] float32 illumination gain per frame
    unit_gain: bool
    blur_r: int  # px reach of the lens blur
    noise_scale: np.float32


def _stage(
    spec: ScenarioSpec, cam: _Camera, scene: _Scene, tex: _Tex, n_frames: int, fps: float
) -> _Stage:
    intr = _intrinsics(spec)
    rays = _rays(intr)
    light = _light(cam)
    bg = _render_background(spec, scene, tex, rays, light, intr)
    gain = _illumination_gain(spec, n_frames, fps)
    blur_r = int(np.ceil(3 * spec.colour_blur)) + 1 if spec.colour_blur > 0 else 0
    noise_scale = np.float32(spec.depth_noise_scale)
    unit_gain = bool(np.all(gain == 1.0))
    return _Stage(
        spec,
        intr,
        cam,
        rays,
        light,
        tex,
        bg,
        scene.floor_index,
        gain,
        unit_gain,
        blur_r,
        noise_scale,
    )


# ---------------------------------------------------------------------------------------------
# Dynamic objects: the walker and the occluders.


class _Dynamic(NamedTuple):
    person: list  # materials of the walker's parts, indexed like body.PART_NAMES
    changed: list | None  # the same after ``shirt_change``
    occluders: list  # materials of every occluder, after the walker's
    offsets: list  # [n_occluders] first material index of each occluder
    phase0: list  # [n_occluders] initial gait phase of each occluder, rad


def _dynamic_objects(spec: ScenarioSpec, seed: int) -> _Dynamic:
    """Materials of the walker and the occluders, and the occluders' gait phases."""
    cl = spec.clothing
    changed = None
    if spec.shirt_change is not None:
        changed = _person_materials(cl, tuple(spec.shirt_change[1]))
    n_parts = len(body.PART_NAMES)
    occ_mats: list[_Material] = []
    offsets = []
    for oc in spec.occluders:
        offsets.append(n_parts + len(occ_mats))
        if oc.kind == "box":
            occ_mats.append(_Material(oc.colour, _ir(oc.colour), "plain", 0.004, 0.05))
        elif oc.kind == "person":
            ocl = oc.clothing or _OCCLUDER_CLOTHING
            occ_mats.extend(_person_materials(ocl, ocl.shirt))
        else:
            raise ValueError(f"unknown occluder kind {oc.kind!r}; expected 'box' or 'person'")
    # The occluders' phases come from a stream of their own, so that adding occluders
    # leaves the layout of a seed as it is.
    rng = np.random.default_rng([seed, 3])
    phase0 = [rng.uniform(0, 2 * np.pi) for _ in spec.occluders]
    return _Dynamic(_person_materials(cl, cl.shirt), changed, occ_mats, offsets, phase0)


def _frame_materials(spec: ScenarioSpec, dyn: _Dynamic, t: int) -> list:
    """Materials of frame ``t``'s dynamic primitives: the walker's, then the occluders'."""
    changed = dyn.changed is not None and t >= spec.shirt_change[0]
    return list(dyn.changed if changed else dyn.person) + dyn.occluders


def _occluder_prims(
    spec: ScenarioSpec, dyn: _Dynamic, t_s: float, walk_sign: float, cam: _Camera
) -> list[rnd.Prim]:
    """Primitives of every occluder at time ``t_s``: object ``2 + k`` for occluder ``k``,
    ``a`` of the way along its straight walk; ``mirror_x`` ones follow the walker's initial
    direction ``walk_sign``."""
    prims = []
    for k, oc in enumerate(spec.occluders):
        if oc.mirror_x and walk_sign < 0:
            oc = dataclasses.replace(
                oc,
                start_xz=(-oc.start_xz[0], oc.start_xz[1]),
                end_xz=(-oc.end_xz[0], oc.end_xz[1]),
            )
        a = np.clip((t_s - oc.t0_s) / max(oc.t1_s - oc.t0_s, 1e-9), 0.0, 1.0)
        xz = (1 - a) * np.asarray(oc.start_xz) + a * np.asarray(oc.end_xz)
        sx, sy, sz = oc.size_m
        if oc.kind == "person":
            prims.extend(_occluder_person(oc, xz, a, dyn.phase0[k], sy, cam, dyn.offsets[k], 2 + k))
            continue
        half = np.array([sx, sy, sz]) / 2
        centre = cam.to_cam((xz[0], sy / 2, xz[1]))
        prims.append(rnd.box(centre, cam.R, half, 2 + k, dyn.offsets[k]))
    return prims


def _joint_part_table() -> np.ndarray:
    """``[J, n_parts] bool``: which body parts count as joint ``j`` being visible."""
    ok = np.zeros((len(body.JOINT_NAMES), len(body.PART_NAMES)), bool)
    for j, jn in enumerate(body.JOINT_NAMES):
        for pn in body.JOINT_PARTS[jn]:
            ok[j, body.P[pn]] = True
    return ok


_JOINT_PART_OK = _joint_part_table()


# ---------------------------------------------------------------------------------------------
# One frame.


class _Frames(NamedTuple):
    """The rendered sequence, filled frame by frame."""

    colour: np.ndarray  # [T, H, W, 3] uint8
    depth: np.ndarray  # [T, H, W] uint16 mm
    mask: np.ndarray  # [T, H, W] bool person pixels
    joints3d: np.ndarray  # [T, J, 3] float32 mm
    joint_vis: np.ndarray  # [T, J] bool
    vis_count: np.ndarray  # [T] visible person pixels
    unocc_count: np.ndarray  # [T] person pixels without the occluders
    occ_boxes: np.ndarray  # [T, K, 4] float32 tight xywh box of each occluder's visible pixels
    occ_count: np.ndarray  # [T, K] its visible pixels
    occ_unocc: np.ndarray  # [T, K] its pixels with nothing else in front of it


def _allocate(T: int, n_occluders: int) -> _Frames:
    H, W, J = HEIGHT, WIDTH, len(body.JOINT_NAMES)
    return _Frames(
        np.empty((T, H, W, 3), np.uint8),
        np.empty((T, H, W), np.uint16),
        np.zeros((T, H, W), bool),
        np.empty((T, J, 3), np.float32),
        np.zeros((T, J), bool),
        np.zeros(T, np.int64),
        np.zeros(T, np.int64),
        np.zeros((T, n_occluders, 4), np.float32),
        np.zeros((T, n_occluders), np.int64),
        np.zeros((T, n_occluders), np.int64),
    )


def _background_frame(st: _Stage, noise: _FrameNoise, colour_t, depth_t, gain_t) -> np.ndarray:
    """Write the noisy empty room into ``colour_t [H, W, 3]`` and ``depth_t [H, W]``;
    returns its ``[H, W] bool`` dropouts."""
    bg = st.bg
    if st.unit_gain:
        cv2.add(bg.u8, noise.colour, dst=colour_t, dtype=cv2.CV_8U)
    else:
        cv2.add(bg.blur * gain_t, noise.colour, dst=colour_t, dtype=cv2.CV_8U)
    cv2.add(bg.z_mm, bg.sigma * noise.depth, dst=depth_t, dtype=cv2.CV_16U)
    missing = bg.missing.copy()
    r, c = bg.cand_r, bg.cand_c
    missing[r, c] |= (noise.amp[r, c] < bg.cand_amp) | (noise.edge[r, c] < bg.cand_edge)
    return missing


def _raycast_window(st: _Stage, win, person_prims, occ_prims) -> tuple[rnd.GBuffer, int]:
    """The window's buffers in front of the room, and how many pixels the walker covers
    before the occluders are cast."""
    r0, r1, c0, c1 = win
    gb = rnd.GBuffer.over(st.bg.gbuf.z[r0:r1, c0:c1])
    rays_w = st.rays.xy[:, r0:r1, c0:c1]
    rnd.raycast(person_prims, 0, gb, rays_w, st.intr, (r0, c0))
    unoccluded = int(np.count_nonzero(gb.pid >= 0))
    if occ_prims:
        rnd.raycast(occ_prims, len(person_prims), gb, rays_w, st.intr, (r0, c0))
    return gb, unoccluded


def _joint_visibility(jc, gb: rnd.GBuffer, obj, ppart, win, intr, vis_row) -> None:
    """Set ``vis_row [J]`` where the joint's own part is the nearest surface at its pixel."""
    r0, r1, c0, c1 = win
    ju = np.rint(intr.fx * jc[:, 0] / jc[:, 2] + intr.cx).astype(int) - c0
    jv = np.rint(intr.fy * jc[:, 1] / jc[:, 2] + intr.cy).astype(int) - r0
    for j in np.nonzero((ju >= 0) & (ju < c1 - c0) & (jv >= 0) & (jv < r1 - r0))[0]:
        pid = gb.pid[jv[j], ju[j]]
        if pid >= 0 and obj[pid] == 1:
            vis_row[j] = _JOINT_PART_OK[j, ppart[pid]]


def _occluder_truth(st: _Stage, out: _Frames, t: int, win, gb: rnd.GBuffer, obj, occ_prims):
    """Each occluder's tight box and visible pixels in frame ``t``, and its pixels with
    nothing but the room behind (a ray cast of it alone): the ground truth of every person
    in a multi-person scene."""
    r0, r1, c0, c1 = win
    seen = gb.pid >= 0
    for k in range(out.occ_boxes.shape[1]):
        mine = [p for p in occ_prims if p.object_id == 2 + k]
        if not mine:
            continue
        m = seen & (obj[np.maximum(gb.pid, 0)] == 2 + k)
        out.occ_count[t, k] = int(np.count_nonzero(m))
        if out.occ_count[t, k]:
            rows, cols = np.nonzero(m.any(axis=1))[0], np.nonzero(m.any(axis=0))[0]
            out.occ_boxes[t, k] = (
                c0 + cols[0],
                r0 + rows[0],
                cols[-1] - cols[0] + 1,
                rows[-1] - rows[0] + 1,
            )
        alone = rnd.GBuffer.over(st.bg.gbuf.z[r0:r1, c0:c1])
        rnd.raycast(mine, 0, alone, st.rays.xy[:, r0:r1, c0:c1], st.intr, (r0, c0))
        out.occ_unocc[t, k] = int(np.count_nonzero(alone.pid >= 0))


def _dynamic_albedo(gb: rnd.GBuffer, dyn, pmat, materials, tex: _Tex):
    """``([n, 3] albedo, [n] infrared reflectivity)`` of the dynamic pixels ``dyn``."""
    pid = gb.pid[dyn]
    uv_d = gb.uv[:, dyn]
    alb = np.empty((len(pid), 3), np.float32)
    ir = np.empty(len(pid), np.float32)
    for i in np.unique(pid):
        sel = pid == i
        m = materials[pmat[i]]
        alb[sel] = _albedo(m, uv_d[:, sel], tex)
        ir[sel] = m.ir
    return alb, ir


def _floor_shadow(st: _Stage, loc, win, shadow_rect, dyn, root_c) -> None:
    """Darken, in place, the floor of ``loc`` (the window's linear colour) around the
    walker's feet: a Gaussian of 0.3 m around the point under the pelvis ``root_c``."""
    r0, r1, c0, c1 = win
    s0, s1 = max(shadow_rect[0], r0), min(shadow_rect[1], r1)
    s2, s3 = max(shadow_rect[2], c0), min(shadow_rect[3], c1)
    ss = (slice(s0, s1), slice(s2, s3))
    zf = st.bg.z_m[ss]
    d2 = (
        (zf * st.rays.rx[ss] - root_c[0]) ** 2
        + (zf * st.rays.ry[ss] - root_c[1]) ** 2
        + (zf - root_c[2]) ** 2
    )
    on_floor = (st.bg.gbuf.pid[ss] == st.floor_index) & ~dyn[s0 - r0 : s1 - r0, s2 - c0 : s3 - c0]
    shade = np.where(on_floor, 1 - 0.45 * np.exp(-d2 / (2 * 0.3**2)), 1.0)
    loc[s0 - r0 : s1 - r0, s2 - c0 : s3 - c0] *= shade[..., None].astype(np.float32)


def _shade_window(st: _Stage, win, dyn, nrm, alb, shadow_rect, root_c, noise, colour_t, gain_t):
    """Shade the dynamic pixels over the room, shadow the floor and blur a margin of
    ``blur_r`` around the window again, so that the objects' edges blur like the room."""
    r0, r1, c0, c1 = win
    blur_r = st.blur_r
    pr0, pr1 = max(r0 - blur_r, 0), min(r1 + blur_r, HEIGHT)
    pc0, pc1 = max(c0 - blur_r, 0), min(c1 + blur_r, WIDTH)
    patch = st.bg.lin[pr0:pr1, pc0:pc1].copy()
    inner = (slice(r0 - pr0, r1 - pr0), slice(c0 - pc0, c1 - pc0))
    loc = patch[inner]
    if shadow_rect is not None:
        _floor_shadow(st, loc, win, shadow_rect, dyn, root_c)
    loc[dyn] = _shade(alb, nrm, st.light)
    patch = _blur(patch, st.spec.colour_blur)[inner]
    if not st.unit_gain:
        patch = patch * gain_t
    ws = (slice(r0, r1), slice(c0, c1))
    cv2.add(patch, noise.colour[ws], dst=colour_t[ws], dtype=cv2.CV_8U)


def _window_edge_prob(st: _Stage, win, zl, gb: rnd.GBuffer, dyn) -> np.ndarray:
    """Dropout probability of depth edges in the window, judged with a 1 px ring of the
    room around it; each dynamic primitive counts as a surface of its own."""
    r0, r1, c0, c1 = win
    er0, er1 = max(r0 - 1, 0), min(r1 + 1, HEIGHT)
    ec0, ec1 = max(c0 - 1, 0), min(c1 + 1, WIDTH)
    ze = st.bg.z_m[er0:er1, ec0:ec1].copy()
    ke = st.bg.gbuf.pid[er0:er1, ec0:ec1].copy()
    e_in = (slice(r0 - er0, r1 - er0), slice(c0 - ec0, c1 - ec0))
    ze[e_in] = zl
    ke[e_in] = np.where(dyn, gb.pid + 100000, ke[e_in])
    far, near = _edge_flags(ze, ke)
    return _edge_prob(far[e_in], near[e_in])


def _window_depth(st: _Stage, win, gb: rnd.GBuffer, dyn, nrm, ir, noise, missing, depth_t):
    """Depth inside the window: noise, dropouts and discontinuities of the dynamic
    surfaces; updates ``missing`` and ``depth_t`` in place."""
    bg, rays = st.bg, st.rays
    r0, r1, c0, c1 = win
    ws = (slice(r0, r1), slice(c0, c1))
    zl = np.where(dyn, gb.z, bg.gbuf.z[ws])
    zl = np.where(np.isfinite(zl), zl, 0.0).astype(np.float32)
    cosd = (
        np.abs(nrm[0] * rays.rx[ws][dyn] + nrm[1] * rays.ry[ws][dyn] + nrm[2]) / rays.norm[ws][dyn]
    )
    cos_l = bg.cos[ws].copy()
    cos_l[dyn] = cosd
    sigma_l = bg.sigma[ws].copy()
    sigma_l[dyn] = (
        kinect_v2_axial_sigma_mm(zl[dyn], np.arccos(np.clip(cosd, 0, 1))) * st.noise_scale
    )
    p_amp_l = bg.p_amp[ws].copy()
    p_amp_l[dyn] = _dropout_prob(ir, cosd, zl[dyn])
    p_edge_l = _window_edge_prob(st, win, zl, gb, dyn)
    zl_mm = zl * np.float32(1000.0)
    missing[ws] = (
        _static_missing(zl_mm, cos_l, st.spec.max_range_mm)
        | (noise.amp[ws] < p_amp_l)
        | (noise.edge[ws] < p_edge_l)
    )
    cv2.add(zl_mm, sigma_l * noise.depth[ws], dst=depth_t[ws], dtype=cv2.CV_16U)


def _render_window(
    st: _Stage,
    out: _Frames,
    t: int,
    win,
    shadow_rect,
    person_prims,
    occ_prims,
    materials,
    root_c,
    noise: _FrameNoise,
    missing,
) -> None:
    """Ray cast the dynamic objects into their window of frame ``t``: mask, joint
    visibility, colour and depth."""
    r0, r1, c0, c1 = win
    ws = (slice(r0, r1), slice(c0, c1))
    gb, out.unocc_count[t] = _raycast_window(st, win, person_prims, occ_prims)
    prims = person_prims + occ_prims
    dyn = gb.pid >= 0
    obj = np.array([p.object_id for p in prims])
    pmat = np.array([p.material for p in prims])
    ppart = np.array([p.part for p in prims])
    person = dyn & (obj[np.maximum(gb.pid, 0)] == 1)
    out.mask[t][ws] = person
    out.vis_count[t] = int(np.count_nonzero(person))
    _occluder_truth(st, out, t, win, gb, obj, occ_prims)
    _joint_visibility(out.joints3d[t], gb, obj, ppart, win, st.intr, out.joint_vis[t])
    nrm = gb.normal[:, dyn]
    alb, ir = _dynamic_albedo(gb, dyn, pmat, materials, st.tex)
    _shade_window(st, win, dyn, nrm, alb, shadow_rect, root_c, noise, out.colour[t], st.gain[t])
    _window_depth(st, win, gb, dyn, nrm, ir, noise, missing, out.depth[t])


def _render_frame(
    st: _Stage,
    walk: _Walk,
    dyn: _Dynamic,
    noise: _FrameNoise,
    t: int,
    walk_sign: float,
    out: _Frames,
) -> None:
    """Frame ``t``: pose the walker and the occluders, draw the noisy room, then render the
    dynamic objects inside the window they can touch."""
    spec, cam = st.spec, st.cam
    root_xz = walk.root_xz[t]
    pose = body.body_pose(root_xz, walk.heading_xz[t], walk.phase[t], spec.speed_mps, spec.height_m)
    out.joints3d[t] = cam.to_cam(pose.joints) * 1000.0
    person_prims = _person_prims(pose, spec.height_m, cam, 0, 1)
    occ_prims = _occluder_prims(spec, dyn, walk.t_s[t], walk_sign, cam)
    win, shadow_rect = _dynamic_window(
        person_prims + occ_prims, root_xz, cam, st.intr, HEIGHT, WIDTH
    )
    missing = _background_frame(st, noise, out.colour[t], out.depth[t], st.gain[t])
    if win is not None:
        root_c = cam.to_cam((root_xz[0], 0.0, root_xz[1])).astype(np.float32)
        materials = _frame_materials(spec, dyn, t)
        _render_window(
            st, out, t, win, shadow_rect, person_prims, occ_prims, materials, root_c, noise, missing
        )
    np.putmask(out.depth[t], missing, 0)
    if spec.colour_holes:
        out.colour[t][missing] = 0


def _render_frames(st: _Stage, walk: _Walk, dyn: _Dynamic, seed: int) -> _Frames:
    out = _allocate(walk.n_frames, len(st.spec.occluders))
    banks = _noise_banks(seed, st.spec.colour_noise)
    walk_sign = -1.0 if walk.heading_xz[0, 0] < 0 else 1.0  # the walker's initial x direction
    for t in range(walk.n_frames):
        _render_frame(st, walk, dyn, _frame_noise(banks, seed, t), t, walk_sign, out)
    return out


# ---------------------------------------------------------------------------------------------
# Ground truth.


def _tight_boxes(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([T, 4] float32 xywh, [T] bool)``: the tight box of each frame's mask, and whether
    it has a pixel; ``(0, 0, 0, 0)`` for an empty mask."""
    boxes = np.zeros((len(mask), 4), np.float32)
    rows_any = mask.any(axis=2)
    cols_any = mask.any(axis=1)
    visible = rows_any.any(axis=1)
    for t in np.nonzero(visible)[0]:
        r = np.nonzero(rows_any[t])[0]
        c = np.nonzero(cols_any[t])[0]
        boxes[t] = (c[0], r[0], c[-1] - c[0] + 1, r[-1] - r[0] + 1)
    return boxes, visible


def _project(joints3d: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """``[..., 3]`` camera points (mm) -> ``[..., 2] float32`` pixel ``(u, v)``."""
    return np.stack(
        [
            intr.fx * joints3d[..., 0] / joints3d[..., 2] + intr.cx,
            intr.fy * joints3d[..., 1] / joints3d[..., 2] + intr.cy,
        ],
        -1,
    ).astype(np.float32)


def _occlusion(vis_count: np.ndarray, unocc_count: np.ndarray):
    """``([T] float32 visible fraction, [T] int8 state)``: 0 none (>= 97 % visible),
    1 partial, 2 full or out of view."""
    vis_frac = (vis_count / np.maximum(unocc_count, 1)).astype(np.float32)
    occlusion = np.where(vis_frac >= 0.97, 0, np.where(vis_frac > 0.0, 1, 2)).astype(np.int8)
    occlusion[unocc_count == 0] = 2
    return vis_frac, occlusion


def _world_to_camera_mm(cam: _Camera) -> np.ndarray:
    """``[4, 4]`` homogeneous world (mm) -> camera (mm) transform."""
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = cam.R
    world_to_camera[:3, 3] = -cam.R @ cam.C * 1000.0
    return world_to_camera


def _meta(spec: ScenarioSpec, seed: int, st: _Stage, walk: _Walk, out: _Frames) -> dict:
    vis_frac, occlusion = _occlusion(out.vis_count, out.unocc_count)
    bg = st.bg
    return dict(
        spec=spec,
        seed=seed,
        # The empty room (no walker, no occluders, no sensor noise): a clean background
        # model for paths that never uncover the middle of the view ("away_back").
        background_colour=bg.u8,
        background_depth=np.where(bg.missing, 0, np.rint(bg.z_mm)).astype(np.uint16),
        camera_height_m=spec.camera_height_m,
        camera_pitch_deg=spec.camera_pitch_deg,
        world_to_camera_mm=_world_to_camera_mm(st.cam),
        up=st.cam.dir_to_cam(np.array([0.0, 1.0, 0.0])),
        joint_visible=out.joint_vis,
        visible_fraction=vis_frac,
        occlusion=occlusion,
        gain=st.gain,
        root_xz_m=walk.root_xz.astype(np.float32),
        heading_xz=walk.heading_xz.astype(np.float32),
        path_waypoints_m=np.asarray(walk.plan.waypoints),
        walk_length_m=walk.plan.walk_length,
        part_names=body.PART_NAMES,
        # Every occluder's ground truth, as the walker's: its tight box (xywh, zeros when
        # unseen), visible pixels and visible fraction (of its pixels with nothing else in
        # front; 0 when out of view), and its identity (``Occluder.identity``).
        occluder_boxes=out.occ_boxes,
        occluder_pixels=out.occ_count,
        occluder_visible_fraction=(out.occ_count / np.maximum(out.occ_unocc, 1)).astype(np.float32),
        occluder_identity=np.array(
            [2 + k if oc.identity is None else oc.identity for k, oc in enumerate(spec.occluders)],
            np.int64,
        ),
        box_convention="xywh top-left, 0-based, pixel c covers [c, c+1); tight box of mask",
    )


# ---------------------------------------------------------------------------------------------
# The generator.


def _resolve(name: str | ScenarioSpec, overrides: dict) -> tuple[str, ScenarioSpec]:
    if isinstance(name, ScenarioSpec):
        spec, label = name, "custom"
    else:
        if name not in SCENARIOS:
            raise KeyError(f"unknown scenario {name!r}; known: {sorted(SCENARIOS)}")
        spec, label = SCENARIOS[name], name
    fields = {f.name for f in dataclasses.fields(ScenarioSpec)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise TypeError(f"unknown ScenarioSpec field(s) {bad}; known: {sorted(fields)}")
    return label, dataclasses.replace(spec, **overrides)


def make_sequence(
    name: str | ScenarioSpec = "walk_across_medium",
    seed: int = 0,
    n_frames: int | None = None,
    **overrides: Any,
) -> SyntheticSequence:
    """Render a synthetic RGB-D sequence.

    name: a key of :data:`SCENARIOS` or a :class:`ScenarioSpec`. seed: layout, path
    direction/offset, gait phase and noise (frame ``t`` of a seed is the same whatever the
    sequence length). n_frames: default ``spec.n_frames``, clipped for single-pass paths
    so the person stays in view. overrides: :class:`ScenarioSpec` fields.

    The layout stream (``[seed, 0]``) draws the path, then the gait phase, the scene and
    the textures, in this order; noise and occluder phases have streams of their own.
    """
    label, spec = _resolve(name, overrides)
    fps = float(spec.fps)
    layout_rng = np.random.default_rng([seed, 0])
    cam = _camera(spec.camera_height_m, spec.camera_pitch_deg)
    walk = _walk(spec, layout_rng, n_frames, fps)
    scene = _scene(spec, cam, layout_rng, walk.keep_out)
    tex = _make_tex(layout_rng)
    dyn = _dynamic_objects(spec, seed)
    st = _stage(spec, cam, scene, tex, walk.n_frames, fps)
    out = _render_frames(st, walk, dyn, seed)
    boxes, visible = _tight_boxes(out.mask)
    return SyntheticSequence(
        out.colour,
        out.depth,
        boxes,
        visible,
        out.joints3d,
        _project(out.joints3d, st.intr),
        body.JOINT_NAMES,
        out.mask,
        st.intr,
        fps,
        label,
        _meta(spec, seed, st, walk, out),
    )


# ---------------------------------------------------------------------------------------------
# Consumers.


def iter_frames(seq: SyntheticSequence) -> Iterator[Frame]:
    """Yield one :class:`cpf_jax.types.Frame` (NumPy arrays) per time step."""
    for t in range(len(seq.colour)):
        yield Frame(colour=seq.colour[t], depth=seq.depth[t])


def stacked_frames(seq: SyntheticSequence) -> Frame:
    """All frames as one :class:`Frame` of ``[T, ...]`` arrays, ready for ``lax.scan``."""
    return Frame(colour=seq.colour, depth=seq.depth)


def contact_sheet(
    seq: SyntheticSequence, frames: tuple[int, ...] | None = None, scale: float = 0.5
) -> np.ndarray:
    """``[h, w, 3] uint8`` RGB overview: per chosen frame, colour (with the GT box and joints)
    above the colourised depth (missing = black)."""
    T = len(seq.colour)
    if frames is None:
        frames = tuple(int(round(x)) for x in np.linspace(0, T - 1, min(4, T)))
    cols = []
    for t in frames:
        rgb = cv2.cvtColor(seq.colour[t], cv2.COLOR_RGB2BGR)
        if seq.visible[t]:
            x, y, w, h = seq.boxes[t]
            cv2.rectangle(rgb, (int(x), int(y)), (int(x + w - 1), int(y + h - 1)), (0, 255, 0), 1)
        for j, (u, v) in enumerate(seq.joints2d[t]):
            c = (0, 255, 255) if seq.meta["joint_visible"][t, j] else (0, 0, 255)
            cv2.circle(rgb, (int(round(u)), int(round(v))), 3, c, -1)
        d = seq.depth[t].astype(np.float32)
        dc = cv2.applyColorMap(
            np.clip((d - 500) / 4000 * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO
        )
        dc[d == 0] = 0
        cv2.putText(
            rgb, f"{seq.name} t={t}", (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1
        )
        cols.append(np.concatenate([rgb, dc], axis=0))
    sheet = np.concatenate(cols, axis=1)
    sheet = cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(sheet, cv2.COLOR_BGR2RGB)


def to_folder(seq: SyntheticSequence, path: str | os.PathLike) -> str:
    """Write the recorded-folder layout and return ``path``.

    ``rgb/000000.png`` (8-bit RGB), ``depth/000000.png`` (16-bit, mm, 0 = missing),
    ``groundtruth_rect.txt`` (OTB: ``x,y,w,h`` per line, 1-based top-left, ``0,0,0,0`` when
    not visible), plus ``groundtruth_joints.npz`` (joints3d mm, joints2d, visible, names)
    and ``info.json`` (fps, intrinsics, scenario).
    """
    path = os.fspath(path)
    os.makedirs(os.path.join(path, "rgb"), exist_ok=True)
    os.makedirs(os.path.join(path, "depth"), exist_ok=True)
    for t in range(len(seq.colour)):
        cv2.imwrite(
            os.path.join(path, "rgb", f"{t:06d}.png"),
            cv2.cvtColor(seq.colour[t], cv2.COLOR_RGB2BGR),
        )
        cv2.imwrite(os.path.join(path, "depth", f"{t:06d}.png"), seq.depth[t])
    with open(os.path.join(path, "groundtruth_rect.txt"), "w") as fh:
        for box, vis in zip(seq.boxes, seq.visible, strict=True):
            if vis:
                x, y, w, h = (float(v) for v in box)
                fh.write(f"{x + 1:g},{y + 1:g},{w:g},{h:g}\n")
            else:
                fh.write("0,0,0,0\n")
    np.savez_compressed(
        os.path.join(path, "groundtruth_joints.npz"),
        joints3d=seq.joints3d,
        joints2d=seq.joints2d,
        visible=seq.visible,
        joint_names=np.array(seq.joint_names),
    )
    with open(os.path.join(path, "info.json"), "w") as fh:
        json.dump(
            dict(
                name=seq.name,
                fps=seq.fps,
                intrinsics=seq.intrinsics._asdict(),
                width=WIDTH,
                height=HEIGHT,
                depth_unit="mm",
                joint_names=list(seq.joint_names),
            ),
            fh,
            indent=1,
        )
    return path


def _main() -> None:
    """``python -m cpf_jax.synthetic [out.png]``: contact sheet of the main scenarios."""
    import sys

    out = sys.argv[1] if len(sys.argv) > 1 else "experiments/results/synthetic_contact_sheet.png"
    picks = [
        ("walk_across_medium", (10, 60)),
        ("walk_towards", (0, -1)),
        ("turn", (12,)),
        ("distractor_pass", (45,)),
    ]
    cols = []
    for name, frames in picks:
        seq = make_sequence(name, seed=0)
        frames = tuple(f % len(seq.colour) for f in frames)
        cols.append(contact_sheet(seq, frames, scale=0.5))
    sheet = np.concatenate(cols, axis=1)
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    cv2.imwrite(out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out} ({os.path.getsize(out) / 1e6:.2f} MB, {sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    _main()
