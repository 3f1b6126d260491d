"""The cascade (thesis ch. 5, SPEC C4): layer 1 tracks the person's box, layer 2 tracks
points on the body inside it, in one jitted step.

::

    config = CascadeConfig(box=RGBDConfig().with_window(box[2:], frame_hw), points=PointConfig())
    filt = build_cascade(config)
    params = default_cascade_params(config)
    state = filt.init(params, key, frame, box, Context(background=bg, points=points_xy))
    state, info = filt.step(params, key, state, frame)   # info.box, info.points.mean3d

Layer 1 is any box filter (``ColourConfig`` or ``RGBDConfig``); its box goes to the point
filter, which cuts its fixed-size depth window around it (static shapes), segments the
body and moves its particles with the box. Colour and depth share one pixel grid (the
frame is registered), and ``PointConfig.intrinsics`` must be that grid's for the 3D
estimates to be millimetres.

Which box layer 2 gets (``box_source``): ``"estimate"``, layer 1's weighted mean (the
whole body), or ``"report"``, the box layer 1 scores (``info.box``; for the grid
variants a tight box of the visible pixels). While layer 1 has lost the target, layer 2
keeps the last box it had, so that the points stay where the body was last seen. With
``foreground`` layer 2's body is limited to foreground pixels against the background
model: layer 1's own (which sees its background updates) when layer 1 is the RGB-D
filter, with the frame's own scene behind its unseen pixels as layer 1 sees it
(``rgbd.filter.unseen_scene``, ``RGBDConfig.side_scene``; without background frames every
pixel is unseen), else ``context.background``. Layer 2 also gets the RGB-D filter's target
depth (``layer1_target_depth``), which anchors the body with ``PointConfig.joined_anchor =
"depth"``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.colour import ColourConfig, ColourParams, build_colour_filter, default_colour_params
from cpf_jax.filter import Cloud, Context, Filter, memoised_build
from cpf_jax.kernels.background import Background, foreground_mask
from cpf_jax.points import (
    PointConfig,
    PointFrame,
    PointInfo,
    PointParams,
    PointState,
    body_extremities,
    body_model,
    body_points_3d,
    build_point_filter,
    default_point_params,
)
from cpf_jax.rgbd import RGBDConfig, RGBDParams, build_rgbd_filter, default_rgbd_params
from cpf_jax.rgbd import filter as rgbd_filter
from cpf_jax.rgbd.filter import unseen_scene
from cpf_jax.types import Frame

__all__ = [
    "BOX_SOURCES",
    "CascadeConfig",
    "CascadeParams",
    "CascadeState",
    "CascadeInfo",
    "build_box_filter",
    "default_box_params",
    "default_cascade_params",
    "build_cascade",
    "check_points",
    "layer2_frame",
    "body_surface",
    "scene_for_layer2",
    "layer1_target_depth",
    "layer2_from_layer1",
    "find_body_points",
    "body_points_confidence",
]

BOX_SOURCES = ("estimate", "report")


def build_box_filter(config: ColourConfig | RGBDConfig) -> Filter:
    """The box filter of a layer-1 config: the colour layer or the RGB-D filter."""
    if isinstance(config, ColourConfig):
        return build_colour_filter(config)
    if isinstance(config, RGBDConfig):
        return build_rgbd_filter(config)
    raise TypeError(
        f"a box filter needs a ColourConfig or an RGBDConfig, got {type(config).__name__}"
    )


def default_box_params(config: ColourConfig | RGBDConfig) -> ColourParams | RGBDParams:
    """The default parameters of a layer-1 config."""
    if isinstance(config, ColourConfig):
        return default_colour_params()
    return default_rgbd_params(config)


@dataclasses.dataclass(frozen=True)
class CascadeConfig:
    """Static, hashable settings of both layers."""

    box: ColourConfig | RGBDConfig = RGBDConfig()
    points: PointConfig = PointConfig()
    box_source: str = "estimate"  # "estimate" | "report" (module docstring)
    # Layer 2's body only from foreground pixels of the background model.
    foreground: bool = False
    # Thresholds of that foreground mask (kernels.background.foreground_mask).
    foreground_depth_mm: float = 150.0
    foreground_depth_rel: float = 0.05

    def __post_init__(self) -> None:
        if self.box_source not in BOX_SOURCES:
            raise ValueError(f"box_source must be one of {BOX_SOURCES}, got {self.box_source!r}")
        if not isinstance(self.box, ColourConfig | RGBDConfig):
            raise TypeError(
                f"box must be a ColourConfig or an RGBDConfig, got {type(self.box).__name__}"
            )
        if not isinstance(self.points, PointConfig):
            raise TypeError(f"points must be a PointConfig, got {type(self.points).__name__}")

    @property
    def layer1_background(self) -> bool:
        """Whether layer 1 keeps the background model in its state (the RGB-D filter)."""
        return isinstance(self.box, RGBDConfig)


class CascadeParams(NamedTuple):
    box: ColourParams | RGBDParams
    points: PointParams


def default_cascade_params(config: CascadeConfig | None = None) -> CascadeParams:
    config = CascadeConfig() if config is None else config
    return CascadeParams(default_box_params(config.box), default_point_params())


class CascadeState(NamedTuple):
    box: Any  # layer 1's state
    points: PointState  # its ``box`` is the last box layer 2 worked in
    background: Background | None  # the context's background when layer 1 keeps none

    @property
    def cloud(self) -> Cloud:
        """Layer 1's particle cloud."""
        return self.box.cloud


