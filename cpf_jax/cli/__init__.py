"""``cpf-track``: track a person's box in a sequence and report metrics.

The driver is thin: it opens a frame source, validates the initial box, calls
one jitted filter step per frame, writes each result as it goes (CSV row,
Rerun log) and prints a summary. Nothing numeric lives here.

Observation models (``--model``): ``rgb`` is the colour layer
(``cpf_jax.colour``, the default); ``rgbd``, ``grid`` and ``grid-occlusion``
are the RGB-D filter's variants (``cpf_jax.rgbd``). Depth is registered to
colour first when a calibration is in effect: ``--calib FILE``, or the
folder's own ``calibration.json`` (``cpf_jax.registration`` format). The RGB-D
models read no background frames by default (``--background none``): each frame's scene
comes from the frame itself (``RGBDConfig.side_scene``), which holds for a camera that
moves and a scene never seen empty. For a static camera, ``--background auto`` takes the
median of the frames, among up to 150 evenly spaced ones, with the least foreground in
front of the farthest surface each pixel shows in a fifth of them (a share at most twice
the quietest's plus 1 % of the frame; at least 5, at most 25;
:func:`cpf_jax.kernels.background.quiet_frames`), so that the empty frames of a
recording whose people come and go make the model.

``--points`` adds layer 2 (``cpf_jax.cascade``): points on the body (``joints``:
a synthetic scenario's head, hands and feet; ``auto``: head, hands and feet found
on the body in the start box, :func:`cpf_jax.cascade.find_body_points`, which
pairs with ``--init auto``; or ``x,y;x,y;...`` pixels of the start frame) tracked
in depth inside every layer-1 box, on the pixels nearer than the background model or,
when layer 1 is the RGB-D filter without background frames, than the frame's own scene.
The CSV gains ``<point>_x, <point>_y`` (pixels), ``<point>_X_mm, _Y_mm, _Z_mm`` (camera
millimetres) and ``<point>_hidden`` (1: hidden, at its predicted place) columns, the Rerun
log the 2D and 3D points, and on a synthetic scenario (``joints``, or ``auto``: each point
against the joint it stands for) the summary gives each point's median 2D and 3D error.

Live sources (``realsense[:serial]``, ``kinect2[:serial]``, a RealSense ``.bag``/``.db3``) are
read once, in order: ``--init`` is required (a box, or ``auto``: the first frame where
:func:`cpf_jax.detect.find_person` finds someone against the background model),
``--background N`` takes the stream's first N frames (``auto``: 25) and tracking
starts after them;
the run ends with the stream, ``--max-frames`` or Ctrl-C, and the camera is stopped
however it ends. The Rerun log goes to ``--rrd FILE``,
a new viewer (``--spawn``) or a running one (``--connect URL``, checked before tracking;
a viewer that goes away during the run fails it with exit 2 once the CSV, ``.rrd``, plot and
summary are written).
``--multi`` tracks every person instead of one (``cpf_jax.multi``, :mod:`cpf_jax.cli.multi`):
no ``--init``, and a background model (``--background none`` takes ``auto``'s quiet
frames there); ``--mot FILE`` writes MOTChallenge lines as it goes, ``--mot-gt FILE``
scores the run, and the Rerun log shows each identity in its own colour with its births,
losses and deaths as text events.
``--plot FILE.png`` draws the run (IoU and ESS / N per frame, the success plot, the body
points' 3D errors when they are scored) at its end, or when it is interrupted.

Results (the run's line, the metrics table, which frames it scores) go to stdout; notes,
warnings (``cpf_jax.errors.InputWarning``: an input converted or guessed) and the compile
time of ``init`` and ``step`` (compiled before the first frame) go to stderr. Exit codes:
0 success, 2 bad input (path, image, box, option, camera, viewer, a model that needs depth
on a source without it, a guess too unsure to start from, more particles than the free
memory holds by XLA's estimate, :mod:`cpf_jax.memory`), 130 interrupted.
"""

from __future__ import annotations

import argparse
import functools
import sys
import warnings
from pathlib import Path

from cpf_jax.cli.inputs import open_inputs, quiet_background
from cpf_jax.cli.model import build_model
from cpf_jax.cli.options import (
    AUTO_BACKGROUND_FRAMES,
    AUTO_CANDIDATES,
    JOINT_DEPTH_OFFSET_MM,
    JOINTS,
    UsageError,
    build_parser,
    model_options,
    param_options,
    parse_background,
    parse_box,
    parse_live_background,
)
from cpf_jax.cli.run import track
from cpf_jax.cli.summary import point_errors, print_summary, write_plot
from cpf_jax.errors import CpfJaxError, InputWarning

__all__ = [
    "AUTO_BACKGROUND_FRAMES",
    "AUTO_CANDIDATES",
    "JOINTS",
    "JOINT_DEPTH_OFFSET_MM",
    "UsageError",
    "build_parser",
    "main",
    "model_options",
    "param_options",
    "parse_background",
    "parse_box",
    "parse_live_background",
    "quiet_background",
]

