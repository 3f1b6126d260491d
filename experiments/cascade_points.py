"""The cascade on synthetic walks: body points tracked in layer 1's boxes vs in ground-truth boxes.

``experiments/depth_points.py`` scores the depth layer with the ground-truth box of every
frame (a perfect layer 1). Here the same points (head, both hands, both feet; combined
spin + geodesic weighting, the same settings, joint offsets and cases) are tracked by
``cpf_jax.cascade``, which takes each frame's box from a layer-1 filter:

* ``gt``: ground-truth boxes (depth_points.py's "combined" row, re-run here);
* ``grid-occlusion``: the RGB-D box filter (N = 150, ``cpf_jax.rgbd``) with a background
  model (walk_towards: the empty room, since the walker covers the middle of the view
  the whole time; walk_across_medium: the median of every 8th frame);
* ``rgb``: the colour layer (N = 150, ``cpf_jax.colour``).

The question is how much of layer 2's error comes from layer 1's boxes. Errors are 3D
distances between the weighted-mean estimate and the joint centre, pooled over keys
(and both hands); ``box SR`` is layer 1's success rate (IoU >= 0.5).

Writes ``experiments/results/cascade_points.{json,md}``.

    python experiments/cascade_points.py [--frames 200] [--keys 3]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import depth_points as dp  # noqa: E402

from cpf_jax import params as pp  # noqa: E402
from cpf_jax.cascade import CascadeConfig, build_cascade, default_cascade_params  # noqa: E402
from cpf_jax.colour import ColourConfig  # noqa: E402
from cpf_jax.filter import Context, track  # noqa: E402
from cpf_jax.kernels.background import median_background  # noqa: E402
from cpf_jax.kernels.boxes import iou  # noqa: E402
from cpf_jax.points import PointConfig  # noqa: E402
from cpf_jax.rgbd import RGBDConfig  # noqa: E402
from cpf_jax.synthetic import make_sequence  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SOURCES = ("gt", "grid-occlusion", "rgb")
N_BOX = 150


def _box_config(source: str, seq) -> ColourConfig | RGBDConfig:
    wh = tuple(float(v) for v in seq.boxes[0, 2:])
    hw = seq.colour.shape[1:3]
    if source == "rgb":
        # The histogram-only colour model, with which the results table was made.
        return ColourConfig(n_particles=N_BOX).histogram_only().with_window(wh, hw)
    return RGBDConfig(variant=source, n_particles=N_BOX).with_window(wh, hw)


def _background(case: str, seq):
    if case == "walk_towards":  # the walker covers the middle of the view throughout
        return median_background(
            jnp.asarray(seq.meta["background_colour"])[None],
            jnp.asarray(seq.meta["background_depth"])[None],
        )
    return median_background(jnp.asarray(seq.colour[::8]), jnp.asarray(seq.depth[::8]))


def run_cascade(case: str, seq, source: str, keys: int, use_fg: bool):
    config = CascadeConfig(
        box=_box_config(source, seq),
        points=PointConfig(weighting="combined").with_foreground()
        if use_fg
        else PointConfig(weighting="combined"),
        foreground=use_fg,
    )
    filt = build_cascade(config)
    params = default_cascade_params(config)
    params = pp.replace(params, "points.estimate.joint_depth_offset", jnp.asarray(dp.JOINT_OFFSET))
    idx = [list(seq.joint_names).index(n) for n in dp.TRACKED]
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    start = jnp.asarray(seq.joints2d[0, idx] + 0.5)
    context = Context(background=_background(case, seq), points=start)
    box = jnp.asarray(seq.boxes[0])
    go = jax.jit(lambda k: track(filt, params, k, frames, box, context)[1])
    out = []
    for k in range(keys):
        t0 = time.perf_counter()
        info = jax.device_get(go(jax.random.PRNGKey(k)))
        out.append((info, time.perf_counter() - t0))
    return out, idx


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--keys", type=int, default=3)
    ap.add_argument("--cases", default=",".join(dp.CASES))
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    report: dict = {"frames": args.frames, "keys": args.keys, "box_particles": N_BOX}
    md = [
        "# The cascade: body points in layer 1's boxes vs ground-truth boxes",
        "",
        "Regenerate with `python experiments/cascade_points.py`; settings as "
        "`depth_points.py` (combined weighting, 100 particles per point, 30 frames/s); "
        f"{args.keys} keys, layer 1 with N = {N_BOX}.",
    ]
    for case in args.cases.split(","):
        kw, use_fg = dp.CASES[case]
        seq = make_sequence(case, seed=0, n_frames=args.frames, fps=30.0, **kw)
        md += [
            "",
            f"## {case}",
            "",
            "| boxes | box SR % | median hand error mm | p90 mm | head median mm "
            "| feet median mm | s / run |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for source in SOURCES:
            if source == "gt":
                fg = dp.temporal_foreground(seq) if use_fg else None
                runs, idx = dp.run(seq, "combined", args.keys, fg)
                box_sr = 100.0
            else:
                runs, idx = run_cascade(case, seq, source, args.keys, use_fg)
                srs = []
                for info, _ in runs:
                    ious = np.asarray(iou(jnp.asarray(info.estimate), jnp.asarray(seq.boxes[1:])))
                    srs.append(100.0 * float(np.mean(ious >= 0.5)))
                box_sr = float(np.mean(srs))
                runs = [(info.points, t) for info, t in runs]
            errs = np.stack([dp.errors(seq, info, idx) for info, _ in runs])  # [keys, T, P]
            hands = errs[..., list(dp.HANDS)]
            row = {
                "box_success_rate": round(box_sr, 1),
                "median_hand_error_mm": round(float(np.median(hands)), 1),
                "p90_hand_error_mm": round(float(np.percentile(hands, 90)), 1),
                "head_median_error_mm": round(float(np.median(errs[..., 0])), 1),
                "feet_median_error_mm": round(float(np.median(errs[..., 3:])), 1),
                "seconds_per_run": round(float(np.median([t for _, t in runs[1:] or runs])), 1),
            }
            report.setdefault(case, {})[source] = row
            md.append(
                f"| {source} | {row['box_success_rate']} | {row['median_hand_error_mm']} | "
                f"{row['p90_hand_error_mm']} | {row['head_median_error_mm']} | "
                f"{row['feet_median_error_mm']} | {row['seconds_per_run']} |"
            )
            print(case, source, row, flush=True)
    md += [
        "",
        "'s / run' is one jitted run of the whole sequence after the first (compile) run; "
        f"load average at the start {load:.1f}.",
    ]
    (RESULTS / "cascade_points.json").write_text(json.dumps(report, indent=1) + "\n")
    (RESULTS / "cascade_points.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'cascade_points.md'}")


if __name__ == "__main__":
    main()
