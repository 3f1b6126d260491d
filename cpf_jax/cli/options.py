"""``cpf-track``'s command line: the argument table and the parsing and checking of every
option, before any frame is read (a bad or misplaced option is one error line)."""

from __future__ import annotations

import argparse

import numpy as np

from cpf_jax import params as pp
from cpf_jax.errors import CpfJaxError
from cpf_jax.points import BODY_POINT_DEPTH_OFFSET_MM, BODY_POINTS

__all__ = [
    "AUTO_BACKGROUND_FRAMES",
    "AUTO_CANDIDATES",
    "AUTO_INIT_MIN_CONFIDENCE",
    "AUTO_POINTS_MIN_CONFIDENCE",
    "FRAMELESS",
    "JOINTS",
    "JOINT_DEPTH_OFFSET_MM",
    "UsageError",
    "build_parser",
    "check_box",
    "model_options",
    "param_options",
    "parse_background",
    "parse_bins",
    "parse_box",
    "parse_layout",
    "parse_live_background",
    "parse_points",
]


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
# --background none reads no background frames: the RGB-D filter takes each frame's scene
# from the frame itself (rgbd.RGBDConfig.side_scene).
FRAMELESS = "none"
AUTO_CANDIDATES = 150
QUIET_STRIDE = 4  # pixel lattice of the candidates' foreground shares
# --init auto and --points auto start only on finds at least this sure (detect,
# cascade.body_points_confidence): a whole upright person in view scores about 1.
AUTO_INIT_MIN_CONFIDENCE = 0.5
AUTO_POINTS_MIN_CONFIDENCE = 0.5


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
            f"--background expects none, auto, empty, N >= 1 or A:B with frames inside "
            f"0..{n_frames - 1}, got {text!r}"
        )
    return frames


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
        "--log-raw",
        action="store_true",
        help="Rerun: log colour and depth pixels raw, every frame (default: JPEG colour, "
        "PNG depth every 3rd frame, about 85 KB a 512x424 frame against 1 MB)",
    )
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
        "--depth-scale",
        type=float,
        default=None,
        metavar="N",
        help="stored depth values per metre of a folder or .npz (1000: mm, 5000: TUM, 1: "
        "metres; default: the format's own, else detected from the values, with a note)",
    )
    p.add_argument(
        "--background",
        default=None,
        help="background frames for the RGB-D models: 'none' (default, with --multi 'auto': "
        "each frame's scene from the frame itself, for a camera that moves or a scene never "
        "seen empty), 'auto' "
        "(a static camera: up to 25 frames with the least foreground among up to 150 evenly "
        "spaced ones; a live stream's first 25), N (evenly spaced over the recording; a live "
        "stream's first N), A:B (frames A..B-1, 0-based) or 'empty' (a synthetic scenario's "
        "empty room)",
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
        "--correlation",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--model rgb: add a correlation filter learnt online on the target against its "
        "surround to the likelihood (default off)",
    )
    p.add_argument(
        "--follow-camera",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--model rgb: move the particles with the whole image's shift between frames "
        "(a panning or shaking camera; default on)",
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
    p.add_argument(
        "--multi",
        action="store_true",
        help="track every person (cpf_jax.multi): people are found by the person detector "
        "against the --background model (none, the default, means auto here: a static "
        "camera's emptiest frames), confirmed, kept through crossings and re-entries "
        "under one identity each; an RGB-D model (grid-occlusion unless --model names one); "
        "no --init",
    )
    p.add_argument(
        "--mot",
        metavar="FILE",
        help="--multi: write MOTChallenge lines frame,id,x,y,w,h,conf,-1,-1,-1 (1-based "
        "frames and pixels) as the run goes",
    )
    p.add_argument(
        "--mot-gt",
        metavar="FILE",
        help="--multi: score the run against this MOTChallenge ground truth "
        "(frame,id,x,y,w,h[,active,class,visibility]): MOTA, MOTP, IDF1, HOTA, id switches",
    )
    p.add_argument(
        "--max-people", type=int, default=6, help="--multi: people tracked at once (slots)"
    )
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--tune-malloc",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="raise glibc's mmap/trim thresholds and keep one malloc arena before JAX starts "
        "(cpu_tuning.tune_malloc: XLA's large temporaries are reused, not faulted in anew "
        "every frame; the process keeps its peak heap; on by default, no effect off glibc)",
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


def model_options(args: argparse.Namespace) -> tuple[dict, dict]:
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
    if args.correlation is not None:
        from cpf_jax.colour import CorrelationConfig

        colour_kw["correlation"] = CorrelationConfig() if args.correlation else None
    if args.follow_camera is not None:
        from cpf_jax.colour.camera import DOWNSCALE

        colour_kw["camera_motion"] = DOWNSCALE if args.follow_camera else None
    layout_opts = args.layout_feature or args.layout_mirror or args.layout_weight is not None
    if layout_opts and "layout" in colour_kw and colour_kw["layout"] is None:
        raise UsageError(
            "--layout-feature, --layout-mirror and --layout-weight need a layout, not --layout off"
        )
    if args.layout_weight is not None and not args.layout_weight >= 0:
        raise UsageError(f"--layout-weight must be >= 0, got {args.layout_weight}")
    if (colour_kw or args.layout_weight is not None) and args.model != "rgb":
        raise UsageError(
            f"--contrast, --unseen, --template-update, --correlation, --follow-camera and "
            f"--layout* apply to --model rgb, "
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
    """``params`` (the colour layer's for ``--model rgb``, else the RGB-D filter's) with the
    command line's parameter options applied: ``--sigma``, ``--layout-weight``,
    ``--size-velocity-decay``, ``--size-hold``."""
    import jax.numpy as jnp

    sigma = "histogram.sigma" if args.model == "rgb" else "colour.sigma"
    values = {
        sigma: args.sigma,
        "layout.weight": args.layout_weight,  # --model rgb only (checked in model_options)
        "motion.size_velocity_decay": args.size_velocity_decay,
        "motion.size_hold": args.size_hold,  # --model rgb only (checked in model_options)
    }
    for path, value in values.items():
        if value is not None:
            params = pp.replace(params, path, jnp.float32(value))
    return params
