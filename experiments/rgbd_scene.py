"""The RGB-D filter without background frames: each frame is its own scene.

    python experiments/rgbd_scene.py               # every part (results/rgbd_scene.*)
    python experiments/rgbd_scene.py --part walks  # one part, the others kept from the JSON
    python experiments/rgbd_scene.py --quick       # fewer scenes and keys, to try a change

``cpf-track --model grid-occlusion`` reads no background frames by default: the filter
takes each frame's scene from the frame (``RGBDConfig.side_scene``), so it tracks from the
first frame of a recording that never shows the empty room, and with a camera that moves.
Three parts, each scored on the box the filter reports (``info.box``, what cpf-track
writes), success rate at IoU 0.5 and AUC in percent:

* The synthetic walks (static camera, walker in view from the first frame), default
  grid-occlusion at N = 200 in two ways: the scenario's empty room given as the
  background (what a static camera with empty frames gives) and the frame's own scene
  (the default). Training seeds 100-102 (on which the defaults were chosen) and
  evaluation seeds 0-2 are reported apart.
* The randomised scenes of ``experiments/unseen.py`` (``cpf_jax.random_scenes``: size,
  view, a camera that pans, follows, shakes or zooms, clutter, look-alikes) with their
  depth: the RGB-D default by camera motion, on unseen.py's evaluation seeds.
* IST images1 (real), from its first ground-truth frame as cpf-track starts it, with
  the calibration: the default against ``--background auto`` (the median of the
  recording's emptiest frames), 8 filter keys. Skipped with a message without
  ../shared/data.

Writes ``results/rgbd_scene.json`` and ``results/rgbd_scene.md`` after each part, each
part with its host and date (``--part`` runs some and keeps the others).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import host  # noqa: E402  (same folder: the CPU name)
from colour_tables import WALKING  # noqa: E402
from unseen import EVAL_SEEDS, score  # noqa: E402

from cpf_jax import synthetic
from cpf_jax.cascade import build_box_filter
from cpf_jax.cli.model import box_config
from cpf_jax.cli.options import build_parser, model_options
from cpf_jax.filter import Context, track_boxes
from cpf_jax.kernels.background import Background
from cpf_jax.random_scenes import make_random_sequence
from cpf_jax.types import Frame

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
IST = ROOT.parent / "shared" / "data" / "ist_piv_rgbd" / "images1"
IST_CALIB = ROOT / "experiments" / "calib" / "ist_piv.json"

WALK_SEEDS = {"train": (100, 101, 102), "eval": (0, 1, 2)}
# The walking scenarios (the target: SR >= 95 % on each) and a walker passing furniture.
SCENARIOS = (*WALKING, "distractor_pass")
WALK_MODES = ("empty room", "own scene")
RANDOM_SEEDS = {"eval": EVAL_SEEDS}
RANDOM_MODES = ("own scene",)
# A walker farther than the sensor's range has no depth: an RGB-D model cannot see him.
MIN_DEPTH_SHARE = 0.5
IST_MODES = ("own scene", "auto background")
IST_KEYS = 8
PARTICLES = 200
# Random scenes are padded to this many frames (the filter is causal: padding at the end
# changes nothing before it), so that one compile serves every scene.
RANDOM_FRAMES = 100


def _config(box, frame_hw, mode: str, *extra: str):
    """``cpf-track --model grid-occlusion``'s config and parameters for ``box``. The
    histogram window is sized for the box rounded up to a power of 1.25 (one compile for
    similar boxes; the window only decides how fast the exact histograms are counted)."""
    args = build_parser().parse_args(
        ["scene", "--model", "grid-occlusion", "--particles", str(PARTICLES), *extra]
    )
    size = 1.25 ** np.ceil(np.log(np.maximum(np.asarray(box[2:4], float), 8.0)) / np.log(1.25))
    config, params = box_config(args, model_options(args), np.r_[box[:2], size], frame_hw)
    return config, params


@functools.cache
def _runner(config):
    """``(keys [K], frames, box, context) -> ([K, T, 4] boxes, [K, T] lost)``, jitted."""
    filt = build_box_filter(config)

    def run(params, keys, frames, box, context):
        one = lambda k: track_boxes(filt, params, k, frames, box, context)  # noqa: E731
        return jax.vmap(one)(keys)

    return jax.jit(run)


def _track(config, params, keys, colour, depth, box, background=None):
    context = None if background is None else Context(background=background)
    frames = Frame(jnp.asarray(colour), jnp.asarray(depth))
    boxes, lost = _runner(config)(params, keys, frames, jnp.asarray(box, jnp.float32), context)
    return np.asarray(boxes), np.asarray(lost)


def walk_row(name: str, seed: int, mode: str) -> dict:
    """One synthetic walk in one mode: ``{"sr", "auc"}``."""
    seq = synthetic.make_sequence(name, seed=seed)
    config, params = _config(seq.boxes[0], seq.colour.shape[1:3], mode)
    bg = None
    if mode == "empty room":
        bg = Background(
            jnp.asarray(seq.meta["background_colour"], jnp.float32),
            jnp.asarray(seq.meta["background_depth"], jnp.float32),
        )
    keys = jax.random.PRNGKey(seed)[None]
    boxes, lost = _track(config, params, keys, seq.colour, seq.depth, seq.boxes[0], bg)
    s = score(boxes[0], seq.boxes, seq.visible, lost[0])
    return {"sr": s["sr"], "auc": s["auc"]}


def _padded(a: np.ndarray, n: int) -> np.ndarray:
    return np.concatenate([a, np.repeat(a[-1:], max(n - len(a), 0), axis=0)])[: max(n, len(a))]


def random_row(seed: int) -> dict:
    """One randomised scene: its camera factor, the share of the walker's first-frame
    pixels with depth, and each mode's ``{"sr", "auc"}``."""
    seq = make_random_sequence(seed)
    t = len(seq.colour)
    colour, depth = _padded(seq.colour, RANDOM_FRAMES), _padded(seq.depth, RANDOM_FRAMES)
    share = float(np.mean(seq.depth[0][seq.mask[0]] > 0)) if seq.mask[0].any() else 0.0
    row = {"seed": seed, "camera": seq.meta["factors"]["camera"], "depth_share": share}
    row["runs"] = {}
    for mode in RANDOM_MODES:
        config, params = _config(seq.boxes[0], seq.colour.shape[1:3], mode)
        keys = jax.random.PRNGKey(0)[None]
        boxes, lost = _track(config, params, keys, colour, depth, seq.boxes[0])
        s = score(boxes[0][:t], seq.boxes, seq.visible, lost[0][:t])
        row["runs"][mode] = {"sr": s["sr"], "auc": s["auc"]}
    return row


