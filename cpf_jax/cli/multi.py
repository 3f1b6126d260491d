"""``cpf-track --multi``: every person in a recording or a stream, with identities.

The driver is thin, as for one person: the inputs of :mod:`cpf_jax.cli.inputs` (frames
registered to colour, the background model, or with ``--background none`` each frame's
own scene; no start box), the multi-person tracker of
:mod:`cpf_jax.multi` jitted once, one ``step`` per frame, and each frame's people written
as they come: MOTChallenge lines (``--mot``), the Rerun log (each identity in its own
colour with its id, births, losses and deaths as text events). At the end a summary, and
the CLEAR MOT, IDF1 and HOTA scores against ``--mot-gt`` (:mod:`cpf_jax.multi.score`).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from cpf_jax.cli.options import UsageError, param_options

__all__ = ["PERSON_SHARE", "check_multi_options", "track_multi", "event_lines"]

#: The histogram window of every slot is sized for a person this share of the frame's
#: width and height (a nearer one takes the exact whole-frame path, slower).
PERSON_SHARE = (0.2, 0.5)


def check_multi_options(args: argparse.Namespace) -> None:
    """Options that do not go with ``--multi`` are one error line; ``--model rgb`` (the
    default) becomes ``grid-occlusion``: the tracker needs depth."""
    clash = [
        name
        for name, given in (
            ("--init", args.init is not None),
            ("--points", args.points is not None),
            ("--out", args.out is not None),
            ("--plot", args.plot is not None),
        )
        if given
    ]
    if clash:
        raise UsageError(
            f"{', '.join(clash)} do not go with --multi: people are found by the detector; "
            "write the boxes with --mot"
        )
    if args.max_people < 1:
        raise UsageError(f"--max-people must be >= 1, got {args.max_people}")
    if args.model == "rgb":
        args.model = "grid-occlusion"


def _model(args: argparse.Namespace, options, frame_hw: tuple[int, int], frameless: bool):
    """The tracker's config, parameters and filter from the command line; ``frameless``:
    no background model, each frame's scene read in the frame (``births.frame_scene``)
    at a person's width, ``PERSON_SHARE`` of the frame's."""
    from cpf_jax.multi import MultiConfig, build_multi_filter, default_multi_params
    from cpf_jax.rgbd import RGBDConfig

    config_kw, _ = options
    rgbd = RGBDConfig(
        variant=args.model,
        n_particles=args.particles,
        hierarchical=not args.no_hierarchical,
        resampler=args.resampler,
        body_term=not args.no_body_term,
        side_scene=RGBDConfig().side_scene if frameless else None,
        **config_kw,
    )
    person = (PERSON_SHARE[0] * frame_hw[1], PERSON_SHARE[1] * frame_hw[0])
    config = MultiConfig(
        rgbd=rgbd, max_targets=args.max_people, scene_width=person[0] if frameless else None
    )
    config = config.with_window(person, frame_hw)
    params = default_multi_params(config)
    params = params._replace(rgbd=param_options(args, params.rgbd))
    return config, params, build_multi_filter(config)


def event_lines(info) -> list[tuple[str, str]]:
    """``[(level, text)]`` of a step's events (``MultiInfo.events``) in words."""
    ev, ident = info.events, np.asarray(info.ident)
    out = []
    for k in np.flatnonzero(np.asarray(ev.confirmed)):
        out.append(("INFO", f"id {ident[k]} born"))
    for k in np.flatnonzero(np.asarray(ev.reidentified)):
        out.append(("INFO", f"id {ident[k]} re-identified"))
    for k in np.flatnonzero(np.asarray(ev.lost)):
        out.append(("WARN", f"id {ident[k]} lost"))
    for k in np.flatnonzero(np.asarray(ev.died)):
        out.append(("WARN", f"id {int(np.asarray(ev.died_ident)[k])} died"))
    return out


def _people(info) -> tuple[np.ndarray, np.ndarray]:
    """``([P] ids, [P, 4] boxes)`` reported this frame, copied out of JAX's arrays."""
    shown = ~np.asarray(info.lost)
    return np.array(info.ident)[shown], np.array(info.box, np.float32)[shown]


