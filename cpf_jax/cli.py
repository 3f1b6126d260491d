"""``cpf-track``: track a person's box in a sequence and report metrics.

The driver is thin: it opens a frame source, validates the initial box, calls
one jitted filter step per frame, writes each result as it goes (CSV row,
Rerun log) and prints a summary. Nothing numeric lives here.

Observation models (``--model``): ``rgb`` is the colour layer
(``cpf_jax.colour``, the default); ``rgbd``, ``grid`` and ``grid-occlusion``
are the RGB-D filter's variants (``cpf_jax.rgbd``). Depth is registered to
colour first when a calibration is in effect: ``--calib FILE``, or the
folder's own ``calibration.json`` (``cpf_jax.registration`` format). The RGB-D
models learn a background from ``--background`` frames of the recording: by default
(``auto``) the median of the frames, among up to 150 evenly spaced ones, with the least
foreground in front of the farthest surface each pixel shows in a fifth of them (a share
at most twice the quietest's plus 1 % of the frame; at least 5, at most 25;
:func:`cpf_jax.kernels.background.quiet_frames`), so that the empty frames of a
recording whose people come and go make the model.

``--points`` adds layer 2 (``cpf_jax.cascade``): points on the body (``joints``:
a synthetic scenario's head, hands and feet; ``auto``: head, hands and feet found
on the body in the start box, :func:`cpf_jax.cascade.find_body_points`, which
pairs with ``--init auto``; or ``x,y;x,y;...`` pixels of the start frame) tracked
in depth inside every layer-1 box. The CSV gains
``<point>_x, <point>_y`` (pixels) and ``<point>_X_mm, _Y_mm, _Z_mm`` (camera
millimetres) columns, the Rerun log the 2D and 3D points, and on a synthetic
scenario (``joints``, or ``auto``: each point against the joint it stands for) the
summary gives each point's median 2D and 3D error.

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
``--plot FILE.png`` draws the run (IoU and ESS / N per frame, the success plot, the body
points' 3D errors when they are scored) at its end, or when it is interrupted.

Exit codes: 0 success, 2 bad input (path, image, box, option, camera, viewer), 130
interrupted.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import sys
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cpf_jax.errors import CpfJaxError, GroundTruthWarning, ViewerUnavailable
from cpf_jax.points import BODY_POINT_DEPTH_OFFSET_MM, BODY_POINTS

__all__ = ["main", "parse_box"]

EXIT_BAD_INPUT = 2


class UsageError(CpfJaxError):
    """A command-line value that cannot be used (message is shown as one line)."""


def parse_box(text: str) -> np.ndarray:
    """``"x,y,w,h"`` (0-based top-left pixels) -> ``[4] float32``."""
    parts = text.replace(" ", "").split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != 4 or not all(np.isfinite(vals)):
        raise UsageError(f"--init expects four numbers x,y,w,h, got {text!r}")
    return np.asarray(vals, np.float32)


def parse_bins(text: str) -> tuple[int, ...]:
    """``"HxS"`` or ``"HxSxV"`` (V: value bins for achromatic pixels) -> tuple."""
    try:
        vals = tuple(int(v) for v in text.lower().split("x"))
    except ValueError:
        vals = ()
    if len(vals) not in (2, 3):
        raise UsageError(f"--bins expects HxS or HxSxV such as 8x8x8, got {text!r}")
    h, s = vals[:2]
    v = vals[2] if len(vals) == 3 else 0
    if not (1 <= h <= 180 and 1 <= s <= 256 and 0 <= v <= 256):
        raise UsageError(f"--bins out of range (1..180 x 1..256 x 0..256): {text!r}")
    return vals


def parse_layout(text: str) -> tuple[int, int] | None:
    """``"RxC"`` (rows x columns of the layout term's grid) or ``"off"`` -> tuple / None."""
    if text.lower() == "off":
        return None
    try:
        vals = tuple(int(v) for v in text.lower().split("x"))
    except ValueError:
        vals = ()
    if len(vals) != 2 or not all(1 <= v <= 64 for v in vals):
        raise UsageError(f"--layout expects RxC (1..64 each) such as 12x3, or off; got {text!r}")
    return vals


#: Points ``--points joints`` tracks, and their joint depth offsets (cpf_jax.points).
JOINTS = BODY_POINTS
JOINT_DEPTH_OFFSET_MM = BODY_POINT_DEPTH_OFFSET_MM


def parse_points(text: str, source, start: int) -> tuple[np.ndarray, tuple[str, ...]]:
    """``([P, 2] points, names)`` of ``--points``: ``joints`` or ``x,y;x,y;...``."""
    if text == "joints":
        seq = getattr(source, "sequence", None)
        names = tuple(getattr(seq, "joint_names", ()))
        if seq is None or not all(n in names for n in JOINTS):
            raise UsageError(
                f"--points joints needs a synthetic scenario; give x,y;x,y;... for "
                f"{source.describe()}"
            )
        idx = [names.index(n) for n in JOINTS]
        # Joint projections (u, v) in the box convention of the point filter.
        return np.asarray(seq.joints2d[start, idx], np.float32) + 0.5, JOINTS
    try:
        pts = [[float(v) for v in item.split(",")] for item in text.split(";") if item.strip()]
    except ValueError:
        pts = []
    if not pts or any(len(q) != 2 for q in pts):
        raise UsageError(f"--points expects 'joints', 'auto' or x,y;x,y;..., got {text!r}")
    return np.asarray(pts, np.float32), tuple(f"p{k}" for k in range(len(pts)))


def check_box(box: np.ndarray, size: tuple[int, int], where: str) -> None:
    """Reject boxes that cannot start a track (``cpf_jax.types.check_box``): not finite,
    a side under 2 px, or no overlap with the ``size = (width, height)`` frame."""
    from cpf_jax.types import check_box as check

    try:
        check(box, (size[1], size[0]), where)
    except ValueError as e:
        raise UsageError(str(e)) from None


# --background auto: the AUTO_BACKGROUND_FRAMES emptiest of up to AUTO_CANDIDATES evenly
# spaced frames (a live stream: its first AUTO_BACKGROUND_FRAMES).
AUTO_BACKGROUND_FRAMES = 25
AUTO_CANDIDATES = 150
QUIET_STRIDE = 4  # pixel lattice of the candidates' foreground shares


def parse_background(text: str, n_frames: int) -> list[int]:
    """``"N"`` (N evenly spaced frames) or ``"A:B"`` (frames A..B-1) -> frame indices;
    ``"auto"``: the candidates of :func:`quiet_background` (up to ``AUTO_CANDIDATES``
    evenly spaced frames)."""
    if text == "auto":
        text = str(AUTO_CANDIDATES)
    try:
        if ":" in text:
            a, b = (int(v) for v in text.split(":"))
            frames = list(range(max(a, 0), min(b, n_frames)))
        else:
            k = int(text)
            if k < 1:
                raise ValueError
            frames = sorted({int(round(v)) for v in np.linspace(0, n_frames - 1, min(k, n_frames))})
    except ValueError:
        frames = None
    if not frames:
        raise UsageError(
            f"--background expects auto, empty, N >= 1 or A:B with frames inside "
            f"0..{n_frames - 1}, got {text!r}"
        )
    return frames


def build_parser() -> argparse.ArgumentParser:
    from cpf_jax.dynamics import MODELS
    from cpf_jax.kernels.resample import SCHEMES

    p = argparse.ArgumentParser(
        prog="cpf-track",
        description="Track a person's bounding box (and, with --points, points on the body).",
    )
    p.add_argument(
        "path",
        help="synthetic scenario name, OTB folder (img/ + groundtruth_rect.txt), "
        "RGB-D folder (rgb/, depth/, groundtruth_rect.txt), .npz or video file, "
        "RealSense .bag/.db3, or a live camera: realsense[:serial] or kinect2[:serial] "
        "(live: --init is required; --background N takes the stream's first N frames)",
    )
    p.add_argument(
        "--init",
        help="initial box x,y,w,h (0-based top-left pixels), or 'auto': start on the first "
        "frame with a person-shaped foreground blob against the --background model",
    )
    p.add_argument("--particles", "-n", type=int, default=200, help="number of particles")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed")
    p.add_argument("--out", help="write frame,x,y,w,h rows (CSV) as the run goes")
    p.add_argument("--rrd", help="write a Rerun recording to this .rrd file")
    p.add_argument(
        "--plot",
        help="write a PNG of the run: IoU (with ground truth) and ESS/N per frame, and the "
        "success plot (also written when the run is interrupted)",
    )
    p.add_argument(
        "--spawn",
        action="store_true",
        help="start a Rerun viewer and stream the log to it (needs a display)",
    )
    p.add_argument(
        "--connect",
        metavar="URL",
        help="stream the Rerun log to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy",
    )
    p.add_argument(
        "--dynamics",
        choices=MODELS,
        help="motion model (default: random_walk for --model rgb, ar1 for the RGB-D models)",
    )
    p.add_argument(
        "--size-velocity-decay",
        type=float,
        default=None,
        metavar="D",
        help="ar1/ar2: share of the box's size velocity kept each frame, in [0, 1] "
        "(default 0.9; 1 is the thesis's undamped model)",
    )
    p.add_argument(
        "--size-hold",
        type=float,
        default=None,
        metavar="H",
        help="--model rgb, motion-guided ar1: how far guided particles moving across the "
        "image keep their size, in [0, 1] (default 1; 0: they carry their size velocity)",
    )
    p.add_argument(
        "--model",
        choices=("rgb", "rgbd", "grid", "grid-occlusion"),
        default="rgb",
        help="observation model: colour only (default) or the RGB-D variants",
    )
    p.add_argument(
        "--calib",
        help="depth-to-colour calibration JSON (default: the folder's calibration.json)",
    )
    p.add_argument(
        "--background",
        default="auto",
        help="background frames for the RGB-D models: 'auto' (default: up to 25 frames with "
        "the least foreground among up to 150 evenly spaced ones; a live stream's first 25), "
        "N (evenly spaced over the recording; a live stream's first N), A:B (frames A..B-1, "
        "0-based) or 'empty' (a synthetic scenario's empty room)",
    )
    p.add_argument(
        "--start",
        type=int,
        default=None,
        help="first frame to track (0-based; default: the first frame with ground truth; "
        "live: the frame after the background frames)",
    )
    p.add_argument(
        "--no-hierarchical", action="store_true", help="plain sampling instead of motion-guided"
    )
    p.add_argument(
        "--no-body-term",
        action="store_true",
        help="RGB-D models: no whole-body colour term (the paper's likelihood alone)",
    )
    p.add_argument("--estimator", choices=("mean", "map", "robust"), default="mean")
    p.add_argument("--resampler", choices=tuple(SCHEMES), default="systematic")
    p.add_argument("--sigma", type=float, default=None, help="likelihood width (default 0.15)")
    p.add_argument(
        "--bins", default=None, help="hue x saturation [x value] bins: 8x8x8 (default) or 8x8"
    )
    p.add_argument(
        "--template-update",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--model rgb: slowly adapt the reference histograms (default on)",
    )
    p.add_argument(
        "--contrast",
        choices=("linear", "mixture", "off"),
        default=None,
        help="--model rgb: per-bin weights of the centre-surround term (default linear; "
        "off: no such term, the thesis's likelihood)",
    )
    p.add_argument(
        "--unseen",
        choices=("background", "neutral"),
        default=None,
        help="--model rgb, linear contrast: colours seen neither in the first box nor "
        "around it count as background or neutral (default)",
    )
    p.add_argument(
        "--layout",
        default=None,
        help="--model rgb: layout term on a RxC grid (default 7x3), or off",
    )
    p.add_argument(
        "--layout-feature",
        choices=("luminance", "gradient"),
        default=None,
        help="--model rgb: what the layout cells hold: mean luminance (default) or "
        "gradient energy in 4 orientations",
    )
    p.add_argument(
        "--layout-mirror",
        action="store_true",
        help="--model rgb: also match the layout's mirror image (a walker who turned round)",
    )
    p.add_argument(
        "--layout-weight",
        type=float,
        default=None,
        help="--model rgb: weight of the layout term (default 10)",
    )
    p.add_argument(
        "--points",
        default=None,
        help="also track points on the body with the depth layer (the cascade): "
        "'joints' (a synthetic scenario's head, hands and feet), 'auto' (head, hands "
        "and feet found on the body in the start box; a person facing the camera) or "
        "x,y;x,y;... (pixels in the start frame; quote it in a shell)",
    )
    p.add_argument(
        "--point-particles", type=int, default=100, help="particles per body point (--points)"
    )
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--tune-malloc",
        action="store_true",
        help="raise glibc mmap/trim thresholds and keep one malloc arena before JAX starts "
        "(CPU speed switch)",
    )
    p.add_argument(
        "--compile-cache",
        default=None,
        metavar="DIR|off",
        help="keep compiled programs in DIR so that the next run with the same model and "
        "sizes starts without compiling (default: $CPF_JAX_COMPILE_CACHE, else "
        "~/.cache/cpf_jax/xla, kept under 1 GiB; a cache JAX is already given, e.g. by "
        "JAX_COMPILATION_CACHE_DIR, is left as it is); 'off': none",
    )
    return p


