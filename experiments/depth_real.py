"""The depth layer on a real RGB-D recording: IST PIV ``images1``, frames 51-90.

Data: ``../shared/data/ist_piv_rgbd/images1`` (Asus Xtion / Kinect-v1-class
structured-light depth, 640 x 480, mm, 0 = missing; SOURCE.md, ANNOTATION.md).
The hand-checked boxes are in *colour* pixels and depth is not registered to
colour. The depth window is chosen by a rough registration of the box: each
box edge is mapped with the recording's own calibration (Kdepth, Krgb, the
26 mm baseline, 0-based principal points) at the median depth inside the
box, after removing the +11 px horizontal offset that ANNOTATION.md measured
between depth and colour edges; two passes (the depth guess of the first
pass sets the baseline parallax of the second).

Runs, per frame, ``cpf_jax.points.body_model`` (hole filling, segmentation,
surface graph, normals, head/neck split, geodesic distances from the head)
with the recording's own depth intrinsics, in three settings:

* ``thesis``: the thesis's rule as written (largest component of the
  ``|dz| < 10 mm`` graph, 15 mm surface edges, no floor removal, no
  background rule);
* ``layer``: the library defaults (thresholds scaled with depth, floor removal
  with the floor normal fitted on the empty frames 1-26, largest component in
  front of the box background);
* ``layer+fg``: as ``layer``, inside a background-subtraction foreground (the
  per-pixel median of the empty frames 1-26 and 103-108, as in ANNOTATION.md),
  with looser thresholds (25 mm / 40 mm at 2 m) because the foreground already
  excludes floor and furniture.

There is no 3D ground truth, so segmentation is scored against the
foreground-inside-box mask (``fg_recall``: share of foreground pixels on the
body; ``leak``: share of the body outside the foreground, i.e. floor,
furniture, walls) and the tracked points are shown, not scored. The point
filter (combined weighting, ``layer+fg`` settings) tracks the head and the two
geodesic extremities of frame 52 (the body pixels farthest from the head in
the left and right halves) through frames 52-90.

Writes ``experiments/results/depth_real.json``, ``depth_real.md`` and the
figure ``depth_real.png`` (colour crop, segmentation per setting, geodesic
map, tracked points).

    python experiments/depth_real.py
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax.filter import Context, track
from cpf_jax.kernels import depth as dk
from cpf_jax.points import (
    PointConfig,
    PointFrame,
    body_model,
    build_point_filter,
    default_point_params,
)
from cpf_jax.types import Intrinsics

ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ist_piv_rgbd" / "images1"
RESULTS = Path(__file__).resolve().parent / "results"
# cameraparametersAsus.mat (SOURCE.md), principal points moved to 0-based pixels.
KD = Intrinsics(567.8956, 568.8557, 312.1240 - 1, 242.5695 - 1)
KC = Intrinsics(534.2856, 534.7452, 309.5674 - 1, 243.0724 - 1)
T_MM = np.array([-26.30589, 0.28027, -0.77569])
SHIFT_PX = 11.0  # ANNOTATION.md: depth edges land 11 px left of colour edges
FRAMES = range(51, 91)
EMPTY = list(range(1, 27)) + list(range(103, 109))
WINDOW = (256, 192)
SHOW = (53, 60, 68, 76, 84, 88)


def load(i: int):
    d = cv2.imread(str(ROOT / "depth" / f"images{i:08d}.png"), cv2.IMREAD_UNCHANGED)
    c = cv2.imread(str(ROOT / "rgb" / f"images{i:08d}.jpg"))
    return d, c


def colour_box_to_depth(box_c: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Colour xywh (0-based) -> depth xywh, through the calibration at the box's median depth."""
    x, y, w, h = box_c
    z = 3000.0
    for _ in range(2):

        def to_depth(u, v, z=z):
            xn = (u - SHIFT_PX - KC.cx) / KC.fx - T_MM[0] / z
            yn = (v - KC.cy) / KC.fy - T_MM[1] / z
            return KD.fx * xn + KD.cx, KD.fy * yn + KD.cy

        x0, y0 = to_depth(x, y)
        x1, y1 = to_depth(x + w, y + h)
        r0, r1 = int(max(y0 + 0.3 * (y1 - y0), 0)), int(min(y0 + 0.7 * (y1 - y0), 479))
        c0, c1 = int(max(x0 + 0.3 * (x1 - x0), 0)), int(min(x0 + 0.7 * (x1 - x0), 639))
        patch = depth[r0 : r1 + 1, c0 : c1 + 1]
        if (patch > 0).any():
            z = float(np.median(patch[patch > 0]))
    return np.array([x0, y0, x1 - x0, y1 - y0], np.float32)


