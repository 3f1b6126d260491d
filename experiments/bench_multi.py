"""Benchmark: the multi-person tracker's step with four people against one target's.

Three steps are timed in one process, interleaved, on synthetic Kinect v2 frames (512 x
424) with the same RGB-D box filter per target (``MultiConfig().rgbd``, its particle count
and the histogram window of ``cpf-track --multi``):

* the single-target RGB-D filter on one walker (``walk_across_medium``): the baseline;
* ``cpf_jax.multi`` with four slots and that one walker (three slots free);
* ``cpf_jax.multi`` with four slots and four people (``group_enter``, started on the
  ground truth of the first frame where all four are in view, so all four are confirmed).

Every step is compiled and run once before timing; each figure is the median over
``--repeats`` passes of ten steps from the same state. Writes
``experiments/results/bench_multi.{json,md}``::

    python experiments/bench_multi.py [--repeats 5]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import host  # noqa: E402  (same folder: the CPU name)

from cpf_jax.filter import Context  # noqa: E402
from cpf_jax.kernels.background import Background  # noqa: E402
from cpf_jax.multi import MultiConfig, build_multi_filter, default_multi_params  # noqa: E402
from cpf_jax.rgbd import build_rgbd_filter, default_rgbd_params  # noqa: E402
from cpf_jax.synthetic import make_sequence  # noqa: E402
from cpf_jax.synthetic_multi import make_people_sequence, people_truth  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

RESULTS = ROOT / "experiments" / "results"
STEPS = 10
#: The slots' histogram window, as ``cpf-track --multi`` sizes it (share of width, height).
PERSON_SHARE = (0.2, 0.5)


def _background(seq) -> Background:
    return Background(
        jnp.asarray(seq.meta["background_colour"], jnp.float32),
        jnp.asarray(seq.meta["background_depth"], jnp.float32),
    )


def _frames(seq, first: int) -> list[Frame]:
    return [
        Frame(jnp.asarray(seq.colour[t]), jnp.asarray(seq.depth[t]))
        for t in range(first, first + STEPS)
    ]


def four_in_view(seq, min_visibility: float = 0.5) -> tuple[int, np.ndarray]:
    """The first frame where four people are at least ``min_visibility`` visible, and
    their ground-truth boxes ``[4, 4]``."""
    gt = people_truth(seq)
    for t in np.unique(gt[:, 0]).astype(int):
        rows = gt[(gt[:, 0] == t) & (gt[:, 8] >= min_visibility)]
        if len(rows) >= 4 and t + STEPS < len(seq.colour):
            return t, rows[:4, 2:6].astype(np.float32)
    raise RuntimeError(f"{seq.name}: no frame with four people in view")


def timed(step, params, state, frames, key) -> list[float]:
    """Seconds of each step over ``frames`` from ``state``."""
    out = []
    for f in frames:
        t0 = time.perf_counter()
        state, _ = jax.block_until_ready(step(params, key, state, f))
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    key = jax.random.PRNGKey(0)
    load = os.getloadavg()[0]

    one = make_sequence("walk_across_medium", 0, n_frames=STEPS + 1)
    group = make_people_sequence("group_enter", 0)
    hw = one.colour.shape[1:3]
    config = MultiConfig(max_targets=4)
    person = (PERSON_SHARE[0] * hw[1], PERSON_SHARE[1] * hw[0])
    config = config.with_window(person, hw)
    params = default_multi_params(config)
    filt = build_multi_filter(config)
    init, step = jax.jit(filt.init), jax.jit(filt.step)

    single = build_rgbd_filter(config.rgbd)
    sparams = default_rgbd_params(config.rgbd)
    sinit, sstep = jax.jit(single.init), jax.jit(single.step)

    f0 = Frame(jnp.asarray(one.colour[0]), jnp.asarray(one.depth[0]))
    walker_box = jnp.asarray(one.boxes[0], jnp.float32)
    one_ctx = Context(background=_background(one))
    runs = {
        "single-target RGB-D filter, one walker (baseline)": (
            sstep,
            sparams,
            sinit(sparams, key, f0, walker_box, one_ctx),
            _frames(one, 1),
        ),
        "multi, 4 slots, one walker": (
            step,
            params,
            init(params, key, f0, walker_box[None], one_ctx),
            _frames(one, 1),
        ),
    }
    t, boxes = four_in_view(group)
    g0 = Frame(jnp.asarray(group.colour[t]), jnp.asarray(group.depth[t]))
    state4 = init(params, key, g0, jnp.asarray(boxes), Context(background=_background(group)))
    runs["multi, 4 slots, four people"] = (step, params, state4, _frames(group, t + 1))

    for fn, p, s, frames in runs.values():  # compile and warm up
        timed(fn, p, s, frames, key)
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.repeats):
        for name, (fn, p, s, frames) in runs.items():
            times[name] += timed(fn, p, s, frames, key)
    _, info = step(params, key, state4, runs["multi, 4 slots, four people"][3][0])
    tracked = int(np.sum(~np.asarray(info.lost)))

    names = list(runs)
    ms = {n: 1000.0 * float(np.median(times[n])) for n in names}
    base = ms[names[0]]
    out = {
        "host": host.describe(),
        "load_average": round(load, 2),
        "frame_hw": list(hw),
        "n_particles": config.rgbd.n_particles,
        "repeats": args.repeats,
        "people_reported_in_first_timed_frame": tracked,
        "ms": {n: round(v, 2) for n, v in ms.items()},
        "ratio_to_single": {n: round(v / base, 2) for n, v in ms.items()},
        "four_people_over_one_walker": round(ms[names[2]] / ms[names[1]], 2),
    }
    lines = [
        "# Multi-person tracker: the step with four people against one target",
        "",
        "Regenerate with `python experiments/bench_multi.py`. "
        f"{hw[1]} x {hw[0]} synthetic frames, {config.rgbd.n_particles} particles per "
        f"target, {STEPS} steps x {args.repeats} passes, interleaved in one process, median "
        f"step; {out['host']}, load average {load:.1f} at the start. The four-people run "
        f"starts on the ground truth of `group_enter` frame {t} ({tracked} people reported "
        "in its first timed step).",
        "",
        "| step | ms | vs single-target filter |",
        "|---|---:|---:|",
    ]
    for n in names:
        lines.append(f"| {n} | {ms[n]:.1f} | {ms[n] / base:.2f}x |")
    lines += [
        "",
        f"Four people against one walker, both in the multi-person tracker: "
        f"{out['four_people_over_one_walker']:.2f}x.",
    ]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_multi.json").write_text(json.dumps(out, indent=1) + "\n")
    (RESULTS / "bench_multi.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
