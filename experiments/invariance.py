"""Particle digests of every filter, to check that a refactor changes no number.

    python experiments/invariance.py --dump DIR            # every case's final state and infos
    python experiments/invariance.py --dump DIR colour_default_n10000   # some cases
    python experiments/invariance.py --compare OLD NEW     # bit-for-bit, leaf by leaf

Each case tracks a whole synthetic scenario (the colour layer at N = 10,000 and 100,000 on
a shorter one) and saves every leaf of the final state and of the stacked infos, named by
its pytree path, to ``DIR/<case>.npz``. ``--compare`` reports, per case, whether every leaf
is equal (NaN equal to NaN) and the largest difference of the ones that are not. Run the
dump on the tree before a change and on the tree after it (two checkouts), then compare.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax.cascade import CascadeConfig, build_box_filter, build_cascade, default_cascade_params
from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
from cpf_jax.filter import Context, track
from cpf_jax.io.synthetic import SyntheticSource
from cpf_jax.kernels.background import median_background
from cpf_jax.points import (
    BODY_POINTS,
    PointConfig,
    PointFrame,
    build_point_filter,
    default_point_params,
)
from cpf_jax.rgbd import RGBDConfig, default_rgbd_params
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame


def _leaves(prefix: str, tree) -> dict:
    return {
        prefix + jax.tree_util.keystr(k): np.asarray(x)
        for k, x in jax.tree_util.tree_flatten_with_path(tree)[0]
    }


def _background(seq, name: str, empty: bool):
    """The scene model a case tracks against: the empty room, or 25 of its frames."""
    if empty:
        e = SyntheticSource(seq, name).empty_background()
        return jax.jit(median_background)(e.colour[None], e.depth[None])
    idx = np.linspace(0, len(seq.colour) - 1, 25).astype(int)
    return jax.jit(median_background)(seq.colour[idx], seq.depth[idx])


def _windowed(config, seq, **kw):
    return config.with_window(
        tuple(float(v) for v in seq.boxes[0, 2:]), seq.colour.shape[1:3], **kw
    )


def _colour_cases(walk) -> dict:
    thesis = ColourConfig(
        n_particles=100,
        model="ar1",
        bins=(8, 8),
        parts=1,
        contrast=None,
        layout=None,
        template_update=False,
        aspect_prior=False,
        tau_height=None,
    )
    mixture = ColourConfig(
        n_particles=300,
        layout_feature="gradient",
        layout_mirror=True,
        contrast="mixture",
        estimator="robust",
        model="ar2",
    )
    cases = {
        "colour_default_n10000": (_windowed(ColourConfig(n_particles=10000), walk), 20),
        "colour_default_n100000": (_windowed(ColourConfig(n_particles=100000), walk), 8),
        "colour_default_n200": (_windowed(ColourConfig(n_particles=200), walk), None),
        "colour_histonly_n200": (
            _windowed(ColourConfig(n_particles=200).histogram_only(), walk),
            None,
        ),
        "colour_thesis_n100": (_windowed(thesis, walk), None),
        "colour_gradmirror_mixture_robust": (_windowed(mixture, walk), None),
        "colour_map_nowindow": (
            ColourConfig(n_particles=150, estimator="map", model="ar1_fixed", rng="jax"),
            40,
        ),
    }
    return {k: (v[0], default_colour_params(), v[1]) for k, v in cases.items()}


def _rgbd_cases(occ) -> dict:
    rgb = _windowed(ColourConfig(n_particles=300, model="ar1", hierarchical=True), occ, growth=1.5)
    configs = {
        "rgbd_gridocc": _windowed(RGBDConfig(variant="grid-occlusion", n_particles=300), occ),
        "rgbd_grid": _windowed(RGBDConfig(variant="grid", n_particles=300), occ),
        "rgbd_rgbd": _windowed(RGBDConfig(variant="rgbd", n_particles=300), occ),
        "rgbd_gridocc_fact_cells_bgupd": _windowed(
            RGBDConfig(
                n_particles=200,
                flag_transition="factorised",
                report="cells",
                background_update=True,
                grid=3,
            ),
            occ,
        ),
        "rgbd_gridocc_fixed_box_nowin": RGBDConfig(
            n_particles=200,
            model="ar1_fixed",
            report="box",
            body_term=False,
            box_term=False,
            border=0.0,
        ),
    }
    cases = {k: (c, default_rgbd_params(c)) for k, c in configs.items()}
    cases["rgbd_rgb"] = (rgb, default_colour_params())
    return cases


def _cascade_cases(tow) -> dict:
    rgb = _windowed(ColourConfig(n_particles=150, model="ar1", hierarchical=True), tow, growth=1.5)
    foreground = PointConfig().with_foreground()
    configs = {
        "cascade_gridocc": CascadeConfig(box=_windowed(RGBDConfig(n_particles=150), tow)),
        "cascade_rgb_report_fg": CascadeConfig(
            box=rgb, box_source="report", foreground=True, points=foreground
        ),
    }
    return {k: (c, default_cascade_params(c)) for k, c in configs.items()}


def _run(out: str, name: str, filt, params, frames, box, context) -> None:
    run = jax.jit(lambda k, f, b, c: track(filt, params, k, f, b, c))
    state, infos = run(jax.random.PRNGKey(3), frames, jnp.asarray(box, jnp.float32), context)
    np.savez(f"{out}/{name}.npz", **_leaves("state", state), **_leaves("info", infos))
    print(name, "saved", flush=True)


def dump(out: str, only: list[str]) -> None:
    """Track every case (or those named in ``only``) and save its leaves."""

    def wanted(name: str) -> bool:
        return not only or name in only

    walk = make_sequence("walk_across_medium", seed=0)
    for name, (config, params, t) in _colour_cases(walk).items():
        if wanted(name):
            _run(
                out,
                name,
                build_colour_filter(config),
                params,
                frames_of(walk, t),
                walk.boxes[0],
                None,
            )
    occ = make_sequence("occlusion_person", seed=0)
    context = Context(background=_background(occ, "occlusion_person", empty=False))
    for name, (config, params) in _rgbd_cases(occ).items():
        if wanted(name):
            filt = build_box_filter(config)
            _run(out, name, filt, params, frames_of(occ), occ.boxes[0], context)
    tow = make_sequence("walk_towards", seed=0)
    joints = [list(tow.joint_names).index(n) for n in BODY_POINTS]
    points = jnp.asarray(tow.joints2d[0, joints] + 0.5, jnp.float32)
    for weighting in ("spin", "geodesic", "combined"):
        name = f"points_{weighting}"
        if wanted(name):
            filt = build_point_filter(PointConfig(n_particles=100, weighting=weighting))
            frames = PointFrame(jnp.asarray(tow.depth), jnp.asarray(tow.boxes, jnp.float32))
            _run(
                out,
                name,
                filt,
                default_point_params(),
                frames,
                tow.boxes[0],
                Context(points=points),
            )
    context = Context(_background(tow, "walk_towards", empty=True), points)
    for name, (config, params) in _cascade_cases(tow).items():
        if wanted(name):
            _run(out, name, build_cascade(config), params, frames_of(tow), tow.boxes[0], context)


def frames_of(seq, t=None) -> Frame:
    """The sequence's frames (its first ``t``) as one ``Frame`` of ``[T, ...]`` arrays."""
    c, d = (seq.colour, seq.depth) if not t else (seq.colour[:t], seq.depth[:t])
    return Frame(jnp.asarray(c), jnp.asarray(d))