def _fail(message: str) -> int:
    print(f"cpf-track: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _warn_line(message, category, filename, lineno, file=None, line=None, *, shown):
    """``warnings.showwarning`` for a run: our input warnings as one line, others as usual."""
    if issubclass(category, GroundTruthWarning):
        print(f"cpf-track: warning: {message}", file=sys.stderr)
    else:
        shown(message, category, filename, lineno, file, line)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", GroundTruthWarning)
            warnings.showwarning = functools.partial(_warn_line, shown=warnings.showwarning)
            return _run(args)
    except (CpfJaxError, ValueError) as e:  # ValueError: config validation
        return _fail(str(e))
    except KeyboardInterrupt:
        print("cpf-track: interrupted; results so far are on disk", file=sys.stderr)
        return 130


def _close_sinks(writer, logger, failing: bool = False) -> None:
    """Close the results CSV and the Rerun logger. With ``failing`` (an exception is
    already on its way), a viewer that cannot take the log is one warning line instead
    of an error that would hide the first."""
    if writer is not None:
        writer.close()
    if logger is None:
        return
    try:
        logger.close()
    except ViewerUnavailable as e:
        if not failing:
            raise
        print(f"cpf-track: warning: {e}", file=sys.stderr)


def _run(args: argparse.Namespace) -> int:
    if args.tune_malloc:
        from cpf_jax.cpu_tuning import tune_malloc

        tune_malloc()
    _compile_cache(args.compile_cache)
    if args.particles < 1:
        raise UsageError(f"--particles must be >= 1, got {args.particles}")
    if args.sigma is not None and not 0 < args.sigma < float("inf"):
        raise UsageError(f"--sigma must be a finite number > 0, got {args.sigma}")
    if args.max_frames is not None and args.max_frames < 1:
        raise UsageError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.plot is not None and Path(args.plot).suffix.lower() != ".png":
        raise UsageError(f"--plot writes a PNG: give a .png path, got {args.plot!r}")
    if args.plot is not None:
        try:  # fail now, not after the run
            Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UsageError(f"--plot {args.plot}: cannot create its folder ({e})") from None

    options = _model_options(args)  # a bad option fails before any frame is read

    from cpf_jax.io import open_source

    source = open_source(args.path)
    with source:  # a camera is stopped, a file closed, however the run ends
        return _track(args, source, options)


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


def _model_options(args: argparse.Namespace) -> tuple[dict, dict]:
    """``(config keywords, colour-only keywords)`` of the model options; one error
    line for a bad or misplaced one (checked before any frame is read)."""
    config_kw = {}
    if args.bins is not None:
        config_kw["bins"] = parse_bins(args.bins)
    if args.dynamics is not None:  # else each config's own default
        config_kw["model"] = args.dynamics
    colour_kw = {}
    if args.contrast is not None:
        colour_kw["contrast"] = None if args.contrast == "off" else args.contrast
    if args.unseen is not None:
        if args.contrast in ("mixture", "off"):
            raise UsageError(
                f"--unseen applies to the linear contrast, not --contrast {args.contrast}"
            )
        colour_kw["unseen"] = args.unseen
    if args.layout is not None:
        colour_kw["layout"] = parse_layout(args.layout)
    if args.layout_feature is not None:
        colour_kw["layout_feature"] = args.layout_feature
    if args.layout_mirror:
        colour_kw["layout_mirror"] = True
    if args.template_update is not None:
        colour_kw["template_update"] = args.template_update
    layout_opts = args.layout_feature or args.layout_mirror or args.layout_weight is not None
    if layout_opts and "layout" in colour_kw and colour_kw["layout"] is None:
        raise UsageError(
            "--layout-feature, --layout-mirror and --layout-weight need a layout, not --layout off"
        )
    if args.layout_weight is not None and not args.layout_weight >= 0:
        raise UsageError(f"--layout-weight must be >= 0, got {args.layout_weight}")
    if (colour_kw or args.layout_weight is not None) and args.model != "rgb":
        raise UsageError(
            f"--contrast, --unseen, --template-update and --layout* apply to --model rgb, "
            f"not {args.model!r}"
        )
    if args.no_body_term and args.model == "rgb":
        raise UsageError("--no-body-term applies to the RGB-D models (--model rgbd|grid|...)")
    decay = args.size_velocity_decay
    if decay is not None:
        from cpf_jax.dynamics import SIZE_VELOCITY_MODELS

        if not 0.0 <= decay <= 1.0:
            raise UsageError(f"--size-velocity-decay must be in [0, 1], got {decay}")
        if args.model == "rgb":
            from cpf_jax.colour import ColourConfig as Config
        else:
            from cpf_jax.rgbd import RGBDConfig as Config
        dynamics = config_kw.get("model", Config.model)
        if dynamics not in SIZE_VELOCITY_MODELS:
            raise UsageError(
                f"--size-velocity-decay applies to --dynamics ar1|ar2 (the models with a "
                f"size velocity), not {dynamics!r}"
            )
    hold = args.size_hold
    if hold is not None:
        if not 0.0 <= hold <= 1.0:
            raise UsageError(f"--size-hold must be in [0, 1], got {hold}")
        from cpf_jax.colour import ColourConfig

        dynamics = config_kw.get("model", ColourConfig.model)
        if args.model != "rgb" or dynamics != "ar1" or args.no_hierarchical:
            raise UsageError(
                "--size-hold applies to --model rgb with --dynamics ar1 and motion-guided "
                "sampling (the RGB-D models propose without it)"
            )
    return config_kw, colour_kw


def param_options(args: argparse.Namespace, params):
    """``params`` (``ColourParams`` or ``RGBDParams``) with the command line's parameter
    options (``--sigma``, ``--layout-weight``, ``--size-velocity-decay``, ``--size-hold``)
    applied."""
    import jax.numpy as jnp

    from cpf_jax.colour import ColourParams

    colour = isinstance(params, ColourParams)
    if args.sigma is not None:
        params = params._replace(**{"sigma" if colour else "sigma_rgb": jnp.float32(args.sigma)})
    if args.layout_weight is not None:  # --model rgb only (checked in _model_options)
        params = params._replace(layout_weight=jnp.float32(args.layout_weight))
    if args.size_velocity_decay is not None:
        params = params._replace(size_velocity_decay=jnp.float32(args.size_velocity_decay))
    if args.size_hold is not None:  # --model rgb only (checked in _model_options)
        params = params._replace(
            motion=params.motion._replace(size_hold=jnp.float32(args.size_hold))
        )
    return params


def _track(args: argparse.Namespace, source, options: tuple[dict, dict]) -> int:
    import jax
    import jax.numpy as jnp

    from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
    from cpf_jax.io import ResultsWriter
    from cpf_jax.io.base import LiveSource
    from cpf_jax.metrics import format_summary, summarise
    from cpf_jax.progress import Progress
    from cpf_jax.types import Frame

    live = isinstance(source, LiveSource)
    bg_note = None  # --background auto: which frames made the background model
    calib = _calibration(args, source)
    auto = args.init is not None and args.init.strip().lower() == "auto"
    # Depth is read by the RGB-D models, the cascade and --init auto's person finder.
    register = _registrar(calib, uses_depth=args.model != "rgb" or args.points is not None or auto)
    # A background model: the RGB-D models' foreground, and --init auto's person finder.
    need_bg = args.model != "rgb" or auto
    if live:
        start, box, bg_frames, frames = _open_live(args, source, register, need_bg, auto)
    else:
        n_frames = len(source)

        def read(i: int) -> Frame:
            return register(source.read(i), f"{source.describe()} frame {i} ({source.names[i]})")

        start, box = _start_and_box(args, source, n_frames, auto)
        bg_frames = None
        if need_bg:
            if args.background == "empty":
                empty = source.empty_background()
                if empty is None:
                    raise UsageError(
                        f"--background empty: {source.describe()} has no empty-scene frame "
                        "(only synthetic scenarios do); give N or A:B"
                    )
                bg_frames = [empty]
            elif args.background == "auto":
                bg_frames, bg_note = quiet_background(read, parse_background("auto", n_frames))
            else:
                bg_frames = [read(i) for i in parse_background(args.background, n_frames)]
        frames = ((i, read(i)) for i in range(start, n_frames))
    scene = None  # the background model of the empty scene
    if bg_frames:
        from cpf_jax.kernels.background import median_background

        scene = jax.jit(median_background)(
            np.stack([f.colour for f in bg_frames]), np.stack([f.depth for f in bg_frames])
        )
    if auto:
        box, frames = _find_start(source, frames, scene)
    frames = itertools.islice(frames, args.max_frames)  # None: to the end
    try:
        start, first_frame = next(frames)
    except StopIteration:
        raise UsageError(f"{source.describe()}: no frame to track") from None
    frames = itertools.chain([(start, first_frame)], frames)
    check_box(box, source.size, source.describe())

    config_kw, colour_kw = options
    frame_hw = (source.size[1], source.size[0])
    background = None if args.model == "rgb" else scene  # the colour layer has none
    if args.model == "rgb":
        config = ColourConfig(
            n_particles=args.particles,
            hierarchical=not args.no_hierarchical,
            estimator=args.estimator,
            resampler=args.resampler,
            **config_kw,
            **colour_kw,
        ).with_window((float(box[2]), float(box[3])), frame_hw)
        params = param_options(args, default_colour_params())
        filt = build_colour_filter(config)
    else:
        from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params

        config = RGBDConfig(
            variant=args.model,
            n_particles=args.particles,
            hierarchical=not args.no_hierarchical,
            resampler=args.resampler,
            body_term=not args.no_body_term,
            **config_kw,
        ).with_window((float(box[2]), float(box[3])), frame_hw)
        params = param_options(args, default_rgbd_params(config))
        filt = build_rgbd_filter(config)
    cascade = None
    point_names: tuple[str, ...] = ()
    if args.points is not None:
        cascade = _cascade(args, source, first_frame, start, box, config, params, calib, background)
        config, params, filt, points0, point_names = cascade
    init = jax.jit(filt.init)
    step = jax.jit(filt.step)

    logger = surface = None
    if args.rrd or args.spawn or args.connect:
        from cpf_jax.viz import RerunLogger

        logger = RerunLogger(args.rrd, spawn=args.spawn, connect=args.connect)
        if cascade is not None:  # layer 2's segmented body, as a 3D point cloud
            from cpf_jax.cascade import body_surface

            surface = jax.jit(body_surface, static_argnums=0)
    point_columns = tuple(
        f"{n}_{c}" for n in point_names for c in ("x", "y", "X_mm", "Y_mm", "Z_mm")
    )
    writer = (
        ResultsWriter(args.out, extra_columns=("ess", "lost", "ms", *point_columns))
        if args.out
        else None
    )

    key = jax.random.PRNGKey(args.seed)
    n_track = None
    if not live:
        n_track = len(source) - start
        n_track = n_track if args.max_frames is None else min(n_track, args.max_frames)
    # One entry per tracked frame, in order: its index, box, lost flag, body points.
    done: list[int] = []
    pred: list[np.ndarray] = []
    lost: list[bool] = []
    esses: list[float] = []
    pts2d: list[np.ndarray] = []
    pts3d: list[np.ndarray] = []
    n_points = len(point_names)
    bar = Progress(n_track, label="tracking", interactive=False if args.no_progress else None)
    n_steps = n_windowed = 0  # colour model: steps whose histograms came from the window
    try:
        state = None
        for i, frame_np in frames:
            frame = Frame(jnp.asarray(frame_np.colour), jnp.asarray(frame_np.depth))
            key, k = jax.random.split(key)
            t0 = time.perf_counter()
            p2 = np.full((n_points, 2), np.nan, np.float32)
            p3 = np.full((n_points, 3), np.nan, np.float32)
            box_used = jnp.asarray(box, jnp.float32)  # layer 2's box (cascade)
            if state is None:
                if cascade is not None:
                    state = init(
                        params, k, frame, jnp.asarray(box), jnp.asarray(points0), background
                    )
                    p2 = np.asarray(points0, np.float32)
                elif background is None:
                    state = init(params, k, frame, jnp.asarray(box))
                else:
                    state = init(params, k, frame, jnp.asarray(box), background)
                est = np.asarray(box, np.float32)
                ess, is_lost = (
                    float(config.box.n_particles if cascade else config.n_particles),
                    False,
                )
            else:
                state, info = step(params, k, state, frame)
                if cascade is not None:
                    p2 = np.asarray(info.points.mean)
                    p3 = np.asarray(info.points.mean3d)
                    box_used = info.box_used
                    info = info.box
                # The RGB-D filters report the box to score (e.g. the visible part).
                est = np.asarray(getattr(info, "report", info.estimate))
                ess, is_lost = float(info.ess), bool(info.lost)
                if hasattr(info, "windowed"):
                    n_steps += 1
                    n_windowed += bool(info.windowed)
            ms = (time.perf_counter() - t0) * 1000.0
            if not np.all(np.isfinite(est)):  # never write a NaN box
                raise CpfJaxError(f"{_frame_name(source, i)}: the filter produced a non-finite box")
            done.append(i)
            pred.append(est)
            lost.append(is_lost)
            esses.append(ess)
            pts2d.append(p2)
            pts3d.append(p3)
            if writer is not None:
                extras = {}
                for n, name in enumerate(point_names):
                    for c, v in zip(("x", "y"), p2[n], strict=True):
                        extras[f"{name}_{c}"] = round(float(v), 2)
                    if np.all(np.isfinite(p3[n])):
                        for c, v in zip(("X_mm", "Y_mm", "Z_mm"), p3[n], strict=True):
                            extras[f"{name}_{c}"] = round(float(v), 1)
                writer.write(
                    i, est, ess=round(ess, 2), lost=int(is_lost), ms=round(ms, 3), **extras
                )
            if logger is not None:
                box_state = state.box if cascade is not None else state
                _log_frame(logger, i, frame_np, source, est, box_state, ess, ms)
                if cascade is not None:
                    logger.log_points2d(i, p2, labels=list(point_names))
                    logger.log_points3d(i, p3, labels=list(point_names))
                    body = surface(config, frame, box_used, background)
                    logger.log_points3d(i, body, "body/surface", radius=0.004)
            bar.update()
        bar.close()  # the final progress line only for a completed run
    except BaseException as exc:
        # An error or Ctrl-C is on its way: close the sinks (the CSV keeps its rows, the
        # .rrd is completed) without letting a viewer that cannot take the log replace it.
        _close_sinks(writer, logger, failing=True)
        if isinstance(exc, KeyboardInterrupt) and args.plot and done:
            try:
                errs = _point_errors_of(args, source, point_names, pts2d, pts3d, done)
                n_box = _n_box(config, cascade)
                _write_plot(args, source, done, pred, lost, esses, n_box, errs)
            except CpfJaxError as e:  # the interrupt, not the plot, is what happened
                print(f"cpf-track: warning: {e}", file=sys.stderr)
        raise
    # A viewer that went away during the run fails the run (exit 2), but only after the
    # results it did produce (CSV, .rrd, plot, summary) are written and printed.
    viewer_error = None
    try:
        _close_sinks(writer, logger)
    except ViewerUnavailable as e:
        viewer_error = e
    n_box = _n_box(config, cascade)
    point_errors = _point_errors_of(args, source, point_names, pts2d, pts3d, done)
    if args.plot and done:
        _write_plot(args, source, done, pred, lost, esses, n_box, point_errors)

    print(
        f"tracked {len(done)} frames of {source.describe()} with N={n_box} "
        f"(model {args.model}{', depth registered' if calib is not None else ''}"
        f"{f', {n_points} body points' if cascade is not None else ''})"
    )
    if bg_note is not None:
        print(f"note: {bg_note}")
    if n_windowed < n_steps:
        print(
            f"note: {n_steps - n_windowed} of {n_steps} steps counted histograms on the whole "
            "frame (exact, slower): particle boxes left the histogram window sized for the "
            "initial box (ColourInfo.windowed)"
        )
    idx = np.asarray(done, int)
    if source.gt_boxes is not None and idx.size:
        vis = None if source.visible is None else np.asarray(source.visible)[idx]
        summary = summarise(np.stack(pred), source.gt_boxes[idx], vis, np.asarray(lost))
        print(format_summary({Path(str(args.path)).name or str(args.path): summary}))
    if point_errors is not None:
        print(_point_table(point_errors))
    if args.out:
        print(f"boxes written to {args.out}")
    if args.rrd:
        print(f"Rerun recording written to {args.rrd}")
    if args.plot and done:
        print(f"plot written to {args.plot}")
    return 0 if viewer_error is None else _fail(str(viewer_error))


def _n_box(config, cascade) -> int:
    """Particles of the box filter (layer 1 of a cascade)."""
    return config.box.n_particles if cascade is not None else config.n_particles


def _write_plot(
    args, source, done, pred, lost, esses, n_particles: int, points: _PointErrors | None = None
) -> None:
    """``--plot``: per-frame IoU (with ground truth; 0 when lost) and ESS / N, the
    success plot with its AUC, and the body points' 3D errors per frame (scored against
    synthetic joints), as one PNG (``cpf_jax.charts``)."""
    from cpf_jax import charts
    from cpf_jax.metrics import run_ious, success_curve

    idx = np.asarray(done, int)
    ess = np.asarray(esses, np.float64) / n_particles
    series = {"ESS / N": (idx, ess)}
    name = Path(str(args.path)).name or str(args.path)
    curve = None
    if source.gt_boxes is not None:
        vis = None if source.visible is None else np.asarray(source.visible)[idx]
        iou, counts = run_ious(np.stack(pred), source.gt_boxes[idx], vis, np.asarray(lost))
        series = {"IoU with the ground truth (0: lost)": (idx, np.where(counts, iou, np.nan))}
        series["ESS / N"] = (idx, ess)
        curve = np.asarray(success_curve(iou, counts))
    panels = [
        charts.line_chart(
            series,
            title=f"{name}: per frame",
            xlabel="frame",
            ylabel="IoU, ESS / N" if curve is not None else "ESS / N",
            ylim=(0.0, 1.0),
            markers=idx.size <= 60,
        )
    ]
    if curve is not None:
        panels.append(charts.success_plot({name: curve}, title=f"{name}: success plot"))
    if points is not None and points.frames.size:
        labels = [
            n if n == j else f"{n} ({j})" for n, j in zip(points.names, points.joints, strict=True)
        ]
        panels.append(
            charts.line_chart(
                {
                    label: (points.frames, np.minimum(points.err3d[:, k], 500.0))
                    for k, label in enumerate(labels)
                },
                title=f"{name}: body points, 3D error (mm, clipped at 500; lost: 500)",
                xlabel="frame",
                ylabel="error (mm)",
                ylim=(0.0, 500.0),
                markers=False,
            )
        )
    try:
        charts.save_png(np.concatenate(panels), args.plot)
    except OSError as e:
        raise CpfJaxError(f"--plot: {e}") from None


def _start_and_box(
    args: argparse.Namespace, source, n_frames: int, auto: bool
) -> tuple[int, np.ndarray | None]:
    """The first frame to track and its box (None: ``--init auto`` finds it), for a
    recording (finite source)."""
    if args.start is not None and not 0 <= args.start < n_frames:
        raise UsageError(f"--start {args.start} is outside 0..{n_frames - 1}")
    if auto:
        return (0 if args.start is None else args.start), None
    start = source.first_visible if args.init is None else 0
    if args.start is not None:
        start = args.start
    if args.init is not None:
        return start, parse_box(args.init)
    if args.start is not None:
        if source.gt_boxes is not None and (source.visible is None or source.visible[start]):
            return start, np.asarray(source.gt_boxes[start], np.float32)
        raise UsageError(
            f"{source.describe()}: no ground-truth box at frame {start}; give --init x,y,w,h"
        )
    box = source.init_box
    if box is None or start is None:
        why = "no ground truth to start from"
        if source.gt_boxes is not None and source.visible is not None and not source.visible.any():
            # Every line is 0,0,0,0, NaN or of a non-positive size (io.groundtruth).
            why = "its ground truth shows the target in no frame"
        raise UsageError(f"{source.describe()}: {why}; give --init x,y,w,h or auto")
    return start, box


def _open_live(args: argparse.Namespace, source, register, need_bg: bool, auto: bool):
    """``(start, box, background frames, frames)`` of a live stream.

    A camera (or a RealSense recording) is read once, in order: the background frames
    (``--background N``: the first N frames, or ``A:B``; the scene should be empty
    then) come before tracking, which starts at ``--start`` (default: the frame after
    the background, 0 for ``--model rgb``). ``frames`` yields ``(index, frame)`` from
    there until the stream ends (``--max-frames`` and Ctrl-C are the caller's).
    ``box`` is None with ``--init auto``.
    """
    where = source.describe()
    if args.init is None:
        raise UsageError(
            f"{where}: a live source has no ground truth; give --init x,y,w,h or --init auto"
        )
    box = None if auto else parse_box(args.init)
    bg = parse_live_background(args.background) if need_bg else (0, 0)
    start = bg[1] if args.start is None else args.start
    if start < bg[1]:
        raise UsageError(
            f"--start {start}: a live stream cannot go back; the background frames "
            f"{bg[0]}..{bg[1] - 1} come first"
        )
    stream = iter(source)
    bg_frames = []
    for i in range(start):
        try:
            frame = register(next(stream), f"{where} frame {i}")
        except StopIteration:
            raise UsageError(
                f"{where}: the stream ended after {i} frames, before frame {start}"
            ) from None
        if bg[0] <= i < bg[1]:
            bg_frames.append(frame)

    def frames():
        for i, raw in enumerate(stream, start):
            yield i, register(raw, f"{where} frame {i}")

    return start, box, bg_frames or None, frames()


def _find_start(source, frames, scene):
    """``(box, frames)`` for ``--init auto``: skip to the first frame in which
    :func:`cpf_jax.detect.find_person` finds someone; ``frames`` starts there."""
    from cpf_jax.detect import find_person

    first = None
    for i, frame in frames:
        if first is None:
            first = i
        box = find_person(frame, scene)
        if box is not None:
            x, y, w, h = (int(v) for v in box)
            print(f"--init auto: a person at {x},{y},{w},{h} in frame {i}", file=sys.stderr)
            return box, itertools.chain([(i, frame)], frames)
    where = source.describe()
    if first is None:
        raise UsageError(f"--init auto: {where} has no frame to search")
    raise UsageError(
        f"--init auto: no person-shaped foreground in frames {first}..{i} of {where} "
        "(is the background the empty scene?); give --init x,y,w,h"
    )


def quiet_background(read, indices: list[int]) -> tuple[list, str]:
    """``--background auto``: of the recording frames ``indices`` (``read(i) -> Frame``),
    those with the least foreground in front of the scene they show, at most
    ``AUTO_BACKGROUND_FRAMES`` (:func:`cpf_jax.kernels.background.quiet_frames`), and
    a line naming them for the run's summary. The candidates are kept only on the
    shares' pixel lattice (every ``QUIET_STRIDE``-th pixel); the chosen frames are read
    again at full resolution."""
    import jax

    from cpf_jax.kernels.background import foreground_shares, quiet_frames

    colour, depth = [], []
    for i in indices:  # one full-resolution frame in memory at a time
        frame = read(i)
        colour.append(np.asarray(frame.colour)[::QUIET_STRIDE, ::QUIET_STRIDE].copy())
        depth.append(np.asarray(frame.depth)[::QUIET_STRIDE, ::QUIET_STRIDE].copy())
    colour, depth = np.stack(colour), np.stack(depth)
    share = jax.jit(foreground_shares, static_argnames="stride")(colour, depth, stride=1)
    n_max = min(AUTO_BACKGROUND_FRAMES, len(indices))
    picked, count = quiet_frames(share, n_max, min(5, n_max))
    chosen = [indices[int(i)] for i in np.asarray(picked)[: int(count)]]
    note = (
        f"background: median of the {len(chosen)} of {len(indices)} frames with the least "
        f"foreground ({_ranges(chosen)}; choose with --background)"
    )
    return [read(i) for i in chosen], note


def _ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5, 7, 8]`` -> ``"0-2, 5, 7-8"``."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)


