"""Tracking metrics: one target (:mod:`~cpf_jax.metrics.single`: IoU, success rate and AUC,
precision, CLEAR MOT of one track, scale adaptation, 3D error) and several
(:mod:`~cpf_jax.metrics.multi`: MOTA, MOTP, IDF1, identity switches, HOTA over tracks with
identities)."""

from cpf_jax.metrics.multi import MotMetrics, mot_metrics
from cpf_jax.metrics.single import (
    OTB_THRESHOLDS,
    ClearMot,
    box_present,
    centre_errors,
    clear_mot,
    format_summary,
    frame_ious,
    gt_visible,
    point_error_summary,
    point_errors,
    precision,
    run_ious,
    run_success_curve,
    success_auc,
    success_curve,
    success_rate,
    summarise,
)

__all__ = [
    "OTB_THRESHOLDS",
    "ClearMot",
    "box_present",
    "gt_visible",
    "frame_ious",
    "centre_errors",
    "success_rate",
    "success_curve",
    "success_auc",
    "precision",
    "clear_mot",
    "point_errors",
    "point_error_summary",
    "summarise",
    "run_ious",
    "run_success_curve",
    "format_summary",
    "MotMetrics",
    "mot_metrics",
]
