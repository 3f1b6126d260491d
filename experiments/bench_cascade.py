"""Benchmark: one jitted step of the whole cascade (thesis ch. 5) on 512 x 424 RGB-D.

    python experiments/bench_cascade.py           # -> results/bench_cascade.{json,md}
    python experiments/bench_cascade.py --quick   # few repeats (smoke test), writes nothing

The scene is ``walk_towards`` (seed 0, frame 20, the person at 2.7 m), as
``cpf-track walk_towards --model grid-occlusion --points joints --background empty``
runs it: layer 1 the grid-occlusion RGB-D filter (library defaults, window from the
ground-truth box) at N = 150 and N = 1,000, layer 2 head, two hands and two feet at 100
particles each inside the empty room's foreground (``PointConfig.with_foreground``).

Timed, every one a median of repeated calls in this process:

* the cascade: one jitted ``build_cascade(config).step``;
* the two layers jitted apart (layer 1's ``step``; layer 2's ``step`` on layer 1's box),
  whose sum against the cascade shows what one program gains or loses;
* layer 1's pieces, each jitted alone: observe (foreground, bins, tables), propose, score
  (cell terms and the flags' marginal likelihood), and the rest of its step;
* layer 2 stage by stage, each jitted alone on the previous stage's outputs:
  segmentation (foreground mask, hole filling, floor, components), surface graph (and
  normals), geodesic distances, spin images (the spin term of eq. 4.7 at every particle),
  point weights (geodesic and depth terms), resampling; "other" is layer 2 less these
  (prediction, recovery, estimates, 3D points);
* the colour layer alone (``ColourConfig`` defaults) at the same N, for ``colour_only_fps``;
* the per-stage baselines of the other benchmarks: ``bench_rgbd``'s OpenCV + NumPy
  per-cell loop for layer 1, ``bench_depth``'s SciPy Dijkstra and NumPy spin-image loop
  (at all 500 particle pixels) for layer 2.

Like ``bench_rgbd.py`` it runs with ``cpu_tuning.tune_malloc()`` and the XLA flags of
``cpu_tuning.xla_cpu_flags(library_fusions=False)`` (``--no-tune-malloc``,
``--no-tune-xla``), and times the cascade again in a fresh process without either: the
path a plain ``jax.jit(filt.step)`` of the Python API takes.
"""

from __future__ import annotations

import argparse
import os
import sys

import host  # same folder: the CPU, its switches, fresh processes


def _parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    host.add_cpu_switch_args(p)
    p.add_argument("--quick", action="store_true", help="few repeats, writes nothing")
    p.add_argument("--repeats", type=int, default=30, help="timed calls per measurement")
    p.add_argument("--out", default=None, help="results path stem (default results/bench_cascade)")
    p.add_argument(
        "--cascade-only", action="store_true", help="time the cascade alone, print JSON (internal)"
    )
    return p.parse_args(argv)


ARGS = _parse_args() if __name__ == "__main__" else _parse_args([])
XLA_FLAGS_GIVEN = os.environ.get("XLA_FLAGS", "")
MALLOC_TUNED = False
if __name__ == "__main__":  # before JAX allocates and reads XLA_FLAGS: see cpf_jax.cpu_tuning
    MALLOC_TUNED, XLA_FLAGS_GIVEN = host.cpu_switches(ARGS.tune_malloc, ARGS.tune_xla)