def parse_live_background(text: str) -> tuple[int, int]:
    """``--background`` of a live stream: ``"N"`` (frames 0..N-1; ``"auto"``: 25) or
    ``"A:B"`` -> ``(A, B)``."""
    if text == "auto":
        text = str(AUTO_BACKGROUND_FRAMES)
    try:
        if ":" in text:
            a, b = (int(v) for v in text.split(":"))
        else:
            a, b = 0, int(text)
    except ValueError:
        a = b = 0
    if not 0 <= a < b:
        raise UsageError(
            f"--background for a live stream expects N >= 1 (its first N frames) or A:B with "
            f"0 <= A < B, got {text!r}"
        )
    return a, b


def _frame_name(source, i: int) -> str:
    names = getattr(source, "names", None)
    return names[i] if names is not None else f"{source.describe()} frame {i}"


def _cascade(args, source, first_frame, start, box, box_config, box_params, calib, background):
    """``(config, params, filter, points, names)`` of the cascade (``--points``)."""
    import jax.numpy as jnp

    from cpf_jax.cascade import CascadeConfig, build_cascade, check_points, default_cascade_params
    from cpf_jax.colour import ColourConfig
    from cpf_jax.points import PointFilterConfig
    from cpf_jax.rgbd import RGBDConfig, default_rgbd_params

    if args.point_particles < 1:
        raise UsageError(f"--point-particles must be >= 1, got {args.point_particles}")
    if getattr(source, "has_depth", True) is False or not np.any(first_frame.depth):
        raise UsageError(f"--points needs depth: {source.describe()} has none at frame {start}")
    auto = args.points == "auto"
    if not auto:
        points, names = parse_points(args.points, source, start)
        points = check_points(points, (source.size[1], source.size[0]))
    if isinstance(box_config, ColourConfig):  # the colour layer as the "rgb" variant
        box_config = RGBDConfig(
            variant="rgb",
            n_particles=box_config.n_particles,
            colour=box_config,
            window=box_config.window,
        )
        box_params = default_rgbd_params(box_config)._replace(colour=box_params)
    # 3D estimates need the intrinsics of the frames' pixel grid: the colour camera's
    # after registration, else the source's own (Kinect v2 depth by default).
    intrinsics = calib.colour if calib is not None else source.intrinsics
    point_kw = {} if intrinsics is None else {"intrinsics": intrinsics}
    foreground = background is not None
    if foreground:  # the union of the sizeable components inside the foreground
        point_kw.update(seg_max_dz_mm=25.0, surface_max_dist_mm=40.0, min_component_fraction=0.05)
    config = CascadeConfig(
        box=box_config,
        points=PointFilterConfig(n_particles=args.point_particles, **point_kw),
        foreground=foreground,
    )
    if auto:
        points, names = _auto_points(config, first_frame, box, background, start)
    params = default_cascade_params(config)
    point_params = params.points
    if args.points in ("joints", "auto"):  # head, hands, feet: the joints lie behind
        offset = jnp.asarray(JOINT_DEPTH_OFFSET_MM, jnp.float32)
        point_params = point_params._replace(joint_depth_offset=offset)
    params = params._replace(box=box_params, points=point_params)
    return config, params, build_cascade(config), points, names


