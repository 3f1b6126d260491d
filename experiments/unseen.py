"""Layer 1 on footage nobody tuned it to: randomised synthetic scenes and OTB Crossing,
cpf-track's defaults against OpenCV's CSRT and KCF on the same frames.

    python experiments/unseen.py                 # the evaluation scenes (results/unseen.*)
    python experiments/unseen.py --split train   # the training scenes (for choosing defaults)

Scenes come from :mod:`cpf_jax.random_scenes`, whose every factor (walker size 40-400 px,
eye-level or high view, camera pan / follow / shake / zoom, poles and signs, look-alike
walkers, lighting change, a low occluder, dark clothes) is drawn from the scene's seed.
The seed ranges below are fixed: defaults are chosen on ``TRAIN_SEEDS`` only, and
``EVAL_SEEDS`` (disjoint) only judge them.

cpf_jax runs with exactly the configuration ``cpf-track`` builds without options
(:func:`cpf_jax.cli.model.box_config`), one run per scene from the first frame's box.
CSRT and KCF live in opencv-contrib-python-headless, which cannot share an environment
with opencv-python-headless; they run in ``.venv-contrib`` (``make contrib-env`` creates
it) through ``experiments/opencv_trackers.py``. Without it their columns are left empty
and the script says so. Their runs are kept in ``~/.cache/cpf_jax/opencv_runs`` under a
digest of the exact frames and start box, so a re-run after a change to cpf_jax re-runs
only cpf_jax.

``--ablation`` runs cpf_jax alone with its terms switched one at a time (``VARIANTS``) and
writes ``results/unseen[_train]_ablation.*``.

Every tracker is scored on every frame where the walker is in view (the first one holds
the start box, as ``cpf-track``'s summary counts it): success rate at IoU 0.5 and the
success plot's AUC, in percent. Writes ``results/unseen.json``, ``results/unseen.md`` and
``results/unseen.png`` (success plots).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax import Frame, track_boxes
from cpf_jax.charts import save_png, success_plot
from cpf_jax.cli.model import box_config
from cpf_jax.cli.options import build_parser, model_options
from cpf_jax.colour import CorrelationConfig
from cpf_jax.colour.camera import DOWNSCALE
from cpf_jax.metrics import run_success_curve, summarise
from cpf_jax.random_scenes import make_random_sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host import describe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
CROSSING = ROOT.parent / "shared" / "data" / "otb" / "Crossing"
CONTRIB_PYTHON = ROOT / ".venv-contrib" / "bin" / "python"
OPENCV_RUNNER = ROOT / "experiments" / "opencv_trackers.py"
OPENCV_CACHE = Path.home() / ".cache" / "cpf_jax" / "opencv_runs"

#: Scenes on which defaults may be chosen, and the disjoint ones that only judge them.
TRAIN_SEEDS = range(0, 200)
EVAL_SEEDS = range(100_000, 100_060)
TRACKERS = ("cpf_jax", "csrt", "kcf")
FACTORS = (
    "size",
    "view",
    "camera",
    "path",
    "thin_clutter",
    "look_alikes",
    "lighting",
    "partial_occlusion",
    "dark_clothes",
)


def _thesis(config):
    """The thesis's likelihood: one stripe, no contrast, layout or aspect prior."""
    return dataclasses.replace(
        config, parts=1, contrast=None, layout=None, aspect_prior=False, correlation=None
    )


def _terms(correlation: bool, camera: bool):
    """cpf-track's layer 1 with the correlation term and the camera stage set."""
    corr = CorrelationConfig() if correlation else None
    factor = DOWNSCALE if camera else None
    return lambda c: dataclasses.replace(c, correlation=corr, camera_motion=factor)


#: The ablation's variants of cpf-track's layer 1 (``--ablation``).
VARIANTS = {
    "histograms, contrast, layout": _terms(False, False),
    "+ correlation filter": _terms(True, False),
    "+ follow camera": _terms(False, True),
    "+ correlation filter + follow camera": _terms(True, True),
    "thesis likelihood": _thesis,
}


