"""Benchmark: the default colour step at 512 x 424, 1280 x 720 and 1920 x 1080, default
path beside the tuned one.

    python experiments/bench_resolution.py           # -> results/bench_resolution.{json,md}
    python experiments/bench_resolution.py --quick   # few repeats, writes nothing

The frame is ``bench_colour``'s 512 x 424 room with its 150 x 200 person, grown to each
size by mirroring the room at its edges (``cv2.BORDER_REFLECT``): the person keeps the
same size in pixels, so the particles read the same window and only the frame-wide work
(bins, summed-area tables, the camera stage) grows with the pixels. The step is the
library's default ``ColourConfig`` at N = 1,000 and 10,000, its window from
``with_window``; timed after ``bench_colour.WARMUP`` steps, median of ``--repeats``.

"default": a fresh process running a plain ``jax.jit(filt.step)`` without the CPU
switches, as a user of the Python API gets it (``cpf-track`` tunes malloc itself);
"tuned": this process, with ``cpu_tuning.tune_malloc()`` and the XLA flags of
``cpu_tuning.xla_cpu_flags(library_fusions=False)`` (``--no-tune-malloc``,
``--no-tune-xla``). Both run in the same invocation, and the ratio is printed.
"""

from __future__ import annotations

import argparse
import os
import sys

import host  # same folder: the CPU, its switches, fresh processes


