"""``cpf-track``'s model: the config, parameters, filter and context the command line asks
for (``--model`` and its options, ``--points`` for the cascade)."""

from __future__ import annotations

import argparse
import sys
import warnings
from typing import Any, NamedTuple

import numpy as np

from cpf_jax.cli.inputs import Inputs
from cpf_jax.cli.options import (
    AUTO_POINTS_MIN_CONFIDENCE,
    JOINT_DEPTH_OFFSET_MM,
    UsageError,
    param_options,
    parse_points,
)
from cpf_jax.filter import Context, Filter

__all__ = ["Model", "build_model"]


class Model(NamedTuple):
    """What ``cpf-track`` runs: one filter in the library's one shape, and its inputs."""

    config: Any  # ColourConfig, RGBDConfig or CascadeConfig
    params: Any
    filt: Filter
    context: Context
    n_particles: int  # of the box filter (layer 1)
    points: tuple[str, ...]  # names of the body points (empty without --points)


def logged(args: argparse.Namespace) -> bool:
    """Whether the run writes a Rerun log (which asks the filters for what it shows)."""
    return bool(args.rrd or args.spawn or args.connect)


def box_config(args: argparse.Namespace, options: tuple[dict, dict], box, frame_hw):
    """Layer 1's config and parameters: the colour layer for ``--model rgb``, else the
    RGB-D filter's variant, with a histogram window sized for the start box."""
    from cpf_jax.cascade import default_box_params
    from cpf_jax.colour import ColourConfig
    from cpf_jax.rgbd import RGBDConfig

    config_kw, colour_kw = options
    common = dict(
        n_particles=args.particles,
        hierarchical=not args.no_hierarchical,
        resampler=args.resampler,
        report_weights=logged(args),  # a logged run colours the particles by weight
        **config_kw,
    )
    if args.model == "rgb":
        config = ColourConfig(estimator=args.estimator, **common, **colour_kw)
    else:
        config = RGBDConfig(variant=args.model, body_term=not args.no_body_term, **common)
    config = config.with_window((float(box[2]), float(box[3])), frame_hw)
    return config, param_options(args, default_box_params(config))


def build_model(args: argparse.Namespace, source, inputs: Inputs, options) -> Model:
    """The filter ``cpf-track`` runs: layer 1 alone, or the cascade with ``--points``."""
    from cpf_jax.cascade import build_box_filter

    frame_hw = (source.size[1], source.size[0])
    config, params = box_config(args, options, inputs.box, frame_hw)
    background = None if args.model == "rgb" else inputs.background  # the colour layer has none
    if args.points is None:
        context = Context(background=background)
        return Model(config, params, build_box_filter(config), context, config.n_particles, ())
    return _cascade(args, source, inputs, config, params, background)


def _cascade(args, source, inputs: Inputs, layer1_config, box_params, background) -> Model:
    """The cascade of ``--points``: layer 2 on the box of layer 1, its points from
    ``joints``, ``auto`` or ``x,y;x,y;...``."""
    import jax.numpy as jnp

    from cpf_jax.cascade import CascadeConfig, build_cascade, check_points, default_cascade_params
    from cpf_jax.points import PointConfig
    from cpf_jax.rgbd import RGBDConfig

    if args.point_particles < 1:
        raise UsageError(f"--point-particles must be >= 1, got {args.point_particles}")
    # 3D estimates need the intrinsics of the frames' pixel grid: the colour camera's
    # after registration, else the source's own (Kinect v2 depth by default).
    calib = inputs.calibration
    intrinsics = calib.colour if calib is not None else source.intrinsics
    if intrinsics is None:
        intrinsics = _guessed_intrinsics(source)
    # Layer 2's body from the foreground: against the background model, or without one
    # against the frame's own scene that the RGB-D filter reads (cascade module docstring).
    frameless = isinstance(layer1_config, RGBDConfig) and layer1_config.side_scene is not None
    foreground = background is not None or frameless
    points_config = PointConfig(  # the log shows the body's surface
        n_particles=args.point_particles, intrinsics=intrinsics, report_surface=logged(args)
    )
    if foreground:
        points_config = points_config.with_foreground()
    config = CascadeConfig(box=layer1_config, points=points_config, foreground=foreground)
    if args.points == "auto":
        points, names = _auto_points(config, inputs, background)
    else:
        points, names = parse_points(args.points, source, inputs.start)
        points = check_points(points, (source.size[1], source.size[0]))
        if args.points != "joints":
            _check_points_in_box(points, inputs.box, inputs.start)
    params = default_cascade_params(config)._replace(box=box_params)
    if args.points in ("joints", "auto"):  # head, hands, feet: the joints lie behind
        offset = jnp.asarray(JOINT_DEPTH_OFFSET_MM, jnp.float32)
        estimate = params.points.estimate._replace(joint_depth_offset=offset)
        params = params._replace(points=params.points._replace(estimate=estimate))
    context = Context(background=background, points=jnp.asarray(points, jnp.float32))
    n = layer1_config.n_particles
    return Model(config, params, build_cascade(config), context, n, tuple(names))