def floor_up(background: np.ndarray, seed: int = 0) -> np.ndarray:
    """Unit normal of the floor plane (towards the camera side), RANSAC on the empty room."""
    v, u = np.nonzero(background > 0)
    keep = v > 0.55 * background.shape[0]  # the floor fills the lower part of the view
    v, u = v[keep], u[keep]
    z = background[v, u].astype(np.float64)
    p = np.stack([z * (u - KD.cx) / KD.fx, z * (v - KD.cy) / KD.fy, z], -1)
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(300):
        a, b, c = p[rng.choice(len(p), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-6:
            continue
        n /= np.linalg.norm(n)
        inl = np.abs((p - a) @ n) < 30.0
        if inl.sum() > best_n:
            best, best_n = inl, inl.sum()
    q = p[best]
    centre = q.mean(0)
    n = np.linalg.svd(q - centre, full_matrices=False)[2][-1]
    if n @ (-centre) < 0:  # the camera is above the floor: the normal points towards it
        n = -n
    return n, float(best_n) / len(p)


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    if not ROOT.is_dir():
        raise SystemExit(f"depth_real: skipped, the recording is not at {ROOT}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    load_avg = os.getloadavg()
    gt = np.loadtxt(ROOT / "groundtruth_rect.txt", delimiter=",")
    empties = np.stack([load(i)[0] for i in EMPTY]).astype(np.float32)
    background = np.nan_to_num(np.nanmedian(np.where(empties > 0, empties, np.nan), 0), nan=0.0)
    up, inlier_share = floor_up(background)

    frames = {i: load(i) for i in FRAMES}
    one_based = np.array([1, 1, 0, 0])
    boxes = {i: colour_box_to_depth(gt[i - 1] - one_based, frames[i][0]) for i in FRAMES}
    fg = {i: np.asarray(dk.foreground_mask(frames[i][0], background, 150.0, 0.05)) for i in FRAMES}
    missing = {}
    for i in FRAMES:
        x, y, w, h = np.round(boxes[i]).astype(int)
        patch = frames[i][0][max(y, 0) : y + h, max(x, 0) : x + w]
        missing[i] = round(float((patch == 0).mean()), 3) if patch.size else 1.0

    base = PointConfig(window=WINDOW, intrinsics=KD, up=tuple(float(x) for x in up))
    settings = {
        "thesis": dataclasses.replace(
            base,
            threshold_depth_mm=None,
            floor_max_tilt_deg=None,
            background_margin_mm=None,
            normal_smoothing=0,
        ),
        "layer": base,
        "layer+fg": dataclasses.replace(base, seg_max_dz_mm=25.0, surface_max_dist_mm=40.0),
    }
    models = {k: jax.jit(lambda d, b, f, c=c: body_model(c, d, b, f)) for k, c in settings.items()}
    stats: dict = {k: [] for k in settings}
    keep: dict = {}
    for i in FRAMES:
        depth = jnp.asarray(frames[i][0])
        for name, f in models.items():
            bm = f(depth, jnp.asarray(boxes[i]), jnp.asarray(fg[i]) if name == "layer+fg" else None)
            rows, cols = np.asarray(bm.rows), np.asarray(bm.cols)
            inside = ((rows >= 0) & (rows < 480))[:, None] & ((cols >= 0) & (cols < 640))[None]
            roi_fg = fg[i][np.clip(rows, 0, 479)][:, np.clip(cols, 0, 639)] & inside
            roi = np.asarray(bm.depth) > 0
            roi_fg &= roi
            body = np.asarray(bm.body)
            stats[name].append(
                {
                    "frame": i,
                    "body_px": int(body.sum()),
                    "fg_recall": round(float((body & roi_fg).sum() / max(roi_fg.sum(), 1)), 3),
                    "leak": round(float((body & ~roi_fg).sum() / max(body.sum(), 1)), 3),
                    "head_found": bool(int(bm.reference_pixels[0, 0]) >= 0 and body.any()),
                    "missing_in_box": missing[i],
                }
            )
            if i in SHOW:
                keep[(i, name)] = jax.device_get(bm)

    # Point tracking through 52-90 with the layer+fg settings.
    cfg = dataclasses.replace(settings["layer+fg"], weighting="combined")
    seq = list(range(52, 91))
    point_frames = PointFrame(
        jnp.asarray(np.stack([frames[i][0] for i in seq])),
        jnp.asarray(np.stack([boxes[i] for i in seq])),
        jnp.asarray(np.stack([fg[i] for i in seq])),
    )
    bm0 = jax.device_get(
        models["layer+fg"](point_frames.depth[0], point_frames.box[0], point_frames.foreground[0])
    )
    g = np.where(np.asarray(bm0.body), np.asarray(bm0.geodesic[0]), -np.inf)
    g = np.where(np.isfinite(g), g, -np.inf)
    half = WINDOW[1] // 2
    starts_rc = [np.asarray(bm0.reference_pixels[0])]
    for sl in (slice(0, half), slice(half, None)):
        sub = np.full_like(g, -np.inf)
        sub[:, sl] = g[:, sl]
        starts_rc.append(np.array(np.unravel_index(np.argmax(sub), g.shape)))
    starts = np.stack(
        [
            np.asarray(dk.window_to_frame(bm0.window, jnp.asarray([c + 0.5, r + 0.5])))
            for r, c in starts_rc
        ]
    )
    filt = build_point_filter(cfg)
    context = Context(points=jnp.asarray(starts, jnp.float32))
    _, info = jax.jit(
        lambda k: track(filt, default_point_params(), k, point_frames, point_frames.box[0], context)
    )(jax.random.PRNGKey(0))
    info = jax.device_get(info)
    tracks = {52: starts}
    for k, i in enumerate(seq[1:]):
        tracks[i] = np.asarray(info.mean[k])

    # Figure: per shown frame, colour crop | thesis | layer | layer+fg | geodesic | points.
    tiles = []
    for i in SHOW:
        depth, colour = frames[i]
        x, y, w, h = gt[i - 1] - np.array([1, 1, 0, 0])
        c = colour.copy()
        cv2.rectangle(c, (int(x), int(y)), (int(x + w), int(y + h)), (0, 255, 0), 2)
        bm_t = keep[(i, "layer+fg")]
        o, s = np.asarray(bm_t.window.origin), float(bm_t.window.scale)
        # colour crop at the depth window's place (rough, for orientation only)
        cc = cv2.resize(
            c[max(int(y - 10), 0) : int(y + h + 10), max(int(x - 30), 0) : int(x + w + 30)],
            (WINDOW[1], WINDOW[0]),
        )
        panels = [cc]
        for name in settings:
            bm = keep[(i, name)]
            d = np.asarray(bm.depth)
            gimg = cv2.cvtColor(
                np.clip((d - 500) / 6000 * 255, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR
            )
            gimg[d == 0] = (60, 0, 60)
            body = np.asarray(bm.body)
            gimg[body] = (0.4 * gimg[body] + np.array([0, 150, 0])).astype(np.uint8)
            cv2.putText(gimg, name, (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
            panels.append(gimg)
        geo = np.asarray(bm_t.geodesic[0])
        fin = np.isfinite(geo) & np.asarray(bm_t.body)
        gm = np.zeros(geo.shape, np.uint8)
        if fin.any():
            gm[fin] = np.clip(geo[fin] / max(geo[fin].max(), 1) * 255, 0, 255).astype(np.uint8)
        gcol = cv2.applyColorMap(gm, cv2.COLORMAP_JET)
        gcol[~fin] = 0
        r, cpx = np.asarray(bm_t.reference_pixels[0])
        cv2.circle(gcol, (int(cpx), int(r)), 4, (255, 255, 255), 1)
        cv2.putText(gcol, "geodesic", (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
        panels.append(gcol)
        pts = panels[3].copy()
        for k, col in enumerate(((0, 0, 255), (255, 0, 0), (0, 255, 255))):
            q = (tracks[i][k] - o) / s
            cv2.drawMarker(pts, (int(q[0]), int(q[1])), col, cv2.MARKER_CROSS, 12, 2)
        cv2.putText(
            pts, f"points, frame {i}", (3, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1
        )
        panels.append(pts)
        tiles.append(np.concatenate(panels, 1))
    cv2.imwrite(str(RESULTS / "depth_real.png"), np.concatenate(tiles, 0))

    def agg(name, key):
        return round(float(np.median([r[key] for r in stats[name]])), 3)

    summary = {
        name: {
            "median_fg_recall": agg(name, "fg_recall"),
            "median_leak": agg(name, "leak"),
            "median_body_px": agg(name, "body_px"),
            "frames_leak_over_0.3": int(sum(r["leak"] > 0.3 for r in stats[name])),
            "frames_recall_under_0.5": int(sum(r["fg_recall"] < 0.5 for r in stats[name])),
        }
        for name in settings
    }
    out = {
        "summary": summary,
        "floor_normal_camera": [round(float(v), 4) for v in up],
        "floor_inlier_share": round(inlier_share, 3),
        "tracking": {
            "points": ["head", "extremity (left half)", "extremity (right half)"],
            "recovered_frames": np.asarray(info.recovered).sum(0).tolist(),
            "mean_on_body": np.asarray(info.on_body).mean(0).round(3).tolist(),
        },
        "per_frame": stats,
        "loadavg": [round(v, 2) for v in load_avg],
    }
    (RESULTS / "depth_real.json").write_text(json.dumps(out, indent=2) + "\n")
    md = [
        "# Depth layer on IST PIV images1, frames 51-90",
        "",
        "| setting | median foreground recall | median leak | frames leak > 0.3 | "
        "frames recall < 0.5 |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, sm in summary.items():
        md.append(
            f"| {name} | {sm['median_fg_recall']} | {sm['median_leak']} | "
            f"{sm['frames_leak_over_0.3']} | {sm['frames_recall_under_0.5']} |"
        )
    md += [
        "",
        "Per frame (fg_recall / leak):",
        "",
        "| frame | " + " | ".join(settings) + " |",
        "|---|" + "---|" * len(settings),
    ]
    for k, i in enumerate(FRAMES):
        md.append(
            f"| {i} | "
            + " | ".join(
                f"{stats[n][k]['fg_recall']:.2f} / {stats[n][k]['leak']:.2f}" for n in settings
            )
            + " |"
        )
    sm = summary
    md += [
        "",
        "## Where segmentation fails on this real depth, and what was done",
        "",
        "`fg_recall` is measured against the background-subtraction foreground inside the "
        "box, which also contains people in front of the target, so it is a measure of "
        "fragmentation and of missing parts, not of picking the right person.",
        "",
        f"- **Kinect-v1-class depth breaks the thesis graph apart.** 20-24 % of the pixels "
        f"are missing, edges are bloated, and depth is quantised in steps of 12 mm at 2 m, "
        f"26 mm at 3 m and 35 mm at 3.5 m (measured on frame 1): one quantisation step "
        f"already exceeds the thesis's 10 mm, so the graph splits the person wherever the "
        f"surface is not facing the camera, and the largest piece is kept "
        f"(median recall {sm['thesis']['median_fg_recall']}). Done: thresholds that scale "
        f"with the pixel pitch, and inside a foreground mask looser ones (25 / 40 mm at 2 m) "
        f"(median recall {sm['layer+fg']['median_fg_recall']}).",
        "- **Floor contact.** The camera looks down at about "
        f"{np.degrees(np.arccos(abs(up[1]))):.0f} deg (floor normal fitted on the empty "
        "frames), so the floor under the feet has nearly the depth of the legs and joins "
        "them (frames 84-88, bottom of the `layer` panel in the figure). Done: floor "
        "removal by normal orientation with the fitted floor normal as `up` (most of the "
        "floor goes, a fringe of speckles stays: leak up to 0.13 at frame 84), and the "
        "background-subtraction foreground, which removes it completely (leak "
        f"{sm['layer+fg']['median_leak']}).",
        "- **Dark hair.** His dark curly hair returns no depth (frames 51-57 at close range: "
        "the head is a ring of holes around the face, see frame 53). One pass of 3x3 "
        "median filling only closes small gaps, so the head region is incomplete, the "
        "head/neck split and the geodesic reference move down to face and neck. Not "
        "solved; larger holes would need inpainting from the colour image or a head model.",
        "- **People touching / passing in front (58-82).** The man in the striped sweater "
        "and then the grey-haired man are nearer and larger inside the target's box, so "
        "the 'largest component in front of the background' rule selects them (frames 60 "
        "and 68 in the figure); the foreground mask contains both people, so it cannot "
        "separate them either. Not solved here: the cascade's per-cell occlusion flags "
        "(C2) or choosing the component that carries the tracked points would be needed. "
        "The point tracks drift during these frames (recoveries: "
        f"{out['tracking']['recovered_frames']} frames for head / extremities).",
        "- Also: the depth is not registered to colour; the box was mapped with the "
        "calibration plus the +11 px shift of ANNOTATION.md at the box's median depth, "
        "which is rough (a few pixels) but enough to choose the window.",
    ]
    (RESULTS / "depth_real.md").write_text("\n".join(md) + "\n")
    print("\n".join(md[:8]))
    print(json.dumps(out["tracking"]))


if __name__ == "__main__":
    main()
