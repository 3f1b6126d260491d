"""The RGB-D filter without background frames: the scene learnt from the tracked frames.

Runs the default grid-occlusion filter (N = 200) on the synthetic walks from their
first frame in three ways: with the scenario's empty room as the background (what a
static camera with empty frames gives), without a background and with the scene learnt
from the tracked frames (``RGBDConfig.learn_scene``, ``cpf-track --background learn``),
and without a background and every pixel foreground (``learn_scene=False``). Training
seeds 100-102 (the decision log's) and the tables' seed 0 are reported apart; success
rate at IoU 0.5 of the filter's estimate, percent, mean over seeds.

Writes ``results/rgbd_scene.json`` and ``results/rgbd_scene.md``.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import host  # same folder: the CPU name
from colour_tables import WALKING  # noqa: E402

from cpf_jax import synthetic
from cpf_jax.filter import Context, track
from cpf_jax.kernels.background import Background
from cpf_jax.metrics.single import frame_ious
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params

RESULTS = Path(__file__).resolve().parent / "results"
TRAIN_SEEDS = (100, 101, 102)
TABLE_SEEDS = (0,)
# The walking scenarios (the target: SR >= 95 % on each) and a walker passing furniture.
SCENARIOS = (*WALKING, "distractor_pass")
MODES = ("empty room", "learnt scene", "every pixel foreground")


def _context(seq, mode: str) -> Context | None:
    if mode != "empty room":
        return None
    colour = jnp.asarray(seq.meta["background_colour"], jnp.float32)
    return Context(
        background=Background(colour, jnp.asarray(seq.meta["background_depth"], jnp.float32))
    )


@functools.cache
def _runner(mode: str, n_particles: int):
    """One jitted run per mode (compiled once per sequence length)."""
    config = RGBDConfig(n_particles=n_particles, learn_scene=mode != "every pixel foreground")
    filt, params = build_rgbd_filter(config), default_rgbd_params(config)
    return jax.jit(lambda k, f, b, c: track(filt, params, k, f, b, c))


def success(name: str, seed: int, mode: str, n_particles: int) -> float:
    """Success rate (%) of the default grid-occlusion filter on scenario ``name``."""
    seq = synthetic.make_sequence(name, seed=seed)
    frames = synthetic.stacked_frames(seq)
    run = _runner(mode, n_particles)
    box = jnp.asarray(seq.boxes[0], jnp.float32)
    _, info = run(jax.random.PRNGKey(seed), frames, box, _context(seq, mode))
    ious = np.asarray(frame_ious(info.estimate, jnp.asarray(seq.boxes[1:])))
    visible = np.asarray(seq.visible[1:], bool)
    return float(100.0 * np.mean(ious[visible] >= 0.5))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--particles", type=int, default=200)
    args = p.parse_args()
    names = args.scenarios.split(",")
    table: dict = {}
    for split, seeds in (("train", TRAIN_SEEDS), ("table", TABLE_SEEDS)):
        for name in names:
            row = {}
            for mode in MODES:
                row[mode] = float(np.mean([success(name, s, mode, args.particles) for s in seeds]))
            table.setdefault(split, {})[name] = row
            print(split, name, "  ".join(f"{m}: {v:5.1f}" for m, v in row.items()), flush=True)
    result = {
        "cpu": host.cpu_name(),
        "particles": args.particles,
        "seeds": {"train": TRAIN_SEEDS, "table": TABLE_SEEDS},
        "success": table,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "rgbd_scene.json").write_text(json.dumps(result, indent=2) + "\n")
    md = [
        "# The RGB-D filter without background frames",
        "",
        f"`python experiments/rgbd_scene.py`; {host.describe()}. Default grid-occlusion filter, "
        f"N = {args.particles}, from each scenario's first frame; success rate at IoU 0.5 of "
        "the estimate, percent (mean over seeds).",
        "",
    ]
    for split, seeds in (("train", TRAIN_SEEDS), ("table", TABLE_SEEDS)):
        md += [f"## Seeds {', '.join(map(str, seeds))} ({split})", ""]
        md += ["| scenario | " + " | ".join(MODES) + " |", "|---|" + "---:|" * len(MODES)]
        for name, row in table[split].items():
            md.append(f"| {name} | " + " | ".join(f"{row[m]:.1f}" for m in MODES) + " |")
        md.append("")
    (RESULTS / "rgbd_scene.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