EXIT_BAD_INPUT = 2


def _fail(message: str) -> int:
    print(f"cpf-track: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _warn_line(message, category, filename, lineno, file=None, line=None, *, shown):
    """``warnings.showwarning`` for a run: our input warnings as one line, others as usual."""
    if issubclass(category, InputWarning):
        print(f"cpf-track: warning: {message}", file=sys.stderr)
    else:
        shown(message, category, filename, lineno, file, line)


# Options whose value may start with "-" (a box or point left of the frame), which argparse
# would otherwise take for an option.
_SIGNED_VALUES = ("--init", "--points")


def _join_signed_values(argv: list[str]) -> list[str]:
    """``--init -30,100,60,80`` read as ``--init=-30,100,60,80``."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a in _SIGNED_VALUES:
            value = next(it, None)
            if value is not None and value.startswith("-") and value[1:2].isdigit():
                out.append(f"{a}={value}")
                continue
            out.extend([a] if value is None else [a, value])
        else:
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(_join_signed_values(argv))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", InputWarning)
            warnings.showwarning = functools.partial(_warn_line, shown=warnings.showwarning)
            return _run(args)
    except (CpfJaxError, ValueError) as e:  # ValueError: config validation
        return _fail(str(e))
    except KeyboardInterrupt:
        print("cpf-track: interrupted; results so far are on disk", file=sys.stderr)
        return 130
    except Exception as e:  # XLA's own out-of-memory, past cpf_jax.memory's estimate
        if type(e).__name__ != "JaxRuntimeError" or "RESOURCE_EXHAUSTED" not in str(e):
            raise
        return _fail(
            "out of memory while tracking (XLA: RESOURCE_EXHAUSTED); use fewer --particles"
        )


def tune_process() -> bool:
    """The CPU switches ``cpf-track`` turns on before JAX allocates (``--tune-malloc``):
    ``cpu_tuning.tune_malloc()``; True when glibc took them."""
    from cpf_jax.cpu_tuning import tune_malloc

    return tune_malloc()


def _run(args: argparse.Namespace) -> int:
    if args.tune_malloc:
        tune_process()
    _compile_cache(args.compile_cache)
    if args.particles < 1:
        raise UsageError(f"--particles must be >= 1, got {args.particles}")
    if args.sigma is not None and not 0 < args.sigma < float("inf"):
        raise UsageError(f"--sigma must be a finite number > 0, got {args.sigma}")
    if args.depth_scale is not None and not 0 < args.depth_scale < float("inf"):
        raise UsageError(f"--depth-scale must be a finite number > 0, got {args.depth_scale}")
    if args.max_frames is not None and args.max_frames < 1:
        raise UsageError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.plot is not None and Path(args.plot).suffix.lower() != ".png":
        raise UsageError(f"--plot writes a PNG: give a .png path, got {args.plot!r}")
    if args.plot is not None:
        try:  # fail now, not after the run
            Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UsageError(f"--plot {args.plot}: cannot create its folder ({e})") from None

    if args.multi:
        from cpf_jax.cli.multi import check_multi_options

        check_multi_options(args)
    elif args.mot or args.mot_gt:
        raise UsageError("--mot and --mot-gt go with --multi")
    options = model_options(args)  # a bad option fails before any frame is read

    from cpf_jax.io import open_source

    source = open_source(args.path, depth_scale=args.depth_scale)
    with source:  # a camera is stopped, a file closed, however the run ends
        return _track(args, source, options)


def _track(args: argparse.Namespace, source, options) -> int:
    """Inputs, model, the tracking loop, then the plot and the summary."""
    if args.multi:
        from cpf_jax.cli.multi import track_multi

        return track_multi(args, source, options)
    inputs = open_inputs(args, source)
    model = build_model(args, source, inputs, options)
    results, viewer_error = track(args, source, inputs, model)
    if args.plot and results.frames:
        errors = point_errors(args, source, model.points, results)
        write_plot(args, source, results, model.n_particles, errors)
    print_summary(args, source, inputs, model, results)
    return 0 if viewer_error is None else _fail(str(viewer_error))


def _compile_cache(choice: str | None) -> str | None:
    """Set up JAX's persistent compilation cache (``--compile-cache``, before anything
    compiles); returns the directory in use, or None. The default directory is a
    convenience: when it cannot be used the run goes on without a cache (one warning
    line); a directory given on the command line that cannot be used is an error."""
    import jax

    from cpf_jax import compile_cache

    if choice == "off":
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    if choice is None:
        own = compile_cache.configured()
        if own is not None:  # JAX_COMPILATION_CACHE_DIR or a notebook's jax.config
            return own
        try:
            return str(compile_cache.enable(compile_cache.default_dir()))
        except OSError as e:
            print(f"cpf-track: warning: no compilation cache ({e})", file=sys.stderr)
            return None
    try:
        return str(compile_cache.enable(choice))
    except OSError as e:
        raise UsageError(f"--compile-cache {choice}: cannot use it ({e})") from None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
