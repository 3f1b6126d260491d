"""The colour layer's discriminative term: a correlation filter learnt online
(``kernels.correlation``), trained on the target against its surround.

Each step samples one search patch around the last estimate (``padding`` times its box),
computes one dense response map over it, and every particle reads the map at its
centre: the term costs one patch, one feature map and two small FFTs per frame whatever
the number of particles. After the estimate the filter learns the estimate's patch at
``params.rate`` unless the target is lost. The log-likelihood a particle gains is
``params.weight * response``, the response being in units of the training label's peak
(about 1 on the trained target, about 0 on its surround).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels import correlation as cf
from cpf_jax.types import Frame

__all__ = [
    "CorrelationConfig",
    "CorrelationParams",
    "CorrelationModel",
    "correlation_init",
    "correlation_scores",
    "correlation_update",
]


@dataclasses.dataclass(frozen=True)
class CorrelationConfig:
    """Static settings of the correlation term."""

    cells: int = 32  # the patch's side in feature cells (n)
    cell_px: int = 4  # a cell's side in patch pixels: the patch is resampled to n * cell_px
    padding: float = 2.5  # the patch is this many times the box in each direction
    # Width of the training label, as a fraction of the box's side in cells (KCF's 0.1).
    label_sigma: float = 0.1
    ridge: float = 1e-2  # lambda of the ridge regression

    def __post_init__(self) -> None:
        if self.cells < 4 or self.cells % 2:
            raise ValueError(f"cells must be even and >= 4, got {self.cells}")
        if self.cell_px < 1:
            raise ValueError(f"cell_px must be >= 1, got {self.cell_px}")
        if not self.padding > 1.0:
            raise ValueError(f"padding must be > 1, got {self.padding}")

    @property
    def label(self) -> Array:
        return cf.label_spectrum(self.cells, self.label_sigma * self.cells / self.padding)


class CorrelationParams(NamedTuple):
    """The correlation term (``ColourConfig.correlation``)."""

    weight: Array  # log-likelihood per unit of response
    rate: Array  # learning rate of the filter's running averages


class CorrelationModel(NamedTuple):
    filter: cf.CorrelationFilter


def _patch_features(config: CorrelationConfig, frame: Frame, box: Array) -> Array:
    """``[n, n, C]`` features of the patch ``padding`` times ``box`` (xywh) around it."""
    centre = box[:2] + box[2:4] / 2
    size = config.padding * box[2:4]
    patch = cf.sample_patch(frame.colour, centre, size, config.cells * config.cell_px)
    return cf.features(patch, config.cell_px)


def correlation_init(
    config: CorrelationConfig | None, frame: Frame, box: Array
) -> CorrelationModel:
    """The filter of the initial box (a 1 x 1 placeholder without the term)."""
    if config is None:
        zero = cf.CorrelationFilter(jnp.zeros((1, 1, 1), jnp.complex64), jnp.zeros((1, 1)))
        return CorrelationModel(zero)
    return CorrelationModel(cf.fit(_patch_features(config, frame, box), config.label))


def correlation_scores(
    config: CorrelationConfig,
    model: CorrelationModel,
    frame: Frame,
    estimate: Array,
    centres: Array,
) -> Array:
    """``[N]`` responses at the particle ``centres [N, 2]`` over the patch around the last
    ``estimate`` (xywh)."""
    resp = cf.response(model.filter, _patch_features(config, frame, estimate), config.ridge)
    cell = config.padding * estimate[2:4] / config.cells  # pixels per cell (x, y)
    disp = (centres - (estimate[:2] + estimate[2:4] / 2)) / cell
    return cf.read_response(resp, disp)


def correlation_update(
    config: CorrelationConfig | None,
    params: CorrelationParams,
    model: CorrelationModel,
    frame: Frame,
    estimate: Array,
    lost: Array,
) -> CorrelationModel:
    """The filter blended with the estimate's patch at ``params.rate``, unless lost."""
    if config is None:
        return model
    new = cf.fit(_patch_features(config, frame, estimate), config.label)
    rate = jnp.where(lost, 0.0, params.rate)
    return CorrelationModel(cf.blend(model.filter, new, rate))
