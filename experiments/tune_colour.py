"""Gradient tuning of the colour layer's likelihood with optax (SPEC C7), held-out check.

The study runs on the histogram-only model (``ColourConfig.histogram_only()``) with the
library's default parameters ("defaults" below).

Tunes ``histogram.sigma``, ``contrast.weight`` and ``aspect.sigma``
(``cpf_jax.tuning.tune``: DIoU loss, Adam on the unconstrained values, the Scibior-Wood
gradient through resampling) on the *training* scenes -- the six walking scenarios with
scene seeds 100-101, the first 60 frames each, one fresh filter seed per sequence and
step -- from two starting points:

* ``thesis``: close to the thesis's likelihood: its hand-set sigma = 1 (nearly flat,
  see the colour module's docstring) and a weak colour-contrast term (weight 5 instead
  of 28; the thesis has none);
* ``defaults``: the library's hand-set defaults (sigma 0.15).

Early stopping: every 5 steps the loss on validation scenes (the same scenarios with
scene seeds 102-103, one fixed filter seed) is computed, and the result is the
parameters with the lowest validation loss (the start included).

Each result is checked on held-out data: the walking scenarios with the evaluation
scene seeds of ``colour_tables.py`` (0, 1, 2; full length), 3 filter seeds, N = 100,
and OTB Crossing (5 seeds) when ``../shared/data`` is there. Writes
``experiments/results/tune_colour.json`` and ``tune_colour.md`` (the loss per step,
the values before and after, held-out success rates; the parameters under their
``KEYS``).

    python experiments/tune_colour.py [--steps 40] [--lr 0.2] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import optax

sys.path.insert(0, str(Path(__file__).resolve().parent))
import colour_tables as ct  # noqa: E402

from cpf_jax import charts, tuning  # noqa: E402
from cpf_jax import params as pp  # noqa: E402
from cpf_jax.colour import (  # noqa: E402
    COLOUR_PROPS,
    ColourConfig,
    build_colour_filter,
    default_colour_params,
)
from cpf_jax.synthetic import make_sequence  # noqa: E402

NAMES = ("histogram.sigma", "contrast.weight", "aspect.sigma")
#: Each tuned parameter's key in the results (JSON, Markdown).
KEYS = {
    "histogram.sigma": "sigma",
    "contrast.weight": "contrast_weight",
    "aspect.sigma": "aspect_sigma",
}
TRAIN_SEEDS = (100, 101)
VALIDATION_SEEDS = (102, 103)  # early stopping: the parameters with the lowest loss on these
TRAIN_FRAMES = 60
EVAL_SEEDS = (0, 1, 2)


def held_out(config: ColourConfig, params, seeds, keys: int) -> dict:
    mean, per = ct.mean_over(ct.WALKING, seeds, keys, config, params)
    out = {"walking_mean": mean, "walking_min": min(per.values()), "per_scenario": per}
    cross = ct.crossing(config.n_particles, 5, config, params)
    if cross is not None:
        out["crossing"] = {"success_rate": cross["success_rate"], "auc": cross["auc"]}
    return out


def _values(params) -> dict:
    return {KEYS[n]: float(pp.get(params, n)) for n in NAMES}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lr", type=float, default=0.2)
    ap.add_argument("--quick", action="store_true", help="2 scenes, 5 steps, 1 held-out seed")
    ap.add_argument("--out", default=str(ct.RESULTS / "tune_colour.json"))
    ap.add_argument("--figure-only", action="store_true", help="redraw the figure from --out")
    args = ap.parse_args()
    if args.figure_only:
        redraw_figure(args.out, TITLE)
        return

    names = ct.WALKING[:2] if args.quick else ct.WALKING
    steps = 5 if args.quick else args.steps
    eval_seeds = EVAL_SEEDS[:1] if args.quick else EVAL_SEEDS
    eval_keys = 1 if args.quick else 3
    seqs = [make_sequence(n, seed=s, n_frames=TRAIN_FRAMES) for n in names for s in TRAIN_SEEDS]
    data = tuning.stack_sequences(seqs)
    validation = tuning.stack_sequences(
        [make_sequence(n, seed=s, n_frames=TRAIN_FRAMES) for n in names for s in VALIDATION_SEEDS]
    )
    # The histogram-only model (ColourConfig.histogram_only): the tuned parameters are
    # its likelihood's. Tuning the default's layout weight is not part of this study.
    config = ct._window_config(ColourConfig(n_particles=100).histogram_only(), ct.WALKING[0])
    run = tuning.runner(build_colour_filter(config))
    loss = jax.jit(tuning.make_loss(run, COLOUR_PROPS))
    fixed_key = jax.random.PRNGKey(12345)  # one key for before / after training losses

    defaults = default_colour_params()
    starts = {
        "thesis": defaults._replace(
            histogram=defaults.histogram._replace(sigma=jnp.float32(1.0)),
            contrast=defaults.contrast._replace(weight=jnp.float32(5.0)),
        ),
        "defaults": defaults,
    }
    res = {
        "names": [KEYS[n] for n in NAMES],
        "train": {
            "scenes": list(names),
            "seeds": list(TRAIN_SEEDS),
            "validation_seeds": list(VALIDATION_SEEDS),
            "frames": TRAIN_FRAMES,
        },
        "held_out": {"seeds": list(eval_seeds), "keys": eval_keys, "n_particles": 100},
        "optimizer": f"adam({args.lr})",
        "steps": steps,
        "runs": {},
    }
    for label, p0 in starts.items():
        t0 = time.perf_counter()

        result = tuning.tune(
            run,
            p0,
            COLOUR_PROPS,
            data,
            NAMES,
            optimizer=optax.adam(args.lr),
            steps=steps,
            key=jax.random.PRNGKey(0),
            callback=tuning.progress(label, NAMES),
            validation=validation,
            validate_every=5,
        )
        seconds = time.perf_counter() - t0

        def train_loss(p):
            free = tuning.unconstrained(p, COLOUR_PROPS, NAMES)
            return float(loss(free, p, fixed_key, data))

        run_res = {
            "before": _values(p0),
            "after": _values(result.params),
            "train_loss_before": train_loss(p0),
            "train_loss_after": train_loss(result.params),
            "tune_seconds": seconds,
            "skipped_steps": sum(e["skipped"] for e in result.history),
            "history": [
                {KEYS.get(k, k): e[k] for k in ("step", "loss", "validation", *NAMES) if k in e}
                for e in result.history
            ],
        }
        for when, p in (("held_out_before", p0), ("held_out_after", result.params)):
            run_res[when] = held_out(config, p, eval_seeds, eval_keys)
            print(label, when, json.dumps(run_res[when]), flush=True)
        res["runs"][label] = run_res
        # Written after each start: an interrupted run keeps the finished ones.
        write_results(res, args.out, _markdown(res), TITLE)


TITLE = "Gradient tuning of the colour likelihood (training scenes)"


def write_results(res: dict, out: str | Path, markdown: str, title: str) -> None:
    """A tuning experiment's JSON, Markdown and loss-curve figure (also ``tune_rgbd``)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    out.with_suffix(".md").write_text(markdown)
    figure(res, out.with_suffix(".png"), title)
    print(f"wrote {out}, {out.with_suffix('.md')} and {out.with_suffix('.png')}", flush=True)


