"""Benchmark: one jitted colour-filter step vs a per-particle OpenCV loop.

    python experiments/bench_colour.py           # full run -> results/bench_colour.{json,md}
    python experiments/bench_colour.py --quick   # few repeats, no table 3.2 (smoke test)
    python experiments/bench_colour.py --no-tune-malloc
    python experiments/bench_colour.py --figure-only  # redraw results/bench_colour.png

The figure (``bench_colour.png``) shows frames/s against N for the step's variants and
the OpenCV loop, and the thesis's Table 3.2 grid (frames/s per box size against N).

"Colour step" = one jitted ``step`` of the library's colour filter
(``cpf_jax.colour.build_colour_filter``) on a 512 x 424 frame: bins of the frame,
propagation of the 8-tuple state (random walk by default), exact histograms of every
particle's box parts and surround ring from one windowed integral histogram, the layout
term's 7 x 3 cell means from a luminance summed-area table, log-likelihood, ESS,
estimate, the estimate's own histogram, template update, systematic resampling. It is
timed with the library defaults, without the layout term and template update
(``ColourConfig.histogram_only``), without following the camera (``camera_motion=None``:
what that stage costs), with the gradient layout, with a finer 12 x 3 layout
grid, and with the same code configured as the thesis's model (one 8x8 H-S histogram per
box, the work per particle of the OpenCV loop; the 8-tuple AR1 with motion-guided
sampling). Each variant's share of timed steps on the histogram window is recorded
(``windowed``, ``<variant>_windowed``; in the table, a share below 100 % follows the
time): the thesis's model runs the exact whole-frame fallback on most steps at N >=
10,000, because its AR1 box sizes drift and the cloud's extreme boxes outgrow the
window. The like-for-like step is timed too: the OpenCV loop's likelihood (the thesis's
one histogram per box, nothing else) on the default random walk (``loop_likelihood``).
With nothing but the histogram to pin the box's size, its random-walk sizes drift on
this still frame as well, and at N = 100,000 most of its steps also take the whole-frame
path.

The baseline does the same per frame with OpenCV and NumPy: one cvtColor, then
per particle crop + ``cv2.calcHist`` on H and S + ``cv2.compareHist``
(``HISTCMP_BHATTACHARYYA``). It is measured up to N = 10,000 and scaled linearly
above (its cost is per particle).

The main settings (N = 1k, 10k, 100k x the variants) are timed interleaved, in
``ROUNDS`` rounds, and the default step is re-timed in ``--fresh-repeats`` more fresh
processes: a shared host's speed drifts over minutes and between processes.
The OpenCV loop is timed in the same rounds (``OPENCV_STEPS_PER_ROUND`` steps at the end
of each), so that the speed-up divides times from the same minutes.

``--tune-malloc`` (default on) calls ``cpf_jax.cpu_tuning.tune_malloc()`` before
JAX allocates anything. ``--tune-xla`` (default on) adds
``cpf_jax.cpu_tuning.xla_cpu_flags(library_fusions=False)`` (no YNNPACK
fusions) to the XLA_FLAGS the environment gives. Both are CPU-specific,
process-wide switches: the main timings are re-run in fresh processes without
each of them, and everything is recorded in the results.
"""

from __future__ import annotations

import argparse
import sys

import host  # same folder: the CPU, its switches, fresh processes


def _parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    host.add_cpu_switch_args(p)
    p.add_argument("--quick", action="store_true", help="few repeats, skip table 3.2")
    p.add_argument("--repeats", type=int, default=50, help="timed steps per setting")
    p.add_argument(
        "--main-only",
        action="store_true",
        help="time the JAX step at N = 1k, 10k, 100k only; print JSON (used for the untuned run)",
    )
    p.add_argument(
        "--no-compare-malloc",
        dest="compare_malloc",
        action="store_false",
        help="skip re-running the main timings in subprocesses without tune_malloc "
        "and without the XLA flags",
    )
    p.add_argument(
        "--fresh-repeats",
        type=int,
        default=3,
        help="re-time the main JAX step (same settings) in this many more fresh processes, "
        "one after another: the host's speed varies between processes (default 3)",
    )
    p.add_argument(
        "--out", default=None, help="results path stem (default experiments/results/bench_colour)"
    )
    p.add_argument(
        "--figure-only",
        action="store_true",
        help="redraw the figure from the results JSON (no timing)",
    )
    p.add_argument(
        "--stat",
        choices=("median", "min"),
        default="median",
        help="median (default) or best-of-N wall time (for a shared, loaded machine); "
        "the same statistic for ours and the baseline",
    )
    return p.parse_args(argv)


import os  # noqa: E402

