"""Layer 2: points on the body tracked in depth with spin images and geodesic distances
(thesis ch. 4, SPEC C3).

::

    filt = build_point_filter(PointConfig(n_particles=100, weighting="combined"))
    params = default_point_params()
    state = filt.init(params, key, PointFrame(depth, box), box, Context(points=points_xy))
    state, info = filt.step(params, key, state, PointFrame(next_depth, next_box))

``config.py`` holds the settings and the body points it knows, ``body.py`` the segmented
body (thesis 4.1-4.3) and ``filter.py`` the point filter.
"""

from cpf_jax.points.body import BodyModel, body_extremities, body_model, body_points_3d
from cpf_jax.points.config import (
    AUTO_POINTS,
    BODY_POINT_DEPTH_OFFSET_MM,
    BODY_POINTS,
    REFERENCES,
    WEIGHTINGS,
    PointConfig,
)
from cpf_jax.points.filter import (
    POINT_PROPS,
    POINTS,
    PointEstimateParams,
    PointFrame,
    PointInfo,
    PointMotionParams,
    PointParams,
    PointState,
    PointWeightParams,
    build_point_filter,
    default_point_params,
    estimate_3d,
)

__all__ = [
    "AUTO_POINTS",
    "BODY_POINTS",
    "BODY_POINT_DEPTH_OFFSET_MM",
    "POINTS",
    "POINT_PROPS",
    "REFERENCES",
    "WEIGHTINGS",
    "BodyModel",
    "PointConfig",
    "PointEstimateParams",
    "PointFrame",
    "PointInfo",
    "PointMotionParams",
    "PointParams",
    "PointState",
    "PointWeightParams",
    "body_extremities",
    "body_model",
    "body_points_3d",
    "build_point_filter",
    "default_point_params",
    "estimate_3d",
]