import datetime  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import bench_colour  # noqa: E402  (same folder: the timing loop)
import bench_depth  # noqa: E402  (same folder: the layer-2 baselines)
import bench_rgbd  # noqa: E402  (same folder: the layer-1 baseline)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cpf_jax.cascade import (  # noqa: E402
    CascadeConfig,
    build_box_filter,
    build_cascade,
    default_cascade_params,
    layer2_frame,
)
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params  # noqa: E402
from cpf_jax.filter import Context  # noqa: E402
from cpf_jax.kernels.background import Background  # noqa: E402
from cpf_jax.points import BODY_POINTS, PointConfig  # noqa: E402
from cpf_jax.points import body as pb  # noqa: E402
from cpf_jax.points import filter as pf  # noqa: E402
from cpf_jax.rgbd import RGBDConfig  # noqa: E402
from cpf_jax.rgbd.depth import depth_template_predict  # noqa: E402
from cpf_jax.rgbd.filter import score_particles, unseen_scene  # noqa: E402
from cpf_jax.rgbd.observe import observe as rgbd_observe  # noqa: E402
from cpf_jax.rgbd.proposal import propose as rgbd_propose  # noqa: E402
from cpf_jax.synthetic import make_sequence  # noqa: E402
from cpf_jax.types import Frame  # noqa: E402

N_BOX = (150, 1_000)
FRAME_INDEX = 20
WARMUP = 10
TARGET_FPS = 30.0
STAGES = (
    "segmentation",
    "surface_graph",
    "geodesic",
    "spin_images",
    "point_weights",
    "resampling",
)


class Scene:
    """The frame pair, background, box and body points the benchmark runs on."""

    def __init__(self):
        t = FRAME_INDEX
        self.seq = make_sequence("walk_towards", seed=0, n_frames=t + 1)
        seq = self.seq
        self.background = Background(
            jnp.asarray(seq.meta["background_colour"], jnp.float32),
            jnp.asarray(seq.meta["background_depth"], jnp.float32),
        )
        self.first = Frame(jnp.asarray(seq.colour[t - 1]), jnp.asarray(seq.depth[t - 1]))
        self.frame = Frame(jnp.asarray(seq.colour[t]), jnp.asarray(seq.depth[t]))
        self.box = np.asarray(seq.boxes[t - 1], np.float32)
        idx = [seq.joint_names.index(name) for name in BODY_POINTS]
        self.points = jnp.asarray(seq.joints2d[t - 1, idx], jnp.float32)
        self.frame_hw = seq.colour.shape[1:3]

    def rgbd_tuple(self):
        """The ``(seq, background, first, frame, box)`` of ``bench_rgbd``'s baseline."""
        return self.seq, self.background, self.first, self.frame, self.box


def cascade_config(scene: Scene, n: int) -> CascadeConfig:
    """The CLI's cascade for this scene (``cli.model``): grid-occlusion, foreground body."""
    box = RGBDConfig(variant="grid-occlusion", n_particles=n).with_window(
        (float(scene.box[2]), float(scene.box[3])), scene.frame_hw
    )
    return CascadeConfig(box=box, points=PointConfig().with_foreground(), foreground=True)


def median_ms(fn, *args, repeats: int) -> float:
    """Median wall time (ms) of ``fn(*args)`` after three untimed calls."""
    for _ in range(3):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def time_filter(filt, params, scene: Scene, context: Context, repeats: int):
    """``(ms, windowed share)`` of one jitted ``filt.step``, its state carried from step to
    step (``bench_colour.timed_steps``); the share is that of the timed steps whose layer 1
    read its histograms from the static window (the others ran the exact whole-frame
    fallback, slower)."""
    key = jax.random.key(0)
    init = jax.jit(lambda k, f, b: filt.init(params, k, f, b, context))
    step = jax.jit(lambda k, s, f: filt.step(params, k, s, f))
    state = init(key, scene.first, jnp.asarray(scene.box))
    times, windowed, _ = bench_colour.timed_steps(step, state, scene.frame, key, repeats, WARMUP)
    return float(np.median(times) * 1e3), windowed


def time_cascade(scene: Scene, n: int, repeats: int) -> tuple[float, object]:
    config = cascade_config(scene, n)
    context = Context(background=scene.background, points=scene.points)
    return time_filter(
        build_cascade(config), default_cascade_params(config), scene, context, repeats
    )