ARGS = _parse_args() if __name__ == "__main__" else _parse_args([])
#: XLA_FLAGS as the environment set them, before --tune-xla adds to them.
XLA_FLAGS_GIVEN = os.environ.get("XLA_FLAGS", "")
MALLOC_TUNED = False
if __name__ == "__main__":  # before JAX allocates and reads XLA_FLAGS: see cpf_jax.cpu_tuning
    MALLOC_TUNED, XLA_FLAGS_GIVEN = host.cpu_switches(ARGS.tune_malloc, ARGS.tune_xla)

import datetime  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cpf_jax.colour import (  # noqa: E402
    ColourConfig,
    build_colour_filter,
    default_colour_params,
)
from cpf_jax.kernels import boxes as B  # noqa: E402
from cpf_jax.kernels import histogram as H  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

FRAME_H, FRAME_W = 424, 512
BOX_WH = (150, 200)  # main benchmark box (w, h)
TAU = np.array([10, 10, 1, 1, 0.1, 0.1, 0.1, 0.1], np.float32)  # thesis 3.3.1 (baseline)
SIGMA = 0.1  # baseline likelihood width
CLOUD_STD = 15.0  # px, initial spread of the particle centres
# Steady-state std of the centres on this scene (the likelihood's width at sigma = 0.1):
# sizes the static histogram window (histogram.suggest_window).
WINDOW_SPREAD = 20.0
SIZE_JITTER = 0.10  # initial box sizes +-10 %
N_MAIN = (1_000, 10_000, 100_000)
N_TABLE = (20, 40, 60, 80, 100, 120, 1_000, 10_000)
TABLE_BOXES = ((100, 150), (150, 150), (150, 200), (150, 250))
BASELINE_MAX_N = 10_000
WARMUP = 20  # untimed steps before timing
ROUNDS = 5  # the main settings' timed steps are spread over this many interleaved rounds
#: The variants timed beside the default: their JSON key prefixes (``<key>_ms_per_frame``,
#: ``<key>_windowed``); their labels are ``VARIANT_LABELS``.
VARIANT_KEYS = {
    "thesis": "thesis_model",
    "loop_likelihood": "loop_likelihood",
    "histogram_only": "histogram_only",
    "gradient": "gradient_layout",
    "layout_12x3": "layout_12x3",
    "no_camera": "no_camera",
}


# ----------------------------------------------------------------------------- scene


