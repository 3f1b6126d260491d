"""Benchmark: a batch of colour-filter runs on one device vs split over CPU devices.

A batch of K filter seeds on one synthetic sequence (walk_across_medium, 150 frames,
N = 1,000) is run three ways, each in a fresh process (the device count is fixed when
JAX starts):

* ``lax.map`` on one device (the baseline: what ``experiments/colour_tables.py`` does);
* ``cpf_jax.batch.run_sharded`` on 1 device (the wrapper's overhead);
* ``run_sharded`` on D devices (``XLA_FLAGS=--xla_force_host_platform_device_count=D``).

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

RESULTS = Path(__file__).resolve().parent / "results"

CHILD = """
import json, sys, time
import jax, jax.numpy as jnp
from cpf_jax.batch import run_sharded
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params, track_boxes
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame

mode, n_keys, n_particles = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
seq = make_sequence("walk_across_medium", seed=0, n_frames=150)
frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
config = ColourConfig(n_particles=n_particles).with_window(seq.boxes[0, 2:], seq.colour.shape[1:3])
filt, params = build_colour_filter(config), default_colour_params()
box = jnp.asarray(seq.boxes[0])
keys = jax.random.split(jax.random.PRNGKey(0), n_keys)

def one(key, frames, box):
    return track_boxes(filt, params, key, frames, box)

if mode == "map":
    run = jax.jit(lambda ks, fr, b: jax.lax.map(lambda k: one(k, fr, b), ks))
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


def _child(mode: str, devices: int, keys: int, particles: int) -> dict:
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode, str(keys), str(particles)],
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
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    rows = [
        ("lax.map, 1 device (baseline)", "map", 1),
        ("run_sharded, 1 device", "sharded", 1),
        (f"run_sharded, {args.devices} devices", "sharded", args.devices),
    ]
    res = {"keys": args.keys, "particles": args.particles, "frames": 150, "cpus": os.cpu_count()}
    base = None
    md = [
        "# Batch runs: one device vs several CPU devices",
        "",
        f"Regenerate with `python experiments/bench_batch.py`. {args.keys} filter seeds x "
        f"walk_across_medium (150 frames), colour filter N = {args.particles}; "
        f"{os.cpu_count()} CPUs, load average {load:.1f} at the start; median of 3 timed runs.",
        "",
        "| setting | devices | s per batch | runs / s | vs baseline |",
        "|---|---:|---:|---:|---:|",
    ]
    for label, mode, devices in rows:
        t0 = time.perf_counter()
        r = _child(mode, devices, args.keys, args.particles)
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