def compare(old_dir: str, new_dir: str) -> int:
    """Cases whose leaves differ (0: every case bit-identical)."""
    bad = 0
    for f in sorted(glob.glob(f"{old_dir}/*.npz")):
        case = os.path.basename(f)[:-4]
        new = f"{new_dir}/{case}.npz"
        if not os.path.exists(new):
            print(f"{case}: missing in {new_dir}")
            bad += 1
            continue
        a, b = np.load(f), np.load(new)
        messages = []
        for k in sorted(set(a.files) | set(b.files)):
            if k not in a.files or k not in b.files:
                messages.append(f"  {k}: only in {'new' if k in b.files else 'old'}")
            elif a[k].shape != b[k].shape:
                messages.append(f"  {k}: shape {a[k].shape} != {b[k].shape}")
            elif not np.array_equal(a[k], b[k], equal_nan=True):
                d = np.nanmax(np.abs(a[k].astype(np.float64) - b[k].astype(np.float64)))
                messages.append(f"  {k}: differs (largest difference {d:g})")
        print(f"{case}: {'bit-identical' if not messages else 'DIFFERENT'} ({len(a.files)} leaves)")
        print("\n".join(messages[:20])) if messages else None
        bad += bool(messages)
    print(f"{bad} case(s) differ")
    return bad


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--dump", metavar="DIR")
    p.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"))
    p.add_argument("cases", nargs="*", help="case names (default: all)")
    args = p.parse_args(argv)
    if args.compare:
        return int(compare(*args.compare) > 0)
    if not args.dump:
        p.error("give --dump DIR or --compare OLD NEW")
    os.makedirs(args.dump, exist_ok=True)
    dump(args.dump, args.cases)
    return 0


if __name__ == "__main__":
    sys.exit(main())
