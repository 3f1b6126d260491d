"""Likelihood pieces shared by the box filters: the histogram likelihood and the aspect prior."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.params import P

__all__ = ["AspectParams", "ASPECT", "aspect_log_prior", "histogram_log_likelihood"]


def histogram_log_likelihood(d2: Array, sigma: Array) -> Array:
    """``log p = -d^2 / (2 sigma^2)`` of squared Bhattacharyya distances (thesis eq. 3.8).

    The constant ``1 / (sqrt(2 pi) sigma)`` cancels when the weights are normalised.
    """
    return -d2 / (2.0 * sigma * sigma)


class AspectParams(NamedTuple):
    """Log-normal prior on a person box's width / height."""

    mean: Array  # prior mean of width / height (pedestrian benchmarks: 0.41)
    sigma: Array  # prior std of log(width / height)


ASPECT = AspectParams(mean=P(0.41, "softplus"), sigma=P(0.3, "softplus"))


def aspect_log_prior(particles: Array, aspect: AspectParams) -> Array:
    """Log-normal prior ``[N]`` on the width / height of ``[N, 8]`` particle boxes.

    Person boxes keep a typical shape: the prior stops a box collapsing onto the torso
    or spreading sideways.
    """
    log_aspect = jnp.log(particles[:, 4] / particles[:, 5]) - jnp.log(aspect.mean)
    return -0.5 * (log_aspect / aspect.sigma) ** 2
