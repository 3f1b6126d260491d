"""Scoring the multi-person tracker against ground truth with identities.

Ground truth rows are MOTChallenge's ``(frame, id, x, y, w, h, active, class, visibility)``
(``cpf_jax.synthetic_multi.people_truth``, ``cpf_jax.io.mot.read_mot`` of a ``gt.txt``);
hypotheses ``(frame, id, x, y, w, h, conf)`` (``filter.people_rows``). A person hardly
seen is neither a miss nor a false positive, as MOTChallenge treats its ignored boxes: a
ground-truth box with visibility under ``min_visibility`` or shorter than ``min_height`` of
the frame is set aside, and so is every hypothesis that matches one of those (IoU at least
``iou_threshold``, one to one per frame) and nothing else. The rest is scored by
:func:`cpf_jax.metrics.mot_metrics` (MOTA, MOTP, IDF1, identity switches, HOTA).
"""

from __future__ import annotations

import numpy as np

from cpf_jax.kernels.boxes import iou
from cpf_jax.metrics import MotMetrics, mot_metrics
from cpf_jax.metrics.assignment import min_cost_assignment

__all__ = ["MIN_VISIBILITY", "MIN_HEIGHT", "split_ignored", "score_people"]

#: Ground-truth boxes less visible than this, or shorter than this share of the frame's
#: height, are ignored (the detector's least person is 15 % of the frame tall).
MIN_VISIBILITY = 0.2
MIN_HEIGHT = 0.1


def split_ignored(
    gt: np.ndarray, frame_height: int, min_visibility: float, min_height: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(scored, ignored)`` ground-truth rows ``[K, 9]`` (module docstring); rows with
    fewer than nine columns count as wholly visible."""
    gt = np.asarray(gt, np.float64).reshape(-1, np.shape(gt)[-1] if np.size(gt) else 9)
    vis = gt[:, 8] if gt.shape[1] > 8 else np.ones(len(gt))
    low = (vis < min_visibility) | (gt[:, 5] < min_height * frame_height)
    return gt[~low], gt[low]


def _drop_ignored_matches(hyp: np.ndarray, ignored: np.ndarray, scored: np.ndarray, thr: float):
    """``hyp`` without the rows matched to an ignored ground-truth box of their frame and
    to no scored one."""
    keep = np.ones(len(hyp), bool)
    for f in np.unique(ignored[:, 0]):
        hs = np.flatnonzero(hyp[:, 0] == f)
        if not hs.size:
            continue
        gi = ignored[ignored[:, 0] == f]
        gs = scored[scored[:, 0] == f]
        m = np.asarray(iou(gi[:, None, 2:6], hyp[None, hs, 2:6]), np.float64)
        rows, cols = min_cost_assignment(np.where(m >= thr, 1.0 - m, np.nan))
        for j in cols:
            ms = np.asarray(iou(gs[:, 2:6], hyp[hs[j], 2:6]), np.float64)
            if not np.any(ms >= thr):
                keep[hs[j]] = False
    return hyp[keep]


def score_people(
    gt: np.ndarray,
    hyp: np.ndarray,
    frame_height: int,
    min_visibility: float = MIN_VISIBILITY,
    min_height: float = MIN_HEIGHT,
    iou_threshold: float = 0.5,
) -> MotMetrics:
    """MOTA, MOTP, IDF1, identity switches and HOTA of ``hyp`` against ``gt`` with the
    hardly seen ground truth set aside (module docstring)."""
    scored, ignored = split_ignored(gt, frame_height, min_visibility, min_height)
    hyp = np.asarray(hyp, np.float64).reshape(-1, np.shape(hyp)[-1] if np.size(hyp) else 7)
    hyp = _drop_ignored_matches(hyp, ignored, scored, iou_threshold)
    return mot_metrics(scored[:, :6], hyp[:, :6], iou_threshold)
