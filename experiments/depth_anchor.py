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
``leak`` the share of the body that is not the walker. Variants (``VARIANTS``): no join
(the sizeable components), the components joined through 160 mm steps to the one at the
box's centre (``joined_anchor="centre"``), and those whose mean depth lies within
``anchor_max_dz_mm`` of layer 1's target depth (``joined_anchor="depth"``).

Writes ``experiments/results/depth_anchor_train.json`` and ``.md``::

    python experiments/depth_anchor.py
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from depth_real import frame_scene_foreground, window_sample

from cpf_jax.cascade import CascadeConfig, layer2_from_layer1
from cpf_jax.points import PointConfig, body_model
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params
from cpf_jax.synthetic_multi import make_people_sequence
from cpf_jax.types import Frame

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
    return out


def layer1_inputs(points: PointConfig, colour, depth, boxes) -> tuple[np.ndarray, np.ndarray]:
    """What the cascade's layer 2 takes from layer 1 in every frame, for the boxes
    ``boxes [T, 4]``: the foreground ``[T, H, W] bool`` and the target's depth ``[T]`` mm
    (``cascade.layer2_from_layer1``), layer 1 (grid-occlusion, no background frames) run
    from ``boxes[0]`` on frame 0."""
    hw = depth.shape[1:]
    box = RGBDConfig(variant="grid-occlusion").with_window((boxes[0][2], boxes[0][3]), hw)
    config = CascadeConfig(box=box, points=points, foreground=True)
    filt = build_rgbd_filter(box)
    params = default_rgbd_params(box)

    def seen(s, f, b):
        inp = layer2_from_layer1(config, None, s, f, b)
        return inp.foreground, inp.target_depth

    def run(key, frames, boxes):
        k0, k1 = jax.random.split(key)
        first = jax.tree_util.tree_map(lambda x: x[0], frames)
        rest = jax.tree_util.tree_map(lambda x: x[1:], frames)
        s = filt.init(params, k0, first, boxes[0])

        def body(s, xs):
            k, f, b = xs
            s, _ = filt.step(params, k, s, f)
            return s, seen(s, f, b)

        keys = jax.random.split(k1, depth.shape[0] - 1)
        _, (fg, z) = jax.lax.scan(body, s, (keys, rest, boxes[1:]))
        fg0, z0 = seen(s, first, boxes[0])
        return jnp.concatenate([fg0[None], fg]), jnp.concatenate([z0[None], z])

    frames = Frame(jnp.asarray(colour), jnp.asarray(depth))
    fg, z = jax.jit(run)(jax.random.PRNGKey(0), frames, jnp.asarray(boxes, jnp.float32))
    return np.asarray(fg), np.asarray(z)


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


def score_sequence(seq) -> dict[str, list[dict]]:
    """Per variant, per contact frame: recall and leak of the walker's body."""
    box0 = np.asarray(seq.boxes[0], np.float64)
    base = PointConfig(window=WINDOW, intrinsics=seq.intrinsics).with_foreground()
    scene_fg = frame_scene_foreground(base, box0, seq.depth.shape[1:])
    run_fg, z = layer1_inputs(base, seq.colour, seq.depth, seq.boxes)
    models = {
        name: jax.jit(lambda d, b, f, zt, c=c: body_model(c, d, b, f, zt))
        for name, c in variants(base).items()
    }
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
