"""Tracking metrics (SPEC C6): IoU, success rate and AUC, precision, CLEAR MOT, SA, 3D error.

Conventions:

* Boxes are ``[T, 4] (x, y, w, h)`` top-left, 0-based float pixels (as in
  :mod:`cpf_jax.kernels.boxes`), one row per frame of a single target.
* ``visible [T] bool``: the target is in view in that frame. When not given it
  is derived from the ground truth: a row is visible when it is finite and has
  ``w > 0`` and ``h > 0`` (OTB writes ``0,0,0,0`` for "not visible").
* ``lost [T] bool``: the tracker reported that it has no box in that frame.
  A predicted row that is non-finite or has ``w <= 0`` or ``h <= 0`` also
  counts as lost.
* Rates are in percent; distances in pixels (boxes) or the unit of the points
  (millimetres for camera-space 3D points).

The aggregate functions take boolean masks instead of dropping frames, so they
keep static shapes and work under ``jit`` and ``vmap`` (e.g. over seeds or
settings). Every ratio is a safe division: an empty denominator gives 0, never
NaN (see each docstring). :func:`summarise` is the NumPy-friendly front door;
it raises ``ValueError`` for empty or mis-shaped input.

Sources: thesis eqs. 3.18-3.19 (IoU, success rate at IoU >= 0.5), OTB success
plot (Wu et al. 2013: success at thresholds ``linspace(0, 1, 21)`` counts
``IoU > t``; AUC is the mean of the curve), the RGB-D occlusion paper's
eqs. 9-10 (CLEAR MOTP/MOTA, scale adaptation SA), thesis eq. 5.5 (3D error).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.kernels.boxes import centre_distance, iou

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
]

# OTB success-plot thresholds.
OTB_THRESHOLDS = np.linspace(0.0, 1.0, 21)


def _safe_ratio(num: Array, den: Array) -> Array:
    den = jnp.asarray(den, jnp.float32)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _mask(mask: Array | None, like: Array) -> Array:
    if mask is None:
        return jnp.ones(like.shape, bool)
    return jnp.asarray(mask, bool)


def box_present(boxes: Array) -> Array:
    """``[..., 4]`` boxes -> ``[...]`` bool: finite with positive width and height."""
    boxes = jnp.asarray(boxes, jnp.float32)
    finite = jnp.all(jnp.isfinite(boxes), axis=-1)
    return finite & (boxes[..., 2] > 0) & (boxes[..., 3] > 0)


def gt_visible(gt_boxes: Array, visible: Array | None = None) -> Array:
    """Visibility of the target: ``visible`` if given, else :func:`box_present` of the GT.

    Given flags are also and-ed with :func:`box_present`, so a visible frame
    always has a usable box.
    """
    present = box_present(gt_boxes)
    return present if visible is None else present & jnp.asarray(visible, bool)


def _clean(boxes: Array) -> Array:
    # Non-finite rows become empty boxes so IoU and distances stay finite.
    boxes = jnp.asarray(boxes, jnp.float32)
    return jnp.where(jnp.isfinite(boxes), boxes, 0.0)


def frame_ious(pred: Array, gt: Array) -> Array:
    """``[T, 4], [T, 4] -> [T]`` IoU per frame (thesis eq. 3.18); empty or NaN rows give 0."""
    return iou(_clean(pred), _clean(gt))


def centre_errors(pred: Array, gt: Array) -> Array:
    """``[T, 4], [T, 4] -> [T]`` distance in pixels between box centres (NaN rows give 0)."""
    return centre_distance(_clean(pred), _clean(gt))


def success_rate(ious: Array, valid: Array | None = None, threshold: float = 0.5) -> Array:
    """Percent of ``valid`` frames with ``IoU >= threshold`` (thesis eq. 3.19).

    No valid frame gives 0.
    """
    ious = jnp.asarray(ious, jnp.float32)
    valid = _mask(valid, ious)
    hits = jnp.sum(valid & (ious >= threshold))
    return 100.0 * _safe_ratio(hits, jnp.sum(valid))


def success_curve(
    ious: Array, valid: Array | None = None, thresholds: Array | None = None
) -> Array:
    """``[K]`` fraction of ``valid`` frames with ``IoU > t`` for each threshold (OTB success plot).

    ``thresholds`` defaults to :data:`OTB_THRESHOLDS` (21 values 0..1). Note the
    strict ``>``: at ``t = 0`` a frame needs some overlap. No valid frame gives zeros.
    """
    ious = jnp.asarray(ious, jnp.float32)
    valid = _mask(valid, ious)
    t = jnp.asarray(OTB_THRESHOLDS if thresholds is None else thresholds, jnp.float32)
    hits = jnp.sum(valid[..., None, :] & (ious[..., None, :] > t[:, None]), axis=-1)
    return _safe_ratio(hits, jnp.sum(valid, axis=-1)[..., None])


def success_auc(ious: Array, valid: Array | None = None) -> Array:
    """Area under the OTB success plot in percent (mean of :func:`success_curve`)."""
    return 100.0 * jnp.mean(success_curve(ious, valid), axis=-1)


def precision(errors: Array, valid: Array | None = None, threshold: float = 20.0) -> Array:
    """Percent of ``valid`` frames with centre error ``<= threshold`` pixels (OTB precision).

    Pass infinite errors for frames where the tracker has no box. No valid frame gives 0.
    """
    errors = jnp.asarray(errors, jnp.float32)
    valid = _mask(valid, errors)
    hits = jnp.sum(valid & (errors <= threshold))
    return 100.0 * _safe_ratio(hits, jnp.sum(valid))


class ClearMot(NamedTuple):
    """CLEAR MOT counts and scores for one target (paper eqs. 9-10); all 0-d arrays."""

    motp: Array  # mean centre distance (px) over matched frames; lower is better
    motp_iou: Array  # mean IoU over matched frames (the overlap variant of MOTP)
    mota: Array  # percent: 100 * (1 - (misses + false_positives + mismatches) / gt_objects)
    sa: Array  # mean sqrt(dw^2 + dh^2) (px) over matched frames; lower is better
    matches: Array
    misses: Array
    false_positives: Array
    mismatches: Array
    gt_objects: Array


def clear_mot(
    pred: Array,
    gt: Array,
    visible: Array | None = None,
    lost: Array | None = None,
    match_iou: float = 0.5,
) -> ClearMot:
    """CLEAR MOT for single-target tracking as in the RGB-D occlusion paper (eqs. 9-10).

    Per frame, with one ground-truth object (when ``visible``) and at most one
    hypothesis (when not ``lost``):

    * match ``c_t = 1`` when both exist and ``IoU >= match_iou``;
    * miss when the object is visible and not matched;
    * false positive when a hypothesis exists and is not matched (this covers
      a box reported while the target is out of view, and a box that misses a
      visible target, which is then a miss and a false positive, as in CLEAR);
    * mismatches are 0: with one object and one hypothesis identity there is no
      identity to switch.

    ``MOTP = sum_t d_t / sum_t c_t`` with ``d_t`` the paper's "error in estimated
    position", the centre distance in pixels (its tables report values such as
    23.6 and 153.1, lower is better). ``motp_iou`` is the overlap variant.
    ``MOTA = 1 - sum_t (m_t + fp_t + mme_t) / sum_t g_t`` in percent; with no
    ground-truth object at all the denominator is taken as 1, so an empty
    sequence with no false positives scores 100 and each false positive costs
    100. ``SA = sum_t sqrt(dw_t^2 + dh_t^2) / sum_t c_t`` over matched frames
    (eq. 10). With no match, MOTP, motp_iou and SA are 0: read ``matches``.
    """
    pred = jnp.asarray(pred, jnp.float32)
    gt = jnp.asarray(gt, jnp.float32)
    vis = gt_visible(gt, visible)
    has_pred = box_present(pred)
    if lost is not None:
        has_pred = has_pred & ~jnp.asarray(lost, bool)
    ious = frame_ious(pred, gt)
    matched = vis & has_pred & (ious >= match_iou)
    n_match = jnp.sum(matched)
    misses = jnp.sum(vis & ~matched)
    fps = jnp.sum(has_pred & ~matched)
    mme = jnp.zeros((), jnp.int32)
    n_gt = jnp.sum(vis)
    dist = centre_errors(pred, gt)
    pc, gc = _clean(pred), _clean(gt)
    scale = jnp.sqrt((pc[..., 2] - gc[..., 2]) ** 2 + (pc[..., 3] - gc[..., 3]) ** 2)
    motp = _safe_ratio(jnp.sum(jnp.where(matched, dist, 0.0)), n_match)
    motp_iou = _safe_ratio(jnp.sum(jnp.where(matched, ious, 0.0)), n_match)
    sa = _safe_ratio(jnp.sum(jnp.where(matched, scale, 0.0)), n_match)
    mota = 100.0 * (1.0 - (misses + fps + mme) / jnp.maximum(n_gt, 1).astype(jnp.float32))
    return ClearMot(motp, motp_iou, mota, sa, n_match, misses, fps, mme, n_gt)


def point_errors(pred: Array, gt: Array) -> Array:
    """``[..., D], [..., D] -> [...]`` Euclidean distance (thesis eq. 5.5; mm for 3D points).

    NaN in either input gives NaN for that point (use :func:`point_error_summary`).
    """
    d = jnp.asarray(pred, jnp.float32) - jnp.asarray(gt, jnp.float32)
    return jnp.sqrt(jnp.sum(d * d, axis=-1))


def point_error_summary(pred: Array, gt: Array) -> dict[str, float]:
    """Mean, median and 90th percentile of :func:`point_errors` over points with finite GT.

    Points whose ground truth is non-finite are ignored; points whose prediction
    is non-finite while the GT is finite are counted in ``missing`` and left out
    of the statistics. With no usable point the statistics are 0 and ``n`` is 0.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"point arrays differ in shape: pred {pred.shape} vs gt {gt.shape}")
    gt_ok = np.all(np.isfinite(gt), axis=-1)
    pred_ok = np.all(np.isfinite(pred), axis=-1)
    err = np.asarray(
        point_errors(np.where(np.isfinite(pred), pred, 0), np.where(np.isfinite(gt), gt, 0))
    )
    use = gt_ok & pred_ok
    e = err[use].astype(np.float64)
    if e.size == 0:
        return {
            "n": 0,
            "missing": int(np.sum(gt_ok & ~pred_ok)),
            "mean": 0.0,
            "median": 0.0,
            "p90": 0.0,
        }
    return {
        "n": int(e.size),
        "missing": int(np.sum(gt_ok & ~pred_ok)),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
    }


