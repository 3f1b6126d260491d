"""cpf_jax: cascaded particle-filter tracking of people in RGB-D video, as pure jitted JAX.

Every filter has one shape (``cpf_jax.filter``): a builder takes a frozen config and
returns ``Filter(init, step)``; ``track`` runs any filter over a sequence as one
``lax.scan``. Layer 1 tracks the person's box in colour (``cpf_jax.colour``) or in RGB-D
with grid cells and occlusion flags (``cpf_jax.rgbd``); layer 2 tracks points on the body
in depth (``cpf_jax.points``); ``cpf_jax.cascade`` runs both in one step; ``cpf_jax.multi``
tracks several people at once with identities. Parameters and
their constraints: ``cpf_jax.params``; kernels: ``cpf_jax.kernels``; frame sources:
``cpf_jax.io``; metrics: ``cpf_jax.metrics``; Rerun logging: ``cpf_jax.viz``; synthetic
sequences: ``cpf_jax.synthetic``; batch runs: ``cpf_jax.batch``; gradient tuning:
``cpf_jax.tuning``.

Importing the package changes no global JAX configuration; ``enable_compile_cache()`` keeps
compiled programs on disk for the next run when asked.
"""

from cpf_jax.cascade import (
    CascadeConfig,
    build_box_filter,
    build_cascade,
    default_box_params,
    default_cascade_params,
)
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
from cpf_jax.compile_cache import enable as enable_compile_cache
from cpf_jax.dynamics import DEFAULT_TAU, MODELS, THESIS_TAU, MotionParams, propagate
from cpf_jax.errors import CameraUnavailable, CpfJaxError, SourceError
from cpf_jax.filter import (
    BOX_INFO_FIELDS,
    Cloud,
    Context,
    Filter,
    particle_boxes,
    track,
    track_boxes,
)
from cpf_jax.io import open_source
from cpf_jax.metrics import summarise
from cpf_jax.multi import MultiConfig, build_multi_filter, default_multi_params
from cpf_jax.points import PointConfig, PointFrame, build_point_filter, default_point_params
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params
from cpf_jax.types import KINECT_V2_DEPTH, Frame, Intrinsics

__version__ = "0.1.0"

__all__ = [
    "BOX_INFO_FIELDS",
    "DEFAULT_TAU",
    "KINECT_V2_DEPTH",
    "MODELS",
    "THESIS_TAU",
    "CameraUnavailable",
    "CascadeConfig",
    "Cloud",
    "ColourConfig",
    "Context",
    "CpfJaxError",
    "Filter",
    "Frame",
    "Intrinsics",
    "MotionParams",
    "MultiConfig",
    "PointConfig",
    "PointFrame",
    "RGBDConfig",
    "SourceError",
    "build_box_filter",
    "build_cascade",
    "build_colour_filter",
    "build_multi_filter",
    "build_point_filter",
    "build_rgbd_filter",
    "default_box_params",
    "default_cascade_params",
    "default_colour_params",
    "default_multi_params",
    "default_point_params",
    "default_rgbd_params",
    "enable_compile_cache",
    "open_source",
    "particle_boxes",
    "propagate",
    "summarise",
    "track",
    "track_boxes",
    "__version__",
]
