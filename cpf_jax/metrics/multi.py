"""Multi-object tracking metrics: CLEAR MOT (MOTA, MOTP, identity switches), IDF1 and HOTA.

Tracks are ``[K, 6]`` rows ``(frame, id, x, y, w, h)``, the first six columns of
MOTChallenge's text format: boxes top-left, in pixels, any frame numbering as long as the
ground truth and the hypotheses share it. A frame is a value of the first column; ids are
compared only within one side. Similarity is box IoU (:func:`cpf_jax.kernels.boxes.iou`).

* CLEAR MOT (Bernardin and Stiefelhagen 2008), as py-motmetrics computes it: in each frame
  a ground-truth object keeps the hypothesis it was matched to last if their IoU still
  reaches ``iou_threshold``; the rest are matched by a minimum-cost assignment of
  ``1 - IoU`` over the pairs that reach it; a match of an object to another hypothesis
  than its last is an identity switch. ``MOTA = 1 - (misses + false positives +
  switches) / ground-truth boxes``; ``MOTP`` is the mean IoU of the matches (MOTChallenge
  reports it so; py-motmetrics reports ``1 - MOTP``).
* IDF1 (Ristani et al. 2016): ground-truth and hypothesis tracks matched one to one, for
  the most frames in which the pair overlaps by ``iou_threshold``;
  ``IDF1 = 2 IDTP / (ground-truth boxes + hypothesis boxes)``.
* HOTA (Luiten et al. 2020, eqs. 1-11, as TrackEval computes it): per frame, pairs are
  matched to maximise IoU weighted by the pair's global alignment (how often the two
  tracks overlap over the sequence); at each threshold ``alpha`` in 0.05, 0.10, ..., 0.95
  the matches with ``IoU >= alpha`` are true positives, ``DetA = TP / (TP + FN + FP)``,
  ``AssA`` the mean over true positives of their tracks' association IoU
  ``TPA / (TPA + FNA + FPA)``, ``HOTA_alpha = sqrt(DetA AssA)``; HOTA is the mean over
  ``alpha``.

Percentages throughout. A sequence with no ground truth and no hypotheses scores 100 %.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cpf_jax.kernels.boxes import iou
from cpf_jax.metrics.assignment import min_cost_assignment

__all__ = ["MotMetrics", "mot_metrics", "HOTA_ALPHAS", "frame_pairs"]

HOTA_ALPHAS = np.arange(1, 20) / 20.0  # 0.05 ... 0.95


class MotMetrics(NamedTuple):
    """The scores of one sequence (percentages and counts)."""

    mota: float
    motp: float  # mean IoU of the CLEAR matches, %
    idf1: float
    hota: float
    deta: float  # HOTA's detection accuracy, mean over alpha
    assa: float  # HOTA's association accuracy, mean over alpha
    id_switches: int
    matches: int
    false_positives: int
    misses: int
    num_gt: int  # ground-truth boxes
    num_hyp: int  # hypothesis boxes


class _Frame(NamedTuple):
    gt_ids: np.ndarray  # [G_t] indices into the sequence's ground-truth ids
    hyp_ids: np.ndarray  # [H_t] indices into the sequence's hypothesis ids
    iou: np.ndarray  # [G_t, H_t]


def _tracks(rows, what: str) -> np.ndarray:
    rows = np.asarray(rows, np.float64)
    if rows.size == 0:
        return np.zeros((0, 6))
    if rows.ndim != 2 or rows.shape[1] < 6:
        raise ValueError(f"{what} must be [K, 6+] rows (frame, id, x, y, w, h), got {rows.shape}")
    if not np.all(np.isfinite(rows[:, :6])):
        raise ValueError(f"{what} has non-finite values in its first six columns")
    return rows[:, :6]


def frame_pairs(gt, hyp) -> tuple[list[_Frame], int, int]:
    """Per frame (in order), the ground-truth and hypothesis id indices present and their
    IoU; and the numbers of distinct ground-truth and hypothesis ids."""
    gt, hyp = _tracks(gt, "ground truth"), _tracks(hyp, "hypotheses")
    g_ids, g_idx = np.unique(gt[:, 1], return_inverse=True)
    h_ids, h_idx = np.unique(hyp[:, 1], return_inverse=True)
    frames = []
    for f in np.union1d(gt[:, 0], hyp[:, 0]):
        gs, hs = np.flatnonzero(gt[:, 0] == f), np.flatnonzero(hyp[:, 0] == f)
        for side, ids in (("ground truth", g_idx[gs]), ("hypotheses", h_idx[hs])):
            if len(np.unique(ids)) != len(ids):
                raise ValueError(f"{side}: an id appears twice in frame {f:g}")
        m = np.asarray(iou(gt[gs, None, 2:6], hyp[None, hs, 2:6]), np.float64)
        frames.append(_Frame(g_idx[gs], h_idx[hs], m.reshape(len(gs), len(hs))))
    return frames, len(g_ids), len(h_ids)


def _clear(frames: list[_Frame], threshold: float) -> tuple[int, int, float]:
    """``(matches, switches, summed IoU of the matches)`` of CLEAR MOT's matching."""
    last: dict[int, int] = {}  # object -> the hypothesis it was matched to last
    matches = switches = 0
    overlap = 0.0
    for fr in frames:
        ok = fr.iou >= threshold
        pairs = []
        kept_g = np.zeros(len(fr.gt_ids), bool)
        kept_h = np.zeros(len(fr.hyp_ids), bool)
        for i, o in enumerate(fr.gt_ids):
            j = np.flatnonzero((fr.hyp_ids == last.get(int(o), -1)) & ~kept_h)
            if j.size and ok[i, j[0]]:
                kept_g[i], kept_h[j[0]] = True, True
                pairs.append((i, int(j[0])))
        cost = np.where(ok & ~kept_g[:, None] & ~kept_h[None, :], 1.0 - fr.iou, np.nan)
        for i, j in zip(*min_cost_assignment(cost), strict=True):
            o, h = int(fr.gt_ids[i]), int(fr.hyp_ids[j])
            switches += int(o in last and last[o] != h)
            pairs.append((int(i), int(j)))
        for i, j in pairs:
            last[int(fr.gt_ids[i])] = int(fr.hyp_ids[j])
            overlap += fr.iou[i, j]
        matches += len(pairs)
    return matches, switches, overlap