def figure(res: dict, path: Path, title: str) -> None:
    """Loss curves of every finished start (``tuning.history_chart``)."""
    runs = {label: r["history"] for label, r in res["runs"].items()}
    charts.save_png(tuning.history_chart(runs, title=title), path)


def redraw_figure(out: str | Path, title: str) -> None:
    """``--figure-only``: the figure again from the JSON at ``out``."""
    out = Path(out)
    figure(json.loads(out.read_text()), out.with_suffix(".png"), title)
    print(f"wrote {out.with_suffix('.png')}")


def _markdown(res: dict) -> str:
    lines = [
        "# Gradient tuning of the colour likelihood (optax, held-out check)",
        "",
        f"Tuned: {', '.join(res['names'])}; {res['optimizer']}, {res['steps']} steps, DIoU loss; "
        f"training scenes {', '.join(res['train']['scenes'])} with scene seeds "
        f"{res['train']['seeds']} (first {res['train']['frames']} frames), early stopping on "
        f"scene seeds {res['train']['validation_seeds']}. Held out: the "
        f"walking scenarios with scene seeds {res['held_out']['seeds']} x "
        f"{res['held_out']['keys']} filter seeds, full length, N = 100; OTB Crossing (5 seeds).",
        "",
        "| start | | " + " | ".join(res["names"]) + " | train loss | walking mean | "
        "walking min | Crossing SR | Crossing AUC |",
        "|---|---|" + "---:|" * (len(res["names"]) + 5),
    ]
    for label, r in res["runs"].items():
        for when in ("before", "after"):
            h = r[f"held_out_{when}"]
            c = h.get("crossing", {})
            vals = " | ".join(f"{r[when][n]:.3f}" for n in res["names"])
            lines.append(
                f"| {label} | {when} | {vals} | {r[f'train_loss_{when}']:.4f} | "
                f"{h['walking_mean']:.1f} | {h['walking_min']:.1f} | "
                f"{c.get('success_rate', float('nan')):.1f} | {c.get('auc', float('nan')):.1f} |"
            )
    lines += ["", "Loss per step (stochastic: a fresh filter seed per sequence and step):", ""]
    for label, r in res["runs"].items():
        losses = ", ".join(f"{e['loss']:.3f}" for e in r["history"])
        lines.append(f"- {label} ({r['tune_seconds']:.0f} s): {losses}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
