"""Reproduce the RGB-D occlusion paper's Tables 1 and 2 (SPEC C2) on synthetic sequences,
and score the four variants on the real IST RGB-D recording.

Variants (rows of the paper's tables): ``rgb`` (the colour layer, ``cpf_jax.colour``,
with the 8-tuple AR1 model and motion-guided sampling), ``rgbd`` (one cell: foreground
ratio x colour x depth), ``grid`` (2 x 2 cells) and ``grid-occlusion`` (2 x 2 cells with
occlusion flags); the last three are ``cpf_jax.rgbd``.

Scenarios (columns), synthetic (``cpf_jax.synthetic``), every sequence
``N_FRAMES`` frames long so that each variant is compiled once:

* ``no_occlusion``: ``walk_across_slow``.
* ``occlusion``: ``occlusion_box`` (a box crossing in front of the walker) and
  ``occlusion_person`` (a similarly dressed person crossing in front).
* ``appearance_change``: ``appearance_change`` (red top -> green jacket at frame 50).
* ``occlusion_return``: ``occlusion_return`` (the walker walks away, turns round while
  another person crosses in front, and comes back: a reversal in depth while hidden,
  like IST's second occlusion); 50 frames, its own length (a second compile per variant).

Each sequence is tracked exactly as ``cpf-track`` would: the filter starts from the
ground-truth box of frame 0, the background is the per-pixel median of 25 evenly
spaced frames of the sequence (``occlusion_return``: the empty room, ``cpf-track
--background empty``, since its walker never uncovers the middle of the view), and
frame 0 is scored. Metrics
(``cpf_jax.metrics.summarise``): MOTP (px, centre distance of matched frames), MOTA
(%), SA (px, size error of matched frames) and success rate (% of visible frames
with IoU >= 0.5), averaged over scene seeds ``EVAL_SEEDS`` x filter keys. Scene seeds
100-103 are training seeds (``--fit-only`` fits the Beta shapes on them; defaults in
``cpf_jax.rgbd`` were tuned there), never scored.

Real data: ``../shared/data/ist_piv_rgbd/images1`` (hand-checked boxes for one person,
frames 51-90, occluded twice; read its ANNOTATION.md). Depth is registered to colour
with ``experiments/calib/ist_piv.json``; the background is the median of the empty
frames 1-26 and 103-108; the filters start from the ground-truth box of frame 52 (the
first with a clearly visible head and shoulders, as the annotation advises) and run to
the end. Reported: success rate and AUC (%) per variant, a contact sheet
(``occlusion_ist_contact_sheet.png``) and success plots (``occlusion_ist_success.png``);
``--ist-only`` re-runs just this part. Skipped with a message when the data is absent.

Run: ``python experiments/occlusion_tables.py`` (``--quick`` for a smoke run:
one seed, short sequences, few particles; results not written unless ``--out``).
Writes ``experiments/results/occlusion_tables.json`` (``{scenario: {variant: {motp,
mota, sa, success_rate}}}`` plus ``"ist_images1": {variant: {success_rate, auc}}``),
``occlusion_tables.md`` and ``occlusion_tables_runs.json`` (every run).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax import charts, rgbd
from cpf_jax.cascade import build_box_filter, default_box_params
from cpf_jax.colour import ColourConfig
from cpf_jax.filter import Context, track_boxes
from cpf_jax.io import SyntheticSource
from cpf_jax.kernels.background import foreground_mask, median_background
from cpf_jax.metrics import run_success_curve, summarise
from cpf_jax.rgbd import RGBDConfig, cell_foreground_ratios, fit_beta
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
IST = ROOT.parent / "shared" / "data" / "ist_piv_rgbd" / "images1"
IST_CALIB = ROOT / "experiments" / "calib" / "ist_piv.json"
IST_START = 51  # 0-based: frame 52, the first with a clear head and shoulders
IST_BACKGROUND = (*range(0, 26), *range(102, 108))  # 0-based empty frames
IST_SHEET_FRAMES = (51, 55, 59, 63, 67, 70, 74, 77, 81, 85)  # 0-based

#: The tables' rows: the colour layer ("rgb") and the RGB-D filter's variants.
VARIANTS = ("rgb", *rgbd.VARIANTS)
SCENARIOS = {
    "no_occlusion": ("walk_across_slow",),
    "occlusion": ("occlusion_box", "occlusion_person"),
    "appearance_change": ("appearance_change",),
    "occlusion_return": ("occlusion_return",),
}
TRAIN_SCENES = ("walk_across_medium", "walk_towards", "turn")
TRAIN_SEEDS = (100, 101, 102, 103)
EVAL_SEEDS = (0, 1)
N_KEYS = 3
N_FRAMES = 150
N_PARTICLES = 150
# 16 filter keys: single IST runs are chaotic (one lost frame decides the rest).
IST_KEYS = 16
# The walker of these stays in the middle of the view (walks away and back): the median
# of its frames would hold the walker, so the background is the empty room (as a real
# set-up records it before the person walks in, like IST's empty frames).
EMPTY_ROOM_BACKGROUND = ("occlusion_return",)
# Single-pass walks tracked at their own length (50 frames), not N_FRAMES.
OWN_LENGTH = ("occlusion_return",)
# Box colours of the contact sheet (RGB): ground truth white, then the variants.
COLOURS = {
    "gt": (255, 255, 255),
    "rgb": (255, 60, 60),
    "rgbd": (255, 200, 0),
    "grid": (60, 160, 255),
    "grid-occlusion": (0, 230, 0),
}


def _background_of(colour: np.ndarray, depth: np.ndarray, idx) -> object:
    idx = np.asarray(idx)
    return jax.jit(median_background)(colour[idx], depth[idx])


@functools.cache
def _sequence(name: str, seed: int, n_frames: int | None):
    seq = make_sequence(name, seed=seed, n_frames=n_frames)
    n_frames = len(seq.colour)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    if name in EMPTY_ROOM_BACKGROUND:
        # The frame ``cpf-track --background empty`` uses.
        empty = SyntheticSource(seq, name).empty_background()
        bg = _background_of(empty.colour[None], empty.depth[None], [0])
    else:
        bg = _background_of(seq.colour, seq.depth, np.linspace(0, n_frames - 1, 25).astype(int))
    return seq, frames, bg


@functools.cache
def _runner(config: ColourConfig | RGBDConfig):
    """One jitted runner per static config: (keys [K], frames, box, bg) -> boxes, lost.

    Frames, box and background are arguments (not constants), so every sequence of the
    same shape reuses the compiled program; filter keys are vmapped. The colour layer
    ignores the background.
    """
    filt = build_box_filter(config)
    params = default_box_params(config)

    def run(keys, frames, box, bg):
        context = Context(background=bg)
        return jax.vmap(lambda k: track_boxes(filt, params, k, frames, box, context))(keys)

    return jax.jit(run)


def _config(variant: str, window_box: tuple[float, float], frame_hw, n_particles: int):
    """The box filter of a row: ``"rgb"`` is the colour layer with the RGB-D filter's
    motion model (8-tuple AR1, motion-guided) and window growth."""
    if variant == "rgb":
        config = ColourConfig(n_particles=n_particles, model="ar1", hierarchical=True)
        return config.with_window(window_box, frame_hw, growth=1.5)
    return RGBDConfig(variant=variant, n_particles=n_particles).with_window(window_box, frame_hw)


def _scores(boxes: np.ndarray, gt: np.ndarray, visible: np.ndarray, lost: np.ndarray) -> dict:
    s = summarise(boxes, gt, visible, lost)
    return {k: s[k] for k in ("motp", "mota", "sa", "success_rate", "auc")}


def synthetic_tables(args) -> tuple[dict, list]:
    """``{scenario: {variant: mean scores}}`` and the list of every run."""
    seeds = EVAL_SEEDS[:1] if args.quick else EVAL_SEEDS
    n_keys = 1 if args.quick else N_KEYS
    n_frames = 30 if args.quick else N_FRAMES
    seqs = {
        (sc, name, seed): _sequence(
            name, seed, None if name in OWN_LENGTH and not args.quick else n_frames
        )
        for sc, names in SCENARIOS.items()
        for name in names
        for seed in seeds
    }
    # One histogram window for all sequences (static shapes: one compile per variant),
    # large enough for the largest ground-truth box.
    any_seq = next(iter(seqs.values()))[0]
    frame_hw = any_seq.colour.shape[1:3]
    w = max(float(s.boxes[:, 2].max()) for s, _, _ in seqs.values())
    h = max(float(s.boxes[:, 3].max()) for s, _, _ in seqs.values())
    runs = []
    keys = jax.random.split(jax.random.PRNGKey(0), n_keys)
    for variant in VARIANTS:
        run = _runner(_config(variant, (w, h), frame_hw, args.particles))
        t0 = time.perf_counter()
        for (sc, name, seed), (seq, frames, bg) in seqs.items():
            boxes, lost = run(keys, frames, jnp.asarray(seq.boxes[0]), bg)
            boxes, lost = np.asarray(boxes), np.asarray(lost)
            for i in range(n_keys):
                s = _scores(boxes[i], seq.boxes, seq.visible, lost[i])
                runs.append(
                    dict(scenario=sc, sequence=name, seed=seed, key=i, variant=variant, **s)
                )
        print(f"  {variant}: {time.perf_counter() - t0:.0f} s", flush=True)
    table = {}
    for sc in SCENARIOS:
        table[sc] = {}
        for variant in VARIANTS:
            sel = [r for r in runs if r["scenario"] == sc and r["variant"] == variant]
            table[sc][variant] = {
                k: round(float(np.mean([r[k] for r in sel])), 2)
                for k in ("motp", "mota", "sa", "success_rate")
            }
            # The spread over scene seeds x keys: one unlucky key can cost a run 30
            # MOTA points (a lost target not found again), so the mean alone misleads.
            table[sc][variant]["mota_min"] = round(float(min(r["mota"] for r in sel)), 2)
    return table, runs


# ----------------------------------------------------------------------------- IST


def _ist_frames():
    from cpf_jax.io import open_source
    from cpf_jax.registration import load_calibration, register_frame

    source = open_source(IST)
    calib = load_calibration(IST_CALIB)
    frames = [register_frame(source.read(i), calib) for i in range(len(source))]
    colour = np.stack([np.asarray(f.colour) for f in frames])
    depth = np.stack([np.asarray(f.depth) for f in frames])
    gt = np.asarray(source.gt_boxes, np.float32)
    visible = gt[:, 2] > 0 if source.visible is None else np.asarray(source.visible, bool)
    return colour, depth, gt, visible


def ist_scores(args) -> tuple[dict | None, dict | None]:
    """``{variant: {success_rate, auc}}`` on IST images1 and the boxes (None: no data)."""
    if not IST.is_dir():
        print(f"IST part skipped: {IST} not found (the shared data is not mounted).")
        return None, None
    colour, depth, gt, visible = _ist_frames()
    bg = _background_of(colour, depth, IST_BACKGROUND)
    stop = len(colour)
    frames = Frame(jnp.asarray(colour[IST_START:stop]), jnp.asarray(depth[IST_START:stop]))
    box = gt[IST_START]
    n_keys = 1 if args.quick else IST_KEYS
    keys = jax.random.split(jax.random.PRNGKey(1), n_keys)
    out, boxes_of = {}, {}
    for variant in VARIANTS:
        cfg = _config(variant, (float(box[2]), float(box[3])), colour.shape[1:3], args.particles)
        boxes, lost = (np.asarray(a) for a in _runner(cfg)(keys, frames, jnp.asarray(box), bg))
        s = [
            _scores(boxes[i], gt[IST_START:stop], visible[IST_START:stop], lost[i])
            for i in range(n_keys)
        ]
        curve = np.mean(
            [
                run_success_curve(boxes[i], gt[IST_START:stop], visible[IST_START:stop], lost[i])
                for i in range(n_keys)
            ],
            axis=0,
        )
        out[variant] = {
            "success_rate": round(float(np.mean([x["success_rate"] for x in s])), 2),
            "auc": round(float(np.mean([x["auc"] for x in s])), 2),
            "auc_per_key": [round(float(x["auc"]), 2) for x in s],
            # OTB success plot (IoU > t, t = 0, 0.05, ..., 1), averaged over the keys.
            "success_curve": curve.round(4).tolist(),
        }
        boxes_of[variant] = (boxes[0], lost[0])
        print(f"  IST {variant}: {out[variant]}", flush=True)
    return out, dict(colour=colour, gt=gt, boxes=boxes_of)


def contact_sheet(ist: dict, path: Path) -> None:
    """Frames of IST images1 with the ground truth (white) and every variant's box."""
    import cv2

    tiles = []
    for t in IST_SHEET_FRAMES:
        img = np.ascontiguousarray(ist["colour"][t])
        boxes = [("gt", ist["gt"][t], False)]
        for v, (b, lost) in ist["boxes"].items():
            boxes.append((v, b[t - IST_START], bool(lost[t - IST_START])))
        for name, b, lost in boxes:
            if lost or b[2] <= 0:
                continue
            x, y, w, h = (int(round(float(v))) for v in b)
            thick = 3 if name == "gt" else 2
            cv2.rectangle(img, (x, y), (x + w, y + h), COLOURS[name], thick)
        cv2.putText(img, f"frame {t + 1}", (12, 34), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255,) * 3, 2)
        tiles.append(cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA))
    rows = [np.concatenate(tiles[i : i + 5], axis=1) for i in range(0, len(tiles), 5)]
    sheet = np.concatenate(rows, axis=0)
    legend = np.zeros((28, sheet.shape[1], 3), np.uint8)
    x = 8
    for name, c in COLOURS.items():
        cv2.putText(legend, name, (x, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, c, 2)
        x += 170
    sheet = np.concatenate([legend, sheet], axis=0)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


# ----------------------------------------------------------------------------- Beta fit


def fit_betas(n_frames: int = 100) -> dict:
    """Maximum-likelihood Beta shapes of the cells' foreground ratios (k = 1, 2) on the
    tight ground-truth boxes of unoccluded frames of the training scenes."""
    masks, boxes = [], []
    for name in TRAIN_SCENES:
        for seed in TRAIN_SEEDS:
            seq, frames, bg = _sequence(name, seed, n_frames)
            fg = jax.vmap(lambda c, d, b=bg: foreground_mask(c, d, b))(frames.colour, frames.depth)
            ok = seq.visible & (seq.meta["occlusion"] == 0)
            masks.append(np.asarray(fg)[ok])
            boxes.append(seq.boxes[ok])
    fg, bx = np.concatenate(masks), np.concatenate(boxes)
    out = {}
    for k in (1, 2):
        r = np.asarray(cell_foreground_ratios(fg, bx, k)).T  # [C, M]
        a, b = fit_beta(r, method="mle")
        out[k] = ([round(float(v), 2) for v in a], [round(float(v), 2) for v in b])
    return out


# ----------------------------------------------------------------------------- output


def success_figure(ist: dict, path: Path) -> None:
    """``occlusion_ist_success.png``: OTB success plots of the four variants on IST."""
    curves = {v: s["success_curve"] for v, s in ist.items() if s.get("success_curve")}
    if curves:
        title = "IST images1, frames 52-90 (OpenCV trackers: best AUC 5.6, CSRT 5.1)"
        charts.save_png(charts.success_plot(curves, title=title), path)


def to_markdown(table: dict, ist: dict | None, meta: dict) -> str:
    lines = [
        "# RGB-D occlusion tables (paper Tables 1-2), synthetic sequences",
        "",
        f"Generated {meta['date']} by `python experiments/occlusion_tables.py` in "
        f"{meta['seconds']:.0f} s. N = {meta['particles']} particles, {meta['n_frames']} "
        "frames per sequence (occlusion_return: its own 50), "
        f"scene seeds {meta['seeds']} x {meta['keys']} filter keys; "
        "MOTP and SA in px (matched frames), MOTA and success rate (IoU >= 0.5) in %; "
        "MOTA min: the lowest MOTA of any single run (scene seed x key).",
        "",
    ]
    for sc, names in SCENARIOS.items():
        lines += [
            f"## {sc} ({', '.join(names)})",
            "",
            "| variant | MOTP px | MOTA % | MOTA min % | SA px | SR % |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for v, s in table[sc].items():
            lines.append(
                f"| {v} | {s['motp']:.1f} | {s['mota']:.1f} | {s['mota_min']:.1f} | "
                f"{s['sa']:.1f} | {s['success_rate']:.1f} |"
            )
        lines.append("")
    lines += ["## IST images1 (real RGB-D, frames 52-108, GT in 52-90)", ""]
    if ist is None:
        lines += ["Skipped: ../shared/data/ist_piv_rgbd/images1 not found.", ""]
    else:
        lines += [
            f"{meta['ist_keys']} filter keys. OpenCV trackers: best AUC 5.6 (CSRT 5.1). "
            "Contact sheet: `occlusion_ist_contact_sheet.png` (key 0; white = ground truth); "
            "success plots: `occlusion_ist_success.png` (mean over the keys).",
            "",
            "| variant | SR % | AUC % | AUC per key |",
            "|---|---:|---:|---|",
        ]
        for v, s in ist.items():
            per_key = " / ".join(f"{a:.1f}" for a in s["auc_per_key"])
            lines.append(f"| {v} | {s['success_rate']:.1f} | {s['auc']:.1f} | {per_key} |")
        lines.append("")
    return "\n".join(lines)


def ist_only(args, out_dir: Path) -> int:
    """Re-run the IST part alone: update ``ist_images1`` in the results JSON (the synthetic
    tables are kept), the contact sheet and the success plot."""
    ist, ist_data = ist_scores(args)
    if ist is None:
        return 1
    path = out_dir / "occlusion_tables.json"
    result = json.loads(path.read_text()) if path.exists() else {}
    for v, s in (result.get("ist_images1") or {}).items():
        if v in ist and abs(s["auc"] - ist[v]["auc"]) > 0.05:
            print(f"note: IST {v} AUC {ist[v]['auc']:.2f} (was {s['auc']:.2f})")
    result["ist_images1"] = ist
    path.write_text(json.dumps(result, indent=2) + "\n")
    runs_path = out_dir / "occlusion_tables_runs.json"
    if runs_path.exists():
        runs = json.loads(runs_path.read_text())
        meta = runs["meta"]
        meta["ist_keys"] = 1 if args.quick else IST_KEYS
        runs_path.write_text(json.dumps(runs, indent=1) + "\n")
        table = {k: v for k, v in result.items() if k != "ist_images1"}
        (out_dir / "occlusion_tables.md").write_text(to_markdown(table, ist, meta))
    contact_sheet(ist_data, out_dir / "occlusion_ist_contact_sheet.png")
    success_figure(ist, out_dir / "occlusion_ist_success.png")
    print(f"IST results written to {out_dir}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smoke run (one seed, 30 frames)")
    p.add_argument("--particles", type=int, default=None, help=f"default {N_PARTICLES}")
    p.add_argument("--no-ist", action="store_true", help="skip the real IST recording")
    p.add_argument("--fit-only", action="store_true", help="print the fitted Beta shapes")
    p.add_argument(
        "--ist-only",
        action="store_true",
        help="re-run only the IST part and update its entry (and figures) in the results",
    )
    p.add_argument("--out", type=Path, default=None, help="results folder")
    args = p.parse_args(argv)
    if args.particles is None:
        args.particles = 64 if args.quick else N_PARTICLES
    if args.fit_only:
        print(json.dumps(fit_betas()))
        return 0
    out_dir = args.out if args.out is not None else (None if args.quick else RESULTS)
    if args.ist_only:
        return ist_only(args, out_dir or RESULTS)
    t0 = time.perf_counter()
    print("synthetic sequences ...", flush=True)
    table, runs = synthetic_tables(args)
    ist, ist_data = (None, None) if args.no_ist else ist_scores(args)
    seconds = time.perf_counter() - t0
    meta = dict(
        date=datetime.date.today().isoformat(),
        seconds=seconds,
        particles=args.particles,
        n_frames=30 if args.quick else N_FRAMES,
        seeds=list(EVAL_SEEDS[:1] if args.quick else EVAL_SEEDS),
        keys=1 if args.quick else N_KEYS,
        ist_keys=1 if args.quick else IST_KEYS,
    )
    result = dict(table)
    if ist is not None:
        result["ist_images1"] = ist
    md = to_markdown(table, ist, meta)
    print(md)
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "occlusion_tables.json").write_text(json.dumps(result, indent=2) + "\n")
        (out_dir / "occlusion_tables.md").write_text(md)
        runs_doc = dict(meta=meta, runs=runs)
        (out_dir / "occlusion_tables_runs.json").write_text(json.dumps(runs_doc, indent=1) + "\n")
        if ist_data is not None:
            contact_sheet(ist_data, out_dir / "occlusion_ist_contact_sheet.png")
            success_figure(ist, out_dir / "occlusion_ist_success.png")
        print(f"written to {out_dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