def track_multi(args: argparse.Namespace, source, options) -> int:
    """Inputs, the tracker, the loop with its outputs, and the summary."""
    import jax
    import jax.numpy as jnp

    from cpf_jax.cli.inputs import frame_name, open_inputs
    from cpf_jax.errors import CpfJaxError
    from cpf_jax.filter import Context
    from cpf_jax.io.mot import MotWriter
    from cpf_jax.progress import Progress
    from cpf_jax.types import Frame

    inputs = open_inputs(args, source)
    frameless = inputs.background is None
    config, params, filt = _model(args, options, (source.size[1], source.size[0]), frameless)
    context = Context(background=inputs.background)
    writer = MotWriter(args.mot) if args.mot else None
    logger = None
    if args.rrd or args.spawn or args.connect:
        from cpf_jax.viz import RerunLogger

        logger = RerunLogger(
            args.rrd, spawn=args.spawn, connect=args.connect, raw=args.log_raw, blueprint=None
        )
    init, step = jax.jit(filt.init), jax.jit(filt.step)
    key = jax.random.PRNGKey(args.seed)
    bar = Progress(
        inputs.n_frames, label="tracking", interactive=False if args.no_progress else None
    )
    rows, seen, times, state = [], set(), [], None
    try:
        for i, frame_np in inputs.frames:
            frame = Frame(jnp.asarray(frame_np.colour), jnp.asarray(frame_np.depth))
            key, k = jax.random.split(key)
            t0 = time.perf_counter()
            if state is None:
                state = jax.block_until_ready(init(params, k, frame, None, context))
                ids, boxes, events = np.zeros(0, np.int64), np.zeros((0, 4), np.float32), []
            else:
                state, info = jax.block_until_ready(step(params, k, state, frame))
                ids, boxes = _people(info)
                events = event_lines(info)
                times.append((time.perf_counter() - t0) * 1000.0)
            if not np.all(np.isfinite(boxes)):  # never write a NaN box
                raise CpfJaxError(f"{frame_name(source, i)}: the tracker produced a non-finite box")
            seen.update(int(n) for n in ids)
            rows.extend([i, n, *b, 1.0] for n, b in zip(ids, boxes, strict=True))
            if writer is not None:
                writer.write(i, ids, boxes)
            if logger is not None:
                logger.log_frame(i, frame_np, source.intrinsics)
                logger.log_people(i, ids, boxes)
                for level, text in events:
                    logger.log_event(i, text, level)
            bar.update(step_ms=times[-1] if times else None)
        bar.close()
    finally:
        if writer is not None:
            writer.close()
        if logger is not None:
            logger.close()
    _summary(args, source, inputs, config, np.asarray(rows, np.float64).reshape(-1, 7), seen, times)
    return 0


def _summary(args, source, inputs, config, rows: np.ndarray, seen: set, times: list) -> None:
    """What was tracked, and the scores against ``--mot-gt``."""
    ms = f", {np.median(times):.1f} ms a step (median)" if times else ""
    print(
        f"tracked {source.describe()} with up to {config.max_targets} people of "
        f"N={config.rgbd.n_particles} (model {args.model}): {len(seen)} identities, "
        f"{len(rows)} boxes{ms}"
    )
    if inputs.note is not None:
        print(f"cpf-track: note: {inputs.note}", file=sys.stderr)
    if args.mot_gt:
        from cpf_jax.io.mot import read_mot
        from cpf_jax.multi.score import MIN_HEIGHT, MIN_VISIBILITY, score_people

        gt = read_mot(args.mot_gt, truth=True)
        m = score_people(gt, rows, source.size[1])
        print(
            f"against {args.mot_gt}: MOTA {m.mota:.1f} %, MOTP {m.motp:.1f} %, IDF1 "
            f"{m.idf1:.1f} %, HOTA {m.hota:.1f} %, {m.id_switches} id switches ({m.matches} "
            f"matched, {m.false_positives} false positives, {m.misses} misses of "
            f"{m.num_gt} boxes; boxes under {MIN_VISIBILITY:.0%} visible or "
            f"{MIN_HEIGHT:.0%} of the frame tall set aside)"
        )
    if args.mot:
        print(f"cpf-track: note: MOTChallenge lines written to {args.mot}", file=sys.stderr)
    if args.rrd:
        print(f"cpf-track: note: Rerun recording written to {args.rrd}", file=sys.stderr)
