"""Which joined components are the tracked person's body when someone touches him or passes
in front: the box's centre against the target's depth from layer 1, on synthetic scenes.

Scenes: ``cpf_jax.synthetic_multi``'s ``two_crossing``, ``three_walkers`` and
``group_enter`` (people crossing nearer and farther than the walker, a group entering in
front of him), on the training seeds ``TRAIN_SEEDS`` (multi_target's; its evaluation seeds
and the real recording never choose). Layer 1 (the grid-occlusion RGB-D filter, no
background frames) runs over each sequence from the walker's first box and gives, every
frame, the target's depth: the mean of its depth templates
(``cascade.layer1_target_depth``). Layer 2's segmentation runs on the walker's
ground-truth box (tight around his visible pixels) in the cascade's setting without
background frames (``layer+scene`` of ``depth_real.py``: the foreground against the frame's
own scene as layer 1 reads it when it starts on the box, ``PointConfig.with_foreground``).

Scored on the **contact frames**: those in which the walker shows at least
``MIN_PIXELS`` pixels and another person's box overlaps his. ``recall`` is the share of
the walker's visible pixels (the generator's mask) in the window that are on the body,
``leak`` the share of the body that is not the walker. Variants (``variants``): no join
(the sizeable components), the components joined through 160 mm steps to the one at the
box's centre (``joined_anchor="centre"``), those whose mean depth lies within
``anchor_max_dz_mm`` of layer 1's target depth (``joined_anchor="depth"``), and the same
with "sizeable" measured against the largest component at that depth
(``anchor_sizeable``). The foreground is the one the cascade's layer 2 gets from the running
layer 1 (``cascade.layer2_from_layer1``); the ``per-frame scene`` rows use instead
``depth_real.py``'s ``layer+scene`` foreground (layer 1 restarted on each frame's box).

Writes ``experiments/results/depth_anchor_train.json`` and ``.md``::

    python experiments/depth_anchor.py
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from depth_real import frame_scene_foreground, layer1_inputs, window_sample

from cpf_jax.points import PointConfig, body_model
from cpf_jax.synthetic_multi import make_people_sequence

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SCENES = ("two_crossing", "three_walkers", "group_enter")
TRAIN_SEEDS = (100, 101, 102, 103)
MIN_PIXELS = 300
#: Settings also run with the foreground of ``depth_real.py``'s ``layer+scene`` (layer 1
#: started on each frame's box), which the real recording is scored with.
PER_FRAME = "per-frame scene:"
PER_FRAME_VARIANTS = ("scene", "joined, centre")
WINDOW = (256, 192)


def variants(base: PointConfig) -> dict[str, PointConfig]:
    """The segmentation settings compared (module docstring)."""
    joined = dataclasses.replace(base, joined_max_dz_mm=160.0)
    out = {"scene": base, "joined, centre": joined}
    for tol in (150.0, 300.0, 500.0):
        out[f"joined, depth {tol:.0f}"] = dataclasses.replace(
            joined, joined_anchor="depth", anchor_max_dz_mm=tol
        )
        out[f"joined, depth {tol:.0f}, sizes at depth"] = dataclasses.replace(
            out[f"joined, depth {tol:.0f}"], anchor_sizeable=True
        )
    return out


def contact_frames(seq) -> list[int]:
    """Frames in which the walker shows and another person's box overlaps his."""
    out = []
    boxes = seq.meta["occluder_boxes"]
    pixels = seq.meta["occluder_pixels"]
    for t in range(len(seq.boxes)):
        if seq.mask[t].sum() < MIN_PIXELS:
            continue
        x, y, w, h = seq.boxes[t]
        for k in range(boxes.shape[1]):
            if pixels[t, k] <= 0:
                continue
            ox, oy, ow, oh = boxes[t, k]
            if ox < x + w and x < ox + ow and oy < y + h and y < oy + oh:
                out.append(t)
                break
    return out


@functools.cache
def _jitted_body_model(config: PointConfig):
    """``body_model`` under ``config``, jitted once for every sequence."""
    return jax.jit(lambda d, b, f, z: body_model(config, d, b, f, z))