def layer2_inputs(scene: Scene, config: CascadeConfig, params):
    """``(layer-2 state, layer 1's box, layer 1's background)`` one cascade step sees."""
    filt = build_cascade(config)
    key = jax.random.key(0)
    context = Context(background=scene.background, points=scene.points)
    state = jax.jit(lambda k, f, b: filt.init(params, k, f, b, context))(
        key, scene.first, jnp.asarray(scene.box)
    )
    _, info = jax.jit(lambda k, s, f: filt.step(params, k, s, f))(key, state, scene.frame)
    return state.points, info.box_used, info.layer1


def time_layer1(scene: Scene, config: CascadeConfig, repeats: int) -> dict:
    """Layer 1's step jitted alone from the cascade's initial state, and its first pieces
    each jitted alone on the state after the warm-up steps: observe (the frame's scene,
    foreground, bins), propose, score (cell terms and the flags' marginal likelihood);
    "other" is the step less these (estimate, extent, template updates, resampling)."""
    params = default_cascade_params(config)
    cfg, p = config.box, params.box
    filt = build_cascade(config)
    key = jax.random.key(0)
    context = Context(background=scene.background, points=scene.points)
    state = jax.jit(lambda k, f, b: filt.init(params, k, f, b, context))(
        key, scene.first, jnp.asarray(scene.box)
    ).box
    box_filter = build_box_filter(cfg)
    ms, windowed = time_filter(box_filter, p, scene, Context(background=scene.background), repeats)
    out = {"layer1_ms": ms, "layer1_windowed": windowed}
    # The pieces see the state the timed steps see: the cloud after the warm-up steps is
    # wider than the initial one and counts on a larger window.
    step = jax.jit(lambda k, s_, f: box_filter.step(p, k, s_, f))
    for i in range(WARMUP):
        state, _ = step(jax.random.fold_in(key, i), state, scene.frame)
    keys = tuple(jax.random.split(key, 4))
    s = state._replace(depth=depth_template_predict(cfg, state.depth))

    def frame_observation(f, s_):
        bg = unseen_scene(cfg, s_.background, f, s_.estimate, s_.depth.depth)
        return rgbd_observe(cfg, p.foreground, f, bg)

    observe = jax.jit(frame_observation)
    obs = observe(scene.frame, s)
    propose = jax.jit(lambda s_, o, d: rgbd_propose(cfg, p, keys, s_, o, d))
    proposal = propose(s, obs, scene.frame.depth)
    score = jax.jit(lambda s_, o, pr: score_particles(cfg, p, key, s_, o, pr))
    stages = {
        "observe": median_ms(observe, scene.frame, s, repeats=repeats),
        "propose": median_ms(propose, s, obs, scene.frame.depth, repeats=repeats),
        "score": median_ms(score, s, obs, proposal, repeats=repeats),
    }
    stages["other"] = out["layer1_ms"] - sum(stages.values())
    out["stages"] = stages
    return out