def _auto_points(config, frame, box, background, start: int):
    """``--points auto``: head, hands and feet found on the body in the start box
    (``cpf_jax.cascade.find_body_points``), printed on stderr; one error line when the
    box holds no body."""
    import jax
    import jax.numpy as jnp

    from cpf_jax.cascade import find_body_points
    from cpf_jax.points import AUTO_POINTS

    xy, reach = jax.jit(find_body_points, static_argnums=0)(
        config, frame, jnp.asarray(box, jnp.float32), background
    )
    xy, reach = np.asarray(xy), np.asarray(reach)
    if not np.all(reach > 0):
        raise UsageError(
            f"--points auto: no body at the box's depth in frame {start}; give x,y;x,y;..."
        )
    found = "; ".join(f"{n} {x:.0f},{y:.0f}" for n, (x, y) in zip(AUTO_POINTS, xy, strict=True))
    print(f"--points auto: {found} in frame {start}", file=sys.stderr)
    return xy.astype(np.float32), AUTO_POINTS


def _auto_joints(source, start: int) -> tuple[str, ...] | None:
    """The synthetic joints ``--points auto``'s points stand for (``AUTO_POINTS`` order:
    "a" is the joint further left in the image at ``start``), or None without joints."""
    seq = getattr(source, "sequence", None)
    names = list(getattr(seq, "joint_names", ()))
    if not all(n in names for n in JOINTS):
        return None
    u = seq.joints2d[start, :, 0]
    out = ["head"]
    for part in ("hand", "foot"):
        left, right = f"left_{part}", f"right_{part}"
        pair = (left, right) if u[names.index(left)] <= u[names.index(right)] else (right, left)
        out.extend(pair)
    return tuple(out)


