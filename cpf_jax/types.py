"""Shared data types: one registered RGB-D frame, camera intrinsics, a filter."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from jax import Array

__all__ = ["Frame", "Intrinsics", "Filter", "KINECT_V2_DEPTH"]


class Frame(NamedTuple):
    """One registered RGB-D frame.

    colour: ``[H, W, 3] uint8``, RGB order.
    depth: ``[H, W] uint16``, millimetres, 0 = missing. Colour-only sources
    give an all-zero depth of the same size.
    """

    colour: Array
    depth: Array


class Intrinsics(NamedTuple):
    """Pinhole intrinsics, 0-based pixel convention: ``u = fx * X / Z + cx``."""

    fx: float
    fy: float
    cx: float
    cy: float


# Kinect v2 depth camera, thesis Table 4.1 (512 x 424 depth image).
KINECT_V2_DEPTH = Intrinsics(fx=365.0, fy=365.0, cx=255.0, cy=205.0)


class Filter(NamedTuple):
    """A particle filter as a pure ``init`` / ``step`` pair (blackjax-style).

    ``init(params, key, frame, box) -> state``
    ``step(params, key, state, frame) -> (state, info)``

    ``params`` is a pytree of continuous (tunable) parameters; the static
    configuration is closed over by the builder that made the filter.
    """

    init: Callable[..., Any]
    step: Callable[..., Any]