def time_layer2(scene: Scene, config: CascadeConfig, repeats: int) -> dict:
    """Layer 2's step jitted alone and stage by stage (module docstring), and the inputs
    of the baselines."""
    params = default_cascade_params(config)
    cfg, pp = config.points, params.points
    state, box, _ = layer2_inputs(scene, config, params)
    bg = scene.background  # layer 1 has not updated it in one frame
    key = jax.random.key(1)
    point_filter = pf.build_point_filter(cfg)

    @jax.jit
    def whole(k, s, f, b):
        return point_filter.step(pp, k, s, layer2_frame(config, f, b, bg))

    out = {"layer2_ms": median_ms(whole, key, state, scene.frame, box, repeats=repeats)}
    segment = jax.jit(lambda f, b: pb.segment_body(cfg, *layer2_frame(config, f, b, bg)))
    surface = jax.jit(lambda sg: pb.body_surface_graph(cfg, sg))
    geodesic = jax.jit(lambda sg, sf: pb.body_geodesics(cfg, sg, sf))
    seg = segment(scene.frame, box)
    surf = surface(seg)
    geo = geodesic(seg, surf)
    bm = pb.assemble_body(seg, surf, *geo)
    keys = tuple(jax.random.split(key, 3))
    xy, vel, hidden, _, _, z_pred = pf.point_predict(cfg, pp, keys, state, box)

    @jax.jit
    def pixels(bm_, xy_):
        rc, inside = pb.window_pixels(bm_, xy_, cfg.window)
        return rc, inside & bm_.body[rc[..., 0], rc[..., 1]]

    rc, on = pixels(bm, xy)
    spin = jax.jit(lambda bm_, s, rc_, on_: pf.spin_term(cfg, pp.weights, bm_, s, rc_, on_))

    @jax.jit
    def weights(bm_, s, rc_, on_, z):
        lw = pf.geodesic_term(pp.weights, bm_, s, rc_) + pf.depth_term(pp.weights, bm_, rc_, z)
        return jnp.where(on_, lw, -jnp.inf)

    lw, _, _ = jax.jit(
        lambda bm_, s, p_, h, z: pf.point_weights(cfg, pp.weights, bm_, s, p_, h, z)
    )(bm, state, xy, hidden, z_pred)
    lw = jax.vmap(lambda w: w - jax.nn.logsumexp(w))(jnp.where(jnp.isfinite(lw), lw, -30.0))
    particles = jnp.concatenate([xy, vel], -1)
    recovered = jnp.zeros(lw.shape[0], bool)
    resample = jax.jit(lambda k, w, p_, r: pf.point_resample(cfg, k, w, p_, r))
    out["stages"] = {
        "segmentation": median_ms(segment, scene.frame, box, repeats=repeats),
        "surface_graph": median_ms(surface, seg, repeats=repeats),
        "geodesic": median_ms(geodesic, seg, surf, repeats=repeats),
        "spin_images": median_ms(spin, bm, state, rc, on, repeats=repeats),
        "point_weights": median_ms(weights, bm, state, rc, on, z_pred, repeats=repeats),
        "resampling": median_ms(resample, key, lw, particles, recovered, repeats=repeats),
    }
    out["stages"]["other"] = out["layer2_ms"] - sum(out["stages"].values())
    out["body"], out["tscale"] = bm, seg.tscale
    out["queries"] = np.asarray(rc).reshape(-1, 2)
    return out


def time_colour_only(scene: Scene, n: int, repeats: int) -> float:
    """The colour layer alone (library defaults) at ``n`` particles."""
    config = ColourConfig(n_particles=n).with_window(
        (float(scene.box[2]), float(scene.box[3])), scene.frame_hw
    )
    filt = build_colour_filter(config)
    return time_filter(filt, default_colour_params(), scene, Context(), repeats)[0]


