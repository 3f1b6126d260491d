"""cpf_jax: cascaded particle-filter tracking of people in RGB-D video, as pure jitted JAX.

Layer 1 (``cpf_jax.colour``) tracks the person's box with H-S colour
histograms (``cpf_jax.rgbd`` adds depth, grid cells and occlusion flags);
layer 2 (``cpf_jax.points``) tracks points on the body in depth, and
``cpf_jax.cascade`` runs both in one jitted step. The kernels they are built
from live in ``cpf_jax.kernels``. Frame
sources and results files are in ``cpf_jax.io``, metrics in
``cpf_jax.metrics``, Rerun logging in ``cpf_jax.viz``, synthetic RGB-D
sequences with ground truth in ``cpf_jax.synthetic``, batch runs over devices in
``cpf_jax.batch``, gradient tuning of the filters' parameters with optax in
``cpf_jax.tuning``, and success plots and other line charts (OpenCV, no plotting
library) in ``cpf_jax.charts``.

Importing the package changes no global JAX configuration.
"""

from cpf_jax.colour import (
    ColourConfig,
    ColourInfo,
    ColourParams,
    ColourState,
    build_colour_filter,
    default_colour_params,
    reference_histogram,
    track,
    track_boxes,
)
from cpf_jax.dynamics import DEFAULT_TAU, MODELS, THESIS_TAU, MotionParams, propagate
from cpf_jax.errors import CameraUnavailable, CpfJaxError, SourceError
from cpf_jax.io import open_source
from cpf_jax.metrics import summarise
from cpf_jax.types import KINECT_V2_DEPTH, Filter, Frame, Intrinsics

__version__ = "0.1.0"

__all__ = [
    "ColourConfig",
    "ColourInfo",
    "ColourParams",
    "ColourState",
    "build_colour_filter",
    "default_colour_params",
    "reference_histogram",
    "track",
    "track_boxes",
    "DEFAULT_TAU",
    "THESIS_TAU",
    "MODELS",
    "MotionParams",
    "propagate",
    "CameraUnavailable",
    "CpfJaxError",
    "SourceError",
    "open_source",
    "summarise",
    "KINECT_V2_DEPTH",
    "Filter",
    "Frame",
    "Intrinsics",
    "__version__",
]