def _idtp(frames: list[_Frame], n_gt: int, n_hyp: int, threshold: float) -> int:
    """IDF1's true positives: the most frames one-to-one track pairs overlap in."""
    together = np.zeros((n_gt, n_hyp))
    for fr in frames:
        together[np.ix_(fr.gt_ids, fr.hyp_ids)] += fr.iou >= threshold
    rows, cols = min_cost_assignment(-together)
    return int(together[rows, cols].sum())


def _hota(frames: list[_Frame], n_gt: int, n_hyp: int) -> tuple[float, float, float]:
    """``(HOTA, DetA, AssA)`` in [0, 1], each the mean over :data:`HOTA_ALPHAS`."""
    potential = np.zeros((n_gt, n_hyp))
    gt_count, hyp_count = np.zeros((n_gt, 1)), np.zeros((1, n_hyp))
    for fr in frames:
        s = fr.iou
        denom = s.sum(0, keepdims=True) + s.sum(1, keepdims=True) - s
        potential[np.ix_(fr.gt_ids, fr.hyp_ids)] += np.where(
            denom > 0, s / np.where(denom > 0, denom, 1), 0
        )
        gt_count[fr.gt_ids, 0] += 1
        hyp_count[0, fr.hyp_ids] += 1
    alignment = potential / np.maximum(gt_count + hyp_count - potential, 1e-12)
    a = len(HOTA_ALPHAS)
    tp, fn, fp = np.zeros(a), np.zeros(a), np.zeros(a)
    counts = np.zeros((a, n_gt, n_hyp))
    for fr in frames:
        rows, cols = min_cost_assignment(-alignment[np.ix_(fr.gt_ids, fr.hyp_ids)] * fr.iou)
        for k, alpha in enumerate(HOTA_ALPHAS):
            hit = fr.iou[rows, cols] >= alpha - np.finfo(float).eps
            tp[k] += hit.sum()
            fn[k] += len(fr.gt_ids) - hit.sum()
            fp[k] += len(fr.hyp_ids) - hit.sum()
            np.add.at(counts[k], (fr.gt_ids[rows[hit]], fr.hyp_ids[cols[hit]]), 1)
    ass_iou = counts / np.maximum(gt_count + hyp_count - counts, 1)
    assa = np.sum(counts * ass_iou, axis=(1, 2)) / np.maximum(tp, 1)
    deta = tp / np.maximum(tp + fn + fp, 1)
    return float(np.mean(np.sqrt(deta * assa))), float(np.mean(deta)), float(np.mean(assa))


def mot_metrics(gt, hyp, iou_threshold: float = 0.5) -> MotMetrics:
    """MOTA, MOTP, IDF1, HOTA and their counts of ``hyp`` against ``gt`` (``[K, 6]`` rows
    ``(frame, id, x, y, w, h)``; see the module docstring for each definition).

    Raises:
      ValueError: for rows that are not ``[K, 6+]`` and finite, or an id twice in a frame.
    """
    frames, n_gt, n_hyp = frame_pairs(gt, hyp)
    num_gt = sum(len(f.gt_ids) for f in frames)
    num_hyp = sum(len(f.hyp_ids) for f in frames)
    matches, switches, overlap = _clear(frames, iou_threshold)
    misses, fps = num_gt - matches, num_hyp - matches
    if num_gt == 0 and num_hyp == 0:
        return MotMetrics(100.0, 100.0, 100.0, 100.0, 100.0, 100.0, 0, 0, 0, 0, 0, 0)
    mota = 100.0 * (1.0 - (misses + fps + switches) / num_gt) if num_gt else -np.inf
    motp = 100.0 * overlap / matches if matches else float("nan")
    idf1 = 100.0 * 2 * _idtp(frames, n_gt, n_hyp, iou_threshold) / (num_gt + num_hyp)
    hota, deta, assa = _hota(frames, n_gt, n_hyp)
    return MotMetrics(
        mota,
        motp,
        idf1,
        100 * hota,
        100 * deta,
        100 * assa,
        switches,
        matches,
        fps,
        misses,
        num_gt,
        num_hyp,
    )