def ist_part(n_keys: int) -> dict | None:
    """IST images1 from its first ground-truth frame, registered with the calibration,
    each mode over ``n_keys`` filter keys: ``{mode: {"sr", "auc", "auc_per_key"}}``."""
    if not IST.is_dir():
        print(f"IST part skipped: {IST} not found (the shared data is not mounted).")
        return None
    from cpf_jax.cli.inputs import open_inputs
    from cpf_jax.io import open_source

    out = {}
    for mode in IST_MODES:
        background = "auto" if mode == "auto background" else "none"
        argv = [str(IST), "--model", "grid-occlusion", "--calib", str(IST_CALIB)]
        args = build_parser().parse_args([*argv, "--background", background])
        source = open_source(args.path)
        inputs = open_inputs(args, source)
        frames = [f for _, f in inputs.frames]
        colour = np.stack([np.asarray(f.colour) for f in frames])
        depth = np.stack([np.asarray(f.depth) for f in frames])
        config, params = _config(inputs.box, colour.shape[1:3], mode, "--background", background)
        keys = jax.random.split(jax.random.PRNGKey(0), n_keys)
        boxes, lost = _track(config, params, keys, colour, depth, inputs.box, inputs.background)
        gt = np.asarray(source.gt_boxes, np.float32)[inputs.start :]
        visible = (
            gt[:, 2] > 0
            if source.visible is None
            else np.asarray(source.visible, bool)[inputs.start :]
        )
        runs = [score(boxes[k], gt, visible, lost[k]) for k in range(n_keys)]
        out[mode] = {
            "start_frame": int(inputs.start),
            "sr": float(np.mean([r["sr"] for r in runs])),
            "auc": float(np.mean([r["auc"] for r in runs])),
            "auc_per_key": [round(float(r["auc"]), 1) for r in runs],
        }
        print(f"IST {mode}: {out[mode]}", flush=True)
    return out


