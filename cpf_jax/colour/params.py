"""Continuous parameters of the colour layer, one ``NamedTuple`` per term, each value
declared beside its constraint (``cpf_jax.params``)."""

from __future__ import annotations

from typing import NamedTuple

from jax import Array

from cpf_jax.colour.correlation import CorrelationParams
from cpf_jax.dynamics import MOTION, MotionParams
from cpf_jax.likelihood import ASPECT, AspectParams
from cpf_jax.params import P, props, values

__all__ = [
    "HistogramParams",
    "ContrastParams",
    "LayoutParams",
    "TemplateParams",
    "EstimateParams",
    "CorrelationParams",
    "ColourParams",
    "COLOUR",
    "COLOUR_PROPS",
    "default_colour_params",
]


class HistogramParams(NamedTuple):
    """The stripe histograms' likelihood (thesis eqs. 3.7-3.8)."""

    sigma: Array  # width of eq. 3.8 on the Bhattacharyya distance
    lost_distance: Array  # the target is lost when even the best particle is farther


class ContrastParams(NamedTuple):
    """The centre-surround colour contrast term (``ColourConfig.contrast``)."""

    weight: Array  # weight of the box's contrast score (0: the thesis's likelihood)
    threshold: Array  # "linear": P(person | bin) above which a colour counts for the box
    fill_ratio: Array  # "mixture": share of a person box's pixels that are person


class LayoutParams(NamedTuple):
    """The layout term (``ColourConfig.layout``)."""

    weight: Array  # weight of the normalised cross-correlation
    rate: Array  # forgetting rate of the layout template (0: the initial box's)


class TemplateParams(NamedTuple):
    """The slow update of the reference histograms (``ColourConfig.template_update``)."""

    rate: Array  # forgetting rate, in [0, 1]
    max_distance: Array  # update only while the estimate's distance is below this


class EstimateParams(NamedTuple):
    """The estimator (``ColourConfig.estimator``)."""

    robust_radius: Array  # robust mean: window half-size as a fraction of the MAP box


class ColourParams(NamedTuple):
    """Every continuous parameter of the colour layer (a pytree)."""

    motion: MotionParams
    histogram: HistogramParams
    contrast: ContrastParams
    layout: LayoutParams
    aspect: AspectParams
    template: TemplateParams
    estimate: EstimateParams
    correlation: CorrelationParams


#: The colour layer's defaults with their constraints. The thesis's ``sigma = 1`` leaves
#: the weights of plausible boxes (distances 0.1-0.6) within [0.84, 0.995], a nearly
#: flat likelihood; 0.15 and the other values were chosen on the synthetic training
#: scenes (docs/decisions.md).
COLOUR = ColourParams(
    # Guided particles moving across the image keep their size (dynamics, "size_hold").
    motion=MOTION._replace(size_hold=P(1.0)),
    histogram=HistogramParams(sigma=P(0.15, "softplus"), lost_distance=P(0.7, "sigmoid")),
    contrast=ContrastParams(
        weight=P(28.0, "softplus"), threshold=P(0.3, "sigmoid"), fill_ratio=P(0.7, "sigmoid")
    ),
    layout=LayoutParams(weight=P(10.0, "softplus"), rate=P(0.0, "sigmoid")),
    aspect=ASPECT,
    template=TemplateParams(rate=P(0.05, "sigmoid"), max_distance=P(0.3, "sigmoid")),
    estimate=EstimateParams(robust_radius=P(0.25, "softplus")),
    correlation=CorrelationParams(weight=P(4.0, "softplus"), rate=P(0.02, "sigmoid")),
)

#: How each colour parameter is tuned (``cpf_jax.tuning``).
COLOUR_PROPS = props(COLOUR)


def default_colour_params() -> ColourParams:
    """The colour layer's default parameters (float32 arrays)."""
    return values(COLOUR)
