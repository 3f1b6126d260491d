"""Randomised synthetic scenes for judging a tracker on footage nobody tuned it to.

:func:`draw_scene` draws every factor of a scene from its seed alone: the walker's size
in the image (40-400 px tall), an eye-level or a high (looking down) view, the path, the
speed and frame rate, the clothes, furniture, thin clutter (poles and signs), look-alike
walkers crossing in front of or behind the walker, lighting change, a partial occluder
and a moving camera (pan, follow, shake, zoom). :func:`make_random_sequence` renders it
with :func:`cpf_jax.synthetic.make_sequence` and then moves the camera.

The moving camera is a virtual one: each output frame is a crop of the rendered frame
(resampled to the full size), which is a pinhole camera whose principal point and focal
length change from frame to frame. A pan is therefore a rotation to first order (there is
no parallax), which holds for the small angles a handheld or panning camera turns through
between frames. The ground truth (boxes, mask, 2D joints) is moved with the pixels; the
per-frame intrinsics are in ``meta["intrinsics"]``.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from cpf_jax import synthetic
from cpf_jax.synthetic import Clothing, Occluder, ScenarioSpec, SyntheticSequence
from cpf_jax.types import KINECT_V2_DEPTH

__all__ = ["CameraMotion", "RandomScene", "draw_scene", "make_random_sequence", "move_camera"]

#: Height of the walker in metres, and the focal length times height in pixel-metres.
_HEIGHT_M = 1.75
_FOCAL_HEIGHT = KINECT_V2_DEPTH.fy * _HEIGHT_M


@dataclass(frozen=True)
class CameraMotion:
    """A virtual camera over a rendered sequence (sizes relative to the frame, motion in
    output pixels per frame).

    ``crop``: side of the crop at rest over the frame's side (1: the whole frame, no motion
    possible). ``follow``: how much the crop's centre follows the walker (0: not at all, 1:
    fully, with the lag of an exponential average of ``follow_lag`` frames). ``pan_px``: a
    steady sweep ``(x, y)``. ``shake_px``: standard deviation of a per-frame jitter.
    ``zoom``: relative amplitude of a sinusoidal change of the crop's size over
    ``zoom_period`` frames.
    """

    crop: float = 1.0
    follow: float = 0.0
    follow_lag: float = 6.0
    pan_px: tuple[float, float] = (0.0, 0.0)
    shake_px: float = 0.0
    zoom: float = 0.0
    zoom_period: float = 60.0

    @property
    def moves(self) -> bool:
        return self.crop < 1.0 and (
            self.follow > 0 or any(self.pan_px) or self.shake_px > 0 or self.zoom > 0
        )


@dataclass(frozen=True)
class RandomScene:
    """One drawn scene: what to render, how the camera moves, and the factors by name
    (categorical values, for per-factor tables; ``size`` and ``target_height_px`` here are
    the drawn ones, :func:`make_random_sequence` replaces them by the rendered median)."""

    seed: int
    spec: ScenarioSpec
    motion: CameraMotion
    n_frames: int
    factors: dict[str, Any]
    attempt: int = 0


def _random_colour(rng: np.random.Generator, dark: bool) -> tuple[int, int, int]:
    """An sRGB colour of random hue; ``dark`` keeps its value under 0.2."""
    h, s = rng.uniform(), rng.uniform(0.2, 0.9)
    v = rng.uniform(0.08, 0.2) if dark else rng.uniform(0.3, 0.9)
    return tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(h, s, v))


def _clothing(rng: np.random.Generator, dark: bool) -> Clothing:
    """The walker's clothes: a random top and trousers, both dark for ``dark``."""
    shirt = _random_colour(rng, dark)
    trousers = _random_colour(rng, dark or rng.uniform() < 0.5)
    return Clothing(shirt=shirt, trousers=trousers, long_sleeves=bool(rng.uniform() < 0.7))


def _look_alike(rng: np.random.Generator, cl: Clothing, similarity: float) -> Clothing:
    """Clothes that differ from ``cl`` by ``1 - similarity`` (:func:`synthetic._similar_colour`)."""
    top = synthetic._similar_colour(rng, cl.shirt, similarity)
    bottom = synthetic._similar_colour(rng, cl.trousers, similarity)
    return Clothing(shirt=tuple(int(c) for c in top), trousers=tuple(int(c) for c in bottom))