def cpf_run(colour: np.ndarray, box: np.ndarray, variant=None) -> tuple[np.ndarray, np.ndarray]:
    """``([T, 4] boxes, [T] lost)`` of ``cpf-track``'s default filter from ``box``, or of
    ``variant(config)`` of its config."""
    args = build_parser().parse_args(["scene"])  # no options: cpf-track's defaults
    config, params = box_config(args, model_options(args), box, colour.shape[1:3])
    if variant is not None:
        config = variant(config)
    from cpf_jax.cascade import build_box_filter

    filt = build_box_filter(config)
    frames = Frame(jnp.asarray(colour), None)
    run = jax.jit(lambda key, f, b: track_boxes(filt, params, key, f, b))
    boxes, lost = run(jax.random.PRNGKey(args.seed), frames, jnp.asarray(box, jnp.float32))
    return np.asarray(boxes), np.asarray(lost)


def _frames_key(colour: np.ndarray, box: np.ndarray) -> str:
    """A digest of the frames, the start box and the OpenCV runner's source."""
    h = hashlib.sha1(np.ascontiguousarray(colour).tobytes())
    h.update(np.asarray(box, np.float32).tobytes())
    h.update(OPENCV_RUNNER.read_bytes())
    return h.hexdigest()


def opencv_runs(python: Path | None, colour: np.ndarray, box: np.ndarray) -> dict:
    """``{"csrt": [T, 4], "kcf": [T, 4]}`` from the contrib environment, or ``{}``. Runs
    are kept in ``OPENCV_CACHE`` under a digest of the exact frames and start box, so that
    re-running the benchmark after a change to cpf_jax does not re-run OpenCV."""
    if python is None:
        return {}
    cached = OPENCV_CACHE / f"{_frames_key(colour, box)}.npz"
    if not cached.exists():
        OPENCV_CACHE.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
            np.savez(src, colour=colour, box=np.asarray(box, np.float32))
            subprocess.run([str(python), str(OPENCV_RUNNER), str(src), str(dst)], check=True)
            shutil.move(dst, cached)
    with np.load(cached) as out:
        return {k: out[k] for k in out.files}


def score(boxes, gt, visible, lost=None) -> dict:
    """Success rate at 0.5 and AUC (percent) and the success curve of one run."""
    s = summarise(np.nan_to_num(boxes), gt, visible, lost)
    curve = run_success_curve(np.nan_to_num(boxes), gt, visible, lost)
    return {"sr": s["success_rate"], "auc": s["auc"], "curve": curve}


def scene_row(seed: int, python: Path | None) -> dict:
    """One scene's factors and every tracker's score on it."""
    seq = make_random_sequence(seed)
    box = seq.boxes[0]
    t0 = time.perf_counter()
    boxes, lost = cpf_run(seq.colour, box)
    seconds = time.perf_counter() - t0
    runs = {"cpf_jax": score(boxes, seq.boxes, seq.visible, lost)}
    for name, b in opencv_runs(python, seq.colour, box).items():
        runs[name] = score(b, seq.boxes, seq.visible)
    return {
        "seed": seed,
        "frames": len(seq.colour),
        "factors": seq.meta["factors"],
        "runs": runs,
        "cpf_seconds": seconds,
    }


def crossing_row(python: Path | None) -> dict | None:
    """Every tracker on OTB Crossing from its first ground-truth box, or None without it."""
    if not CROSSING.exists():
        return None
    from cpf_jax.io import open_source

    src = open_source(str(CROSSING))
    rec = src.load_all()
    box = np.asarray(src.init_box, np.float32)
    boxes, lost = cpf_run(rec.colour, box)
    runs = {"cpf_jax": score(boxes, rec.boxes, rec.visible, lost)}
    for name, b in opencv_runs(python, rec.colour, box).items():
        runs[name] = score(b, rec.boxes, rec.visible)
    return {"frames": len(rec.colour), "runs": runs}


def _mean(rows: list[dict], tracker: str, key: str) -> float | None:
    vals = [r["runs"][tracker][key] for r in rows if tracker in r["runs"]]
    return float(np.mean(vals)) if vals else None


