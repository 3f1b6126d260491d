"""Every filter follows the one shape of ``cpf_jax.filter``: the same ``init`` / ``step``
signatures, every box filter's info starting with ``BOX_INFO_FIELDS`` and its state holding
a ``Cloud``, one ``track`` for all; and every parameter tree matches its ``Prop`` tree.

Shapes are checked with ``jax.eval_shape`` (a trace, no compile), so every variant is
covered at the cost of tracing it.
"""

from __future__ import annotations

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cpf_jax
from cpf_jax import params as pp
from cpf_jax.cascade import CascadeConfig, build_cascade, default_cascade_params
from cpf_jax.colour import COLOUR_PROPS, ColourConfig, build_colour_filter, default_colour_params
from cpf_jax.filter import BOX_INFO_FIELDS, Cloud, Context, Filter, track, track_boxes
from cpf_jax.kernels.background import Background
from cpf_jax.points import (
    POINT_PROPS,
    PointConfig,
    PointFrame,
    build_point_filter,
    default_point_params,
)
from cpf_jax.rgbd import VARIANTS, RGBDConfig, build_rgbd_filter, default_rgbd_params, rgbd_props
from cpf_jax.types import Frame, nominal_intrinsics

H, W, T, N = 96, 128, 4, 16
INTRINSICS = nominal_intrinsics(W, H)  # the point filter checks them against the frame
BOX = np.array([40.0, 20.0, 30.0, 60.0], np.float32)
POINTS = np.array([[55.0, 30.0], [50.0, 70.0]], np.float32)


def _frames(t: int = T) -> Frame:
    colour = jax.ShapeDtypeStruct((t, H, W, 3), jnp.uint8)
    depth = jax.ShapeDtypeStruct((t, H, W), jnp.uint16)
    return Frame(colour, depth)


def _background() -> Background:
    return Background(
        jax.ShapeDtypeStruct((H, W, 3), jnp.float32), jax.ShapeDtypeStruct((H, W), jnp.float32)
    )


BOX_FILTERS = {
    "colour": (ColourConfig(n_particles=N), build_colour_filter, lambda c: default_colour_params()),
    **{
        f"rgbd-{v}": (RGBDConfig(variant=v, n_particles=N), build_rgbd_filter, default_rgbd_params)
        for v in VARIANTS
    },
    "cascade-rgbd": (
        CascadeConfig(
            box=RGBDConfig(n_particles=N), points=PointConfig(n_particles=8, intrinsics=INTRINSICS)
        ),
        build_cascade,
        default_cascade_params,
    ),
    "cascade-colour": (
        CascadeConfig(
            box=ColourConfig(n_particles=N),
            points=PointConfig(n_particles=8, intrinsics=INTRINSICS),
        ),
        build_cascade,
        default_cascade_params,
    ),
}


@pytest.mark.parametrize("name", [*BOX_FILTERS, "points"])
def test_every_builder_returns_the_one_filter_shape(name):
    if name == "points":
        config, build = PointConfig(n_particles=8, intrinsics=INTRINSICS), build_point_filter
    else:
        config, build, _ = BOX_FILTERS[name]
    filt = build(config)
    assert isinstance(filt, Filter)
    init = inspect.signature(filt.init).parameters
    step = inspect.signature(filt.step).parameters
    assert list(init) == ["params", "key", "frame", "box", "context"]
    assert init["context"].default is None
    assert list(step) == ["params", "key", "state", "frame"]
    # Equal configs give the same Filter (JAX's caches key on the function objects).
    assert build(config) is filt