def _size_and_distance(rng: np.random.Generator, height_px: float) -> tuple[float, float]:
    """``(distance m, focal scale)`` that show a 1.75 m walker ``height_px`` tall, with the
    focal scale kept in ``[0.55, 1.5]`` and the distance in ``[1.8, 9]`` m."""
    lo = max(1.8, 0.55 * _FOCAL_HEIGHT / height_px)
    hi = min(9.0, 1.5 * _FOCAL_HEIGHT / height_px)
    d = float(rng.uniform(lo, max(lo, hi)))
    return d, float(np.clip(height_px * d / _FOCAL_HEIGHT, 0.55, 1.5))


def _walkers(rng, n: int, d: float, room: float, tan_fov: float, cl: Clothing, duration: float):
    """``n`` look-alike walkers crossing the whole view in front of (closer than) or behind
    the walker's path, each starting at its own time and fast enough to cross the view
    before the sequence ends; and how many pass in front."""
    out, in_front = [], 0
    for _ in range(n):
        front = d > 2.0 and rng.uniform() < 0.5
        z = rng.uniform(max(1.2, d - 1.0), d - 0.5) if front else rng.uniform(d + 0.6, room - 0.4)
        in_front += int(front)
        x0 = z * tan_fov + 0.4
        t0 = rng.uniform(0.0, 0.5 * duration)
        speed = min(max(rng.uniform(0.6, 1.4), 2 * x0 / (duration - t0)), 2.5)
        similar = _look_alike(rng, cl, rng.uniform(0.75, 0.95))
        out.append(
            Occluder(
                size_m=(0.5, rng.uniform(1.6, 1.9), 0.3),
                start_xz=(-x0, z),
                end_xz=(x0, z),
                t0_s=t0,
                t1_s=t0 + 2 * x0 / speed,
                kind="person",
                mirror_x=True,
                clothing=similar,
            )
        )
    return out, in_front


def _low_occluder(rng, d: float) -> Occluder:
    """A low box (a counter, a low wall) standing between the camera and the walk."""
    z = max(1.0, d - rng.uniform(0.4, 0.9))
    x = rng.uniform(-0.6, 0.6) * d * 0.5
    size = (rng.uniform(0.6, 1.6), rng.uniform(0.7, 1.2), 0.4)
    rgb = tuple(int(c) for c in synthetic._FURNITURE_COLOURS[rng.integers(13)])
    return Occluder(size_m=size, start_xz=(x, z), end_xz=(x, z), t0_s=0.0, t1_s=0.0, colour=rgb)


def _camera_motion(rng: np.random.Generator) -> tuple[CameraMotion, str]:
    """A camera that stays put (35 %), pans steadily, follows the walker, or shakes, each
    with an optional zoom; and its factor name."""
    kind = rng.choice(["static", "pan", "follow", "shake"], p=[0.35, 0.2, 0.25, 0.2])
    if kind == "static":
        return CameraMotion(), "static"
    crop = rng.uniform(0.7, 0.85)
    sweep = tuple(float(v) for v in rng.uniform(-1.0, 1.0, 2) * np.array([2.5, 0.6]))
    zoom = float(rng.uniform(0.05, 0.15)) if rng.uniform() < 0.4 else 0.0
    motion = CameraMotion(
        crop=crop,
        follow=float(rng.uniform(0.6, 1.0)) if kind == "follow" else 0.0,
        pan_px=sweep if kind == "pan" else (0.0, 0.0),
        shake_px=float(rng.uniform(1.5, 5.0)) if kind == "shake" else float(rng.uniform(0, 0.8)),
        zoom=zoom,
        zoom_period=float(rng.uniform(40, 90)),
    )
    return motion, f"{kind}+zoom" if zoom else str(kind)