def _guessed_intrinsics(source):
    """Intrinsics for a source that has none (``cpf_jax.types.nominal_intrinsics``), with a
    warning: the body points' millimetres rest on them."""
    from cpf_jax.errors import InputWarning
    from cpf_jax.types import nominal_intrinsics

    w, h = source.size
    k = nominal_intrinsics(w, h)
    what = "Kinect v2 depth's" if (w, h) == (512, 424) else "a 70 degree field of view's"
    warnings.warn(
        f"{source.describe()} has no intrinsics; assuming {what} "
        f"(fx = fy = {k.fx:g}, cx = {k.cx:g}, cy = {k.cy:g} for {w}x{h}), so the points' "
        'millimetres are rough; give {"intrinsics": {"fx", "fy", "cx", "cy"}} in the '
        "folder's calibration.json",
        InputWarning,
        stacklevel=2,
    )
    return k


def _check_points_in_box(points: np.ndarray, box: np.ndarray, start: int) -> None:
    """Points given as ``x,y`` lie in the start box (a tenth of its size of slack): layer 2
    tracks points on the body inside layer 1's box, not on the scene around it."""
    x, y, w, h = (float(v) for v in box)
    slack_x, slack_y = 0.1 * w, 0.1 * h
    inside = (
        (points[:, 0] >= x - slack_x)
        & (points[:, 0] <= x + w + slack_x)
        & (points[:, 1] >= y - slack_y)
        & (points[:, 1] <= y + h + slack_y)
    )
    if not inside.all():
        shown = "; ".join(f"{px:g},{py:g}" for px, py in points[~inside])
        raise UsageError(
            f"--points: {shown} outside the start box {x:g},{y:g},{w:g},{h:g} (frame {start}); "
            "layer 2 tracks points on the body inside layer 1's box"
        )


def _auto_points(config, inputs: Inputs, background):
    """``--points auto``: head, hands and feet found on the body in the start box
    (``cpf_jax.cascade.find_body_points``), printed on stderr; one error line when the box
    holds no body."""
    import jax
    import jax.numpy as jnp

    from cpf_jax.cascade import body_points_confidence, find_body_points
    from cpf_jax.points import AUTO_POINTS

    xy, reach = jax.jit(find_body_points, static_argnums=0)(
        config, inputs.first, jnp.asarray(inputs.box, jnp.float32), background
    )
    xy, reach = np.asarray(xy), np.asarray(reach)
    if not np.all(reach > 0):
        raise UsageError(
            f"--points auto: no body at the box's depth in frame {inputs.start}; give x,y;x,y;..."
        )
    confidence, doubts = body_points_confidence(reach)
    found = "; ".join(f"{n} {x:.0f},{y:.0f}" for n, (x, y) in zip(AUTO_POINTS, xy, strict=True))
    found = f"{found} in frame {inputs.start}, confidence {confidence:.2f}"
    if confidence < AUTO_POINTS_MIN_CONFIDENCE:
        raise UsageError(
            f"--points auto: found {found} (< {AUTO_POINTS_MIN_CONFIDENCE}: "
            f"{'; '.join(doubts)}); give the points as x,y;x,y;..."
        )
    print(f"--points auto: {found}", file=sys.stderr)
    for doubt in doubts:  # accepted, but the box may not show every part asked for
        print(f"--points auto: {doubt}", file=sys.stderr)
    return xy.astype(np.float32), AUTO_POINTS