@pytest.mark.parametrize("name", list(BOX_FILTERS))
def test_box_filters_share_their_info_fields_state_cloud_and_track(name):
    config, build, default = BOX_FILTERS[name]
    filt, params = build(config), default(config)
    context = Context(background=_background(), points=POINTS)
    key = jax.random.PRNGKey(0)
    state, infos = jax.eval_shape(
        lambda f, b, c: track(filt, params, key, f, b, c), _frames(), BOX, context
    )
    assert infos._fields[: len(BOX_INFO_FIELDS)] == BOX_INFO_FIELDS
    assert infos.box.shape == (T - 1, 4) and infos.estimate.shape == (T - 1, 4)
    for field in ("lost", "ess", "log_evidence", "windowed"):
        assert getattr(infos, field).shape == (T - 1,), field
    assert infos.lost.dtype == jnp.bool_ and infos.windowed.dtype == jnp.bool_
    assert isinstance(state.cloud, Cloud)
    assert state.cloud.particles.shape == (N, 8) and state.cloud.previous.shape == (N, 8)
    assert state.cloud.log_weights.shape == (N,)
    boxes, lost = jax.eval_shape(
        lambda f, b, c: track_boxes(filt, params, key, f, b, c), _frames(), BOX, context
    )
    assert boxes.shape == (T, 4) and lost.shape == (T,)
    particles, log_weights = jax.eval_shape(cpf_jax.particle_boxes, state)
    assert particles.shape == (N, 4) and log_weights.shape == (N,)
    # The weights before resampling are reported only when the config asks for them.
    assert infos.weighed_cloud is None
    reporting = _reporting_weights(config)
    _, infos = jax.eval_shape(
        lambda f, b, c: track(build(reporting), params, key, f, b, c), _frames(), BOX, context
    )
    assert infos.weighed_cloud.particles.shape == (T - 1, N, 8)
    assert infos.weighed_cloud.log_weights.shape == (T - 1, N)


def _reporting_weights(config):
    """``config`` (or a cascade's layer 1) with ``report_weights`` on."""
    if isinstance(config, CascadeConfig):
        return dataclasses.replace(config, box=_reporting_weights(config.box))
    return dataclasses.replace(config, report_weights=True)


def test_the_point_filter_runs_through_the_same_track():
    filt = build_point_filter(PointConfig(n_particles=8, window=(32, 24), intrinsics=INTRINSICS))
    frames = PointFrame(
        jax.ShapeDtypeStruct((T, H, W), jnp.uint16), jax.ShapeDtypeStruct((T, 4), jnp.float32)
    )
    state, infos = jax.eval_shape(
        lambda f, b: track(
            filt, default_point_params(), jax.random.PRNGKey(0), f, b, Context(points=POINTS)
        ),
        frames,
        BOX,
    )
    assert state.particles.shape == (2, 8, 4)
    assert infos.mean.shape == (T - 1, 2, 2) and infos.mean3d.shape == (T - 1, 2, 3)


def test_the_point_filter_needs_its_points():
    filt = build_point_filter(PointConfig(n_particles=8, window=(32, 24), intrinsics=INTRINSICS))
    frame = PointFrame(jnp.zeros((H, W), jnp.uint16), jnp.asarray(BOX))
    with pytest.raises(ValueError, match="points to track"):
        filt.init(default_point_params(), jax.random.PRNGKey(0), frame, BOX)


@pytest.mark.parametrize(
    "spec_props",
    [
        (default_colour_params(), COLOUR_PROPS),
        (default_rgbd_params(RGBDConfig(grid=3)), rgbd_props(RGBDConfig(grid=3))),
        (default_point_params(), POINT_PROPS),
    ],
    ids=["colour", "rgbd", "points"],
)
def test_every_parameter_has_its_prop_beside_it(spec_props):
    params, props = spec_props
    for path in pp.paths(props):
        prop = pp.get(props, path)
        assert prop.constraint in pp.BIJECTORS, path
        value = pp.get(params, path)
        assert value is None or jnp.asarray(value).dtype == jnp.float32, path
    # Every value has exactly one Prop, and a Prop without a value is an unset option.
    value_paths = {
        jax.tree_util.keystr(k)[1:] for k, _ in jax.tree_util.tree_flatten_with_path(params)[0]
    }
    prop_paths = set(pp.paths(props))
    assert value_paths <= prop_paths
    assert all(pp.get(params, p) is None for p in prop_paths - value_paths)


def test_the_box_filters_nest_one_parameter_class_per_shared_term():
    colour = default_colour_params()
    rgbd = default_rgbd_params()
    # The motion model and the aspect prior are one class each, shared, not copied fields.
    assert type(colour.motion) is type(rgbd.motion)
    assert type(colour.aspect) is type(rgbd.aspect)
    for params in (colour, rgbd):
        top = {f for f in params._fields}
        for field in ("tau", "size_velocity_decay", "aspect_mean", "aspect_sigma"):
            assert field not in top
        assert params.motion.tau.shape == (8,)