def time_baselines(scene: Scene, layer2: dict, config: CascadeConfig, repeats: int) -> dict:
    """The per-stage baselines of ``bench_rgbd`` and ``bench_depth`` on the same frame."""
    bm = layer2["body"]
    cfg = config.points
    points = np.asarray(bm.points, np.float64)
    body = np.asarray(bm.body)
    src = np.asarray(bm.reference_pixels)[0]
    tscale = np.broadcast_to(np.asarray(layer2["tscale"]), body.shape)
    max_dist = float(cfg.surface_max_dist_mm * np.median(tscale[body]))
    source = int(src[0] * cfg.window[1] + src[1])

    def geodesic():
        return bench_depth.scipy_geodesic(points, body, source, max_dist)

    def spin():
        return bench_depth.spin_numpy(
            np.asarray(bm.points),
            np.asarray(bm.normals),
            np.asarray(bm.spin_valid),
            layer2["queries"],
            cfg.spin_bin_factor * float(bm.mesh_resolution),
            cfg.spin_width,
            cfg.support_angle_deg,
        )

    few = max(2, repeats // 10)
    out = {
        "geodesic_scipy_ms": median_ms(geodesic, repeats=few),
        "spin_numpy_ms": median_ms(spin, repeats=few),
    }
    for n in N_BOX:
        out[f"layer1_opencv_ms_{n}"] = bench_rgbd.time_baseline(n, scene.rgbd_tuple(), few)
    return out


def untuned_cascade(repeats: int) -> dict | None:
    """``{N: ms}`` of the cascade in a fresh process without ``tune_malloc`` or the XLA flags
    (both process-wide): a plain ``jax.jit(filt.step)`` of the Python API."""
    args = ["--cascade-only", "--no-tune-malloc", "--no-tune-xla", f"--repeats={repeats}"]
    return host.fresh_process_json(__file__, args, XLA_FLAGS_GIVEN)


def _row(n: int, r: dict) -> str:
    untuned = r.get("cascade_ms_untuned")
    plain = f"{untuned:.1f} ({1e3 / untuned:.1f})" if untuned else "-"
    return (
        f"| {n:,} | {r['cascade_ms']:.1f} ({r['cascade_fps']:.1f}, "
        f"{100 * r['cascade_windowed']:.0f} %) | {plain} | "
        f"{r['layer1_ms']:.1f} ({100 * r['layer1_windowed']:.0f} %) | {r['layer2_ms']:.1f} | "
        f"{r['layers_sum_ms']:.1f} | "
        f"{r['colour_only_ms']:.1f} ({r['colour_only_fps']:.0f}) | {r['baseline_ms']:.0f} | "
        f"{r['baseline_ms'] / r['cascade_ms']:.0f}x |"
    )


def _markdown(results: dict) -> str:
    meta = results["meta"]
    lines = [
        "# Whole-cascade step benchmark",
        "",
        f"{meta['frame']}, {meta['cpu']} ({meta['cores']} cores), jax {meta['jax']}, "
        f"{meta['date']}; load average before / after: {meta['load_before']} / "
        f"{meta['load_after']}; malloc tuned: {meta['malloc_tuned']}; XLA_FLAGS: "
        f"`{meta['xla_flags'] or '(unset)'}`. Median of {meta['repeats']} calls.",
        f"Command: `{meta['command']}`",
        "",
        "ms per frame (frames/s; for the cascade and layer 1 the share of the timed steps "
        "whose layer 1 read its window, the others ran its exact whole-frame fallback). "
        "Cascade: one jitted step, layer 1 grid-occlusion at N box "
        "particles, layer 2 five body points at 100 particles; plain jit: the same step in a "
        "fresh process without the CPU switches; layers apart: layer 1 and layer 2 each "
        "jitted alone, summed; baseline: OpenCV + NumPy per-cell loop (layer 1) + SciPy "
        "Dijkstra + NumPy spin-image loop (layer 2), which leave out segmentation, "
        "surface graph, weights and resampling.",
        "",
        "| N | cascade | plain jit | layer 1 | layer 2 | layers apart | colour layer alone "
        "| baseline | speed-up |",
        "|---:|" + "---:|" * 8,
    ]
    for n in N_BOX:
        lines.append(_row(n, results["by_n"][str(n)]))
    stages = results["breakdown"]
    lines += [
        "",
        f"Breakdown at N = {N_BOX[0]} (each stage jitted alone on the previous one's output; "
        "'other' is layer 2 less its stages: prediction, recovery, estimates, 3D points):",
        "",
        "| stage | ms | share of the layers' sum |",
        "|---|---:|---:|",
    ]
    total = sum(stages.values())
    for name, ms in stages.items():
        lines.append(f"| {name.replace('_', ' ')} | {ms:.2f} | {100 * ms / total:.0f} % |")
    lines += [
        "",
        "Layer 1's pieces (each jitted alone on the state after the warm-up steps; 'other': "
        "estimate, extent, template updates, resampling):",
        "",
        "| N | observe (scene, foreground, bins) | propose | score (cells, flags) | other "
        "| layer 1 |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for n in N_BOX:
        r = results["by_n"][str(n)]
        st = r["layer1_stages"]
        lines.append(
            f"| {n:,} | {st['observe']:.1f} | {st['propose']:.1f} | {st['score']:.1f} | "
            f"{st['other']:.1f} | {r['layer1_ms']:.1f} |"
        )
    base = results["baselines"]
    fps = results["cascade_fps"]
    gap = "reaches" if fps >= TARGET_FPS else "is short of"
    lines += [
        "",
        f"Target: {TARGET_FPS:.0f} frames/s on the AMD EPYC host; this run's cascade at N = "
        f"{N_BOX[0]} {gap} it at {fps:.1f} frames/s ({meta['cpu']}).",
        f"Layer-2 baselines: SciPy geodesic {base['geodesic_scipy_ms']:.1f} ms (ours "
        f"{stages['geodesic']:.1f}); NumPy spin images at {meta['queries']} particle pixels "
        f"{base['spin_numpy_ms']:.0f} ms (ours {stages['spin_images']:.1f}).",
    ]
    return "\n".join(lines) + "\n"


def main(args) -> dict:
    repeats = 5 if args.quick else args.repeats
    scene = Scene()
    if args.cascade_only:
        print(json.dumps({str(n): time_cascade(scene, n, repeats)[0] for n in N_BOX}))
        return {}
    load_before = os.getloadavg()
    layer2 = time_layer2(scene, cascade_config(scene, N_BOX[0]), repeats)
    baselines = time_baselines(scene, layer2, cascade_config(scene, N_BOX[0]), repeats)
    by_n = {}
    for n in N_BOX:
        config = cascade_config(scene, n)
        cascade_ms, windowed = time_cascade(scene, n, repeats)
        layer1 = time_layer1(scene, config, repeats)
        layer1_ms = layer1["layer1_ms"]
        colour_ms = time_colour_only(scene, n, repeats)
        baseline = baselines[f"layer1_opencv_ms_{n}"]
        baseline += baselines["geodesic_scipy_ms"] + baselines["spin_numpy_ms"]
        by_n[str(n)] = {
            "cascade_ms": cascade_ms,
            "cascade_fps": 1e3 / cascade_ms,
            "layer1_ms": layer1_ms,
            "layer2_ms": layer2["layer2_ms"],
            "layers_sum_ms": layer1_ms + layer2["layer2_ms"],
            "colour_only_ms": colour_ms,
            "colour_only_fps": 1e3 / colour_ms,
            "baseline_ms": baseline,
            "layer1_stages": layer1["stages"],
            "cascade_windowed": windowed,
            "layer1_windowed": layer1["layer1_windowed"],
        }
        shown = {k: v for k, v in by_n[str(n)].items() if k != "layer1_stages"}
        shown = {k: v for k, v in shown.items() if v is not None}
        print(f"N={n:,}: " + ", ".join(f"{k} {v:.2f}" for k, v in shown.items()), flush=True)
    untuned = None if args.quick else untuned_cascade(repeats)
    for n in N_BOX:
        by_n[str(n)]["cascade_ms_untuned"] = None if untuned is None else untuned[str(n)]
    head = by_n[str(N_BOX[0])]
    results = {
        **{k: head[k] for k in ("cascade_ms", "cascade_fps", "colour_only_fps")},
        **{k: head[k] for k in ("layer1_ms", "layer2_ms", "cascade_ms_untuned")},
        "breakdown": {"layer1": head["layer1_ms"], **layer2["stages"]},
        "by_n": by_n,
        "baselines": baselines,
        "meta": {
            "frame": f"512x424 walk_towards seed 0 frame {FRAME_INDEX}",
            "cpu": host.cpu_name(),
            "cores": os.cpu_count(),
            "jax": jax.__version__,
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "load_before": [round(v, 2) for v in load_before],
            "load_after": [round(v, 2) for v in os.getloadavg()],
            "malloc_tuned": MALLOC_TUNED,
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "repeats": repeats,
            "queries": int(layer2["queries"].shape[0]),
            "n_box": list(N_BOX),
            "command": "python " + " ".join(["experiments/bench_cascade.py"] + sys.argv[1:]),
        },
    }
    md = _markdown(results)
    print(md)
    if not args.quick or args.out:
        stem = Path(args.out) if args.out else Path(__file__).parent / "results" / "bench_cascade"
        stem.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
        stem.with_suffix(".md").write_text(md)
    return results


if __name__ == "__main__":
    main(ARGS)
