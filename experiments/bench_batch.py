"""Benchmark: a batch of filter runs on one device (lax.map, vmap) vs split over CPU devices.

A batch of K filter seeds on one synthetic sequence (walk_across_medium, 150 frames,
colour filter N = 1,000) is run these ways, each in a fresh process (the device count is
fixed when JAX starts):

* ``lax.map`` on one device (the baseline: what ``experiments/colour_tables.py`` does);
* ``vmap`` on one device, and ``vmap`` with the histogram kernel's exactness fallback
  as a ``select`` (``kernels.histogram.batch_all`` replaced by the identity: what vmap
  did before it, running the whole-frame tables for every member and frame);
* ``cpf_jax.batch.run_sharded`` on 1 device (the wrapper's overhead);
* ``run_sharded`` on D devices (``XLA_FLAGS=--xla_force_host_platform_device_count=D``).

The three one-device modes are also timed for the grid-occlusion RGB-D filter (N = 150,
``occlusion_person``, 60 frames), whose step counts two windowed tables.

Each is timed after a compile run (median of 3), in runs per second, with the ratio to
the baseline. On a CPU the D devices share the host's cores: a gain comes from running
D items' independent programs side by side instead of one after another with
intra-op threads. Writes ``experiments/results/bench_batch.{json,md}``.

    python experiments/bench_batch.py [--keys 8] [--devices 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import host  # same folder: the CPU name

RESULTS = Path(__file__).resolve().parent / "results"

CHILD = """
import json, sys, time
import jax, jax.numpy as jnp
from cpf_jax.batch import run_sharded
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
from cpf_jax.filter import Context, track_boxes
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame

mode, n_keys, n_particles, model = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
if mode == "vmap-select":  # the fallback's cond as before batch_all: a select under vmap
    import cpf_jax.kernels.histogram as H
    H.batch_all = lambda flag: flag
    mode = "vmap"
keys = jax.random.split(jax.random.PRNGKey(0), n_keys)
if model == "colour":
    seq = make_sequence("walk_across_medium", seed=0, n_frames=150)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    # The histogram-only model, as the results table was made.
    config = ColourConfig(n_particles=n_particles).histogram_only().with_window(
        seq.boxes[0, 2:], seq.colour.shape[1:3]
    )
    filt, params, context = build_colour_filter(config), default_colour_params(), None
else:
    from cpf_jax import rgbd
    from cpf_jax.kernels.background import median_background
    seq = make_sequence("occlusion_person", seed=0, n_frames=60)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    bg = median_background(frames.colour[::6], frames.depth[::6])
    config = rgbd.RGBDConfig(n_particles=n_particles).with_window(
        tuple(float(v) for v in seq.boxes[0, 2:]), seq.colour.shape[1:3]
    )
    filt, params = rgbd.build_rgbd_filter(config), rgbd.default_rgbd_params(config)
    context = Context(background=bg)


def one(key, frames, box):
    return track_boxes(filt, params, key, frames, box, context)[0]


box = jnp.asarray(seq.boxes[0])

if mode == "map":
    run = jax.jit(lambda ks, fr, b: jax.lax.map(lambda k: one(k, fr, b), ks))
    go = lambda: run(keys, frames, box)
elif mode == "vmap":
    run = jax.jit(jax.vmap(one, in_axes=(0, None, None)))
    go = lambda: run(keys, frames, box)
else:
    go = lambda: run_sharded(one, keys, frames, box)
jax.block_until_ready(go())
times = []
for _ in range(3):
    t0 = time.perf_counter()
    jax.block_until_ready(go())
    times.append(time.perf_counter() - t0)
times.sort()
print(json.dumps({"devices": len(jax.devices()), "seconds": times[1]}))
"""


def _child(mode: str, devices: int, keys: int, particles: int, model: str = "colour") -> dict:
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode, str(keys), str(particles), model],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keys", type=int, default=8)
    ap.add_argument("--devices", type=int, default=2)
    ap.add_argument("--particles", type=int, default=1000)
    ap.add_argument("--rgbd-particles", type=int, default=150)
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    rows = [
        ("lax.map, 1 device (baseline)", "map", 1),
        ("vmap, 1 device", "vmap", 1),
        ("vmap, fallback as a select (before batch_all)", "vmap-select", 1),
        ("run_sharded, 1 device", "sharded", 1),
        (f"run_sharded, {args.devices} devices", "sharded", args.devices),
    ]
    rgbd_rows = [
        ("grid-occlusion: lax.map, 1 device (baseline)", "map", 1),
        ("grid-occlusion: vmap, 1 device", "vmap", 1),
        ("grid-occlusion: vmap, fallback as a select (before batch_all)", "vmap-select", 1),
    ]
    res = {
        "keys": args.keys,
        "particles": args.particles,
        "rgbd_particles": args.rgbd_particles,
        "frames": 150,
        "cpus": os.cpu_count(),
        "cpu": host.cpu_name(),
    }
    md = [
        "# Batch runs: one device vs several CPU devices",
        "",
        f"Regenerate with `python experiments/bench_batch.py`. {args.keys} filter seeds x "
        f"walk_across_medium (150 frames), colour filter N = {args.particles}; "
        f"{host.describe()}, load average {load:.1f} at the start; median of 3 timed runs. "
        f"Grid-occlusion rows: the same {args.keys} seeds x occlusion_person (60 frames), "
        f"N = {args.rgbd_particles}.",
        "",
        "| setting | devices | s per batch | runs / s | vs baseline |",
        "|---|---:|---:|---:|---:|",
    ]
    for group, model, particles in (
        (rows, "colour", args.particles),
        (rgbd_rows, "rgbd", args.rgbd_particles),
    ):
        base = None
        for label, mode, devices in group:
            t0 = time.perf_counter()
            r = _child(mode, devices, args.keys, particles, model)
            s = r["seconds"]
            base = s if base is None else base
            entry = {
                "devices": r["devices"],
                "seconds_per_batch": round(s, 3),
                "runs_per_second": round(args.keys / s, 2),
                "speedup": round(base / s, 2),
            }
            res[label] = entry
            md.append(
                f"| {label} | {r['devices']} | {entry['seconds_per_batch']} | "
                f"{entry['runs_per_second']} | {entry['speedup']}x |"
            )
            print(label, entry, f"({time.perf_counter() - t0:.0f} s with set-up)", flush=True)
    (RESULTS / "bench_batch.json").write_text(json.dumps(res, indent=1) + "\n")
    (RESULTS / "bench_batch.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_batch.md'}")


if __name__ == "__main__":
    main()
