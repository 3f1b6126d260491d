"""Gradient tuning of the RGB-D grid-occlusion filter with optax (SPEC C7), held-out check.

Tunes parameters of ``cpf_jax.rgbd`` (``cpf_jax.tuning.tune`` with ``tuning.runner``:
DIoU loss on the weighted-mean box, Adam on the unconstrained values, the Scibior-Wood
gradient through resampling) on synthetic *training* scenes -- occlusion_box,
occlusion_person, appearance_change and walk_across_medium with scene seeds 100-101,
the first 90 frames each, one fresh filter seed per sequence and step -- from the
hand-set defaults, in two settings:

* ``likelihood``: the widths and floors of the cell terms and the Beta weight
  (``colour.sigma``, ``depth.sigma``, ``colour.floor``, ``depth.floor``, ``beta.weight``);
* ``likelihood+flags``: ``colour.sigma``, ``depth.sigma``, ``beta.weight`` and the
  occlusion model (eq. 1's constant ``occlusion.log_occluded``, the flag transitions
  ``occlusion.p_occlude`` / ``occlusion.p_reveal``).

Early stopping: every 5 steps the loss on validation scenes (the same scenarios, scene
seeds 102-103, one fixed filter seed); the result is the parameters with the lowest
validation loss (the start included). Each result is checked on held-out data: the
synthetic scenarios of ``occlusion_tables.py`` (its evaluation seeds, keys, length and
N = 150; grid-occlusion MOTA and success rate) and the real IST recording (8 filter
keys; AUC as in the occlusion tables) when ``../shared/data`` is there. Writes
``experiments/results/tune_rgbd.json`` and ``tune_rgbd.md`` (the parameters under
their ``KEYS``).

    python experiments/tune_rgbd.py [--steps 25] [--lr 0.1] [--quick]
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

sys.path.insert(0, str(Path(__file__).resolve().parent))
import occlusion_tables as ot  # noqa: E402
import tune_colour  # noqa: E402

from cpf_jax import params as pp  # noqa: E402
from cpf_jax import tuning  # noqa: E402
from cpf_jax.filter import Context, track_boxes  # noqa: E402
from cpf_jax.rgbd import build_rgbd_filter, default_rgbd_params, rgbd_props  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

SETTINGS = {
    "likelihood": ("colour.sigma", "depth.sigma", "colour.floor", "depth.floor", "beta.weight"),
    "likelihood+flags": (
        "colour.sigma",
        "depth.sigma",
        "beta.weight",
        "occlusion.log_occluded",
        "occlusion.p_occlude",
        "occlusion.p_reveal",
    ),
}
#: Each tuned parameter's key in the results (JSON, Markdown).
KEYS = {
    "colour.sigma": "sigma_rgb",
    "depth.sigma": "sigma_depth",
    "colour.floor": "colour_floor",
    "depth.floor": "depth_floor",
    "beta.weight": "beta_weight",
    "occlusion.log_occluded": "log_occluded",
    "occlusion.p_occlude": "p_occlude",
    "occlusion.p_reveal": "p_reveal",
}
TRAIN_SCENES = ("occlusion_box", "occlusion_person", "appearance_change", "walk_across_medium")
TRAIN_SEEDS = (100, 101)
VALIDATION_SEEDS = (102, 103)
TRAIN_FRAMES = 90
IST_KEYS = 8


def _data(scenes, seeds, n_frames):
    seqs, bgs = [], []
    for name in scenes:
        for seed in seeds:
            seq, _, bg = ot._sequence(name, seed, n_frames)
            seqs.append(seq)
            bgs.append(bg)
    return seqs, tuning.stack_sequences(seqs, bgs)


@functools.cache
def _runner(config):
    """(params, keys, frames, box, bg) -> boxes, lost; params are an argument."""
    filt = build_rgbd_filter(config)

    def run(params, keys, frames, box, bg):
        context = Context(background=bg)
        return jax.vmap(lambda k: track_boxes(filt, params, k, frames, box, context))(keys)

    return jax.jit(run)


def synthetic_held_out(params, quick: bool) -> dict:
    """Grid-occlusion MOTA (mean, worst run) and success rate per scenario of the
    occlusion tables, on their evaluation seeds and keys."""
    seeds = ot.EVAL_SEEDS[:1] if quick else ot.EVAL_SEEDS
    n_keys = 1 if quick else ot.N_KEYS
    n_frames = 30 if quick else ot.N_FRAMES
    seqs = {
        (sc, name, seed): ot._sequence(
            name, seed, None if name in ot.OWN_LENGTH and not quick else n_frames
        )
        for sc, names in ot.SCENARIOS.items()
        for name in names
        for seed in seeds
    }
    any_seq = next(iter(seqs.values()))[0]
    w = max(float(s.boxes[:, 2].max()) for s, _, _ in seqs.values())
    h = max(float(s.boxes[:, 3].max()) for s, _, _ in seqs.values())
    config = ot._config("grid-occlusion", (w, h), any_seq.colour.shape[1:3], ot.N_PARTICLES)
    run = _runner(config)
    keys = jax.random.split(jax.random.PRNGKey(0), n_keys)
    runs: dict[str, list] = {}
    for (sc, _, _), (seq, frames, bg) in seqs.items():
        boxes, lost = (np.asarray(a) for a in run(params, keys, frames, seq.boxes[0], bg))
        for i in range(n_keys):
            runs.setdefault(sc, []).append(ot._scores(boxes[i], seq.boxes, seq.visible, lost[i]))
    return {
        sc: {
            "mota": round(float(np.mean([r["mota"] for r in rs])), 2),
            "mota_min": round(float(min(r["mota"] for r in rs)), 2),
            "success_rate": round(float(np.mean([r["success_rate"] for r in rs])), 2),
        }
        for sc, rs in runs.items()
    }


@functools.cache
def _ist():
    colour, depth, gt, visible = ot._ist_frames()
    bg = ot._background_of(colour, depth, ot.IST_BACKGROUND)
    s = ot.IST_START
    frames = Frame(jnp.asarray(colour[s:]), jnp.asarray(depth[s:]))
    return frames, gt[s:], visible[s:], bg, colour.shape[1:3]


def ist_held_out(params, quick: bool) -> dict | None:
    if not ot.IST.is_dir():
        print(f"IST skipped: {ot.IST} not found (the shared data is not mounted).")
        return None
    frames, gt, visible, bg, frame_hw = _ist()
    config = ot._config(
        "grid-occlusion", (float(gt[0][2]), float(gt[0][3])), frame_hw, ot.N_PARTICLES
    )
    n_keys = 1 if quick else IST_KEYS
    keys = jax.random.split(jax.random.PRNGKey(1), n_keys)  # the occlusion tables' keys
    boxes, lost = (np.asarray(a) for a in _runner(config)(params, keys, frames, gt[0], bg))
    aucs = [ot._scores(boxes[i], gt, visible, lost[i])["auc"] for i in range(n_keys)]
    return {
        "auc": round(float(np.mean(aucs)), 2),
        "auc_first4": round(float(np.mean(aucs[:4])), 2),
        "auc_per_key": [round(float(a), 2) for a in aucs],
    }


def _values(params, names) -> dict:
    return {KEYS[n]: round(float(np.mean(np.asarray(pp.get(params, n)))), 4) for n in names}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--quick", action="store_true", help="1 scene, 2 steps, 1 held-out key")
    ap.add_argument("--out", default=str(ot.RESULTS / "tune_rgbd.json"))
    ap.add_argument("--figure-only", action="store_true", help="redraw the figure from --out")
    args = ap.parse_args()
    if args.figure_only:
        tune_colour.redraw_figure(args.out, TITLE)
        return
    scenes = TRAIN_SCENES[:1] if args.quick else TRAIN_SCENES
    steps = 2 if args.quick else args.steps
    n_frames = 30 if args.quick else TRAIN_FRAMES
    train_seqs, data = _data(scenes, TRAIN_SEEDS, n_frames)
    val_seqs, validation = _data(scenes, VALIDATION_SEEDS, n_frames)
    w = max(float(s.boxes[:, 2].max()) for s in train_seqs + val_seqs)
    h = max(float(s.boxes[:, 3].max()) for s in train_seqs + val_seqs)
    config = ot._config("grid-occlusion", (w, h), train_seqs[0].colour.shape[1:3], ot.N_PARTICLES)
    run = tuning.runner(build_rgbd_filter(config))
    p0 = default_rgbd_params(config)
    props = rgbd_props(config)
    res = {
        "train": {
            "scenes": list(scenes),
            "seeds": list(TRAIN_SEEDS),
            "validation_seeds": list(VALIDATION_SEEDS),
            "frames": n_frames,
            "n_particles": ot.N_PARTICLES,
        },
        "optimizer": f"adam({args.lr})",
        "steps": steps,
        "held_out_before": {
            "synthetic": synthetic_held_out(p0, args.quick),
            "ist": ist_held_out(p0, args.quick),
        },
        "runs": {},
    }
    print("defaults", json.dumps(res["held_out_before"]), flush=True)
    for label, names in SETTINGS.items():
        t0 = time.perf_counter()

        result = tuning.tune(
            run,
            p0,
            props,
            data,
            names,
            optimizer=optax.adam(args.lr),
            steps=steps,
            key=jax.random.PRNGKey(0),
            callback=tuning.progress(label, names),
            validation=validation,
            validate_every=5,
        )
        validated = [e for e in result.history if "validation" in e]
        res["runs"][label] = {
            "names": [KEYS[n] for n in names],
            "before": _values(p0, names),
            "after": _values(result.params, names),
            "validation_start": result.start_validation,
            "validation_best": min(
                [result.start_validation] + [e["validation"] for e in validated]
            ),
            "tune_seconds": round(time.perf_counter() - t0, 1),
            "skipped_steps": sum(e["skipped"] for e in result.history),
            "history": [
                {
                    KEYS.get(k, k): (float(np.mean(e[k])) if k in names else e[k])
                    for k in e
                    if k != "skipped"
                }
                for e in result.history
            ],
            "held_out_after": {
                "synthetic": synthetic_held_out(result.params, args.quick),
                "ist": ist_held_out(result.params, args.quick),
            },
        }
        print(label, json.dumps(res["runs"][label]["held_out_after"]), flush=True)
        # Written after each setting: an interrupted run keeps the finished ones.
        tune_colour.write_results(res, args.out, _markdown(res), TITLE)


TITLE = "Gradient tuning of the grid-occlusion likelihood (synthetic occlusion scenes)"


def _row(label: str, values: dict, names, held: dict) -> str:
    syn = held["synthetic"]
    ist = held["ist"]
    cells = [f"{values.get(n, ''):g}" if n in values else "" for n in names]
    occ = syn.get("occlusion", {})
    ret = syn.get("occlusion_return", {})
    app = syn.get("appearance_change", {})
    ist_auc = f"{ist['auc']:.1f}" if ist else "n/a"
    return (
        f"| {label} | "
        + " | ".join(cells)
        + f" | {occ.get('mota', float('nan')):.1f} ({occ.get('mota_min', float('nan')):.1f})"
        + f" | {ret.get('mota', float('nan')):.1f} | {app.get('success_rate', float('nan')):.1f}"
        + f" | {ist_auc} |"
    )


def _markdown(res: dict) -> str:
    names = sorted({n for r in res["runs"].values() for n in r["names"]})
    lines = [
        "# Gradient tuning of the RGB-D grid-occlusion filter (optax, held-out check)",
        "",
        f"Regenerate with `python experiments/tune_rgbd.py`. {res['optimizer']}, "
        f"{res['steps']} steps, DIoU loss on the weighted-mean box; training scenes "
        f"{', '.join(res['train']['scenes'])} with scene seeds {res['train']['seeds']} (first "
        f"{res['train']['frames']} frames, N = {res['train']['n_particles']}), early stopping "
        f"on scene seeds {res['train']['validation_seeds']}. Held out: the synthetic "
        "scenarios of `occlusion_tables.py` (its evaluation seeds and keys) and the real IST "
        f"recording ({IST_KEYS} keys).",
        "",
        "| parameters | "
        + " | ".join(f"`{n}`" for n in names)
        + " | occlusion MOTA (worst) | occlusion_return MOTA | appearance_change SR | IST AUC |",
        "|---|" + "---:|" * (len(names) + 4),
    ]
    p0 = {}
    for r in res["runs"].values():
        p0.update(r["before"])
    lines.append(_row("defaults", p0, names, res["held_out_before"]))
    for label, r in res["runs"].items():
        lines.append(_row(f"tuned: {label}", r["after"], names, r["held_out_after"]))
    lines += [
        "",
        f"IST AUC: the mean over {IST_KEYS} filter keys (`jax.random.split(PRNGKey(1), "
        f"{IST_KEYS})`, vmapped in one program; `occlusion_tables.md` reports "
        f"{ot.IST_KEYS} keys of its own split). Single keys "
        "range over about 20 points, so differences of a few points are noise.",
        "",
        "Validation loss (defaults / best, the parameters kept):",
    ]
    for label, r in res["runs"].items():
        lines.append(
            f"- {label}: {r['validation_start']:.4f} / {r['validation_best']:.4f} "
            f"({r['tune_seconds']:.0f} s, {r['skipped_steps']} skipped steps)"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