def summarise(
    pred_boxes: Array,
    gt_boxes: Array,
    visible: Array | None = None,
    lost: Array | None = None,
    *,
    iou_threshold: float = 0.5,
    precision_px: float = 20.0,
) -> dict[str, float | int]:
    """All box metrics of one single-target run, as plain Python numbers.

    Args:
      pred_boxes: ``[T, 4]`` xywh predictions (NaN or empty rows mean "no box").
      gt_boxes: ``[T, 4]`` xywh ground truth (``0,0,0,0`` or NaN: not visible).
      visible: optional ``[T]`` bool, and-ed with the GT box being present.
      lost: optional ``[T]`` bool, the tracker's own "lost" flag.

    Success rate, AUC and precision use only frames where the target is
    visible; a visible frame where the tracker is lost scores IoU 0 and an
    infinite centre error. ``centre_error`` is the mean over visible frames
    with a box. Keys: ``frames, visible, success_rate, auc, precision,
    mean_iou, centre_error, motp, motp_iou, mota, sa, matches, misses,
    false_positives, mismatches``.

    Raises:
      ValueError: when there are no frames, or shapes do not match.
    """
    pred, gt, vis_in, lost_in = _run_inputs(pred_boxes, gt_boxes, visible, lost)
    out = _box_scores(pred, gt, vis_in, lost_in, iou_threshold, precision_px)
    counts = (
        "frames",
        "visible",
        "boxed",
        "lost",
        "matches",
        "misses",
        "false_positives",
        "mismatches",
    )
    return {k: int(v) if k in counts else float(v) for k, v in out.items()}


