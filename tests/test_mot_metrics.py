"""Multi-object metrics (cpf_jax.metrics.multi) against py-motmetrics and hand-computed cases,
and the assignment they rest on against SciPy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from cpf_jax.metrics import mot_metrics
from cpf_jax.metrics.assignment import min_cost_assignment


@pytest.mark.parametrize("seed", range(4))
def test_min_cost_assignment_matches_scipy_with_forbidden_pairs(seed):
    rng = np.random.default_rng(seed)
    for _ in range(200):
        n, m = rng.integers(1, 9, 2)
        cost = rng.random((n, m))
        cost[rng.random((n, m)) < 0.3] = np.nan
        rows, cols = min_cost_assignment(cost)
        ok = np.isfinite(cost)
        assert np.all(ok[rows, cols]) and len(set(cols)) == len(cols)
        if not ok.any():
            assert rows.size == 0
            continue
        # SciPy on the same pricing of forbidden pairs, then those pairs dropped.
        r, c = linear_sum_assignment(np.where(ok, cost, 4 * min(n, m) + 1))
        keep = ok[r, c]
        assert len(rows) == keep.sum()
        np.testing.assert_allclose(cost[rows, cols].sum(), cost[r[keep], c[keep]].sum())


def _scene(rng, frames=30, n=4):
    """Ground truth of ``n`` boxes moving straight, and hypotheses that miss some, jitter,
    swap identities now and then and add a wandering false positive."""
    gt, hyp = [], []
    pos, vel = rng.uniform(0, 200, (n, 2)), rng.normal(0, 3, (n, 2))
    size, ids = rng.uniform(20, 60, (n, 2)), np.arange(n) + 10
    for t in range(frames):
        pos += vel
        if rng.random() < 0.1:
            a, b = rng.choice(n, 2, replace=False)
            ids[[a, b]] = ids[[b, a]]
        for k in range(n):
            if rng.random() < 0.9:
                gt.append([t, k, *pos[k], *size[k]])
            if rng.random() < 0.85:
                jitter = rng.normal(0, 6, 2), size[k] * rng.uniform(0.8, 1.2, 2)
                hyp.append([t, ids[k], *(pos[k] + jitter[0]), *jitter[1]])
        if rng.random() < 0.2:
            hyp.append([t, 99, *rng.uniform(0, 200, 2), 30, 30])
    return np.array(gt), np.array(hyp)


def _motmetrics(gt, hyp, monkeypatch):
    monkeypatch.setattr(np, "asfarray", lambda a, dtype=np.float64: np.asarray(a, dtype), False)
    import motmetrics as mm  # 1.4 calls np.asfarray, which NumPy 2 removed

    acc = mm.MOTAccumulator(auto_id=False)
    for t in np.union1d(gt[:, 0], hyp[:, 0]):
        g, h = gt[gt[:, 0] == t], hyp[hyp[:, 0] == t]
        d = mm.distances.iou_matrix(g[:, 2:6], h[:, 2:6], max_iou=0.5)
        acc.update(g[:, 1].astype(int), h[:, 1].astype(int), d, frameid=int(t))
    names = ["mota", "motp", "idf1", "num_switches", "num_false_positives", "num_misses"]
    return mm.metrics.create().compute(acc, metrics=names, name="run").iloc[0]


def test_the_cross_check_scenes_have_switches_misses_and_false_positives():
    for seed in range(6):
        m = mot_metrics(*_scene(np.random.default_rng(seed)))
        assert m.id_switches > 0 and m.misses > 0 and m.false_positives > 0, (seed, m)


@pytest.mark.parametrize("seed", range(6))
def test_clear_mot_and_idf1_agree_with_py_motmetrics(seed, monkeypatch):
    gt, hyp = _scene(np.random.default_rng(seed))
    ours, ref = mot_metrics(gt, hyp), _motmetrics(gt, hyp, monkeypatch)
    assert ours.id_switches == ref["num_switches"]
    assert (ours.false_positives, ours.misses) == (ref["num_false_positives"], ref["num_misses"])
    assert ours.mota == pytest.approx(100 * ref["mota"], abs=1e-9)
    assert ours.motp == pytest.approx(100 * (1 - ref["motp"]), abs=1e-3)  # IoU in float32
    assert ours.idf1 == pytest.approx(100 * ref["idf1"], abs=1e-9)


def test_hota_of_a_track_split_in_two_by_hand():
    # One person in 4 frames, found exactly (IoU 1) by hypothesis 1 in frames 0-1 and by
    # hypothesis 2 in frames 2-3. Every alpha: TP 4, FN = FP = 0, so DetA = 1; each pair's
    # association IoU is 2 / (4 + 2 - 2) = 0.5, so AssA = (2 x 0.5 + 2 x 0.5) / 4 = 0.5 and
    # HOTA = sqrt(1 x 0.5). CLEAR: 4 matches, one switch, MOTA 75 %; IDF1 2 x 2 / (4 + 4).
    box = [10.0, 20.0, 30.0, 60.0]
    gt = np.array([[t, 7, *box] for t in range(4)])
    hyp = np.array([[t, 1 if t < 2 else 2, *box] for t in range(4)])
    m = mot_metrics(gt, hyp)
    assert m.deta == pytest.approx(100.0) and m.assa == pytest.approx(50.0)
    assert m.hota == pytest.approx(100 * np.sqrt(0.5))
    assert (m.mota, m.id_switches, m.idf1, m.motp) == (75.0, 1, 50.0, 100.0)


def test_hota_averages_over_the_localisation_thresholds_by_hand():
    # IoU 0.61 in both frames: a true positive for the 12 alphas 0.05-0.60 (DetA = AssA =
    # 1 there), a miss and a false positive for the 7 above (DetA = 0): HOTA = 12 / 19.
    gt = np.array([[t, 0, 0.0, 0.0, 10.0, 10.0] for t in range(2)])
    hyp = np.array([[t, 5, 0.0, 0.0, 10.0, 6.1] for t in range(2)])
    m = mot_metrics(gt, hyp)
    assert m.hota == pytest.approx(100 * 12 / 19) and m.deta == pytest.approx(100 * 12 / 19)
    assert m.assa == pytest.approx(100 * 12 / 19)  # AssA 1 where there are matches, else 0
    assert m.mota == 100.0 and m.motp == pytest.approx(61.0, abs=1e-4)


def test_nothing_to_track_and_bad_rows():
    assert mot_metrics(np.zeros((0, 6)), np.zeros((0, 6))).mota == 100.0
    only_fp = mot_metrics(np.zeros((0, 6)), np.array([[0, 1, 0, 0, 5, 5]]))
    assert only_fp.false_positives == 1 and only_fp.hota == 0.0
    with pytest.raises(ValueError, match=r"\[K, 6\+\] rows"):
        mot_metrics(np.zeros((3, 4)), np.zeros((0, 6)))
    with pytest.raises(ValueError, match="an id appears twice in frame 2"):
        mot_metrics(np.array([[2, 1, 0, 0, 5, 5], [2, 1, 9, 9, 5, 5]]), np.zeros((0, 6)))


def test_motchallenge_files_round_trip_in_0_based_frames_and_pixels(tmp_path):
    from cpf_jax.errors import SourceError
    from cpf_jax.io import MotWriter, read_mot

    with MotWriter(tmp_path / "run.txt") as out:
        out.write(0, [3, 4], [[0.0, 10.0, 20.0, 40.0], [5.5, 6.0, 7.0, 8.0]], [0.9, 0.5])
        out.write(2, [3], [[1.0, 11.0, 20.0, 40.0]])
    text = (tmp_path / "run.txt").read_text().splitlines()
    assert text[0] == "1,3,1.00,11.00,20.00,40.00,0.900,-1,-1,-1"  # 1-based, as MOTChallenge
    rows = read_mot(tmp_path / "run.txt")
    np.testing.assert_allclose(
        rows[:, :6], [[0, 3, 0, 10, 20, 40], [0, 4, 5.5, 6, 7, 8], [2, 3, 1, 11, 20, 40]]
    )
    assert mot_metrics(rows, rows).mota == 100.0
    (tmp_path / "bad.txt").write_text("1,2,3\n")
    with pytest.raises(SourceError, match=r"bad.txt:1: expected 'frame,id,x,y,w,h"):
        read_mot(tmp_path / "bad.txt")