class _PointErrors(NamedTuple):
    names: tuple[str, ...]  # the tracked points
    joints: tuple[str, ...]  # the synthetic joint each point stands for
    frames: np.ndarray  # [T'] frames scored (visible target, not the initial frame)
    err2d: np.ndarray  # [T', P] px
    err3d: np.ndarray  # [T', P] mm (inf: no 3D estimate)


def _point_errors_of(args, source, names, pts2d, pts3d, done) -> _PointErrors | None:
    """Errors of the tracked points against the synthetic joints they stand for
    (``--points joints`` or ``auto`` on a synthetic scenario), over the tracked frames
    ``done`` where the target is visible; None without joints to score against."""
    if not names or not done or args.points not in ("joints", "auto"):
        return None
    done = np.asarray(done, int)
    joints = tuple(names) if args.points == "joints" else _auto_joints(source, done[0])
    if joints is None:
        return None
    seq = source.sequence
    idx = [list(seq.joint_names).index(n) for n in joints]
    sel = np.ones(len(done), bool)
    sel[0] = False  # the initial frame has no 3D estimate
    if source.visible is not None:
        sel &= np.asarray(source.visible, bool)[done]
    frames = done[sel]
    p2, p3 = np.stack(pts2d)[sel], np.stack(pts3d)[sel]
    e2 = np.linalg.norm(p2 - (seq.joints2d[frames][:, idx] + 0.5), axis=-1)
    e3 = np.linalg.norm(p3 - seq.joints3d[frames][:, idx], axis=-1)
    e3 = np.where(np.isfinite(e3), e3, np.inf)  # no 3D estimate counts as lost
    return _PointErrors(tuple(names), joints, frames, e2, e3)