def run_ious(
    pred_boxes: Array,
    gt_boxes: Array,
    visible: Array | None = None,
    lost: Array | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``([T] IoU, [T] bool counts)`` of one run by the rules of :func:`summarise`: a lost
    or empty box scores IoU 0, and only frames with a visible ground-truth box count.

    Raises:
      ValueError: as :func:`summarise`.
    """
    pred, gt, vis_in, lost_in = _run_inputs(pred_boxes, gt_boxes, visible, lost)
    ious, vis, _ = _run_ious(pred, gt, vis_in, lost_in)
    return np.asarray(ious, np.float64), np.asarray(vis, bool)


def run_success_curve(
    pred_boxes: Array,
    gt_boxes: Array,
    visible: Array | None = None,
    lost: Array | None = None,
) -> np.ndarray:
    """``[21]`` OTB success plot of one run (fraction of counted frames with ``IoU > t``,
    ``t`` in :data:`OTB_THRESHOLDS`; frames and IoUs of :func:`run_ious`). Its mean x 100
    is ``summarise(...)["auc"]``.

    Raises:
      ValueError: as :func:`summarise`.
    """
    ious, counts = run_ious(pred_boxes, gt_boxes, visible, lost)
    return np.asarray(success_curve(ious, counts), np.float64)


def _run_inputs(pred_boxes, gt_boxes, visible, lost) -> tuple[np.ndarray, ...]:
    pred = np.asarray(pred_boxes, np.float32)
    gt = np.asarray(gt_boxes, np.float32)
    if pred.ndim != 2 or pred.shape[-1] != 4 or gt.shape != pred.shape:
        raise ValueError(
            f"expected pred and gt boxes of shape [T, 4], got {pred.shape} and {gt.shape}"
        )
    if pred.shape[0] == 0:
        raise ValueError("cannot summarise an empty run (0 frames)")
    for name, flags in (("visible", visible), ("lost", lost)):
        if flags is not None and np.shape(flags) != (pred.shape[0],):
            raise ValueError(f"{name} must have shape ({pred.shape[0]},), got {np.shape(flags)}")
    vis_in = np.ones(pred.shape[0], bool) if visible is None else np.asarray(visible, bool)
    lost_in = np.zeros(pred.shape[0], bool) if lost is None else np.asarray(lost, bool)
    return pred, gt, vis_in, lost_in


def _run_ious(pred: Array, gt: Array, visible: Array, lost: Array) -> tuple[Array, ...]:
    """Per-frame IoU (0 without a box), frames that count (GT visible), frames with a box."""
    vis = gt_visible(gt, visible)
    has_box = box_present(pred) & ~lost
    return jnp.where(has_box, frame_ious(pred, gt), 0.0), vis, has_box


@jax.jit
def _box_scores(
    pred: Array, gt: Array, visible: Array, lost: Array, iou_threshold: Array, precision_px: Array
) -> dict[str, Array]:
    # One compiled program per sequence length: the CLI and tests call this often.
    ious, vis, has_box = _run_ious(pred, gt, visible, lost)
    err = centre_errors(pred, gt)
    err_or_inf = jnp.where(has_box, err, jnp.inf)
    mot = clear_mot(pred, gt, vis, ~has_box, match_iou=iou_threshold)
    with_box = vis & has_box
    return {
        "frames": jnp.asarray(pred.shape[0]),
        "visible": jnp.sum(vis),
        "boxed": jnp.sum(with_box),
        "lost": jnp.sum(lost),
        "success_rate": success_rate(ious, vis, iou_threshold),
        "auc": success_auc(ious, vis),
        "precision": precision(err_or_inf, vis, precision_px),
        "mean_iou": _safe_ratio(jnp.sum(jnp.where(vis, ious, 0.0)), jnp.sum(vis)),
        "centre_error": _safe_ratio(jnp.sum(jnp.where(with_box, err, 0.0)), jnp.sum(with_box)),
        "motp": mot.motp,
        "motp_iou": mot.motp_iou,
        "mota": mot.mota,
        "sa": mot.sa,
        "matches": mot.matches,
        "misses": mot.misses,
        "false_positives": mot.false_positives,
        "mismatches": mot.mismatches,
    }


# (key, column header, format) for the CLI table.
_COLUMNS = (
    ("frames", "frames", "{:d}"),
    ("visible", "visible", "{:d}"),
    ("matches", "matched", "{:d}"),
    ("lost", "lost", "{:d}"),
    ("success_rate", "SR@0.5 %", "{:.1f}"),
    ("auc", "AUC %", "{:.1f}"),
    ("precision", "P@20px %", "{:.1f}"),
    ("centre_error", "CE px", "{:.1f}"),
    ("motp", "MOTP px", "{:.1f}"),
    ("mota", "MOTA %", "{:.1f}"),
    ("sa", "SA px", "{:.1f}"),
)

# The count each mean is taken over: with none, the table shows "-", not 0.
_BASIS = {
    "success_rate": "visible",
    "auc": "visible",
    "precision": "visible",
    "mean_iou": "visible",
    "mota": "visible",
    "centre_error": "boxed",
    "motp": "matches",
    "motp_iou": "matches",
    "sa": "matches",
}


def format_summary(
    summaries: Mapping[str, Mapping[str, float | int]] | Mapping[str, float | int],
) -> str:
    """A Markdown table of one :func:`summarise` result or a ``{name: result}`` mapping.

    Missing keys, and means over no frames (a zero count in ``_BASIS``: no visible
    frame, no frame with a box, no match), are shown as ``-``.
    """
    if summaries and all(not isinstance(v, Mapping) for v in summaries.values()):
        rows = {"run": summaries}
    else:
        rows = dict(summaries)  # type: ignore[arg-type]
    header = ["run"] + [title for _, title, _ in _COLUMNS]
    body = []
    for name, s in rows.items():
        cells = [str(name)]
        for key, _, fmt in _COLUMNS:
            v = s.get(key)  # type: ignore[union-attr]
            basis = s.get(_BASIS.get(key, ""), 1)  # type: ignore[union-attr]
            empty = v is None or basis == 0 or (fmt != "{:d}" and not np.isfinite(float(v)))
            cells.append("-" if empty else fmt.format(int(v) if fmt == "{:d}" else float(v)))
        body.append(cells)
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]

    def fmt_row(cells: list[str]) -> str:
        return (
            "| "
            + " | ".join(
                c.ljust(w) if i == 0 else c.rjust(w)
                for i, (c, w) in enumerate(zip(cells, widths, strict=True))
            )
            + " |"
        )

    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([fmt_row(header), sep, *(fmt_row(r) for r in body)])