class CascadeInfo(NamedTuple):
    box: Array  # [4] xywh, layer 1's box
    lost: Array
    ess: Array
    log_evidence: Array
    estimate: Array  # [4] xywh, layer 1's estimate
    windowed: Array
    layer1: Any  # layer 1's whole info
    points: PointInfo  # layer 2
    box_used: Array  # [4] xywh, the box layer 2 worked in

    @property
    def weighed_cloud(self):
        """Layer 1's particles before resampling (``report_weights``), or None."""
        return self.layer1.weighed_cloud


def check_points(points_xy, frame_hw: tuple[int, int]) -> np.ndarray:
    """``[P, 2] float32`` initial points, or one clear ``ValueError``: each must be finite
    and inside the frame (frame pixels, box convention)."""
    p = np.asarray(points_xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1:
        raise ValueError(f"points must be an array of shape [P, 2] with P >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"points must be finite, got {p.tolist()}")
    h, w = frame_hw
    outside = (p[:, 0] < 0) | (p[:, 0] >= w) | (p[:, 1] < 0) | (p[:, 1] >= h)
    if outside.any():
        raise ValueError(f"points outside the {w}x{h} frame: {p[outside].tolist()}")
    return p.astype(np.float32)


def layer1_target_depth(box_config: ColourConfig | RGBDConfig, s1) -> Array | None:
    """``[]`` mm: the target's depth in layer 1's state ``s1`` as the RGB-D filter reads it
    (``rgbd.filter.target_depth``, the median of its known depth templates; 0: none known;
    they learn only from cells voted visible, so someone passing in front does not move
    them); None for the colour layer."""
    if not isinstance(box_config, RGBDConfig):
        return None
    return rgbd_filter.target_depth(s1.depth.depth)


def layer2_frame(
    config: CascadeConfig,
    frame: Frame,
    box: Array,
    background: Background | None,
    target_depth: Array | None = None,
) -> PointFrame:
    """Layer 2's frame for ``box``: the depth, the foreground when configured, and the
    target's depth (``layer1_target_depth``) that anchors the body."""
    fg = None
    if config.foreground and background is not None:
        fg = foreground_mask(
            frame.colour,
            frame.depth,
            background,
            depth_abs=config.foreground_depth_mm,
            depth_rel=config.foreground_depth_rel,
        )
    return PointFrame(frame.depth, box, fg, target_depth)


def layer2_from_layer1(
    config: CascadeConfig, own: Background | None, s1, frame: Frame, box: Array
) -> PointFrame:
    """Layer 2's frame for ``box`` given layer 1's state ``s1`` on ``frame``: the foreground
    against layer 1's background (``own`` when layer 1 keeps none; module docstring) and the
    target's depth (``layer1_target_depth``)."""
    bg2 = _layer2_background(config, own, s1, frame)
    return layer2_frame(config, frame, box, bg2, layer1_target_depth(config.box, s1))


def _background(context: Context | None) -> Background | None:
    if context is None or context.background is None:
        return None
    return Background(
        jnp.asarray(context.background.colour, jnp.float32),
        jnp.asarray(context.background.depth, jnp.float32),
    )


def scene_for_layer2(
    config: CascadeConfig, frame: Frame, box: Array, background: Background | None
) -> Background | None:
    """The background layer 2 reads in ``frame`` for ``box`` outside a step: ``background``,
    or without one, when layer 1 is the RGB-D filter reading each frame's own scene, that
    scene as layer 1 starts on ``box`` (``_layer2_background``)."""
    if background is not None or not config.layer1_background or config.box.side_scene is None:
        return background
    s1 = build_box_filter(config.box).init(
        default_box_params(config.box), jax.random.PRNGKey(0), frame, box
    )
    return _layer2_background(config, None, s1, frame)


def body_surface(
    config: CascadeConfig, frame: Frame, box: Array, background: Background | None = None
) -> Array:
    """``[Hw * Ww, 3]`` mm: camera-frame points of layer 2's segmented body in ``box`` (NaN
    off the body), as a step sees it; for display (``cpf-track`` logs it to Rerun)."""
    box = jnp.asarray(box, jnp.float32)
    inp = layer2_frame(config, frame, box, scene_for_layer2(config, frame, box, background))
    return body_points_3d(body_model(config.points, inp.depth, inp.box, inp.foreground))


def find_body_points(
    config: CascadeConfig, frame: Frame, box: Array, background: Background | None = None
) -> tuple[Array, Array]:
    """Points to start layer 2 on, found on the body in ``box``: ``[5, 2]`` frame positions
    of ``AUTO_POINTS`` and the reach ``[4]`` mm of the hands and feet
    (``points.body_extremities``)."""
    box = jnp.asarray(box, jnp.float32)
    inp = layer2_frame(config, frame, box, scene_for_layer2(config, frame, box, background))
    bm = body_model(config.points, inp.depth, inp.box, inp.foreground)
    return body_extremities(config.points, bm)


# The farthest limb of a whole body lies at least this far (mm, geodesic from the head or
# the centroid, ``find_body_points``) along its surface; a box with only head and shoulders
# has its "feet" at the shoulders, at most about 600 mm.
WHOLE_BODY_REACH_MM = 900.0
NO_BODY_REACH_MM = 500.0


def body_points_confidence(reach) -> tuple[float, tuple[str, ...]]:
    """``(confidence, doubts)`` that ``find_body_points``'s ``reach [4]`` mm belong to a
    whole body in the box: the farthest limb's reach, 0 at ``NO_BODY_REACH_MM`` and 1 from
    ``WHOLE_BODY_REACH_MM``, and in words what lowered it."""
    far = float(np.max(reach))
    share = float(
        np.clip((far - NO_BODY_REACH_MM) / (WHOLE_BODY_REACH_MM - NO_BODY_REACH_MM), 0, 1)
    )
    doubts = ()
    if share < 1:
        doubts = (
            f"the farthest limb is {far:.0f} mm from the body's centre, and a whole body's "
            f"reaches {WHOLE_BODY_REACH_MM:.0f} mm: is all of it in the box?",
        )
    return share, doubts


def _layer2_background(
    config: CascadeConfig, own: Background | None, s1, frame: Frame
) -> Background | None:
    """The background layer 2's foreground is taken against (module docstring): layer 1's
    state's, its unseen pixels given the frame's scene around layer 1's estimate ``s1``."""
    if not config.layer1_background:
        return own
    if config.box.side_scene is None:
        return s1.background
    return unseen_scene(config.box, s1.background, frame, s1.estimate, s1.depth.depth)


@memoised_build
def build_cascade(config: CascadeConfig) -> Filter:
    """The two-layer cascade's ``Filter(init, step)``; ``init`` reads ``context.points``
    and ``context.background``."""
    layer1 = build_box_filter(config.box)
    layer2 = build_point_filter(config.points)

    def init(params, key, frame, box, context=None):
        k1, k2 = jax.random.split(key)
        box = jnp.asarray(box, jnp.float32)
        background = _background(context)
        points = None if context is None else context.points
        s1 = layer1.init(params.box, k1, frame, box, Context(background=background))
        own = None if config.layer1_background else background
        inp = layer2_from_layer1(config, own, s1, frame, box)
        s2 = layer2.init(params.points, k2, inp, box, Context(points=points))
        return CascadeState(s1, s2, own)

    def step(params, key, state, frame):
        k1, k2 = jax.random.split(key)
        s1, i1 = layer1.step(params.box, k1, state.box, frame)
        new_box = i1.estimate if config.box_source == "estimate" else i1.box
        box = jnp.where(i1.lost, state.points.box, new_box)
        inp = layer2_from_layer1(config, state.background, s1, frame, box)
        s2, i2 = layer2.step(params.points, k2, state.points, inp)
        common = (i1.box, i1.lost, i1.ess, i1.log_evidence, i1.estimate, i1.windowed)
        info = CascadeInfo(*common, i1, i2, box)
        return CascadeState(s1, s2, state.background), info

    return Filter(init, step)