def draw_scene(seed: int, attempt: int = 0) -> RandomScene:
    """Every factor of scene ``seed``, from the stream ``[seed, 77, attempt]`` alone
    (:func:`make_random_sequence` draws again, ``attempt + 1``, a scene in which the
    walker is never clear enough to start a track)."""
    rng = np.random.default_rng([seed, 77, attempt])
    motion, camera = _camera_motion(rng)
    height_px = float(np.exp(rng.uniform(np.log(40.0), np.log(400.0))))
    d, focal = _size_and_distance(rng, height_px * motion.crop)
    high = bool(rng.uniform() < 0.4)
    cam_h = rng.uniform(2.2, 2.6) if high else rng.uniform(1.0, 1.6)
    pitch = rng.uniform(22.0, 38.0) if high else rng.uniform(0.0, 10.0)
    path = str(rng.choice(["pace", "towards", "away", "turn"], p=[0.55, 0.15, 0.15, 0.15]))
    # A single pass (towards, away, turn) lasts a few seconds: at 10 frames/s too few frames.
    fps = float(rng.choice([10.0, 15.0, 30.0] if path == "pace" else [15.0, 30.0, 30.0]))
    speed = float(rng.uniform(0.5, 1.5))
    n_frames = 100
    dark = bool(rng.uniform() < 0.3)
    cl = _clothing(rng, dark)
    room = max(4.4, d + 2.0)
    tan_fov = KINECT_V2_DEPTH.cx / (KINECT_V2_DEPTH.fx * focal)
    half = max(3.2, 0.6 * room * tan_fov + 0.5)
    n_poles = int(rng.choice([0, 0, 2, 4, 6]))
    n_alike = int(rng.choice([0, 0, 1, 2]))
    walkers, in_front = _walkers(rng, n_alike, d, room, tan_fov, cl, n_frames / fps)
    partial = bool(rng.uniform() < 0.3)
    occluders = tuple(walkers) + ((_low_occluder(rng, d),) if partial else ())
    light = str(rng.choice(["none", "none", "drift", "switch"]))
    spec = ScenarioSpec(
        path=path,
        speed_mps=speed,
        fps=fps,
        n_frames=n_frames,
        distance_m=d,
        near_m=max(1.4, d - 1.5),
        far_m=min(d + 1.5, room - 0.3),
        clothing=cl,
        clutter=int(rng.integers(4, 13)),
        clutter_match=float(rng.uniform(0.0, 0.5)),
        distractor_similarity=float(rng.uniform(0.6, 0.95)),
        backdrop=str(rng.choice(["low", "full"])),
        illumination=light,
        illumination_strength=float(rng.uniform(0.2, 0.5)),
        camera_height_m=float(cam_h),
        camera_pitch_deg=float(pitch),
        room_depth_m=float(room + 0.5),
        room_half_width_m=float(half),
        poles=n_poles,
        occluders=occluders,
        focal_scale=focal,
    )
    factors = {
        "size": "small" if height_px < 80 else "large" if height_px > 200 else "medium",
        "view": "high" if high else "eye",
        "camera": camera,
        "path": path,
        "thin_clutter": "poles" if n_poles else "none",
        "look_alikes": "in_front" if in_front else "behind" if n_alike else "none",
        "lighting": light,
        "partial_occlusion": "yes" if partial else "no",
        "dark_clothes": "yes" if dark else "no",
        "target_height_px": round(height_px, 1),
    }
    return RandomScene(seed, spec, motion, n_frames, factors, attempt)


def _crop_path(boxes: np.ndarray, visible: np.ndarray, motion: CameraMotion, rng, hw):
    """``[T, 4]`` crops ``(x0, y0, w, h)`` in the rendered frame, kept inside it."""
    H, W = hw
    T = len(boxes)
    t = np.arange(T, dtype=np.float64)
    scale = motion.crop * (1.0 + motion.zoom * np.sin(2 * np.pi * t / motion.zoom_period))
    cw, ch = W * np.minimum(scale, 1.0), H * np.minimum(scale, 1.0)
    centres = boxes[:, :2] + boxes[:, 2:] / 2
    last = np.array([W / 2, H / 2])
    smooth = np.empty((T, 2))
    alpha = 1.0 / max(motion.follow_lag, 1.0)
    for i in range(T):
        if visible[i]:
            last = last + alpha * (centres[i] - last) if i else centres[i]
        smooth[i] = last
    rest = np.array([W / 2, H / 2])
    centre = rest + motion.follow * (smooth - rest)
    sweep = np.asarray(motion.pan_px) * t[:, None] * (cw / W)[:, None]
    shake = rng.normal(0.0, motion.shake_px, (T, 2)) * (cw / W)[:, None]
    centre = centre + shake
    x0 = _bounce(centre[:, 0] - cw / 2 + sweep[:, 0], W - cw)
    y0 = _bounce(centre[:, 1] - ch / 2 + sweep[:, 1], H - ch)
    return np.stack([x0, y0, cw, ch], axis=1)


