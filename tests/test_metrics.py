"""Tests for cpf_jax.metrics: against plain-Python references, under jit and vmap."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel
from hypothesis import given, settings
from hypothesis import strategies as st

from cpf_jax import metrics as M


def ref_iou(a, b):
    """Plain-Python IoU of two xywh boxes."""
    ax1, ay1, bx1, by1 = a[0] + a[2], a[1] + a[3], b[0] + b[2], b[1] + b[3]
    iw = max(0.0, min(ax1, bx1) - max(a[0], b[0]))
    ih = max(0.0, min(ay1, by1) - max(a[1], b[1]))
    inter = iw * ih
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def ref_summary(pred, gt, visible, lost, thr=0.5):
    """A frame-by-frame loop written straight from the definitions."""
    ious, errs, vis_n = [], [], 0
    m = fp = miss = 0
    d_sum = s_sum = 0.0
    for p, g, v, lo in zip(pred, gt, visible, lost, strict=True):
        has = (not lo) and p[2] > 0 and p[3] > 0
        if v:
            vis_n += 1
            i = ref_iou(p, g) if has else 0.0
            ious.append(i)
            cx = (p[0] + p[2] / 2) - (g[0] + g[2] / 2)
            cy = (p[1] + p[3] / 2) - (g[1] + g[3] / 2)
            errs.append(math.hypot(cx, cy) if has else math.inf)
            if has and i >= thr:
                m += 1
                d_sum += math.hypot(cx, cy)
                s_sum += math.hypot(p[2] - g[2], p[3] - g[3])
            else:
                miss += 1
                fp += int(has)
        else:
            fp += int(has)
    n = max(vis_n, 1)
    curve = [sum(i > t for i in ious) / n for t in np.linspace(0, 1, 21)]
    return {
        "success_rate": 100 * sum(i >= thr for i in ious) / n,
        "auc": 100 * float(np.mean(curve)),
        "precision": 100 * sum(e <= 20 for e in errs) / n,
        "motp": d_sum / m if m else 0.0,
        "sa": s_sum / m if m else 0.0,
        "mota": 100 * (1 - (miss + fp) / n),
        "matches": m,
        "misses": miss,
        "false_positives": fp,
    }


def random_run(rng, t=40):
    gt = np.column_stack([rng.uniform(0, 100, (t, 2)), rng.uniform(5, 40, (t, 2))]).astype(
        np.float32
    )
    pred = gt + rng.normal(0, 6, gt.shape).astype(np.float32)
    pred[:, 2:] = np.abs(pred[:, 2:]) + 1
    visible = rng.random(t) > 0.2
    gt[~visible] = 0
    lost = rng.random(t) < 0.1
    return pred, gt, visible, lost


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_summarise_matches_reference_loop(seed):
    pred, gt, visible, lost = random_run(np.random.default_rng(seed))
    got = M.summarise(pred, gt, visible, lost)
    want = ref_summary(pred.tolist(), gt.tolist(), visible, lost)
    for key, value in want.items():
        assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-3), key
    assert got["frames"] == len(pred)
    assert got["visible"] == int(visible.sum())
    assert got["mismatches"] == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_run_ious_and_success_curve_follow_the_reference_loop(seed):
    pred, gt, visible, lost = random_run(np.random.default_rng(seed))
    curve = M.run_success_curve(pred, gt, visible, lost)
    # Plain loop: visible frames only, a lost frame scores IoU 0, strict "> t".
    ious = [
        0.0 if lost[t] else ref_iou(pred[t].tolist(), gt[t].tolist())
        for t in range(len(pred))
        if visible[t]
    ]
    want = [np.mean([v > th for v in ious]) for th in np.linspace(0, 1, 21)]
    np.testing.assert_allclose(curve, want, atol=1e-6)
    got, counts = M.run_ious(pred, gt, visible, lost)
    np.testing.assert_array_equal(counts, visible)
    np.testing.assert_allclose(got[counts], ious, atol=1e-6)
    assert 100 * curve.mean() == pytest.approx(M.summarise(pred, gt, visible, lost)["auc"])
    with pytest.raises(ValueError, match="lost must have shape"):
        M.run_success_curve(pred, gt, visible, lost[:-1])


def test_hand_worked_example():
    gt = np.array([[10, 10, 20, 20], [10, 10, 20, 20], [0, 0, 0, 0], [5, 5, 10, 10]], np.float32)
    pred = np.array([[10, 10, 20, 20], [15, 10, 20, 20], [3, 3, 4, 4], [np.nan] * 4], np.float32)
    s = M.summarise(pred, gt)
    assert s["visible"] == 3
    assert s["mean_iou"] == pytest.approx((1 + 0.6 + 0) / 3)
    assert s["success_rate"] == pytest.approx(200 / 3)
    # frame 3: box with target out of view -> FP; frame 4: lost on a visible target -> miss
    assert (s["matches"], s["misses"], s["false_positives"]) == (2, 1, 1)
    assert s["mota"] == pytest.approx(100 * (1 - 2 / 3))
    assert s["motp"] == pytest.approx(2.5)  # centre distances 0 and 5 over 2 matches
    assert s["motp_iou"] == pytest.approx(0.8)


def test_lost_flag_suppresses_false_positive_when_out_of_view():
    gt = np.zeros((3, 4), np.float32)
    pred = np.tile(np.float32([1, 1, 5, 5]), (3, 1))
    assert M.summarise(pred, gt)["false_positives"] == 3
    s = M.summarise(pred, gt, lost=np.array([True, True, False]))
    assert s["false_positives"] == 1
    # no GT object at all: denominator taken as 1
    assert s["mota"] == pytest.approx(0.0)
    assert M.summarise(pred, gt, lost=np.ones(3, bool))["mota"] == pytest.approx(100.0)


def test_scale_adaptation_eq10():
    gt = np.array([[0, 0, 40, 40], [0, 0, 40, 40]], np.float32)
    pred = np.array([[0, 0, 43, 44], [0, 0, 46, 48]], np.float32)  # dw,dh = (3,4), (6,8)
    mot = M.clear_mot(pred, gt, match_iou=0.5)
    assert float(mot.sa) == pytest.approx((5 + 10) / 2)


def test_success_curve_uses_strict_threshold_and_otb_grid():
    ious = jnp.array([0.0, 0.5, 1.0])
    curve = np.asarray(M.success_curve(ious))
    assert curve.shape == (21,)
    assert curve[0] == pytest.approx(2 / 3)  # IoU > 0
    assert curve[10] == pytest.approx(1 / 3)  # IoU > 0.5
    assert curve[-1] == 0.0  # IoU > 1 never
    assert float(M.success_rate(ious)) == pytest.approx(200 / 3)  # >= 0.5
    assert float(M.success_auc(ious)) == pytest.approx(100 * curve.mean())


def test_perfect_tracking():
    gt = np.array([[3, 4, 10, 12]] * 5, np.float32)
    s = M.summarise(gt, gt)
    assert s["success_rate"] == 100 and s["precision"] == 100 and s["mota"] == 100
    assert s["auc"] == pytest.approx(100 * 20 / 21)  # IoU 1 is not > 1
    assert s["motp"] == 0 and s["sa"] == 0


def test_no_nan_without_visible_frames_or_matches():
    gt = np.zeros((4, 4), np.float32)
    pred = np.full((4, 4), np.nan, np.float32)
    s = M.summarise(pred, gt)
    assert all(math.isfinite(v) for v in s.values())
    assert s["visible"] == 0 and s["success_rate"] == 0 and s["motp"] == 0


def test_bad_input_raises_value_error():
    with pytest.raises(ValueError, match="empty"):
        M.summarise(np.zeros((0, 4)), np.zeros((0, 4)))
    with pytest.raises(ValueError, match=r"\[T, 4\]"):
        M.summarise(np.zeros((3, 4)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="visible"):
        M.summarise(np.zeros((3, 4)), np.zeros((3, 4)), visible=np.ones(2, bool))


def test_scores_match_the_reference_loop_plainly_under_jit_and_vmap():
    runs = [random_run(np.random.default_rng(s), t=30) for s in range(4)]

    def scores(p, g, v, lo):
        ious = M.frame_ious(p, g)
        mot = M.clear_mot(p, g, v, lo)
        return M.success_rate(ious, v), M.success_auc(ious, v), mot.mota, mot.motp

    def reference(p, g, v, lo):
        # Success rate and AUC of the raw IoUs (lost frames keep theirs) over visible frames.
        p, g = np.asarray(p).tolist(), np.asarray(g).tolist()
        ious = [ref_iou(a, b) for a, b, vis in zip(p, g, v, strict=True) if vis]
        n = max(len(ious), 1)
        curve = [sum(i > t for i in ious) / n for t in np.linspace(0, 1, 21)]
        mot = ref_summary(p, g, v, lo)
        sr = 100 * sum(i >= 0.5 for i in ious) / n
        return sr, 100 * float(np.mean(curve)), mot["mota"], mot["motp"]

    check_kernel(scores, reference, runs[0], batch=runs, rtol=1e-5, atol=1e-4)


def test_precision_counts_lost_frames_as_failures():
    err = jnp.array([1.0, 25.0, jnp.inf, 20.0])
    assert float(M.precision(err)) == pytest.approx(50.0)
    assert float(M.precision(err, jnp.array([True, False, False, True]))) == 100.0


def test_point_errors_3d():
    gt = np.array([[0, 0, 1000], [0, 0, 2000], [np.nan] * 3, [10, 0, 0]], np.float64)
    pred = np.array([[3, 4, 1000], [0, 0, 2012], [1, 1, 1], [np.nan] * 3])
    np.testing.assert_allclose(np.asarray(M.point_errors(pred[:2], gt[:2])), [5, 12])
    s = M.point_error_summary(pred, gt)
    assert s["n"] == 2 and s["missing"] == 1
    assert s["median"] == pytest.approx(8.5) and s["mean"] == pytest.approx(8.5)
    assert s["p90"] == pytest.approx(np.percentile([5, 12], 90))
    assert M.point_error_summary(np.zeros((0, 3)), np.zeros((0, 3)))["n"] == 0
    with pytest.raises(ValueError):
        M.point_error_summary(np.zeros((2, 3)), np.zeros((3, 3)))


def test_format_summary_table():
    gt = np.array([[3, 4, 10, 12]] * 5, np.float32)
    s = M.summarise(gt, gt)
    one = M.format_summary(s)
    lines = one.splitlines()
    assert len(lines) == 3 and "SR@0.5 %" in lines[0] and "MOTA %" in lines[0]
    assert "100.0" in lines[2]
    many = M.format_summary({"cpf": s, "baseline": {"frames": 5}})
    assert many.splitlines()[3].startswith("| baseline") and " - " in many.splitlines()[3]
    assert len({len(line) for line in many.splitlines()}) == 1  # aligned columns


box = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(0, 60), st.floats(0, 60))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(box, box), min_size=1, max_size=8))
def test_metrics_are_bounded_and_finite(pairs):
    pred = np.array([p for p, _ in pairs], np.float32)
    gt = np.array([g for _, g in pairs], np.float32)
    s = M.summarise(pred, gt)
    assert all(math.isfinite(v) for v in s.values())
    for key in ("success_rate", "auc", "precision"):
        assert 0 <= s[key] <= 100
    assert s["mota"] <= 100
    assert s["matches"] + s["misses"] == s["visible"]