def score_sequence(seq) -> dict[str, list[dict]]:
    """Per variant, per contact frame: recall and leak of the walker's body."""
    box0 = np.asarray(seq.boxes[0], np.float64)
    base = PointConfig(window=WINDOW, intrinsics=seq.intrinsics).with_foreground()
    scene_fg = frame_scene_foreground(base, box0, seq.depth.shape[1:])
    run_fg, z = layer1_inputs(base, seq.colour, seq.depth, seq.boxes)
    models = {name: _jitted_body_model(c) for name, c in variants(base).items()}
    settings = {f"{PER_FRAME} {n}": n for n in PER_FRAME_VARIANTS}
    settings.update({n: n for n in models})
    out: dict[str, list[dict]] = {name: [] for name in settings}
    for t in contact_frames(seq):
        depth = jnp.asarray(seq.depth[t])
        box = jnp.asarray(seq.boxes[t], jnp.float32)
        own_fg = scene_fg(jnp.asarray(seq.colour[t]), depth, box)
        for name, model in settings.items():
            fg = own_fg if name.startswith(PER_FRAME) else jnp.asarray(run_fg[t])
            bm = models[model](depth, box, fg, jnp.float32(z[t]))
            body = np.asarray(bm.body)
            own = window_sample(seq.mask[t], bm)
            out[name].append(
                {
                    "frame": t,
                    "target_depth": round(float(z[t]), 1),
                    "recall": round(float((body & own).sum() / max(own.sum(), 1)), 3),
                    "leak": round(float((body & ~own).sum() / max(body.sum(), 1)), 3),
                }
            )
    return out


def summary(rows: list[dict]) -> dict:
    r = np.array([x["recall"] for x in rows])
    k = np.array([x["leak"] for x in rows])
    return {
        "frames": len(rows),
        "median_recall": round(float(np.median(r)), 3) if len(r) else None,
        "median_leak": round(float(np.median(k)), 3) if len(k) else None,
        "mean_recall": round(float(np.mean(r)), 3) if len(r) else None,
        "mean_leak": round(float(np.mean(k)), 3) if len(k) else None,
        "frames_recall_under_0.5": int((r < 0.5).sum()),
        "frames_leak_over_0.5": int((k > 0.5).sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence")
    args = parser.parse_args()
    load_avg = os.getloadavg()
    per_seq = {}
    for scene in SCENES:
        for seed in TRAIN_SEEDS:
            seq = make_people_sequence(scene, seed, args.frames)
            per_seq[f"{scene}/{seed}"] = score_sequence(seq)
            print(scene, seed, {n: summary(v) for n, v in per_seq[f"{scene}/{seed}"].items()})
    names = list(next(iter(per_seq.values())))
    pooled = {n: summary([r for s in per_seq.values() for r in s[n]]) for n in names}
    per_scene = {
        scene: {
            n: summary([r for k, s in per_seq.items() if k.startswith(scene + "/") for r in s[n]])
            for n in names
        }
        for scene in SCENES
    }
    out = {
        "setup": {"scenes": SCENES, "seeds": TRAIN_SEEDS, "frames": args.frames},
        "pooled": pooled,
        "per_scene": per_scene,
        "per_sequence": per_seq,
        "loadavg": [round(v, 2) for v in load_avg],
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "depth_anchor_train.json").write_text(json.dumps(out, indent=2) + "\n")
    md = [
        "# The body's anchor on synthetic contact frames (training seeds)",
        "",
        "Regenerate with `python experiments/depth_anchor.py` (the module docstring defines "
        f"every score). Scenes {', '.join(SCENES)}, seeds {list(TRAIN_SEEDS)}, the walker's "
        "ground-truth box, layer 1's target depth.",
        "",
        "| setting | contact frames | median recall | median leak | mean recall | mean leak "
        "| frames recall < 0.5 | frames leak > 0.5 |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n, s in pooled.items():
        md.append(
            f"| {n} | {s['frames']} | {s['median_recall']} | {s['median_leak']} | "
            f"{s['mean_recall']} | {s['mean_leak']} | {s['frames_recall_under_0.5']} | "
            f"{s['frames_leak_over_0.5']} |"
        )
    md += ["", "Per scene (mean recall / mean leak):", ""]
    md += ["| setting | " + " | ".join(SCENES) + " |", "|---|" + "---|" * len(SCENES)]
    for n in names:
        cells = [
            f"{per_scene[sc][n]['mean_recall']} / {per_scene[sc][n]['mean_leak']}" for sc in SCENES
        ]
        md.append(f"| {n} | " + " | ".join(cells) + " |")
    md += ["", f"Load average at the start: {load_avg[0]:.1f}."]
    (RESULTS / "depth_anchor_train.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