def make_frame(seed: int = 0) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """A 512 x 424 RGB indoor frame with a drawn person; returns ``(frame, person xywh)``.

    Muted, textured background (walls, a door, a floor, furniture: low
    saturation as in Kinect footage of rooms), a person filling a 150 x 200
    box (skin, red shirt and arms, blue trousers), sensor-like noise.
    """
    rng = np.random.default_rng(seed)
    img = np.empty((FRAME_H, FRAME_W, 3), np.float32)
    img[:] = (178, 170, 158)  # wall
    img[300:] = (120, 96, 74)  # wooden floor
    img[60:300, 40:130] = (140, 120, 100)  # door
    img[210:330, 360:480] = (90, 92, 98)  # grey sofa
    img[40:120, 330:450] = (150, 160, 150)  # picture frame
    # Texture: mostly luminance (shading), a little chroma.
    coarse = rng.normal(0, 12, (FRAME_H // 8, FRAME_W // 8, 1)) + rng.normal(
        0, 4, (FRAME_H // 8, FRAME_W // 8, 3)
    )
    img += cv2.resize(coarse.astype(np.float32), (FRAME_W, FRAME_H), interpolation=cv2.INTER_CUBIC)
    w, h = BOX_WH
    x0, y0 = 181, 112
    cx = x0 + w // 2
    cv2.ellipse(img, (cx, y0 + 22), (18, 22), 0, 0, 360, (224, 172, 140), -1)  # head
    cv2.rectangle(img, (cx - 45, y0 + 45), (cx + 45, y0 + 125), (200, 30, 40), -1)  # shirt
    cv2.rectangle(img, (x0 + 3, y0 + 48), (cx - 46, y0 + 125), (190, 40, 45), -1)  # arms
    cv2.rectangle(img, (cx + 46, y0 + 48), (x0 + w - 3, y0 + 125), (190, 40, 45), -1)
    cv2.rectangle(img, (cx - 42, y0 + 125), (cx - 3, y0 + h - 1), (40, 50, 120), -1)  # legs
    cv2.rectangle(img, (cx + 3, y0 + 125), (cx + 42, y0 + h - 1), (40, 50, 120), -1)
    img += rng.normal(0, 6, img.shape).astype(np.float32)  # sensor noise
    return np.clip(img, 0, 255).astype(np.uint8), (float(x0), float(y0), float(w), float(h))


def reference_histogram(frame: np.ndarray, xywh, bins=H.DEFAULT_BINS) -> np.ndarray:
    hsv = cv2.cvtColor(frame, cv2.COLOR_RGB2HSV)
    x0, y0, x1, y1 = np.asarray(B.xywh_to_rect(jnp.asarray(xywh, jnp.float32)))
    crop = np.ascontiguousarray(hsv[y0:y1, x0:x1])
    return cv2.calcHist([crop], [0, 1], None, list(bins), [0, 180, 0, 256]).ravel()


def init_particles(key, n: int, xywh) -> jax.Array:
    """``[n, 8]`` state (cx, cy, vx, vy, w, h, vw, vh): a cloud around the box, sizes +-10 %.

    The starting cloud of the OpenCV baseline (the library filter starts from
    its own ``init`` and is warmed up before timing).
    """
    x, y, w, h = xywh
    k1, k2 = jax.random.split(key)
    c = jnp.asarray([x + w / 2, y + h / 2]) + CLOUD_STD * jax.random.normal(k1, (n, 2))
    wh = jnp.asarray([w, h]) * (1 + SIZE_JITTER * jax.random.uniform(k2, (n, 2), minval=-1))
    zeros = jnp.zeros((n, 2))
    return jnp.concatenate([c, zeros, wh, zeros], axis=1).astype(jnp.float32)


# ----------------------------------------------------------------------------- the step

# The library's default colour model, and the same code configured as the thesis's
# (one 8x8 H-S histogram per box, no contrast / ring / aspect terms: the same work
# per particle as the OpenCV loop).
#: ``ColourConfig.histogram_only()`` as keyword arguments.
HISTOGRAM_ONLY = {"layout": None, "template_update": False, "unseen": "background"}
#: The default layout grid, "RxC" (``ColourConfig.layout``).
GRID = "x".join(map(str, ColourConfig().layout))
#: Each variant's label in the table, the printout and the figure.
VARIANT_LABELS = {
    "thesis": "thesis model",
    "loop_likelihood": "the OpenCV loop's likelihood, random walk",
    "histogram_only": "histogram only (no layout, no update)",
    "gradient": f"gradient layout {GRID}",
    "layout_12x3": "layout 12x3",
    "no_camera": "without following the camera",
}
VARIANTS = {
    "default": {},
    "thesis": {
        "bins": (8, 8),
        "parts": 1,
        "contrast": None,
        "aspect_prior": False,
        "model": "ar1",
        **HISTOGRAM_ONLY,
    },
    # The OpenCV loop's work per particle (one 8x8 H-S histogram, Bhattacharyya; no
    # centre-surround term, ``contrast=None``) on the default random walk.
    "loop_likelihood": {
        "bins": (8, 8),
        "parts": 1,
        "contrast": None,
        "aspect_prior": False,
        **HISTOGRAM_ONLY,
    },
    # The default without its layout term and template update: what those cost.
    "histogram_only": HISTOGRAM_ONLY,
    "gradient": {"layout_feature": "gradient"},
    # A finer layout grid than the default (ColourConfig.layout): what it costs.
    "layout_12x3": {"layout": (12, 3)},
    # The default without its camera stage (ColourConfig.camera_motion): what following
    # the camera costs.
    "no_camera": {"camera_motion": None},
}


def make_colour_step(n_particles: int, box_wh=BOX_WH, *, variant: str = "default"):
    """The library's jitted filter step for ``n_particles`` on the benchmark frame.

    Returns ``(step, init)`` with ``init(key, frame, xywh) -> state`` and
    ``step(key, state, frame) -> (state, info)`` (``cpf_jax.colour``), the
    histogram window sized by ``ColourConfig.with_window`` from the box.
    """
    config = ColourConfig(n_particles=n_particles, **VARIANTS[variant]).with_window(
        box_wh, (FRAME_H, FRAME_W)
    )
    filt = build_colour_filter(config)
    params = default_colour_params()
    step = jax.jit(lambda key, state, frame: filt.step(params, key, state, frame))
    init = jax.jit(lambda key, frame, box: filt.init(params, key, frame, box))
    return step, init, config


# ----------------------------------------------------------------------------- baseline


def opencv_step(rng, particles: np.ndarray, frame: np.ndarray, ref_hist: np.ndarray, bins):
    """The same step as a user would write it with OpenCV + NumPy (per-particle loop)."""
    n = len(particles)
    state = particles.copy()
    state[:, [0, 1, 4, 5]] += state[:, [2, 3, 6, 7]]
    state += TAU * rng.standard_normal(state.shape).astype(np.float32)
    hsv = cv2.cvtColor(frame, cv2.COLOR_RGB2HSV)
    ref = ref_hist.astype(np.float32)
    d = np.empty(n)
    for i, (cx, cy, _, _, w, h, _, _) in enumerate(state):
        x0, y0 = int(np.floor(cx - w / 2 + 0.5)), int(np.floor(cy - h / 2 + 0.5))
        x1, y1 = int(np.floor(cx + w / 2 + 0.5)), int(np.floor(cy + h / 2 + 0.5))
        x0, x1 = max(x0, 0), min(x1, FRAME_W)
        y0, y1 = max(y0, 0), min(y1, FRAME_H)
        if x1 <= x0 or y1 <= y0:
            d[i] = 1.0
            continue
        hist = cv2.calcHist([hsv[y0:y1, x0:x1]], [0, 1], None, list(bins), [0, 180, 0, 256])
        d[i] = cv2.compareHist(hist.ravel(), ref, cv2.HISTCMP_BHATTACHARYYA)
    log_w = -(d**2) / (2 * SIGMA**2)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    _ = w @ state
    u = (rng.random() + np.arange(n)) / n
    idx = np.clip(np.searchsorted(np.cumsum(w), u), 0, n - 1)
    return state[idx]


# ----------------------------------------------------------------------------- timing


def _median_ms(times) -> float:
    """The run's timing statistic (``--stat``: median or best of the repeats), in ms."""
    stat = np.min if ARGS.stat == "min" else np.median
    return float(stat(times) * 1e3)


def _frame(frame: np.ndarray) -> Frame:
    return Frame(jnp.asarray(frame), jnp.zeros(frame.shape[:2], jnp.uint16))


def time_jax_step(n: int, box_wh, frame, repeats: int, variant: str = "default") -> dict:
    """One setting timed on its own (``time_jax_steps_interleaved`` with one round)."""
    return time_jax_steps_interleaved([(n, box_wh, variant)], frame, repeats, rounds=1)[0]


def time_jax_steps_interleaved(
    specs, frame, repeats: int, rounds: int = ROUNDS, each_round=None
) -> list[dict]:
    """``time_jax_step`` for every ``(n, box_wh, variant)`` in ``specs``, interleaved.

    Each setting is compiled and warmed up first; then ``rounds`` rounds time
    ``repeats // rounds`` steps of every setting in turn (each continuing its own
    particle cloud). The host's speed drifts over minutes: timed one after another, a
    slow spell falls on one setting alone; interleaved, it falls on all.
    ``each_round()`` (optional) runs at the end of every round: the OpenCV loop's
    timing (``OpenCVLoop``), so that the speed-up compares the same minutes.
    """
    frame_j = _frame(frame)
    per = max(1, repeats // rounds)
    runs = []
    for n, box_wh, variant in specs:
        x, y = FRAME_W / 2 - box_wh[0] / 2, FRAME_H / 2 - box_wh[1] / 2
        xywh = jnp.asarray((x, y, float(box_wh[0]), float(box_wh[1])), jnp.float32)
        step, init, _ = make_colour_step(n, box_wh, variant=variant)
        key = jax.random.key(0)
        state = init(key, frame_j, xywh)
        for i in range(WARMUP):
            state, _ = step(jax.random.fold_in(key, i), state, frame_j)
        jax.block_until_ready(state)
        runs.append({"step": step, "state": state, "key": key, "times": [], "windowed": 0})
    for r in range(rounds):
        for run in runs:
            state, step = run["state"], run["step"]
            for j in range(per):
                k = jax.random.fold_in(run["key"], 1000 + r * per + j)
                t0 = time.perf_counter()
                state, info = step(k, state, frame_j)
                jax.block_until_ready((state, info))
                run["times"].append(time.perf_counter() - t0)
                run["windowed"] += bool(info.windowed)
            run["state"], run["info"] = state, info
        if each_round is not None:
            each_round()
    out = []
    for run in runs:
        ms = _median_ms(run["times"])
        out.append(
            {
                "ms_per_frame": ms,
                "fps": 1e3 / ms,
                "final_ess": float(run["info"].ess),
                # Share of the timed steps on the windowed path (the rest ran the exact
                # whole-frame fallback: particle boxes outgrew the window).
                "windowed": run["windowed"] / len(run["times"]),
            }
        )
    return out


def timed_steps(step, state, frame, key, repeats: int, warmup: int = WARMUP):
    """Wall times (s) of ``repeats`` jitted ``step(key, state, frame)`` calls, the share of
    them whose info says ``windowed``, and the last info.

    ``warmup`` untimed steps first: compile, let the cloud settle onto the target
    and the allocator reach its steady state (the first ~10 calls still grow the
    heap). Step keys: ``fold_in(key, i)`` while warming up, ``fold_in(key, 1000 + i)``
    timed.
    """
    for i in range(warmup):
        state, _ = step(jax.random.fold_in(key, i), state, frame)
    jax.block_until_ready(state)
    times, windowed = [], 0
    for i in range(repeats):
        k = jax.random.fold_in(key, 1000 + i)
        t0 = time.perf_counter()
        state, info = step(k, state, frame)
        jax.block_until_ready((state, info))
        times.append(time.perf_counter() - t0)
        windowed += bool(info.windowed)
    return times, windowed / repeats, info


class OpenCVLoop:
    """The OpenCV baseline at ``n`` particles, one timed ``opencv_step`` per ``step()`` call
    (its particle cloud carried on); ``ms()`` is the run's statistic of the times."""

    def __init__(self, n: int, frame, bins=H.DEFAULT_BINS):
        x, y = FRAME_W / 2 - BOX_WH[0] / 2, FRAME_H / 2 - BOX_WH[1] / 2
        xywh = (x, y, float(BOX_WH[0]), float(BOX_WH[1]))
        self.frame, self.bins = frame, bins
        self.ref = reference_histogram(frame, xywh, bins)
        self.rng = np.random.default_rng(0)
        particles = np.asarray(init_particles(jax.random.key(0), n, xywh))
        self.particles = opencv_step(self.rng, particles, frame, self.ref, bins)  # warm-up
        self.times: list[float] = []

    def step(self) -> None:
        t0 = time.perf_counter()
        self.particles = opencv_step(self.rng, self.particles, self.frame, self.ref, self.bins)
        self.times.append(time.perf_counter() - t0)

    def ms(self) -> float:
        return _median_ms(self.times)


#: OpenCV steps timed per round of the main JAX timings, by N: 10 and 5 steps over the
#: ``ROUNDS`` rounds.
OPENCV_STEPS_PER_ROUND = {1_000: 2, 10_000: 1}


def time_table_pass(window: tuple[int, int], repeats: int = 50) -> dict:
    """This host's memory speed at the size that matters: one jitted elementwise pass
    (``t + 1``) over an array shaped like the window's stored integral histogram
    (``[h + 1, w + 1, channels]`` uint16). The step writes and reads that table about
    three times (x pass, row loop, corner gathers), so hosts whose caches move it
    slowly run the step slowly whatever its code."""
    channels = H._table_channels(ColourConfig().n_bins, jnp.uint16)
    table = jnp.zeros((window[0] + 1, window[1] + 1, channels), jnp.uint16)
    bump = jax.jit(lambda t: t + jnp.uint16(1))
    jax.block_until_ready(bump(table))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(bump(table))
        times.append(time.perf_counter() - t0)
    ms = _median_ms(times)
    return {"mb": table.nbytes / 1e6, "ms": ms, "gb_per_s": 2 * table.nbytes / ms / 1e6}


# ----------------------------------------------------------------------------- main


def _variant_cell(r: dict, key: str) -> str:
    """A variant's ms per frame, with its windowed share when some steps fell back."""
    prefix = f"{key}_" if key else ""  # "": the default's own keys
    ms = r.get(f"{prefix}ms_per_frame", float("nan"))
    share = r.get(f"{prefix}windowed", 1.0)
    return f"{ms:.2f}" + ("" if share >= 1.0 else f" ({share:.0%})")


def _markdown(results: dict) -> str:
    meta = results["meta"]
    lines = [
        "# Colour step benchmark",
        "",
        f"{meta['frame']} frame, box {meta['box']}, {meta['model']}, "
        f"{meta['cpu']} ({meta['cores']} cores), jax {meta['jax']}, {meta['date']}.",
        f"Load average before / after: {meta['load_before']} / {meta['load_after']}; "
        f"malloc tuned: {meta['malloc_tuned']}; XLA_FLAGS: `{meta['xla_flags'] or '(unset)'}`.",
        f"Command: `{meta['command']}`",
        "",
        "| N | JAX ms/frame | JAX frames/s | OpenCV loop ms/frame | speed-up | "
        + " | ".join(f"JAX, {VARIANT_LABELS[v]} ms" for v in VARIANT_KEYS)
        + " |",
        "|---:|---:|---:|---:|---:|" + "---:|" * len(VARIANT_KEYS),
    ]
    for n in N_MAIN:
        r = results.get(str(n))
        if r is None:
            continue
        scaled = "" if n <= BASELINE_MAX_N else " (scaled)"
        lines.append(
            f"| {n:,} | {_variant_cell(r, '')} | {r['fps']:.1f} | "
            f"{r['baseline_ms_per_frame']:.1f}{scaled} | {r['speedup']:.0f}x | "
            + " | ".join(_variant_cell(r, key) for key in VARIANT_KEYS.values())
            + " |"
        )
    shares = [
        results[str(n)].get(k, 1.0)
        for n in N_MAIN
        if str(n) in results
        for k in ["windowed"] + [f"{key}_windowed" for key in VARIANT_KEYS.values()]
    ]
    if any(share < 1.0 for share in shares):
        lines += [
            "",
            "(w %): only w % of that setting's timed steps ran on the histogram window; the "
            "rest ran the exact whole-frame fallback (`ColourInfo.windowed`), which is "
            "slower. Under the AR1 model the box sizes drift with their size velocities (and "
            "under the random walk too when nothing but the histogram weighs them, as with "
            "the OpenCV loop's likelihood), and at large N the cloud's extreme boxes outgrow "
            "the window sized for the initial box, or the 65,535 pixels a uint16 count "
            "holds: one such particle sends the whole step to the fallback.",
        ]
    table = results.get("table_3_2")
    if table:
        ns = table["n_particles"]
        lines += [
            "",
            "Table 3.2 (thesis: C++ at 3.2 GHz, box 150x200: N=20 18.4, N=100 4.85, N=120 3.81 "
            "frames/s): frames/s of the JAX colour step by box size (w x h) and N.",
            "",
            "| box | " + " | ".join(f"{n:,}" for n in ns) + " |",
            "|---|" + "---:|" * len(ns),
        ]
        marked = False
        for box, fps in table["fps"].items():
            win = table.get("windowed", {}).get(box, [1.0] * len(fps))
            cells = [f"{v:.0f}" + ("*" if s < 1.0 else "") for v, s in zip(fps, win, strict=True)]
            marked |= any(s < 1.0 for s in win)
            lines.append(f"| {box} | " + " | ".join(cells) + " |")
        if marked:
            lines += [
                "",
                "\\* Some timed steps (share in the JSON, `table_3_2.windowed`) ran the "
                "exact whole-frame fallback instead of the histogram window: a particle box "
                "left the window sized for the initial box (`ColourConfig.with_window`). "
                "With a 150x150 box most steps do: the figure in the frame is about 200 px "
                "tall, the estimate grows towards it and its particles outgrow the 256x256 "
                "window. `ColourInfo.windowed` reports it per step.",
            ]
    if meta.get("untuned_ms_per_frame"):
        un = meta["untuned_ms_per_frame"]
        lines += [
            "",
            "Same JAX step without `tune_malloc` (fresh process): "
            + ", ".join(f"N={int(n):,} {v:.2f} ms" for n, v in un.items())
            + ".",
        ]
    if meta.get("no_xla_tuning_ms_per_frame"):
        un = meta["no_xla_tuning_ms_per_frame"]
        given = meta.get("xla_flags_given") or "(unset)"
        lines += [
            "",
            f"Same JAX step without `--tune-xla` (fresh process, XLA_FLAGS `{given}`): "
            + ", ".join(f"N={int(n):,} {v:.2f} ms" for n, v in un.items())
            + ".",
        ]
    if meta.get("fresh_repeats_ms_per_frame"):
        fresh = meta["fresh_repeats_ms_per_frame"]
        k = len(next(iter(fresh.values())))
        parts = [
            f"N={int(n):,} " + _process_runs_text([results[n]["ms_per_frame"]] + more, fps=True)
            for n, more in fresh.items()
        ]
        lines += [
            "",
            f"The main run and {k} more fresh processes with the same settings, one after "
            "another (this host's speed varies between processes and over minutes): "
            + "; ".join(parts)
            + ".",
        ]
    if meta.get("table_pass"):
        tp = meta["table_pass"]
        lines += [
            "",
            f"This host's memory speed at the table's size: one elementwise pass over an "
            f"array shaped like the window's integral histogram ({tp['mb']:.1f} MB uint16) "
            f"took {tp['ms']:.2f} ms ({tp['gb_per_s']:.1f} GB/s read + write). The step "
            "writes and reads that table about three times, so compare hosts by this "
            "figure too, not by core count alone.",
        ]
    if "fast_path_rate" in meta:
        lines += [
            "",
            "Share of the timed steps on the fast (windowed) path (`ColourInfo.windowed`): "
            f"{meta['fast_path_rate']}.",
        ]
    return "\n".join(lines) + "\n"


def _process_runs_text(runs: list[float], fps: bool = False) -> str:
    """``"a / b / c ms (median m)"`` for one N's ms/frame in several processes."""
    median = float(np.median(runs))
    rate = f", {1000 / median:.1f} frames/s" if fps else ""
    return " / ".join(f"{v:.2f}" for v in runs) + f" ms (median {median:.2f}{rate})"


def _untuned_main_timings(repeats: int, without: str | None = "malloc") -> dict | None:
    """The main JAX timings from a fresh process without ``tune_malloc`` (``without="malloc"``)
    or without the ``--tune-xla`` flags (``"xla"``): both are process-wide settings.
    ``without=None``: the same settings as this process (a repeat in a fresh process)."""
    args = ["--main-only", f"--repeats={repeats}", f"--stat={ARGS.stat}"]
    xla_flags = os.environ.get("XLA_FLAGS")
    if without is None:
        if not ARGS.tune_malloc:
            args.append("--no-tune-malloc")
        if not ARGS.tune_xla:
            args.append("--no-tune-xla")
    elif without == "malloc":
        args.append("--no-tune-malloc")
    else:
        args.append("--no-tune-xla")
        xla_flags = XLA_FLAGS_GIVEN
    return host.fresh_process_json(__file__, args, xla_flags)


def main(args) -> dict:
    frame, _ = make_frame()
    repeats = 10 if args.quick else args.repeats
    load_before = os.getloadavg()
    results: dict = {}
    variants = ["default"] if args.main_only else ["default", *VARIANT_KEYS]
    specs = [(n, BOX_WH, v) for n in N_MAIN for v in variants]
    # The OpenCV loop is timed in the same rounds as the JAX settings (at the end of each).
    loops = (
        {} if args.main_only else {n: OpenCVLoop(n, frame) for n in N_MAIN if n <= BASELINE_MAX_N}
    )

    def opencv_round():
        for n, loop in loops.items():
            for _ in range(OPENCV_STEPS_PER_ROUND.get(n, 1)):
                loop.step()

    timed = dict(
        zip(
            specs,
            time_jax_steps_interleaved(specs, frame, repeats, each_round=opencv_round),
            strict=True,
        )
    )
    for n in N_MAIN:
        r = timed[(n, BOX_WH, "default")]
        results[str(n)] = r
        if not args.main_only:
            for variant, key in VARIANT_KEYS.items():
                # Each variant's time and its share of steps on the windowed path (the
                # rest ran the exact whole-frame fallback, which is slower).
                r[f"{key}_ms_per_frame"] = timed[(n, BOX_WH, variant)]["ms_per_frame"]
                r[f"{key}_windowed"] = timed[(n, BOX_WH, variant)]["windowed"]
            others = ", ".join(
                f"{VARIANT_LABELS[v]} {r[f'{key}_ms_per_frame']:.2f} ms"
                for v, key in VARIANT_KEYS.items()
            )
            print(
                f"JAX   N={n:>7,}: {r['ms_per_frame']:7.2f} ms  {r['fps']:7.1f} fps ({others})",
                flush=True,
            )
    if args.main_only:
        print(json.dumps(results))
        return results
    per_particle = None
    for n in N_MAIN:
        if n <= BASELINE_MAX_N:
            ms = loops[n].ms()
            per_particle = ms / n
            print(f"OpenCV N={n:>7,}: {ms:8.1f} ms", flush=True)
        else:
            ms = per_particle * n
        results[str(n)]["baseline_ms_per_frame"] = ms
        results[str(n)]["baseline_scaled"] = n > BASELINE_MAX_N
        results[str(n)]["speedup"] = ms / results[str(n)]["ms_per_frame"]
    rate = {str(n): results[str(n)]["windowed"] for n in N_MAIN}
    window = ColourConfig().with_window(BOX_WH, (FRAME_H, FRAME_W)).window
    table_pass = time_table_pass(window)
    print(
        f"One pass over the window's table ({table_pass['mb']:.1f} MB): "
        f"{table_pass['ms']:.2f} ms ({table_pass['gb_per_s']:.1f} GB/s read + write)",
        flush=True,
    )
    untuned = no_xla = None
    if args.tune_malloc and args.compare_malloc and not args.quick:
        untuned = _untuned_main_timings(repeats)
        if untuned:
            for n in N_MAIN:
                ms = untuned[str(n)]["ms_per_frame"]
                print(f"JAX (malloc not tuned) N={n:>7,}: {ms:7.2f} ms", flush=True)
    if args.tune_xla and args.compare_malloc and not args.quick:
        no_xla = _untuned_main_timings(repeats, without="xla")
        if no_xla:
            for n in N_MAIN:
                ms = no_xla[str(n)]["ms_per_frame"]
                print(f"JAX (no XLA flags) N={n:>7,}: {ms:7.2f} ms", flush=True)
    fresh: dict[str, list[float]] = {str(n): [] for n in N_MAIN}
    for _ in range(0 if args.quick else max(0, args.fresh_repeats)):
        again = _untuned_main_timings(repeats, without=None)
        for n in N_MAIN if again else ():
            fresh[str(n)].append(again[str(n)]["ms_per_frame"])
    if any(fresh.values()):
        for n in N_MAIN:
            runs = [results[str(n)]["ms_per_frame"]] + fresh[str(n)]
            print(f"JAX N={n:>7,} in {len(runs)} processes: {_process_runs_text(runs)}", flush=True)
    if not args.quick:
        table = {"n_particles": list(N_TABLE), "fps": {}, "ms_per_frame": {}, "windowed": {}}
        for w, h in TABLE_BOXES:
            fps, ms, win = [], [], []
            for n in N_TABLE:
                r = time_jax_step(n, (w, h), frame, max(10, repeats // 2))
                fps.append(r["fps"])
                ms.append(r["ms_per_frame"])
                win.append(r["windowed"])
            table["fps"][f"{w}x{h}"] = fps
            table["ms_per_frame"][f"{w}x{h}"] = ms
            table["windowed"][f"{w}x{h}"] = win
            print(f"table 3.2 {w}x{h}: " + " ".join(f"{v:.0f}" for v in fps), flush=True)
        results["table_3_2"] = table
    results["meta"] = {
        "cpu": host.cpu_name(),
        "cores": os.cpu_count(),
        "jax": jax.__version__,
        "opencv": cv2.__version__,
        "bins": list(ColourConfig().bins),
        "model": "library default (cpf_jax.colour): 8x8 H-S + 8 value bins, 2 parts, "
        f"centre-surround ring, contrast and aspect terms, layout {GRID}, template update, "
        "random-walk motion",
        "frame": f"{FRAME_W}x{FRAME_H}",
        "box": f"{BOX_WH[0]}x{BOX_WH[1]}",
        "window": list(window),
        "table_pass": table_pass,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "load_before": [round(v, 2) for v in load_before],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "malloc_tuned": MALLOC_TUNED,
        "untuned_ms_per_frame": (
            {n: r["ms_per_frame"] for n, r in untuned.items()} if untuned else None
        ),
        "no_xla_tuning_ms_per_frame": (
            {n: r["ms_per_frame"] for n, r in no_xla.items()} if no_xla else None
        ),
        "fresh_repeats_ms_per_frame": fresh if any(fresh.values()) else None,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "xla_flags_given": XLA_FLAGS_GIVEN,
        "repeats": repeats,
        "timing": f"{ARGS.stat} of repeats, jax.block_until_ready, {WARMUP} warm-up steps "
        f"excluded; the main JAX settings and the OpenCV loop ({OPENCV_STEPS_PER_ROUND} "
        f"steps per round) interleaved in {ROUNDS} rounds (Table 3.2 timed one setting "
        "after another)",
        "fast_path_rate": rate,
        "command": "python " + " ".join(["experiments/bench_colour.py"] + sys.argv[1:]),
    }
    md = _markdown(results)
    print(md)
    if not args.quick or args.out:
        stem = Path(args.out) if args.out else Path(__file__).parent / "results" / "bench_colour"
        stem.parent.mkdir(parents=True, exist_ok=True)
        stem.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
        stem.with_suffix(".md").write_text(md)
        figure(results, stem.with_suffix(".png"))
    return results


def fps_chart(ns, ms_by_label: dict, title: str, xlabel: str = "particles N"):
    """Frames/s against N (log axis) of each label's ms-per-frame list (None: not timed)."""
    from cpf_jax import charts

    series = {
        label: (ns, [1000.0 / v if v else float("nan") for v in ms])
        for label, ms in ms_by_label.items()
        if any(v is not None for v in ms)
    }
    top = max(max((v for v in y if v == v), default=1.0) for _, y in series.values())
    return charts.line_chart(
        series, title=title, xlabel=xlabel, ylabel="frames/s", log_x=True, ylim=(0.0, 1.1 * top)
    )


def figure(results: dict, path: Path) -> None:
    """Frames/s vs N of each step variant and the OpenCV loop; the Table 3.2 grid."""
    from cpf_jax import charts

    ns = [int(k) for k in results if k.isdigit()]
    variants = {
        "ours (default)": "ms_per_frame",
        **{VARIANT_LABELS[v]: f"{key}_ms_per_frame" for v, key in VARIANT_KEYS.items()},
        "OpenCV calcHist + compareHist loop": "baseline_ms_per_frame",
    }
    meta = results["meta"]
    panels = [
        fps_chart(
            ns,
            {label: [results[str(n)].get(key) for n in ns] for label, key in variants.items()},
            f"One colour step, {meta['frame']} frame, box {meta['box']} ({meta['cores']} cores)",
            "particles N (OpenCV loop scaled linearly above N = 10,000)",
        )
    ]
    table = results.get("table_3_2")
    if table:
        panels.append(
            fps_chart(
                table["n_particles"],
                table["ms_per_frame"],
                "Table 3.2: frames/s per box size (thesis, C++: 150x200 N = 100 at 4.85)",
            )
        )
    charts.save_png(np.concatenate(panels), path)


def redraw_figure(out: str | None, name: str, draw) -> None:
    """``--figure-only``: ``draw(results, png path)`` from the JSON at the results stem
    ``out`` (default ``results/<name>``); shared with ``bench_rgbd``."""
    stem = Path(out) if out else Path(__file__).parent / "results" / name
    draw(json.loads(stem.with_suffix(".json").read_text()), stem.with_suffix(".png"))
    print(f"wrote {stem.with_suffix('.png')}")


if __name__ == "__main__":
    if ARGS.figure_only:
        redraw_figure(ARGS.out, "bench_colour", figure)
    else:
        main(ARGS)