def _point_table(errors: _PointErrors) -> str:
    """Median 2D / 3D error of each point (Markdown)."""
    lines = ["| point | joint | median 2D error px | median 3D error mm |", "|---|---|---:|---:|"]
    for k, name in enumerate(errors.names):
        e2, e3 = errors.err2d[:, k], errors.err3d[:, k]
        med2 = float(np.median(e2)) if e2.size else float("nan")
        med3 = float(np.median(e3)) if e3.size else float("nan")
        lines.append(f"| {name} | {errors.joints[k]} | {med2:.1f} | {med3:.1f} |")
    return "\n".join(lines)


def _calibration(args: argparse.Namespace, source):
    """The calibration in effect: ``--calib``, else the folder's ``calibration.json``.

    A folder's file that is not in the registration format is ignored by the
    colour model (it reads intrinsics from it) and an error for the RGB-D models.
    """
    from cpf_jax.registration import CalibrationError, calibration_from_dict, load_calibration

    if args.calib is not None:
        return load_calibration(args.calib)
    if not getattr(source, "calibration", None):
        return None
    where = f"{source.path}/calibration.json" if source.path is not None else "calibration"
    try:
        return calibration_from_dict(source.calibration, source=where)
    except CalibrationError:
        if args.model == "rgb":
            return None
        raise


