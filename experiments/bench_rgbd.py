"""Benchmark: one jitted RGB-D box-filter step vs a per-particle OpenCV + NumPy loop.

    python experiments/bench_rgbd.py            # -> results/bench_rgbd.{json,md}
    python experiments/bench_rgbd.py --quick    # few repeats, N <= 1,000 (smoke test)
    python experiments/bench_rgbd.py --figure-only  # redraw results/bench_rgbd.png

"RGB-D step" = one jitted ``step`` of ``cpf_jax.rgbd.build_rgbd_filter`` for each
of the paper's RGB-D variants ("rgbd", "grid", "grid-occlusion"; the "rgb" row is
the colour layer, timed by ``bench_colour.py``) on a 512 x 424 synthetic
Kinect-v2 frame (``walk_across_medium``, seed 0, frame 10, with its empty room as
the background model), library defaults, the histogram window sized by
``RGBDConfig.with_window`` from the ground-truth box: foreground mask, colour
and depth bins, propagation, per-cell foreground ratio, colour and median-depth
terms of every particle from windowed integral histograms, border strips, the
occlusion-flag posterior over the 2^C flag states, the detector and recovery
proposals, estimate, template update, resampling.

The baseline is what the paper's per-cell likelihood costs when written with
OpenCV and NumPy (less work than our step: no border strips, flags or
proposals): per frame one ``cvtColor`` and a vectorised foreground mask; per
particle and per cell of the 2 x 2 grid the foreground ratio (``mask.mean``),
a masked ``cv2.calcHist`` on H and S compared with the cell's template by
``cv2.compareHist`` (Bhattacharyya), and ``np.median`` of the cell's foreground
depth. It is measured up to N = 1,000 and scaled linearly above (its cost is
per particle).

Like ``bench_colour.py`` it calls ``cpu_tuning.tune_malloc()`` before JAX
allocates (``--no-tune-malloc`` to skip) and adds
``cpu_tuning.xla_cpu_flags(library_fusions=False)`` to ``XLA_FLAGS``
(``--no-tune-xla``), and times the grid-occlusion step again in a fresh process without
either, the path a plain ``jax.jit(filt.step)`` of the Python API takes.
"""

from __future__ import annotations

import argparse
import os
import sys

import host  # same folder: the CPU, its switches, fresh processes


def _parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    host.add_cpu_switch_args(p)
    p.add_argument("--quick", action="store_true", help="few repeats, N <= 1,000")
    p.add_argument("--repeats", type=int, default=30, help="timed steps per setting")
    p.add_argument("--out", default=None, help="results path stem (default results/bench_rgbd)")
    p.add_argument("--figure-only", action="store_true", help="redraw the figure from the JSON")
    p.add_argument(
        "--steps-only", action="store_true", help="time grid-occlusion alone, print JSON (internal)"
    )
    return p.parse_args(argv)


ARGS = _parse_args() if __name__ == "__main__" else _parse_args([])
XLA_FLAGS_GIVEN = os.environ.get("XLA_FLAGS", "")
MALLOC_TUNED = False
if __name__ == "__main__":  # before JAX allocates and reads XLA_FLAGS: see cpf_jax.cpu_tuning
    MALLOC_TUNED, XLA_FLAGS_GIVEN = host.cpu_switches(ARGS.tune_malloc, ARGS.tune_xla)

import datetime  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import bench_colour  # noqa: E402  (same folder: the timing loop)
import cv2  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cpf_jax.filter import Context  # noqa: E402
from cpf_jax.kernels.background import Background  # noqa: E402
from cpf_jax.kernels.boxes import xywh_to_rect  # noqa: E402
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params  # noqa: E402
from cpf_jax.synthetic import make_sequence  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

VARIANTS = ("rgbd", "grid", "grid-occlusion")
N_ALL = (150, 1_000, 10_000)
BASELINE_MAX_N = 1_000
WARMUP = 10
FRAME_INDEX = 10
HS_BINS = (8, 8)
FG_DEPTH_MM = 150.0  # baseline foreground: depth differs from the background by this
FG_COLOUR = 40.0  # ... or colour by this (max abs channel difference)


