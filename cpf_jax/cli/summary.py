"""``cpf-track``'s results: the summary printed at the end of a run, the body points' errors
against synthetic joints, and the ``--plot`` figure."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cpf_jax.cli.options import JOINTS
from cpf_jax.errors import CpfJaxError

__all__ = [
    "Results",
    "point_errors",
    "point_table",
    "print_summary",
    "scored_line",
    "write_plot",
]


class Results(NamedTuple):
    """One entry per tracked frame, in order."""

    frames: list  # frame indices
    boxes: list  # [4] xywh boxes
    lost: list  # bool
    ess: list  # float
    points2d: list  # [P, 2] px
    points3d: list  # [P, 3] mm
    windowed: list  # bool, one per step (not the first frame)


def new_results() -> Results:
    return Results([], [], [], [], [], [], [])


def _auto_joints(source, start: int) -> tuple[str, ...] | None:
    """The synthetic joints ``--points auto``'s points stand for (``AUTO_POINTS`` order:
    "a" is the joint further left in the image at ``start``), or None without joints."""
    seq = getattr(source, "sequence", None)
    names = list(getattr(seq, "joint_names", ()))
    if not all(n in names for n in JOINTS):
        return None
    u = seq.joints2d[start, :, 0]
    out = ["head"]
    for part in ("hand", "foot"):
        left, right = f"left_{part}", f"right_{part}"
        pair = (left, right) if u[names.index(left)] <= u[names.index(right)] else (right, left)
        out.extend(pair)
    return tuple(out)


class PointErrors(NamedTuple):
    names: tuple[str, ...]  # the tracked points
    joints: tuple[str, ...]  # the synthetic joint each point stands for
    frames: np.ndarray  # [T'] frames scored (visible target, not the given initial frame)
    err2d: np.ndarray  # [T', P] px
    err3d: np.ndarray  # [T', P] mm (inf: no 3D estimate)


def point_errors(args, source, names, results: Results) -> PointErrors | None:
    """Errors of the tracked points against the synthetic joints they stand for
    (``--points joints`` or ``auto`` on a synthetic scenario), over the tracked frames
    ``done`` where the target is visible; None without joints to score against."""
    if not names or not results.frames or args.points not in ("joints", "auto"):
        return None
    done = np.asarray(results.frames, int)
    joints = tuple(names) if args.points == "joints" else _auto_joints(source, done[0])
    if joints is None:
        return None
    seq = source.sequence
    idx = [list(seq.joint_names).index(n) for n in joints]
    sel = np.ones(len(done), bool)
    sel[0] = False  # the initial frame is where the points were given, not tracked
    if source.visible is not None:
        sel &= np.asarray(source.visible, bool)[done]
    frames = done[sel]
    p2, p3 = np.stack(results.points2d)[sel], np.stack(results.points3d)[sel]
    e2 = np.linalg.norm(p2 - (seq.joints2d[frames][:, idx] + 0.5), axis=-1)
    e3 = np.linalg.norm(p3 - seq.joints3d[frames][:, idx], axis=-1)
    e3 = np.where(np.isfinite(e3), e3, np.inf)  # no 3D estimate counts as lost
    return PointErrors(tuple(names), joints, frames, e2, e3)


def point_table(errors: PointErrors) -> str:
    """Median 2D / 3D error of each point (Markdown)."""
    lines = ["| point | joint | median 2D error px | median 3D error mm |", "|---|---|---:|---:|"]
    for k, name in enumerate(errors.names):
        e2, e3 = errors.err2d[:, k], errors.err3d[:, k]
        med2 = float(np.median(e2)) if e2.size else float("nan")
        med3 = float(np.median(e3)) if e3.size else float("nan")
        lines.append(f"| {name} | {errors.joints[k]} | {med2:.1f} | {med3:.1f} |")
    return "\n".join(lines)


def write_plot(
    args: argparse.Namespace,
    source,
    results: Results,
    n_particles: int,
    points: PointErrors | None = None,
) -> None:
    """``--plot``: per-frame IoU (with ground truth; 0 when lost) and ESS / N, the
    success plot with its AUC, and the body points' 3D errors per frame (scored against
    synthetic joints), as one PNG (``cpf_jax.charts``)."""
    from cpf_jax import charts
    from cpf_jax.metrics import run_ious, success_curve

    idx = np.asarray(results.frames, int)
    ess = np.asarray(results.ess, np.float64) / n_particles
    pred, lost = np.stack(results.boxes), np.asarray(results.lost)
    series = {"ESS / N": (idx, ess)}
    name = Path(str(args.path)).name or str(args.path)
    curve = None
    if source.gt_boxes is not None:
        vis = None if source.visible is None else np.asarray(source.visible)[idx]
        iou, counts = run_ious(pred, source.gt_boxes[idx], vis, lost)
        series = {"IoU with the ground truth (0: lost)": (idx, np.where(counts, iou, np.nan))}
        series["ESS / N"] = (idx, ess)
        curve = np.asarray(success_curve(iou, counts))
    panels = [
        charts.line_chart(
            series,
            title=f"{name}: per frame",
            xlabel="frame",
            ylabel="IoU, ESS / N" if curve is not None else "ESS / N",
            ylim=(0.0, 1.0),
            markers=idx.size <= 60,
        )
    ]
    if curve is not None:
        panels.append(charts.success_plot({name: curve}, title=f"{name}: success plot"))
    if points is not None and points.frames.size:
        labels = [
            n if n == j else f"{n} ({j})" for n, j in zip(points.names, points.joints, strict=True)
        ]
        panels.append(
            charts.line_chart(
                {
                    label: (points.frames, np.minimum(points.err3d[:, k], 500.0))
                    for k, label in enumerate(labels)
                },
                title=f"{name}: body points, 3D error (mm, clipped at 500; lost: 500)",
                xlabel="frame",
                ylabel="error (mm)",
                ylim=(0.0, 500.0),
                markers=False,
            )
        )
    try:
        charts.save_png(np.concatenate(panels), args.plot)
    except OSError as e:
        raise CpfJaxError(f"--plot: {e}") from None


def print_summary(args: argparse.Namespace, source, inputs, model, results: Results) -> None:
    """The run in a few lines: what was tracked, the metrics table against the ground truth
    with which frames it scores, and the body points' errors on stdout; notes and where the
    outputs went on stderr."""
    from cpf_jax.metrics import format_summary, summarise

    registered = ", depth registered" if inputs.calibration is not None else ""
    points = f", {len(model.points)} body points" if model.points else ""
    print(
        f"tracked {len(results.frames)} frames of {source.describe()} with "
        f"N={model.n_particles} (model {args.model}{registered}{points})"
    )
    if inputs.note is not None:
        _note(inputs.note)
    n_steps, n_windowed = len(results.windowed), sum(results.windowed)
    if n_windowed < n_steps:
        _note(
            f"{n_steps - n_windowed} of {n_steps} steps counted histograms on the whole "
            "frame (exact, slower): particle boxes left the histogram window sized for the "
            "initial box (info.windowed)"
        )
    idx = np.asarray(results.frames, int)
    if source.gt_boxes is not None and idx.size:
        vis = None if source.visible is None else np.asarray(source.visible)[idx]
        lost = np.asarray(results.lost)
        summary = summarise(np.stack(results.boxes), source.gt_boxes[idx], vis, lost)
        print(format_summary({Path(str(args.path)).name or str(args.path): summary}))
        print(scored_line(idx, source.gt_boxes[idx], vis, summary))
    elif idx.size:
        print("no ground truth: nothing scored (boxes only)")
    errors = point_errors(args, source, model.points, results)
    if errors is not None:
        print(point_table(errors))
    if args.out:
        _note(f"boxes written to {args.out}")
    if args.rrd:
        _note(f"Rerun recording written to {args.rrd}")
    if args.plot and results.frames:
        _note(f"plot written to {args.plot}")


def scored_line(frames: np.ndarray, gt: np.ndarray, visible, summary: dict) -> str:
    """Which of the tracked ``frames`` the table scores, which it leaves out and why, and
    how many were matched (IoU >= 0.5) and reported lost."""
    from cpf_jax.cli.inputs import ranges
    from cpf_jax.metrics import gt_visible

    counted = np.asarray(gt_visible(gt, visible), bool)
    line = (
        f"scored {int(counted.sum())} of {frames.size} tracked frames "
        f"({frames[0]}-{frames[-1]}, the first being the start box); matched "
        f"{summary['matches']} (IoU >= 0.5), lost {summary['lost']}"
    )
    if not counted.all():
        left = [int(i) for i in frames[~counted]]
        line += f"; left out, the target not visible in the ground truth: {ranges(left)}"
    if frames[0] > 0:
        before = ranges(list(range(int(frames[0]))))
        line += f"; frame(s) {before} come before the start and are not tracked"
    return line


def _note(message: str) -> None:
    print(f"cpf-track: note: {message}", file=sys.stderr)