def _parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    host.add_cpu_switch_args(p)
    p.add_argument("--quick", action="store_true", help="few repeats, writes nothing")
    p.add_argument("--repeats", type=int, default=30, help="timed steps per setting")
    p.add_argument(
        "--out", default=None, help="results path stem (default results/bench_resolution)"
    )
    p.add_argument(
        "--timings-only", action="store_true", help="print this process's JSON (internal)"
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

import bench_colour  # noqa: E402  (same folder: the frame and the timing loop)
import cv2  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params  # noqa: E402
from cpf_jax.colour import filter as colour_filter  # noqa: E402
from cpf_jax.colour.camera import camera_shift  # noqa: E402
from cpf_jax.colour.config import bin_index  # noqa: E402

SIZES = ((424, 512), (720, 1280), (1080, 1920))  # (height, width)
N = (1_000, 10_000)


def grown_frame(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``bench_colour.make_frame`` mirrored out to ``height x width``, centred; returns
    ``(frame, person xywh)``."""
    frame, box = bench_colour.make_frame()
    fh, fw = frame.shape[:2]
    top, left = (height - fh) // 2, (width - fw) // 2
    big = cv2.copyMakeBorder(
        frame, top, height - fh - top, left, width - fw - left, cv2.BORDER_REFLECT
    )
    return big, np.asarray([box[0] + left, box[1] + top, box[2], box[3]], np.float32)


def time_step(n: int, size: tuple[int, int], repeats: int) -> float:
    """Median ms of the default colour step at ``n`` particles on a frame of ``size``."""
    colour, box = grown_frame(*size)
    config = ColourConfig(n_particles=n).with_window((float(box[2]), float(box[3])), size)
    filt = build_colour_filter(config)
    params = default_colour_params()
    frame = bench_colour._frame(colour)
    key = jax.random.key(0)
    state = jax.jit(lambda k, f, b: filt.init(params, k, f, b))(key, frame, jnp.asarray(box))
    step = jax.jit(lambda k, s, f: filt.step(params, k, s, f))
    times, _, _ = bench_colour.timed_steps(step, state, frame, key, repeats)
    return float(np.median(times) * 1e3)


def time_pieces(size: tuple[int, int], repeats: int) -> dict:
    """Median ms of the step's frame-wide pieces at N = 1,000 on a frame of ``size``, each
    jitted alone: the bins, ``observe`` (the bins and the contrast and layout terms'
    summed-area table of the whole frame) and the camera stage."""
    colour, box = grown_frame(*size)
    config = ColourConfig(n_particles=N[0]).with_window((float(box[2]), float(box[3])), size)
    filt = build_colour_filter(config)
    params = default_colour_params()
    frame = bench_colour._frame(colour)
    state = jax.jit(lambda k, f, b: filt.init(params, k, f, b))(
        jax.random.key(0), frame, jnp.asarray(box)
    )
    pieces = {
        "bins": jax.jit(lambda s, f: bin_index(f.colour, config.bins)),
        "observe": jax.jit(lambda s, f: colour_filter.observe(config, s, f)),
        "camera": jax.jit(
            lambda s, f: camera_shift(
                config.camera_motion, s.camera, f.colour, s.estimate, config.camera_min_peak
            )
        ),
    }
    out = {}
    for name, fn in pieces.items():
        jax.block_until_ready(fn(state, frame))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(state, frame))
            times.append(time.perf_counter() - t0)
        out[name] = float(np.median(times) * 1e3)
    return out


def timings(repeats: int) -> dict:
    """``{"steps": {"HxW": {N: ms}}, "pieces": {"HxW": {piece: ms}}}`` in this process."""
    return {
        "steps": {f"{h}x{w}": {str(n): time_step(n, (h, w), repeats) for n in N} for h, w in SIZES},
        "pieces": {f"{h}x{w}": time_pieces((h, w), repeats) for h, w in SIZES},
    }


def _markdown(results: dict) -> str:
    meta = results["meta"]
    lines = [
        "# The colour step against the frame size",
        "",
        f"{meta['cpu']} ({meta['cores']} cores), jax {meta['jax']}, {meta['date']}; load "
        f"average before / after: {meta['load_before']} / {meta['load_after']}. Median of "
        f"{meta['repeats']} steps.",
        f"Command: `{meta['command']}`",
        "",
        "ms per step (frames/s) of the default colour filter, the person 150 x 200 px at "
        "every size (the room mirrored outwards). Default: a plain `jax.jit(filt.step)` "
        "in a fresh process without the CPU switches; tuned: `tune_malloc()` and "
        f"XLA_FLAGS `{meta['xla_flags'] or '(unset)'}`.",
        "",
        "| frame | N | default | tuned | default / tuned |",
        "|---|---:|---:|---:|---:|",
    ]
    tuned, default = results["tuned"], results["default"] or {}
    for size, by_n in tuned["steps"].items():
        for n, ms in by_n.items():
            plain = default.get("steps", {}).get(size, {}).get(n)
            shown = "-" if plain is None else f"{plain:.1f} ({1e3 / plain:.0f})"
            ratio = "-" if plain is None else f"{plain / ms:.2f}"
            w, h = size.split("x")[::-1]
            lines.append(
                f"| {w} x {h} | {int(n):,} | {shown} | {ms:.1f} ({1e3 / ms:.0f}) | {ratio} |"
            )
    lines += [
        "",
        "The frame-wide pieces at N = 1,000, each jitted alone, ms default / tuned: the "
        "bins, `observe` (the bins and the contrast and layout terms' summed-area table of "
        "the whole frame) and the camera stage (phase correlation of the frame downscaled "
        "4x).",
        "",
        "| frame | bins | observe | camera |",
        "|---|---:|---:|---:|",
    ]
    for size, pieces in tuned["pieces"].items():
        plain = default.get("pieces", {}).get(size, {})
        cells = [f"{plain.get(k, float('nan')):.1f} / {v:.1f}" for k, v in pieces.items()]
        w, h = size.split("x")[::-1]
        lines.append(f"| {w} x {h} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(args) -> dict:
    repeats = 5 if args.quick else args.repeats
    if args.timings_only:
        print(json.dumps(timings(repeats)))
        return {}
    load_before = os.getloadavg()
    tuned = timings(repeats)
    default = host.fresh_process_json(
        __file__,
        ["--timings-only", "--no-tune-malloc", "--no-tune-xla", f"--repeats={repeats}"],
        XLA_FLAGS_GIVEN,
    )
    results = {
        "tuned": tuned,
        "default": default,
        "meta": {
            "cpu": host.cpu_name(),
            "cores": os.cpu_count(),
            "jax": jax.__version__,
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "load_before": [round(v, 2) for v in load_before],
            "load_after": [round(v, 2) for v in os.getloadavg()],
            "malloc_tuned": MALLOC_TUNED,
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "repeats": repeats,
            "command": "python " + " ".join(["experiments/bench_resolution.py"] + sys.argv[1:]),
        },
    }
    md = _markdown(results)
    print(md)
    if not args.quick or args.out:
        stem = (
            Path(args.out) if args.out else Path(__file__).parent / "results" / "bench_resolution"
        )
        stem.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
        stem.with_suffix(".md").write_text(md)
    return results


if __name__ == "__main__":
    main(ARGS)