def _scene():
    seq = make_sequence("walk_across_medium", seed=0, n_frames=FRAME_INDEX + 2)
    t = FRAME_INDEX
    bg = Background(
        jnp.asarray(seq.meta["background_colour"], jnp.float32),
        jnp.asarray(seq.meta["background_depth"], jnp.float32),
    )
    first = Frame(jnp.asarray(seq.colour[t - 1]), jnp.asarray(seq.depth[t - 1]))
    frame = Frame(jnp.asarray(seq.colour[t]), jnp.asarray(seq.depth[t]))
    return seq, bg, first, frame, np.asarray(seq.boxes[t - 1], np.float32)


def time_step(variant: str, n: int, scene, repeats: int) -> dict:
    """Median wall time of one jitted step (after ``WARMUP`` untimed steps)."""
    seq, bg, first, frame, box = scene
    config = RGBDConfig(variant=variant, n_particles=n).with_window(
        (float(box[2]), float(box[3])), seq.colour.shape[1:3]
    )
    filt = build_rgbd_filter(config)
    params = default_rgbd_params(config)
    step = jax.jit(lambda k, s, f: filt.step(params, k, s, f))
    key = jax.random.key(0)
    context = Context(background=bg)
    init = jax.jit(lambda k, f, b: filt.init(params, k, f, b, context))
    state = init(key, first, jnp.asarray(box))
    times, windowed, info = bench_colour.timed_steps(step, state, frame, key, repeats, WARMUP)
    ms = float(np.median(times) * 1e3)
    return {
        "ms_per_frame": ms,
        "fps": 1e3 / ms,
        "ess": float(info.ess),
        # Share of the timed steps whose histograms came from the window (the rest
        # ran the exact whole-frame fallback: some particle rect left the window).
        "windowed": windowed,
    }


# ----------------------------------------------------------------------------- baseline


def _cells(rect, k: int = 2):
    x0, y0, x1, y1 = rect
    xs = np.linspace(x0, x1, k + 1).round().astype(int)
    ys = np.linspace(y0, y1, k + 1).round().astype(int)
    return [(xs[j], ys[i], xs[j + 1], ys[i + 1]) for i in range(k) for j in range(k)]


def _cell_features(hsv, mask, depth, cell):
    x0, y0, x1, y1 = cell
    m = mask[y0:y1, x0:x1]
    if m.size == 0:
        return 0.0, np.zeros(HS_BINS[0] * HS_BINS[1], np.float32), 0.0
    ratio = float(m.mean())
    hist = cv2.calcHist(
        [np.ascontiguousarray(hsv[y0:y1, x0:x1])],
        [0, 1],
        np.ascontiguousarray(m.astype(np.uint8)),
        list(HS_BINS),
        [0, 180, 0, 256],
    ).ravel()
    z = depth[y0:y1, x0:x1][m & (depth[y0:y1, x0:x1] > 0)]
    return ratio, hist, float(np.median(z)) if z.size else 0.0


