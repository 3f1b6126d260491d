"""Reproduce the thesis's colour-layer tables (T 3.1, 3.3, 3.4, 3.5) on synthetic sequences.

Every number is a success rate (% of frames with IoU >= 0.5 against the
ground-truth box) averaged over several synthetic scenes (scene seeds) and
several filter seeds, exactly as ``cpf-track`` would track them: initialised
with the ground-truth box of frame 0, frame 0 included in the score.

Tables:
* ``table_3_1``: success rate vs N = 20..160, averaged over the walking scenarios.
* ``table_3_3``: walking speed (slow 0.4 / medium 0.8 / fast 1.2 m/s) at N = 100.
* ``table_3_4``: dynamic models at N = 100 (walking scenarios).
* ``table_3_1_ar1``: Table 3.1 with the thesis's model (8-tuple AR1 with
  motion-guided sampling) instead of the default random walk.
* ``table_3_5``: plain vs hierarchical (motion-guided) sampling at N = 50, on
  the 8-tuple AR1 model (the one the thesis guides).
* The thesis's AR1 and AR2 rows (``table_3_1_ar1``, ``table_3_4``'s "original"
  and "8-tuple AR2", ``table_3_5``, the ablation's thesis row) keep its undamped
  velocities (``size_velocity_decay = 1``); ``table_3_4``'s two "damped" rows and
  ``table_3_5_damped`` use the library's AR1 and AR2, whose size velocities decay.
* ``table_3_5_default``: the same on the default random walk, which the
  estimate's velocity guides (``cpf_jax.dynamics``).
* ``per_scenario_n100`` and ``min_success_n100``: every walking scenario at N = 100.
* ``sigma_sweep``: likelihood width sigma at N = 100 (why sigma = 1 is too flat).
* ``likelihood_ablation``: from the thesis's likelihood (one H-S histogram, no
  contrast term) to ours at N = 100, a term at a time.
* ``likelihood_terms``: the default against the histogram-only model
  (``ColourConfig.histogram_only``: no layout term, no template update, unseen
  colours as background), against the default
  without each of those three, and against the alternatives (layout weight 20,
  the gradient layout, the mixture contrast) at N = 100: walking mean and
  minimum, the two look-alike scenes (``dark_clothes``, ``distractor_pass``),
  and Crossing success rate / AUC.
* ``extra_scenarios``: the distractor, light-switch and dark-clothes scenes at N = 100.
* ``crossing``: real OTB Crossing (../shared/data/otb/Crossing), if present.

Run: ``python experiments/colour_tables.py`` (``--quick`` for a smoke run); the run
is made of parts (``PARTS``: particles, thesis_model, models, sampling, sigma,
ablation, scenes, terms), each written when it finishes with its host, date and
time, and ``--part NAME`` reruns one part into the existing results. Writes
``experiments/results/colour_tables.json``, ``.md`` and ``.png`` (Table 3.1 against
the thesis's, Crossing success plots; ``--figure-only`` redraws it from the JSON).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import host  # same folder: the CPU model
import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax import charts
from cpf_jax import params as pp
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
from cpf_jax.dynamics import SIZE_VELOCITY_MODELS, THESIS_TAU
from cpf_jax.filter import track_boxes
from cpf_jax.metrics import run_success_curve, summarise
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
CROSSING = ROOT.parent / "shared" / "data" / "otb" / "Crossing"

WALKING = (
    "walk_across_slow",
    "walk_across_medium",
    "walk_across_fast",
    "walk_towards",
    "walk_away",
    "turn",
)
EXTRA = ("distractor_pass", "light_switch", "dark_clothes")
# Scenes where the clothes' colours are the background's: the likelihood terms'
# variants are scored on them too.
LOOKALIKE = ("dark_clothes", "distractor_pass")
#: The ``likelihood_terms`` row without the default's layout term, template update and
#: neutral unseen colours (``ColourConfig.histogram_only``).
HISTOGRAM_ONLY = "histogram only (no layout, no template update, unseen background)"
#: The ``likelihood_terms`` row with the finer 12x3 layout grid; the label is a key of the
#: results JSON.
LAYOUT_12X3 = "layout 12x3 (the former default)"
#: The parameters the results record (``meta.params``): JSON key -> parameter path.
PARAM_KEYS = {
    "sigma": "histogram.sigma",
    "contrast_weight": "contrast.weight",
    "contrast_threshold": "contrast.threshold",
    "fill_ratio": "contrast.fill_ratio",
    "layout_weight": "layout.weight",
    "layout_rate": "layout.rate",
    "aspect_mean": "aspect.mean",
    "aspect_sigma": "aspect.sigma",
    "tau": "motion.tau",
    "template_rate": "template.rate",
    "template_max_distance": "template.max_distance",
    "lost_distance": "histogram.lost_distance",
    "robust_radius": "estimate.robust_radius",
    "size_velocity_decay": "motion.size_velocity_decay",
}
SPEEDS = {"slow": "walk_across_slow", "medium": "walk_across_medium", "fast": "walk_across_fast"}
# Table 3.4's rows: the thesis's original model and its three variants, plus the random walk.
MODELS = {
    "8-tuple AR1 (original)": "ar1",
    "4-tuple AR1": "ar1_fixed",
    "4-tuple AR2": "ar2_fixed",
    "8-tuple AR2": "ar2",
    "random walk": "random_walk",
}


@functools.cache
def _sequence(name: str, seed: int):
    seq = make_sequence(name, seed=seed)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    return seq, frames


@functools.cache
def _runner(config: ColourConfig):
    """One jitted batch runner per static config: (params, keys, frames, box) -> boxes."""
    filt = build_colour_filter(config)

    # lax.map (not vmap) over filter seeds: the tables were made this way (vmap now
    # runs the same branches, but its per-key floating-point results differ).
    def run(params, keys, frames, box):
        return jax.lax.map(lambda k: track_boxes(filt, params, k, frames, box)[0], keys)

    return jax.jit(run)


def _window_config(config: ColourConfig, name: str) -> ColourConfig:
    """The config with one histogram window for every scenario: the largest of the
    windows ``with_window`` sizes from each scenario's first box (one compile per
    config instead of one per config and scenario; with ``contain`` a larger
    window only widens the truncation of the motion noise)."""
    windows = []
    for other in WALKING + EXTRA:
        seq, _ = _sequence(other, 0)
        box_wh = tuple(float(v) for v in seq.boxes[0, 2:])
        windows.append(config.with_window(box_wh, seq.colour.shape[1:3]).window)
    window = (max(w[0] for w in windows), max(w[1] for w in windows))
    return dataclasses.replace(config, window=window)


def success_rates(name: str, scene_seeds, keys: int, config: ColourConfig, params) -> list[float]:
    """Success rate (%) of every (scene seed, filter seed) run of one scenario."""
    run = _runner(_window_config(config, name))
    out = []
    for s in scene_seeds:
        seq, frames = _sequence(name, s)
        ks = jax.random.split(jax.random.PRNGKey(1000 + s), keys)
        boxes = np.asarray(run(params, ks, frames, jnp.asarray(seq.boxes[0])))
        for b in boxes:
            out.append(summarise(b, seq.boxes, seq.visible)["success_rate"])
    return out


def mean_over(names, scene_seeds, keys, config, params) -> tuple[float, dict[str, float]]:
    per = {n: float(np.mean(success_rates(n, scene_seeds, keys, config, params))) for n in names}
    return float(np.mean(list(per.values()))), per


def crossing(n_particles: int, keys: int, config: ColourConfig, params) -> dict | None:
    if not CROSSING.exists():
        return None
    from cpf_jax.io import open_source

    src = open_source(str(CROSSING))
    rec = src.load_all()
    frames = Frame(jnp.asarray(rec.colour), jnp.asarray(rec.depth))
    box = jnp.asarray(src.init_box)
    cfg = dataclasses.replace(config, n_particles=n_particles).with_window(
        tuple(np.asarray(box[2:])), rec.colour.shape[1:3]
    )
    ks = jax.random.split(jax.random.PRNGKey(7), keys)
    boxes = np.asarray(_runner(cfg)(params, ks, frames, box))
    runs = [summarise(b, rec.boxes, rec.visible) for b in boxes]
    curve = np.mean([run_success_curve(b, rec.boxes, rec.visible) for b in boxes], axis=0)
    return {
        "success_rate": float(np.mean([r["success_rate"] for r in runs])),
        "auc": float(np.mean([r["auc"] for r in runs])),
        "precision": float(np.mean([r["precision"] for r in runs])),
        "n_particles": n_particles,
        "runs": keys,
        "success_rate_per_run": [round(r["success_rate"], 1) for r in runs],
        # OTB success plot (IoU > t for t = 0, 0.05, ..., 1), averaged over the runs.
        "success_curve": curve.round(4).tolist(),
    }


def likelihood_term_variants(base: ColourConfig, params) -> dict:
    """``likelihood_terms`` rows: label -> (config, params); the first is the default.

    The default's three real-video terms (layout 7x3, template update, unseen colours
    neutral) taken away together and one at a time, then the alternatives.
    """
    grid = "x".join(map(str, base.layout))
    return {
        "default": (base, params),
        HISTOGRAM_ONLY: (base.histogram_only(), params),
        "no layout": (dataclasses.replace(base, layout=None), params),
        "no template update": (dataclasses.replace(base, template_update=False), params),
        "unseen background": (dataclasses.replace(base, unseen="background"), params),
        "layout_weight 20": (base, pp.replace(params, "layout.weight", jnp.float32(20.0))),
        f"gradient layout {grid}": (dataclasses.replace(base, layout_feature="gradient"), params),
        # A finer grid, slower (experiments/bench_colour.py).
        LAYOUT_12X3: (dataclasses.replace(base, layout=(12, 3)), params),
        "mixture contrast, histogram only": (
            dataclasses.replace(base.histogram_only(), contrast="mixture"),
            params,
        ),
        f"mixture + layout {grid} (contrast_weight 5, layout_weight 20, no update)": (
            dataclasses.replace(base, contrast="mixture", template_update=False),
            params._replace(
                contrast=params.contrast._replace(weight=jnp.float32(5.0)),
                layout=params.layout._replace(weight=jnp.float32(20.0)),
            ),
        ),
    }


# The thesis's Table 3.1 (success rate % vs N), drawn beside ours.
THESIS_TABLE_3_1 = {
    20: 37.5,
    40: 49.0,
    60: 68.0,
    80: 79.0,
    100: 85.5,
    120: 87.0,
    140: 90.5,
    160: 91.0,
}


def figure(res: dict, path: Path) -> None:
    """``colour_tables.png``: Table 3.1 against the thesis's, and the Crossing success
    plots of the default and the optional likelihood terms (what the run has so far)."""
    panels = []
    if res.get("table_3_1"):
        series = {
            "ours (default: random walk)": _curve(res["table_3_1"]),
            "ours, thesis model (8-tuple AR1, motion-guided)": _curve(
                res.get("table_3_1_ar1") or {}
            ),
            "thesis Table 3.1": _curve(THESIS_TABLE_3_1),
        }
        series = {k: v for k, v in series.items() if len(v[0])}
        panels.append(
            charts.line_chart(
                series,
                title="Table 3.1: success rate vs particles (synthetic walking scenes)",
                xlabel="particles N",
                ylabel="success rate (%)",
                ylim=(0, 100),
            )
        )
    curves = {}
    if (res.get("crossing") or {}).get("success_curve"):
        curves["default"] = res["crossing"]["success_curve"]
    for label, row in res.get("likelihood_terms", {}).items():
        if label != "default" and (row.get("crossing") or {}).get("success_curve"):
            curves[label] = row["crossing"]["success_curve"]
    if curves:
        panels.append(
            charts.success_plot(
                curves, title="OTB Crossing, N = 100 (OpenCV CSRT: AUC 70.0, success rate 95.0)"
            )
        )
    if panels:
        width = max(p.shape[1] for p in panels)
        charts.save_png(
            np.concatenate(
                [
                    np.pad(p, ((0, 0), (0, width - p.shape[1]), (0, 0)), constant_values=255)
                    for p in panels
                ]
            ),
            path,
        )


def _curve(d: dict) -> tuple[list[float], list[float]]:
    return [float(k) for k in d], [float(v) for v in d.values()]


def add_crossing_curves(res: dict) -> None:
    """Re-run Crossing for the rows that lack a success curve (JSON from before curves
    were stored), with the row's own settings and seeds, and check the scores match."""
    base, params = ColourConfig(), default_colour_params()
    rows = [("default", res.get("crossing"), (base, params))]
    variants = likelihood_term_variants(base, params)
    for label, row in res.get("likelihood_terms", {}).items():
        if label != "default" and label in variants:
            rows.append((label, row.get("crossing"), variants[label]))
    for label, stored, (cfg, p) in rows:
        if not stored or stored.get("success_curve"):
            continue
        fresh = crossing(stored["n_particles"], stored["runs"], cfg, p)
        if fresh is None:
            return
        for k in ("success_rate", "auc"):
            if abs(fresh[k] - stored[k]) > 0.05:
                print(f"warning: Crossing {label} {k} {fresh[k]:.2f} != stored {stored[k]:.2f}")
        stored["success_curve"] = fresh["success_curve"]
        print(f"crossing curve: {label}", flush=True)


