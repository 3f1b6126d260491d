"""The cascade: layer 1 tracks the person's box, layer 2 tracks points on the body
inside it, in one jitted step (thesis ch. 5, SPEC C4).

Usage::

    box = RGBDConfig(variant="grid-occlusion", n_particles=300)
    config = CascadeConfig(
        box=box.with_window(box_wh, frame_hw),  # without a window: exact but slower
        points=PointFilterConfig(n_particles=100, weighting="combined"),
    )
    filt = build_cascade(config)
    params = default_cascade_params(config)
    state = filt.init(params, key, frame, box_xywh, points_xy, background)
    state, info = filt.step(params, key, state, next_frame)
    # or a whole sequence as one lax.scan (vmap over keys, settings or sequences):
    state, infos = track_cascade(filt, params, key, frames, box_xywh, points_xy, background)

One frame (``step``): the layer-1 filter (``cpf_jax.rgbd.build_rgbd_filter``,
any variant: ``"rgb"`` is the colour layer of ``cpf_jax.colour``) steps on the
registered RGB-D frame; its box goes to the layer-2 point filter
(``cpf_jax.points.build_point_filter``), which cuts its fixed-size depth window
around the box (static shapes), segments the body there and moves the points'
particles with the box (``PointFilterConfig.follow_box``) before weighting them
by spin images and geodesic distances. Colour and depth share one pixel grid:
the frame is registered (synthetic Kinect-v2 frames are; a real recording goes
through ``cpf_jax.registration.register_frame``), and
``PointFilterConfig.intrinsics`` must be the intrinsics of that grid (the
depth camera's for Kinect-like frames, the colour camera's after registering
depth to colour) for the 3D estimates to be in millimetres.

Which box layer 2 gets (``CascadeConfig.box_source``): ``"estimate"`` (default),
the weighted-mean whole-body box, or ``"report"``, the box layer 1 scores
(``RGBDInfo.report``; for the grid variants a tight box of the visible pixels
while the target is partly occluded). Recovery: on a frame where layer 1 has
lost the target (``info.box.lost``), layer 2 keeps the last box layer 1 did
not lose, so the points stay where the body was last seen instead of following
a frame-wide search; the point filter's own recovery (every particle off the
body) still applies. ``info.box_used`` is the box layer 2 worked in.

With ``CascadeConfig.foreground`` and a background model, layer 2's body is
restricted to the foreground pixels (``kernels.background.foreground_mask``)
and takes the union of the sizeable components inside it
(``PointFilterConfig.min_component_fraction``), which keeps a side-on body
apart from a wall it touches in depth.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.kernels.background import Background, foreground_mask
from cpf_jax.points import (
    PointFilterConfig,
    PointInfo,
    PointInputs,
    PointParams,
    PointState,
    body_extremities,
    body_model,
    build_point_filter,
    default_point_params,
)
from cpf_jax.rgbd import RGBDConfig, RGBDInfo, RGBDParams, build_rgbd_filter, default_rgbd_params
from cpf_jax.types import Filter, Frame, memoised_build, scan_filter

__all__ = [
    "BOX_SOURCES",
    "CascadeConfig",
    "CascadeParams",
    "CascadeState",
    "CascadeInfo",
    "default_cascade_params",
    "build_cascade",
    "track_cascade",
    "check_points",
    "body_surface",
    "find_body_points",
]

BOX_SOURCES = ("estimate", "report")


@dataclasses.dataclass(frozen=True)
class CascadeConfig:
    """Static, hashable settings of both layers (changing one recompiles)."""

    box: RGBDConfig = RGBDConfig()
    points: PointFilterConfig = PointFilterConfig()
    box_source: str = "estimate"  # "estimate" | "report" (module docstring)
    # Layer 2's body only from foreground pixels of the background model (needs a
    # background at init; without one every pixel counts as foreground).
    foreground: bool = False
    # Thresholds of the foreground mask (kernels.background.foreground_mask).
    foreground_depth_mm: float = 150.0
    foreground_depth_rel: float = 0.05

    def __post_init__(self) -> None:
        if self.box_source not in BOX_SOURCES:
            raise ValueError(f"box_source must be one of {BOX_SOURCES}, got {self.box_source!r}")
        if not isinstance(self.box, RGBDConfig):
            raise TypeError(f"box must be an RGBDConfig, got {type(self.box).__name__}")
        if not isinstance(self.points, PointFilterConfig):
            raise TypeError(f"points must be a PointFilterConfig, got {type(self.points).__name__}")


class CascadeParams(NamedTuple):
    """Continuous parameters of both layers (a pytree; tunable as each layer's)."""

    box: RGBDParams
    points: PointParams


def default_cascade_params(config: CascadeConfig | None = None) -> CascadeParams:
    config = CascadeConfig() if config is None else config
    return CascadeParams(default_rgbd_params(config.box), default_point_params())


class CascadeState(NamedTuple):
    box: Any  # layer 1's state (RGBDState; ColourState for the "rgb" variant)
    points: PointState  # its ``box`` is the last box layer 2 worked in
    background: Background | None


class CascadeInfo(NamedTuple):
    box: RGBDInfo  # layer 1
    points: PointInfo  # layer 2
    box_used: Array  # [4] xywh, the box layer 2 worked in


def check_points(points_xy, frame_hw: tuple[int, int]) -> np.ndarray:
    """``[P, 2] float32`` initial points, or one clear ``ValueError``.

    Points are ``(x, y)`` frame pixels in the box convention (a pixel ``(r, c)``
    covers ``[c, c+1) x [r, r+1)``); each must be finite and inside the frame.
    """
    p = np.asarray(points_xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1:
        raise ValueError(f"points must be an array of shape [P, 2] with P >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"points must be finite, got {p.tolist()}")
    h, w = frame_hw
    outside = (p[:, 0] < 0) | (p[:, 0] >= w) | (p[:, 1] < 0) | (p[:, 1] >= h)
    if outside.any():
        bad = p[outside].tolist()
        raise ValueError(f"points outside the {w}x{h} frame: {bad}")
    return p.astype(np.float32)


def _point_inputs(
    config: CascadeConfig, frame: Frame, box: Array, background: Background | None
) -> PointInputs:
    """Layer 2's inputs for ``box``: the depth, and the foreground when configured."""
    fg = None
    if config.foreground and background is not None:
        fg = foreground_mask(
            frame.colour,
            frame.depth,
            background,
            depth_abs=config.foreground_depth_mm,
            depth_rel=config.foreground_depth_rel,
        )
    return PointInputs(frame.depth, box, fg)


def body_surface(
    config: CascadeConfig, frame: Frame, box_xywh: Array, background: Background | None = None
) -> Array:
    """``[Hw * Ww, 3]`` mm: camera-frame points of layer 2's segmented body in ``box_xywh``
    (the window, foreground and segmentation its step uses), NaN off the body.

    For display: ``cpf-track --points`` logs it to Rerun as ``world/body/surface`` with
    ``info.box_used``. Static shapes; jit it once (``config`` static). It repeats the
    step's pre-processing, so it costs about as much as a layer-2 step's segmentation.
    """
    box = jnp.asarray(box_xywh, jnp.float32)
    inp = _point_inputs(config, frame, box, background)
    bm = body_model(config.points, inp.depth, inp.box, inp.foreground)
    pts = jnp.where(bm.body[..., None], bm.points, jnp.nan)
    return pts.reshape(-1, 3)


def find_body_points(
    config: CascadeConfig, frame: Frame, box_xywh: Array, background: Background | None = None
) -> tuple[Array, Array]:
    """Points to start layer 2 on, found in the body inside ``box_xywh``: frame positions
    ``[5, 2]`` of ``cpf_jax.points.AUTO_POINTS`` (head, hands, feet) and the geodesic
    reach ``[4]`` mm of the hands and feet (``cpf_jax.points.body_extremities``).

    The body is segmented as a layer-2 step does it (window, foreground,
    components). ``cpf-track --points auto`` uses it on the start frame. Static
    shapes; jit it once (``config`` static).
    """
    box = jnp.asarray(box_xywh, jnp.float32)
    inp = _point_inputs(config, frame, box, background)
    bm = body_model(config.points, inp.depth, inp.box, inp.foreground)
    return body_extremities(config.points, bm)


@memoised_build
def build_cascade(config: CascadeConfig) -> Filter:
    """``Filter(init, step)`` of the two-layer cascade.

    ``init(params, key, frame, box_xywh, points_xy, background=None) -> state``
    and ``step(params, key, state, frame) -> (state, CascadeInfo)``.
    """
    layer1 = build_rgbd_filter(config.box)
    layer2 = build_point_filter(config.points)

    def inputs(frame: Frame, box: Array, background: Background | None) -> PointInputs:
        return _point_inputs(config, frame, box, background)

    def init(
        params: CascadeParams,
        key: Array,
        frame: Frame,
        box_xywh: Array,
        points_xy: Array,
        background: Background | None = None,
    ) -> CascadeState:
        k1, k2 = jax.random.split(key)
        box = jnp.asarray(box_xywh, jnp.float32)
        if background is not None:
            background = Background(
                jnp.asarray(background.colour, jnp.float32),
                jnp.asarray(background.depth, jnp.float32),
            )
        s1 = layer1.init(params.box, k1, frame, box, background)
        pts = jnp.asarray(points_xy, jnp.float32)
        s2 = layer2.init(params.points, k2, inputs(frame, box, background), pts)
        return CascadeState(s1, s2, background)

    def step(
        params: CascadeParams, key: Array, state: CascadeState, frame: Frame
    ) -> tuple[CascadeState, CascadeInfo]:
        k1, k2 = jax.random.split(key)
        s1, i1 = layer1.step(params.box, k1, state.box, frame)
        new_box = i1.estimate if config.box_source == "estimate" else i1.report
        box = jnp.where(i1.lost, state.points.box, new_box)
        s2, i2 = layer2.step(params.points, k2, state.points, inputs(frame, box, state.background))
        return CascadeState(s1, s2, state.background), CascadeInfo(i1, i2, box)

    return Filter(init=init, step=step)


def track_cascade(
    filt: Filter,
    params: CascadeParams,
    key: Array,
    frames: Frame,
    box_xywh: Array,
    points_xy: Array,
    background: Background | None = None,
):
    """A whole sequence as one ``lax.scan``: init on ``frames[0]`` with the box and
    points ``[P, 2]``, steps on ``1..T-1``. Returns ``(final_state, infos)`` with
    infos ``[T - 1, ...]``. Works under ``jit`` and ``vmap``."""
    return scan_filter(filt, params, key, frames, box_xywh, points_xy, background)