def opencv_step(rng, centres, colour, depth, bg_colour, bg_depth, templates, wh):
    """The paper's per-cell likelihood for every particle with OpenCV + NumPy; resample."""
    n = len(centres)
    centres = centres + rng.normal(0, 5.0, centres.shape)
    hsv = cv2.cvtColor(colour, cv2.COLOR_RGB2HSV)
    diff_c = np.abs(colour.astype(np.int16) - bg_colour.astype(np.int16)).max(-1)
    z, zb = depth.astype(np.float32), bg_depth.astype(np.float32)
    mask = (diff_c > FG_COLOUR) | ((z > 0) & (zb > 0) & (np.abs(z - zb) > FG_DEPTH_MM))
    fh, fw = depth.shape
    log_w = np.empty(n)
    for i, (cx, cy) in enumerate(centres):
        x0, y0 = int(np.clip(cx - wh[0] / 2, 0, fw)), int(np.clip(cy - wh[1] / 2, 0, fh))
        x1, y1 = int(np.clip(cx + wh[0] / 2, 0, fw)), int(np.clip(cy + wh[1] / 2, 0, fh))
        total = 0.0
        for cell, (t_hist, t_z) in zip(_cells((x0, y0, x1, y1)), templates, strict=True):
            ratio, hist, med = _cell_features(hsv, mask, depth, cell)
            d = cv2.compareHist(hist, t_hist, cv2.HISTCMP_BHATTACHARYYA) if hist.sum() else 1.0
            beta = 2.0 * np.log(max(ratio, 1e-3)) + np.log(max(1.0 - ratio, 1e-3))
            total += beta - d * d / (2 * 0.2**2) - ((med - t_z) / 200.0) ** 2 / 2
        log_w[i] = total
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    u = (rng.random() + np.arange(n)) / n
    return centres[np.clip(np.searchsorted(np.cumsum(w), u), 0, n - 1)]


def time_baseline(n: int, scene, repeats: int) -> float:
    seq, bg, _, frame, box = scene
    colour, depth = np.asarray(frame.colour), np.asarray(frame.depth)
    bg_c, bg_z = np.asarray(seq.meta["background_colour"]), np.asarray(seq.meta["background_depth"])
    hsv = cv2.cvtColor(colour, cv2.COLOR_RGB2HSV)
    mask = np.abs(depth.astype(np.float32) - bg_z) > FG_DEPTH_MM
    rect = np.asarray(xywh_to_rect(jnp.asarray(box))).astype(int)
    templates = [(h, z) for _, h, z in (_cell_features(hsv, mask, depth, c) for c in _cells(rect))]
    rng = np.random.default_rng(0)
    centres = np.tile(box[:2] + box[2:] / 2, (n, 1)).astype(np.float64)
    centres = opencv_step(rng, centres, colour, depth, bg_c, bg_z, templates, box[2:])  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        centres = opencv_step(rng, centres, colour, depth, bg_c, bg_z, templates, box[2:])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


# ----------------------------------------------------------------------------- main


def _markdown(results: dict) -> str:
    meta = results["meta"]
    ns = meta["n_particles"]
    lines = [
        "# RGB-D box-filter step benchmark",
        "",
        f"{meta['frame']}, {meta['cpu']} ({meta['cores']} cores), jax {meta['jax']}, "
        f"{meta['date']}; load average before / after: {meta['load_before']} / "
        f"{meta['load_after']}; malloc tuned: {meta['malloc_tuned']}; XLA_FLAGS: "
        f"`{meta['xla_flags'] or '(unset)'}`. Median of {meta['repeats']} steps.",
        f"Command: `{meta['command']}`",
        "",
        "ms per frame (frames/s, share of the timed steps on the windowed histogram path: "
        "`RGBDInfo.windowed`; the other steps counted exactly on the whole frame, slower); "
        "the OpenCV + NumPy per-particle loop computes only the paper's per-cell terms "
        "(module docstring); plain jit: the grid-occlusion step in a fresh process without "
        "the CPU switches, as the Python API runs it by default"
        + (f", scaled linearly above N = {BASELINE_MAX_N:,}" if max(ns) > BASELINE_MAX_N else "")
        + ".",
        "",
        "| N | " + " | ".join(VARIANTS) + " | grid-occlusion, plain jit | OpenCV loop "
        "| speed-up (grid-occlusion) |",
        "|---:|" + "---:|" * (len(VARIANTS) + 3),
    ]
    for n in ns:
        r = results[str(n)]
        cells = [
            f"{r[v]['ms_per_frame']:.2f} ({r[v]['fps']:.0f}, {100 * r[v]['windowed']:.0f} %)"
            for v in VARIANTS
        ]
        base = r["baseline_ms_per_frame"]
        scaled = " (scaled)" if n > BASELINE_MAX_N else ""
        speedup = base / r["grid-occlusion"]["ms_per_frame"]
        plain = r["grid-occlusion"].get("ms_untuned")
        plain = "-" if plain is None else f"{plain:.2f} ({1e3 / plain:.0f})"
        lines.append(
            f"| {n:,} | "
            + " | ".join(cells)
            + f" | {plain} | {base:.1f}{scaled} | {speedup:.0f}x |"
        )
    return "\n".join(lines) + "\n"