def _md_row(d: dict, fmt="{:.1f}") -> tuple[str, str]:
    keys = list(d)
    return "| " + " | ".join(keys) + " |", "| " + " | ".join(fmt.format(d[k]) for k in keys) + " |"


def markdown(res: dict) -> str:
    lines = ["# Colour-layer tables (synthetic sequences)", "", res["meta"]["note"], ""]
    lines += ["Figure: `colour_tables.png` (Table 3.1, Crossing success plots).", ""]

    def table(title, d):
        if not d:
            return
        head, row = _md_row(d)
        sep = "|" + "|".join("---:" for _ in d) + "|"
        lines.extend([f"## {title}", "", head, sep, row, ""])

    table(
        "Table 3.1: success rate (%) vs number of particles (thesis: 37.5 ... 91)",
        res.get("table_3_1"),
    )
    table(
        "Table 3.1 with the thesis's model (8-tuple AR1, undamped, motion-guided sampling)",
        res.get("table_3_1_ar1"),
    )
    table(
        "Table 3.3: success rate (%) vs walking speed, N = 100 (thesis: 84 / 82.5 / 74.5)",
        res.get("table_3_3"),
    )
    table("Table 3.4: dynamic models, N = 100 (thesis: 83 / 81 / 77.5 / 59)", res.get("table_3_4"))
    table(
        "Table 3.5: plain vs hierarchical sampling, N = 50 (thesis: 60 / 79.5)",
        res.get("table_3_5"),
    )
    table(
        "Table 3.5 with the library's AR1 (size velocity damped, ColourParams."
        "size_velocity_decay), N = 50",
        res.get("table_3_5_damped"),
    )
    table(
        "Table 3.5 on the default random walk (guided by the estimate's velocity), N = 50",
        res.get("table_3_5_default"),
    )
    table("Every walking scenario at N = 100", res.get("per_scenario_n100"))
    table("Likelihood width sigma, N = 100", res.get("sigma_sweep"))
    table("Likelihood ablation, N = 100", res.get("likelihood_ablation"))
    table("Other scenarios, N = 100", res.get("extra_scenarios"))
    if res.get("likelihood_terms"):
        lines += [
            "## Likelihood terms, N = 100 (the default and variants)",
            "",
            "| variant | walking mean | walking min | dark_clothes | distractor_pass |"
            " Crossing SR | Crossing AUC |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
    for label, r in res.get("likelihood_terms", {}).items():
        c = r.get("crossing") or {}
        look = r.get("lookalike", {})
        lines.append(
            f"| {label} | {r['walking_mean']:.1f} | {r['walking_min']:.1f} | "
            + " | ".join(f"{look.get(n, float('nan')):.1f}" for n in LOOKALIKE)
            + f" | {c.get('success_rate', float('nan')):.1f} | {c.get('auc', float('nan')):.1f} |"
        )
    lines.append("")
    if res.get("crossing"):
        c = res["crossing"]
        lines += [
            "## OTB Crossing (real, 120 frames)",
            "",
            f"N = {c['n_particles']}, {c['runs']} seeds: success rate {c['success_rate']:.1f} %, "
            f"AUC {c['auc']:.1f}, precision@20px {c['precision']:.1f} % "
            "(OpenCV CSRT 95.0 / 70.0, MIL 25.8 / 18.7, CamShift 0.8 / 5.7).",
            "",
        ]
    if "min_success_n100" in res:
        lines.append(
            f"min success at N = 100 over walking scenarios: {res['min_success_n100']:.1f} %"
        )
    parts = res["meta"].get("parts", {})
    if parts:
        lines += ["", "| part | run | host | seconds |", "|---|---|---|---:|"]
        lines += [
            f"| {name} | {p['date']} | {p['host']} | {p['seconds']} |" for name, p in parts.items()
        ]
    if not res["meta"].get("complete", True):
        lines.append("INCOMPLETE: the run stopped before every table was written.")
    return "\n".join(lines) + "\n"


def _part_particles(res: dict, run: _Run) -> None:
    """Table 3.1 (success rate vs N) and, from its N = 100 row, Table 3.3 and every scenario."""
    res["table_3_1"] = {}
    for n in run.ns:
        cfg = dataclasses.replace(run.base, n_particles=n)
        mean, per = mean_over(WALKING, run.seeds, run.keys, cfg, run.params)
        res["table_3_1"][str(n)] = mean
        if n == 100:
            res["per_scenario_n100"] = per
            res["min_success_n100"] = float(min(per.values()))
            res["table_3_3"] = {k: per[v] for k, v in SPEEDS.items()}
        print(f"N={n}: {mean:.1f} % {per}", flush=True)
        run.save()


def _part_thesis_model(res: dict, run: _Run) -> None:
    """Table 3.1 with the thesis's own model (8-tuple AR1, motion-guided, its velocities
    undamped as in eqs. 3.14-3.17): the scenes are hard enough that N matters for it (the
    default random walk needs fewer particles)."""
    res["table_3_1_ar1"] = {}
    for n in (20, 60, 100, 160) if not run.quick else run.ns:
        cfg = dataclasses.replace(run.base, n_particles=n, model="ar1", hierarchical=True)
        res["table_3_1_ar1"][str(n)] = mean_over(WALKING, run.seeds, run.keys, cfg, run.undamped)[0]
        print(f"N={n}, ar1: {res['table_3_1_ar1'][str(n)]:.1f} %", flush=True)
        run.save()


def _part_models(res: dict, run: _Run) -> None:
    """Table 3.4: the dynamic models at N = 100; the thesis's rows keep its undamped
    models and the library's damped AR1 and AR2 are reported beside them."""
    n100 = dataclasses.replace(run.base, n_particles=100)
    res["table_3_4"] = {}
    for label, model in MODELS.items():
        if model == run.base.model:
            res["table_3_4"][label] = res["table_3_1"]["100"]
            continue
        p = run.undamped if model in SIZE_VELOCITY_MODELS else run.params
        mean, _ = mean_over(WALKING, run.seeds, run.keys, dataclasses.replace(n100, model=model), p)
        res["table_3_4"][label] = mean
        print(f"model {label}: {mean:.1f} %", flush=True)
        run.save()
    decay = float(run.params.motion.size_velocity_decay)
    for model in SIZE_VELOCITY_MODELS:
        label = f"8-tuple {model.upper()}, size velocity damped ({decay:g})"
        res["table_3_4"][label] = mean_over(
            WALKING, run.seeds, run.keys, dataclasses.replace(n100, model=model), run.params
        )[0]
        print(f"model {label}: {res['table_3_4'][label]:.1f} %", flush=True)
        run.save()


def _part_sampling(res: dict, run: _Run) -> None:
    """Table 3.5: motion-guided sampling, the thesis's refinement of its AR1 model, compared
    on ar1 as in the thesis and on the default random walk (guided by the estimate)."""
    for key, model, p in (
        ("table_3_5", "ar1", run.undamped),
        ("table_3_5_damped", "ar1", run.params),
        ("table_3_5_default", run.base.model, run.params),
    ):
        n50 = dataclasses.replace(run.base, n_particles=50, model=model)
        res[key] = {
            label: mean_over(
                WALKING, run.seeds, run.keys, dataclasses.replace(n50, hierarchical=h), p
            )[0]
            for label, h in (("plain", False), ("hierarchical", True))
        }
        print(f"table 3.5, {model}: {res[key]}", flush=True)
    run.save()


def _part_sigma(res: dict, run: _Run) -> None:
    """The likelihood width sigma at N = 100 (why sigma = 1 is too flat)."""
    n100 = dataclasses.replace(run.base, n_particles=100)
    res["sigma_sweep"] = {}
    for sigma in (0.05, 0.1, 0.2, 0.5, 1.0):
        p = pp.replace(run.params, "histogram.sigma", jnp.float32(sigma))
        if abs(sigma - float(run.params.histogram.sigma)) < 1e-6:
            res["sigma_sweep"][str(sigma)] = res["table_3_1"]["100"]
            continue
        res["sigma_sweep"][str(sigma)] = mean_over(WALKING, run.seeds, run.keys, n100, p)[0]
    print(f"sigma sweep: {res['sigma_sweep']}", flush=True)
    run.save()


def _part_ablation(res: dict, run: _Run) -> None:
    """From the thesis's likelihood to ours at N = 100, one term at a time (histogram-only
    rows first, then the default's layout, template update and neutral unseen colours)."""
    hist100 = dataclasses.replace(run.base, n_particles=100).histogram_only()
    thesis_cfg = dataclasses.replace(
        hist100, parts=1, ring_margin=0.0, model="ar1", hierarchical=False
    )
    no_contrast = pp.replace(run.params, "contrast.weight", jnp.float32(0.0))
    u = run.undamped
    thesis_p = u._replace(
        contrast=u.contrast._replace(weight=jnp.float32(0.0)),
        histogram=u.histogram._replace(sigma=jnp.float32(1.0)),
        motion=u.motion._replace(tau=jnp.asarray(THESIS_TAU, jnp.float32)),
    )
    s, k = run.seeds, run.keys
    one_part = dataclasses.replace(hist100, parts=1, ring_margin=0.0)
    res["likelihood_ablation"] = {
        "thesis (1 histogram, sigma=1, thesis tau)": mean_over(WALKING, s, k, thesis_cfg, thesis_p)[
            0
        ],
        "1 histogram, no contrast, our sigma/tau": mean_over(WALKING, s, k, one_part, no_contrast)[
            0
        ],
        "2 parts, no contrast": mean_over(
            WALKING, s, k, dataclasses.replace(hist100, ring_margin=0.0), no_contrast
        )[0],
    }
    hist_mean, hist_per = mean_over(WALKING, s, k, hist100, run.params)
    res["likelihood_ablation"]["2 parts + contrast (histogram only)"] = hist_mean
    res["likelihood_ablation"]["ours (default: + layout, template update, unseen neutral)"] = res[
        "table_3_1"
    ]["100"]
    # The histogram-only walking runs, which ``likelihood_terms`` reuses (same config, seeds).
    res["histogram_only_per_scenario"] = hist_per
    print(f"ablation: {res['likelihood_ablation']}", flush=True)
    run.save()


def _part_scenes(res: dict, run: _Run) -> None:
    """The distractor, light-switch and dark-clothes scenes at N = 100, and OTB Crossing."""
    n100 = dataclasses.replace(run.base, n_particles=100)
    res["extra_scenarios"] = mean_over(EXTRA, run.seeds, run.keys, n100, run.params)[1]
    res["crossing"] = crossing(100, run.crossing_keys, run.base, run.params)
    print(f"crossing: {res['crossing']}", flush=True)
    run.save()


def _part_terms(res: dict, run: _Run) -> None:
    """The default against each of its real-video terms taken away and the alternatives:
    walking, the look-alike scenes and Crossing at N = 100."""
    res["likelihood_terms"] = {}
    for label, (cfg, p) in likelihood_term_variants(run.base, run.params).items():
        cfg100 = dataclasses.replace(cfg, n_particles=100)
        if label == "default":
            per, cross = res["per_scenario_n100"], res["crossing"]
            look = {n: res["extra_scenarios"][n] for n in LOOKALIKE}
        else:
            per = (
                res["histogram_only_per_scenario"]
                if label == HISTOGRAM_ONLY
                else mean_over(WALKING, run.seeds, run.keys, cfg100, p)[1]
            )
            cross = crossing(100, run.crossing_keys, cfg, p)
            look = mean_over(LOOKALIKE, run.seeds, run.keys, cfg100, p)[1]
        res["likelihood_terms"][label] = {
            "walking_mean": float(np.mean(list(per.values()))),
            "walking_min": float(min(per.values())),
            "per_scenario": per,
            "lookalike": look,
            "crossing": cross,
        }
        print(f"terms {label}: {res['likelihood_terms'][label]}", flush=True)
        run.save()


#: The run's parts in order: name -> (function, the parts whose results it reads).
PARTS = {
    "particles": (_part_particles, ()),
    "thesis_model": (_part_thesis_model, ()),
    "models": (_part_models, ("particles",)),
    "sampling": (_part_sampling, ()),
    "sigma": (_part_sigma, ("particles",)),
    "ablation": (_part_ablation, ("particles",)),
    "scenes": (_part_scenes, ()),
    "terms": (_part_terms, ("particles", "ablation", "scenes")),
}


class _Run(NamedTuple):
    """What every part reads: the seeds, the configs and the writer of the results."""

    seeds: range
    keys: int
    ns: tuple
    quick: bool
    base: ColourConfig
    params: object
    undamped: object
    crossing_keys: int
    save: Callable[[], None]


def _meta(seeds, keys: int, base: ColourConfig, params) -> dict:
    return {
        "scene_seeds": len(seeds),
        "filter_seeds": keys,
        "walking_scenarios": list(WALKING),
        "config": {k: str(v) for k, v in dataclasses.asdict(base).items()},
        "params": {
            k: np.asarray(pp.get(params, path)).round(4).tolist() for k, path in PARAM_KEYS.items()
        },
        "jax": jax.__version__,
        "note": (
            f"Success rate (%, IoU >= 0.5) averaged over {len(seeds)} scene seeds x {keys} "
            f"filter seeds per scenario; walking scenarios: {', '.join(WALKING)}."
        ),
        "parts": {},
        "complete": False,
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene-seeds", type=int, default=3)
    ap.add_argument("--keys", type=int, default=3, help="filter seeds per scene")
    ap.add_argument("--quick", action="store_true", help="one scene, one key, fewer rows")
    ap.add_argument(
        "--part",
        action="append",
        choices=list(PARTS),
        help="run only these parts (repeatable); the others are kept from the JSON at --out",
    )
    ap.add_argument("--out", default=str(RESULTS / "colour_tables.json"))
    ap.add_argument(
        "--figure-only",
        action="store_true",
        help="redraw the figure from the JSON at --out (re-running Crossing for missing curves)",
    )
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.figure_only:
        res = json.loads(out.read_text())
        add_crossing_curves(res)
        out.write_text(json.dumps(res, indent=2) + "\n")
        figure(res, out.with_suffix(".png"))
        print(f"wrote {out.with_suffix('.png')}")
        return res
    seeds = range(1 if args.quick else args.scene_seeds)
    keys = 1 if args.quick else args.keys
    base = ColourConfig()
    params = default_colour_params()
    meta = _meta(seeds, keys, base, params)
    res: dict = {"meta": meta}
    if args.part:
        res = _kept_parts(out, meta, args.part)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    part_name = ""

    def save():
        """Write what the run has so far: an interrupted run keeps its finished tables."""
        res["meta"]["parts"][part_name] = {
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "host": host.describe(),
            "seconds": round(time.time() - t0),
        }
        res["meta"]["complete"] = set(res["meta"]["parts"]) == set(PARTS)
        out.write_text(json.dumps(res, indent=2) + "\n")
        out.with_suffix(".md").write_text(markdown(res))
        figure(res, out.with_suffix(".png"))
        # Drop compiled runners between tables: a whole run compiles dozens of
        # configs, and with every executable kept LLVM runs out of memory.
        _runner.cache_clear()
        jax.clear_caches()

    run = _Run(
        seeds=seeds,
        keys=keys,
        ns=(20, 100) if args.quick else (20, 40, 60, 80, 100, 120, 140, 160),
        quick=args.quick,
        base=base,
        params=params,
        undamped=pp.replace(params, "motion.size_velocity_decay", jnp.float32(1.0)),
        crossing_keys=1 if args.quick else 5,
        save=save,
    )
    for name, (part, _) in PARTS.items():
        if args.part and name not in args.part:
            continue
        part_name, t0 = name, time.time()
        res["meta"]["parts"].pop(name, None)
        part(res, run)
    print(markdown(res))
    return res


def _kept_parts(out: Path, meta: dict, parts: list[str]) -> dict:
    """The results at ``out`` to run ``parts`` on. Results of other seeds, another config or
    other parameters are dropped (with a line saying so); a part whose inputs are missing
    is a clear error."""
    res = json.loads(out.read_text()) if out.exists() else {}
    old = res.get("meta", {})
    keys = ("scene_seeds", "filter_seeds", "config", "params")
    stale = [k for k in keys if old.get(k) != meta[k]]
    if stale:
        if res:
            print(f"{out}: not this run's {', '.join(stale)}; its tables are dropped")
        res, old = {}, {}
    res["meta"] = {**meta, "parts": old.get("parts", {})}
    for name in parts:
        missing = [d for d in PARTS[name][1] if d not in res["meta"]["parts"] and d not in parts]
        if missing:
            raise SystemExit(f"{out}: part {name} reads {', '.join(missing)}, not yet run")
    return res


if __name__ == "__main__":
    main()