def _registrar(calib, uses_depth: bool = True):
    """``register(frame, name) -> Frame``: depth registered to colour by ``calib`` (one
    jitted call per frame; the frame unchanged when there is no calibration).

    Without a calibration the depth must already be registered to the colour image: a
    depth image of another size is one error line naming the frame (``uses_depth``; the
    colour layer alone never reads depth, so it leaves raw depth alone)."""
    if calib is None:

        def unregistered(f, name: str):
            if uses_depth and f.depth.shape != f.colour.shape[:2]:
                raise UsageError(
                    f"{name}: depth is {f.depth.shape[1]}x{f.depth.shape[0]} but colour is "
                    f"{f.colour.shape[1]}x{f.colour.shape[0]}; without a calibration "
                    "(--calib FILE, or the folder's calibration.json) depth must already be "
                    "registered to the colour image"
                )
            return f

        return unregistered
    import jax

    from cpf_jax.registration import register_depth
    from cpf_jax.types import Frame

    register_jit = jax.jit(register_depth, static_argnums=(1,))

    def register(f: Frame, name: str) -> Frame:
        if f.depth.shape[::-1] != tuple(calib.depth_size):
            raise UsageError(
                f"{name}: depth is {f.depth.shape[1]}x{f.depth.shape[0]} but the "
                f"calibration expects {calib.depth_size[0]}x{calib.depth_size[1]}"
            )
        if f.colour.shape[1::-1] != tuple(calib.colour_size):
            raise UsageError(
                f"{name}: colour is {f.colour.shape[1]}x{f.colour.shape[0]} but the "
                f"calibration expects {calib.colour_size[0]}x{calib.colour_size[1]}"
            )
        return Frame(f.colour, np.asarray(register_jit(f.depth, calib)))

    return register


def _log_frame(logger, i, frame_np, source, est, state, ess, ms) -> None:
    import jax.numpy as jnp

    from cpf_jax.kernels.boxes import cxcywh_to_xywh

    logger.log_frame(i, frame_np, source.intrinsics)
    logger.log_box(i, est, label="cpf")
    if source.gt_boxes is not None and (source.visible is None or source.visible[i]):
        logger.log_gt_box(i, source.gt_boxes[i])
    p = state.particles
    boxes = np.asarray(cxcywh_to_xywh(p[:, jnp.array([0, 1, 4, 5])]))
    logger.log_particles(i, boxes, np.asarray(state.log_weights), log_weights=True)
    logger.log_scalar(i, "ess", ess)
    logger.log_scalar(i, "ms_per_frame", ms)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