def _bounce(x: np.ndarray, top: np.ndarray) -> np.ndarray:
    """``x`` reflected into ``[0, top]`` (a sweep that turns back at the edges)."""
    top = np.maximum(top, 1e-6)
    period = np.mod(x, 2 * top)
    return np.where(period > top, 2 * top - period, period)


def _warp(img: np.ndarray, crop, interp: int) -> np.ndarray:
    """The crop ``(x0, y0, w, h)`` of ``img`` resampled to ``img``'s size (pixel centres
    at integer coordinates)."""
    H, W = img.shape[:2]
    x0, y0, cw, ch = crop
    sx, sy = cw / W, ch / H
    m = np.array([[sx, 0.0, x0 + 0.5 * sx - 0.5], [0.0, sy, y0 + 0.5 * sy - 0.5]])
    flags = interp | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(img, m, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def _warp_all(frames: np.ndarray, crops: np.ndarray, interp: int) -> np.ndarray:
    """Every frame ``t`` of ``frames`` warped by its crop ``crops[t]``."""
    return np.stack([_warp(frames[t], crops[t], interp) for t in range(len(frames))])


def move_camera(seq: SyntheticSequence, motion: CameraMotion, seed: int) -> SyntheticSequence:
    """``seq`` seen through the virtual camera ``motion`` (module docstring); the same
    sequence when the camera does not move. Adds ``meta["crop_xywh"]`` ``[T, 4]`` and
    ``meta["intrinsics"]`` ``[T, 4]`` ``(fx, fy, cx, cy)``."""
    if not motion.moves:
        return seq
    T, H, W = seq.depth.shape
    crops = _crop_path(seq.boxes, seq.visible, motion, np.random.default_rng([seed, 78]), (H, W))
    colour = _warp_all(seq.colour, crops, cv2.INTER_LINEAR)
    depth = _warp_all(seq.depth, crops, cv2.INTER_NEAREST)
    mask = _warp_all(seq.mask.astype(np.uint8), crops, cv2.INTER_NEAREST) > 0
    boxes, visible = synthetic._tight_boxes(mask)
    sx, sy = W / crops[:, 2], H / crops[:, 3]
    k = seq.intrinsics
    intr = np.stack(
        [
            k.fx * sx,
            k.fy * sy,
            (k.cx + 0.5 - crops[:, 0]) * sx - 0.5,
            (k.cy + 0.5 - crops[:, 1]) * sy - 0.5,
        ],
        axis=1,
    ).astype(np.float32)
    j2 = seq.joints2d
    joints2d = np.stack(
        [
            (j2[..., 0] + 0.5 - crops[:, None, 0]) * sx[:, None] - 0.5,
            (j2[..., 1] + 0.5 - crops[:, None, 1]) * sy[:, None] - 0.5,
        ],
        axis=-1,
    ).astype(j2.dtype)
    meta = dict(seq.meta, crop_xywh=crops.astype(np.float32), intrinsics=intr, camera_motion=motion)
    first = type(k)(*(float(v) for v in intr[0]))
    return seq._replace(
        colour=colour,
        depth=depth,
        boxes=boxes,
        visible=visible,
        mask=mask,
        joints2d=joints2d,
        intrinsics=first,
        meta=meta,
    )


#: Per-frame entries of a sequence's ``meta``.
_PER_FRAME_META = (
    "joint_visible",
    "visible_fraction",
    "occlusion",
    "gain",
    "root_xz_m",
    "heading_xz",
    "crop_xywh",
    "intrinsics",
)


def _first_clear_frame(rendered: SyntheticSequence, moved: SyntheticSequence) -> int | None:
    """The first frame where at least 60 % of the walker is unoccluded by the occluders,
    his head and his torso or pelvis are seen (joint visibility, which counts what the
    room's poles and signs hide too, and which these joints keep whatever way he faces),
    at least 90 % of him is inside the moved camera's view, and his box is 10 px tall and
    clear of the frame's edges: a tracker's start box; None when there is no such frame."""
    if moved is rendered:
        in_view = np.ones(len(rendered.mask), bool)
    else:
        crops = moved.meta["crop_xywh"]
        zoom = (rendered.mask.shape[2] / crops[:, 2]) * (rendered.mask.shape[1] / crops[:, 3])
        kept = moved.mask.sum(axis=(1, 2)) / np.maximum(rendered.mask.sum(axis=(1, 2)) * zoom, 1)
        in_view = kept >= 0.9
    visible = np.moveaxis(rendered.meta["joint_visible"], 1, 0)
    seen = dict(zip(rendered.joint_names, visible, strict=True))
    head = seen["head_top"] & seen["head"]
    joints_seen = head & (seen["torso"] | seen["pelvis"])
    unoccluded = (rendered.meta["visible_fraction"] >= 0.6) & joints_seen
    x, y, w, h = moved.boxes.T
    height, width = moved.mask.shape[1:]
    inside = (x > 0) & (y > 0) & (x + w < width) & (y + h < height)
    clear = unoccluded & in_view & inside & (h >= 10)
    hits = np.flatnonzero(clear)
    return int(hits[0]) if len(hits) else None


def _from_frame(seq: SyntheticSequence, start: int) -> SyntheticSequence:
    """``seq`` from frame ``start`` on."""
    if start == 0:
        return seq
    cut = slice(start, None)
    meta = dict(seq.meta, start_frame=start)
    for k in _PER_FRAME_META:
        if k in meta:
            meta[k] = meta[k][cut]
    return seq._replace(
        colour=seq.colour[cut],
        depth=seq.depth[cut],
        boxes=seq.boxes[cut],
        visible=seq.visible[cut],
        joints3d=seq.joints3d[cut],
        joints2d=seq.joints2d[cut],
        mask=seq.mask[cut],
        meta=meta,
    )


#: Draws of one seed before :func:`make_random_sequence` gives up.
MAX_ATTEMPTS = 8


def _render(scene: RandomScene) -> tuple[SyntheticSequence, int | None]:
    rendered = synthetic.make_sequence(scene.spec, seed=scene.seed)
    moved = move_camera(rendered, scene.motion, scene.seed)
    return moved, _first_clear_frame(rendered, moved)


def make_random_sequence(scene: int | RandomScene) -> SyntheticSequence:
    """Render scene ``scene`` (a seed or a drawn :class:`RandomScene`), move its camera,
    and start it at the first frame where the walker is clear enough to be given as a
    start box (``_first_clear_frame``; ``meta["start_frame"]`` says which). A seed whose
    walker is never clear is drawn again (``draw_scene(seed, attempt)``); a given scene
    whose walker is never clear is a ``ValueError``."""
    if isinstance(scene, RandomScene):
        moved, start = _render(scene)
        if start is None:
            raise ValueError(f"scene {scene.seed}: the walker is never clear enough to start")
    else:
        for attempt in range(MAX_ATTEMPTS):
            drawn = draw_scene(int(scene), attempt)
            moved, start = _render(drawn)
            if start is not None:
                break
        else:
            raise ValueError(f"scene {scene}: no clear start in {MAX_ATTEMPTS} draws")
        scene = drawn
    seq = _from_frame(moved, start)
    heights = seq.boxes[seq.visible, 3]
    height = float(np.median(heights)) if len(heights) else 0.0
    size = "small" if height < 80 else "large" if height > 200 else "medium"
    factors = dict(scene.factors, size=size, target_height_px=height)
    meta = dict(seq.meta, factors=factors, attempt=scene.attempt)
    return seq._replace(name=f"random_{scene.seed}", meta=meta)
