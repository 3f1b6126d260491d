"""Tracking metrics: one target (:mod:`~cpf_jax.metrics.single`: IoU, success rate and AUC,
precision, CLEAR MOT of one track, scale adaptation, 3D error) and several
(:mod:`~cpf_jax.metrics.multi`: MOTA, MOTP, IDF1, identity switches, HOTA over tracks with
identities)."""

from cpf_jax.metrics import single
from cpf_jax.metrics.multi import MotMetrics, mot_metrics
from cpf_jax.metrics.single import *  # noqa: F403  (its __all__ is this package's too)

__all__ = [*single.__all__, "MotMetrics", "mot_metrics"]