def untuned_steps(repeats: int, ns) -> dict | None:
    """``{N: ms}`` of the grid-occlusion step in a fresh process without ``tune_malloc`` or the
    XLA flags (both process-wide): a plain ``jax.jit(filt.step)`` of the Python API."""
    args = ["--steps-only", "--no-tune-malloc", "--no-tune-xla", f"--repeats={repeats}"]
    if max(ns) <= 1_000:
        args.append("--quick")
    return host.fresh_process_json(__file__, args, XLA_FLAGS_GIVEN)


def main(args) -> dict:
    scene = _scene()
    repeats = 5 if args.quick else args.repeats
    ns = tuple(n for n in N_ALL if not args.quick or n <= 1_000)
    if args.steps_only:
        ms = {str(n): time_step("grid-occlusion", n, scene, repeats)["ms_per_frame"] for n in ns}
        print(json.dumps(ms))
        return {}
    load_before = os.getloadavg()
    results: dict = {}
    per_particle = None
    for n in ns:
        r = {v: time_step(v, n, scene, repeats) for v in VARIANTS}
        if n <= BASELINE_MAX_N:
            r["baseline_ms_per_frame"] = time_baseline(n, scene, max(3, repeats // 5))
            per_particle = r["baseline_ms_per_frame"] / n
        else:
            r["baseline_ms_per_frame"] = per_particle * n
        r["baseline_scaled"] = n > BASELINE_MAX_N
        results[str(n)] = r
        print(
            f"N={n:>6,}: "
            + "  ".join(f"{v} {r[v]['ms_per_frame']:.2f} ms" for v in VARIANTS)
            + f"  OpenCV loop {r['baseline_ms_per_frame']:.1f} ms",
            flush=True,
        )
    untuned = None if args.quick else untuned_steps(repeats, ns)
    for n in ns:
        plain = None if untuned is None else untuned[str(n)]
        results[str(n)]["grid-occlusion"]["ms_untuned"] = plain
    results["meta"] = {
        "frame": f"512x424 walk_across_medium seed 0 frame {FRAME_INDEX}",
        "cpu": host.cpu_name(),
        "cores": os.cpu_count(),
        "jax": jax.__version__,
        "opencv": cv2.__version__,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "load_before": [round(v, 2) for v in load_before],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "malloc_tuned": MALLOC_TUNED,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "repeats": repeats,
        "n_particles": list(ns),
        "command": "python " + " ".join(["experiments/bench_rgbd.py"] + sys.argv[1:]),
    }
    md = _markdown(results)
    print(md)
    if not args.quick or args.out:
        stem = Path(args.out) if args.out else Path(__file__).parent / "results" / "bench_rgbd"
        stem.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
        stem.with_suffix(".md").write_text(md)
        figure(results, stem.with_suffix(".png"))
    return results


def figure(results: dict, path: Path) -> None:
    """``bench_rgbd.png``: frames/s against N of each variant's step and the loop."""
    from cpf_jax import charts

    ns = results["meta"]["n_particles"]
    ms = {v: [results[str(n)][v]["ms_per_frame"] for n in ns] for v in VARIANTS}
    ms["OpenCV + NumPy per-cell loop"] = [results[str(n)]["baseline_ms_per_frame"] for n in ns]
    title = f"One RGB-D step, {results['meta']['frame']} ({results['meta']['cores']} cores)"
    charts.save_png(bench_colour.fps_chart(ns, ms, title), path)


if __name__ == "__main__":
    if ARGS.figure_only:
        bench_colour.redraw_figure(ARGS.out, "bench_rgbd", figure)
    else:
        main(ARGS)