def _forget_compiles(keep: int = 6) -> None:
    """Drop the compiled runs once more than ``keep`` configs hold them: every window and
    length compiles its own, and an XLA:CPU process that keeps a few dozen runs out of
    memory maps."""
    if _runner.cache_info().currsize > keep:
        _runner.cache_clear()
        jax.clear_caches()


def _mean(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def _heading(part: dict) -> str:
    return f"{part['host']}, {part['date']}, N = {part['particles']}."


def _mode_table(first: str, counts: list[str], modes: tuple, table: dict) -> list[str]:
    """Markdown rows of ``table`` (``{row name: {count: n, mode: {"sr", "auc"}}}``): the
    row's name, its ``counts`` columns, then SR / AUC per mode, and a blank line."""
    md = ["| " + " | ".join([first, *counts, *modes]) + " |"]
    md += ["|---|" + "---:|" * (len(counts) + len(modes))]
    for name, row in table.items():
        cells = [str(row[c]) for c in counts]
        cells += [f"{row[m]['sr']:.1f} / {row[m]['auc']:.1f}" for m in modes]
        md.append(f"| {name} | " + " | ".join(cells) + " |")
    return [*md, ""]


def markdown(parts: dict) -> str:
    """The Markdown tables of the parts present in ``parts`` (``{name: {host, date,
    particles, result}}``)."""
    md = [
        "# The RGB-D filter without background frames",
        "",
        "`python experiments/rgbd_scene.py`. cpf-track's grid-occlusion filter, scored on the "
        "box it reports: success rate at IoU 0.5 / AUC, percent. 'own scene': the default, "
        "each frame's scene from the frame itself (`RGBDConfig.side_scene`); 'empty room': "
        "the scenario's empty room given as the background.",
        "",
    ]
    if "walks" in parts:
        walks = parts["walks"]
        md += ["## Synthetic walks (static camera, walker in view from the first frame)", ""]
        md += [_heading(walks), ""]
        for split, table in walks["result"].items():
            seeds = WALK_SEEDS[split]
            md += [f"Seeds {', '.join(map(str, seeds))} ({split}), mean over seeds:", ""]
            md += _mode_table("scenario", [], WALK_MODES, table)
    if "random" in parts:
        random = parts["random"]
        md += ["## Randomised scenes with depth, by camera motion", "", _heading(random), ""]
        for split, table in random["result"]["by_camera"].items():
            seeds = RANDOM_SEEDS[split]
            md += [
                f"{split} seeds {seeds.start}-{seeds.stop - 1}; by camera motion the scenes "
                f"whose walker has depth on at least {MIN_DEPTH_SHARE:.0%} of his first-frame "
                "pixels, then the others (farther than the sensor's range) together:",
                "",
            ]
            md += _mode_table("camera", ["scenes"], RANDOM_MODES, table)
    if parts.get("ist", {}).get("result"):
        ist = parts["ist"]["result"]
        start = next(iter(ist.values()))["start_frame"]
        n_keys = len(next(iter(ist.values()))["auc_per_key"])
        md += [
            f"## IST images1 from its first ground-truth frame ({start}, 0-based), {n_keys} keys",
            "",
            _heading(parts["ist"]),
            "",
            "| background | SR | AUC | AUC per key |",
            "|---|---:|---:|---|",
        ]
        for mode, row in ist.items():
            keys = ", ".join(f"{a:.1f}" for a in row["auc_per_key"])
            md.append(f"| {mode} | {row['sr']:.1f} | {row['auc']:.1f} | {keys} |")
        md.append("")
    return "\n".join(md)


def _by_camera(rows: list[dict]) -> dict:
    """Mean scores per camera motion over the scenes whose walker has depth (at least
    ``MIN_DEPTH_SHARE`` of his first-frame pixels), and over those without, apart."""
    rows_in = [r for r in rows if r["depth_share"] >= MIN_DEPTH_SHARE]
    rows_out = [r for r in rows if r["depth_share"] < MIN_DEPTH_SHARE]
    part = _camera_means(rows_in)
    if rows_out:
        part["walker beyond the depth range"] = _camera_means(rows_out)["all"]
    return part


def _camera_means(rows: list[dict]) -> dict:
    cameras = sorted({r["camera"] for r in rows})
    part = {}
    for camera in [*cameras, "all"]:
        sel = [r for r in rows if camera in ("all", r["camera"])]
        part[camera] = {"scenes": len(sel)}
        for m in RANDOM_MODES:
            runs = [r["runs"][m] for r in sel]
            part[camera][m] = {"sr": _mean(runs, "sr"), "auc": _mean(runs, "auc")}
    return part


PARTS = ("ist", "walks", "random")
RESULT_JSON = RESULTS / "rgbd_scene.json"


def _walks(quick: bool) -> dict:
    out = {}
    for split, seeds in WALK_SEEDS.items():
        seeds = seeds[:1] if quick else seeds
        table = {}
        for name in SCENARIOS:
            table[name] = {}
            for mode in WALK_MODES:
                rows = [walk_row(name, s, mode) for s in seeds]
                table[name][mode] = {"sr": _mean(rows, "sr"), "auc": _mean(rows, "auc")}
            _forget_compiles()
            cells = "  ".join(
                f"{m}: {v['sr']:5.1f}/{v['auc']:5.1f}" for m, v in table[name].items()
            )
            print(f"{split} {name} {cells}", flush=True)
        out[split] = table
    return out


def _random(quick: bool) -> dict:
    out = {"by_camera": {}, "rows": {}}
    for split, seeds in RANDOM_SEEDS.items():
        seeds = seeds[:4] if quick else seeds
        rows = []
        for s in seeds:
            rows.append(random_row(s))
            _forget_compiles()
            print(f"{split} scene {s} {rows[-1]['camera']} {rows[-1]['runs']}", flush=True)
        out["by_camera"][split] = _by_camera(rows)
        out["rows"][split] = rows
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="a few scenes and one key each")
    p.add_argument("--part", action="append", choices=PARTS, help="run only this part (repeatable)")
    args = p.parse_args(argv)
    run = {
        "ist": lambda: ist_part(1 if args.quick else IST_KEYS),
        "walks": lambda: _walks(args.quick),
        "random": lambda: _random(args.quick),
    }
    result = {}
    if not args.quick and RESULT_JSON.is_file():
        result = json.loads(RESULT_JSON.read_text()).get("parts", {})
    for part in args.part or PARTS:
        stamp = {"host": host.describe(), "date": datetime.date.today().isoformat()}
        result[part] = {**stamp, "particles": PARTICLES, "result": run[part]()}
        if args.quick:
            continue
        RESULTS.mkdir(parents=True, exist_ok=True)
        RESULT_JSON.write_text(json.dumps({"parts": result}, indent=1) + "\n")
        (RESULTS / "rgbd_scene.md").write_text(markdown(result))
        print(f"written: {RESULTS / 'rgbd_scene.md'} ({part})", flush=True)
    if args.quick:
        print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