def summary(rows: list[dict]) -> dict:
    """The JSON's ``synthetic`` entry: scene count, mean SR / AUC per tracker, and the
    same per value of every factor."""
    out: dict = {"scenes": len(rows)}
    for t in TRACKERS:
        out[t] = {"sr": _mean(rows, t, "sr"), "auc": _mean(rows, t, "auc")}
    per: dict = {}
    for f in FACTORS:
        groups = defaultdict(list)
        for r in rows:
            groups[str(r["factors"][f])].append(r)
        per[f] = {
            v: {
                "scenes": len(g),
                **{t: {"sr": _mean(g, t, "sr"), "auc": _mean(g, t, "auc")} for t in TRACKERS},
            }
            for v, g in sorted(groups.items())
        }
    out["per_factor"] = per
    return out


def _cell(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def _pair(d: dict) -> str:
    return f"{_cell(d['sr'])} / {_cell(d['auc'])}"


def markdown(results: dict, split: str, seeds: range) -> str:
    syn = results["synthetic"]
    lines = [
        "# Layer 1 on scenes nobody tuned it to",
        "",
        f"`python experiments/unseen.py{'' if split == 'eval' else ' --split ' + split}`; "
        f"host {results['host']}. {syn['scenes']} randomised synthetic scenes "
        f"(`cpf_jax.random_scenes`, {split} seeds {seeds.start}-{seeds.stop - 1}); cpf_jax "
        "with `cpf-track`'s defaults, OpenCV 5 CSRT and KCF (opencv-contrib) on the same "
        "frames. Success rate at IoU 0.5 / AUC, percent, mean over scenes.",
        "",
        "| tracker | synthetic SR / AUC | OTB Crossing SR / AUC |",
        "|---|---:|---:|",
    ]
    cross = results.get("crossing")
    for t in TRACKERS:
        c = _pair(cross[t]) if cross and t in cross else "-"
        lines.append(f"| {t} | {_pair(syn[t])} | {c} |")
    if results.get("opencv_missing"):
        lines += ["", f"CSRT and KCF were not run: {results['opencv_missing']}"]
    lines += ["", "## Per factor (SR / AUC)", ""]
    lines += [
        "| factor | value | scenes | " + " | ".join(TRACKERS) + " |",
        "|---|---|---:|" + "---:|" * 3,
    ]
    for f, groups in syn["per_factor"].items():
        for v, g in groups.items():
            cells = " | ".join(_pair(g[t]) for t in TRACKERS)
            lines.append(f"| {f} | {v} | {g['scenes']} | {cells} |")
    lines += ["", "Figure: `unseen.png` (success plots, synthetic scenes and Crossing).", ""]
    return "\n".join(lines)


def figure(rows: list[dict], cross: dict | None, path: Path) -> None:
    """Success plots: mean over the synthetic scenes, and Crossing."""
    panels = []
    curves = {}
    for t in TRACKERS:
        c = [r["runs"][t]["curve"] for r in rows if t in r["runs"]]
        if c:
            curves[t] = np.mean(c, axis=0)
    panels.append(success_plot(curves, title=f"{len(rows)} synthetic scenes"))
    if cross:
        panels.append(
            success_plot(
                {t: cross["runs"][t]["curve"] for t in cross["runs"]}, title="OTB Crossing"
            )
        )
    save_png(np.concatenate(panels, axis=1), path)


def contrib_python(given: str | None) -> tuple[Path | None, str | None]:
    """The contrib environment's Python, or None and why it is missing."""
    py = Path(given) if given else CONTRIB_PYTHON
    if not py.exists():
        return None, f"no {py} (run `make contrib-env` to create it)"
    check = subprocess.run(
        [str(py), "-c", "import cv2; cv2.TrackerCSRT.create(); cv2.TrackerKCF.create()"],
        capture_output=True,
        text=True,
    )
    if check.returncode:
        return None, f"{py} has no opencv-contrib trackers: {check.stderr.strip()[-200:]}"
    return py, None


def _strip(row: dict) -> dict:
    """A row for the JSON: curves rounded."""
    runs = {
        t: {"sr": r["sr"], "auc": r["auc"], "curve": np.round(r["curve"], 4).tolist()}
        for t, r in row["runs"].items()
    }
    return dict(row, runs=runs)


def ablation(seeds: range, out: Path, split: str) -> None:
    """Every variant of ``VARIANTS`` on ``seeds``: which term gains where (cpf_jax only)."""
    rows = {name: [] for name in VARIANTS}
    for seed in seeds:
        seq = make_random_sequence(seed)
        cells = []
        for name, variant in VARIANTS.items():
            boxes, lost = cpf_run(seq.colour, seq.boxes[0], variant)
            r = score(boxes, seq.boxes, seq.visible, lost)
            rows[name].append(
                {"seed": seed, "factors": seq.meta["factors"], "sr": r["sr"], "auc": r["auc"]}
            )
            cells.append(f"{r['sr']:5.1f}/{r['auc']:5.1f}")
        print(f"scene {seed}: " + "  ".join(cells), flush=True)
    table = {
        name: {
            "sr": float(np.mean([r["sr"] for r in rs])),
            "auc": float(np.mean([r["auc"] for r in rs])),
        }
        for name, rs in rows.items()
    }
    out.write_text(
        json.dumps(
            {
                "host": describe(),
                "split": split,
                "seeds": [seeds.start, seeds.stop],
                "variants": table,
                "scenes": rows,
            },
            indent=1,
        )
    )
    flag = "" if split == "eval" else f" --split {split}"
    lines = [
        "# Layer 1's terms, one at a time, on randomised scenes",
        "",
        f"`python experiments/unseen.py --ablation{flag}`; host {describe()}; {len(seeds)} "
        f"{split} scenes (seeds {seeds.start}-{seeds.stop - 1}). cpf-track's default layer 1 "
        "with one term added or taken away. Success rate at IoU 0.5 / AUC, percent, mean over "
        "scenes.",
        "",
        "| variant | SR | AUC |",
        "|---|---:|---:|",
    ]
    args = build_parser().parse_args(["scene"])
    default, _ = box_config(args, model_options(args), np.array([0, 0, 40, 100]), (424, 512))
    for name, t in table.items():
        same = VARIANTS[name](default) == default
        lines.append(f"| {name}{' (default)' if same else ''} | {t['sr']:.1f} | {t['auc']:.1f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(out.with_suffix(".md").read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", choices=("eval", "train"), default="eval")
    p.add_argument("--scenes", type=int, help="only the first N scenes of the split")
    p.add_argument("--contrib-python", help="Python of an opencv-contrib environment")
    p.add_argument("--out", type=Path, help="JSON path (default results/unseen[_train].json)")
    p.add_argument(
        "--ablation", action="store_true", help="cpf_jax's terms one at a time (no OpenCV)"
    )
    args = p.parse_args(argv)
    seeds = EVAL_SEEDS if args.split == "eval" else TRAIN_SEEDS
    if args.scenes:
        seeds = seeds[: args.scenes]
    stem = "unseen" if args.split == "eval" else "unseen_train"
    if args.ablation:
        ablation(seeds, args.out or RESULTS / f"{stem}_ablation.json", args.split)
        return 0
    python, missing = contrib_python(args.contrib_python)
    if missing:
        print(f"note: CSRT and KCF skipped: {missing}", file=sys.stderr)
    rows = []
    for seed in seeds:
        row = scene_row(seed, python)
        rows.append(row)
        cells = "  ".join(f"{t} {r['sr']:5.1f}/{r['auc']:5.1f}" for t, r in row["runs"].items())
        print(f"scene {seed}: {row['frames']} frames  {cells}", flush=True)
    cross = crossing_row(python)
    results = {
        "host": describe(),
        "split": args.split,
        "seeds": [seeds.start, seeds.stop],
        "synthetic": summary(rows),
        "crossing": None
        if cross is None
        else {t: {"sr": r["sr"], "auc": r["auc"]} for t, r in cross["runs"].items()},
        "opencv_missing": missing,
        "scenes": [_strip(r) for r in rows],
    }
    out = args.out or RESULTS / f"{stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    out.with_suffix(".md").write_text(markdown(results, args.split, seeds))
    figure(rows, cross, out.with_suffix(".png"))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
