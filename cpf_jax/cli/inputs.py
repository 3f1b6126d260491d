"""``cpf-track``'s inputs: the frame source's frames (registered when a calibration is in
effect), the first frame to track and its box, and the background model of the scene."""

from __future__ import annotations

import argparse
import itertools
import sys
import warnings
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

from cpf_jax.cli.options import (
    AUTO_BACKGROUND_FRAMES,
    AUTO_INIT_MIN_CONFIDENCE,
    FRAMELESS,
    QUIET_STRIDE,
    UsageError,
    check_box,
    parse_background,
    parse_box,
    parse_live_background,
)

__all__ = ["Inputs", "frame_name", "open_inputs", "quiet_background", "ranges"]


class Inputs(NamedTuple):
    """What the tracking loop starts from."""

    start: int  # the first frame tracked
    box: np.ndarray  # [4] its box (x, y, w, h)
    frames: Iterator  # (index, Frame) from ``start`` on
    first: Any  # the first frame (also the first item of ``frames``)
    background: Any  # the scene's Background (None without one)
    calibration: Any  # the depth-to-colour calibration in effect (None: none)
    note: str | None  # which frames made the background (``--background auto``)
    n_frames: int | None  # frames to track (None: a live stream)


def open_inputs(args: argparse.Namespace, source) -> Inputs:
    """Calibration, registration, start frame and box, background model, ``--init auto``
    and ``--max-frames``, for a recording or a live stream."""
    from cpf_jax.io.base import LiveSource
    from cpf_jax.io.groundtruth import check_groundtruth

    live = isinstance(source, LiveSource)
    calib = _calibration(args, source)
    auto = args.init is not None and args.init.strip().lower() == "auto"
    # Depth is read by the RGB-D models, the cascade and --init auto's person finder.
    uses_depth = args.model != "rgb" or args.points is not None or auto
    register = _registrar(calib, uses_depth=uses_depth)
    # A background model: the RGB-D models' foreground (unless each frame is its own
    # scene, --background none; --multi's births then read it too) and --init auto's
    # person finder (with --background none, the quiet frames of --background auto).
    multi = getattr(args, "multi", False)
    if args.background is None:  # the default: each frame's own scene; --multi's quiet frames
        args.background = "auto" if multi else FRAMELESS
    frameless = args.background == FRAMELESS
    need_bg = (args.model != "rgb" and not frameless) or auto
    note = None
    if live:
        start, box, bg_frames, frames = _open_live(args, source, register, need_bg, auto)
        n_frames = None
    else:
        start, box, bg_frames, frames, note = _open_recording(args, source, register, need_bg, auto)
        n_frames = len(source) - start
        n_frames = n_frames if args.max_frames is None else min(n_frames, args.max_frames)
    scene = _median_background(bg_frames)
    if auto:
        box, frames = _find_start(source, frames, scene)
    frames = itertools.islice(frames, args.max_frames)  # None: to the end
    try:
        start, first = next(frames)
    except StopIteration:
        raise UsageError(f"{source.describe()}: no frame to track") from None
    if box is not None or not multi:
        check_box(box, source.size, source.describe())
    if not live and source.gt_boxes is not None:
        check_groundtruth(source.gt_boxes, source.visible, source.size, source.describe())
    _check_colour(source, start, first)
    _check_depth(args, source, start, first)
    if uses_depth:
        more = (bg_frames or [])[:4]
        if not more and not live:  # no background frames read: four spread over the recording
            name = source.describe()
            more = [register(source.read(i), name) for i in parse_background("4", len(source))]
        _check_alignment([first, *more], source.describe())
    frames = itertools.chain([(start, first)], frames)
    return Inputs(start, box, frames, first, None if frameless else scene, calib, note, n_frames)


def _check_depth(args: argparse.Namespace, source, start: int, first) -> None:
    """A model that reads depth (``--model`` other than ``rgb``, ``--points``) on a
    source without any is one error line, not a run that is lost in every frame."""
    needs = [f"--model {args.model}"] if args.model != "rgb" else []
    needs += ["--points"] if args.points is not None else []
    if not needs:
        return
    if not source.has_depth:
        why = "has no depth images (colour only)"
    elif not np.any(first.depth):
        why = f"has no depth at frame {start} (every pixel is 0, i.e. missing)"
        later = _first_where(source, start + 1, lambda f: np.any(f.depth))
        if later is not None:
            raise UsageError(
                f"{' and '.join(needs)} read depth, but {source.describe()} {why}; its "
                f"depth starts at frame {later}: start there with --start {later}"
            )
    else:
        return
    raise UsageError(
        f"{' and '.join(needs)} read depth, but {source.describe()} {why}; "
        "track the colour alone with --model rgb and no --points"
    )


def _first_where(source, begin: int, test, look: int = 300) -> int | None:
    """The first frame from ``begin`` (of the next ``look``) that passes ``test(frame)``,
    for a recording; None for a live stream or when none does."""
    from cpf_jax.io.base import LiveSource

    if isinstance(source, LiveSource):
        return None
    return next(
        (i for i in range(begin, min(len(source), begin + look)) if test(source.read(i))), None
    )


def _check_colour(source, start: int, first) -> None:
    """A blank start frame (one colour throughout: a camera warming up, a fade) is one error
    line naming the first frame that is not, since the box's appearance is learnt there."""
    if np.ptp(first.colour) > 0:
        return
    from cpf_jax.io.base import LiveSource

    value = ",".join(str(int(v)) for v in first.colour[0, 0])
    later = _first_where(source, start + 1, lambda f: np.ptp(f.colour) > 0)
    if isinstance(source, LiveSource):
        hint = "a camera still warming up? Start later, with a larger --background N"
    elif later is not None:
        hint = f"frame {later} is the first that is not: start there with --start {later}"
    else:
        hint = "none of the next 300 frames is otherwise"
    raise UsageError(
        f"{source.describe()} frame {start} is blank (every pixel RGB {value}), so the box's "
        f"colour cannot be learnt there; {hint}"
    )


def _check_alignment(frames: list, where: str) -> None:
    """A warning when the depth of ``frames`` (registered, or taken as registered) lines up
    with the colour only after a shift (:func:`cpf_jax.registration.check_alignment`)."""
    from cpf_jax.errors import InputWarning
    from cpf_jax.registration import check_alignment

    colour = np.stack([np.asarray(f.colour) for f in frames])
    depth = np.stack([np.asarray(f.depth) for f in frames])
    if colour.shape[1:3] != depth.shape[1:]:
        return  # the colour layer alone, on raw depth of another size
    found = check_alignment(colour, depth)
    if found.mirrored:
        warnings.warn(
            f"{where}: the depth lines up with the colour only when flipped left-right (edge "
            f"score {found.score_mirrored:.2f} flipped, {found.score:.2f} as given in "
            f"{len(frames)} frames): one of the two streams is mirrored; flip the depth "
            "images (or the colour) so that both show the scene the same way round",
            InputWarning,
            stacklevel=2,
        )
    elif found.misaligned:
        dx, dy = found.shift
        warnings.warn(
            f"{where}: {found.describe()} in {len(frames)} frames: the depth is not "
            f"registered to the colour; give the recording's calibration with --calib (its "
            f'"offset_px": [{dx}, {dy}] moves the depth onto the colour)',
            InputWarning,
            stacklevel=2,
        )


def _open_recording(args, source, register, need_bg: bool, auto: bool):
    """``(start, box, background frames, frames, note)`` of a recording (finite source)."""
    n_frames = len(source)

    def read(i: int):
        return register(source.read(i), f"{source.describe()} frame {i} ({source.names[i]})")

    start, box = _start_and_box(args, source, n_frames, auto)
    bg_frames, note = None, None
    if need_bg:
        # With --background none only --init auto's finder needs one: the quiet frames.
        mode = "auto" if args.background == FRAMELESS else args.background
        if mode == "empty":
            empty = source.empty_background()
            if empty is None:
                raise UsageError(
                    f"--background empty: {source.describe()} has no empty-scene frame "
                    "(only synthetic scenarios do); give N or A:B"
                )
            bg_frames = [empty]
        elif mode == "auto":
            bg_frames, note = quiet_background(read, parse_background("auto", n_frames))
        else:
            indices = parse_background(args.background, n_frames)
            bg_frames = [read(i) for i in indices]
            note = _clamped_background(args.background, indices, n_frames)
    frames = ((i, read(i)) for i in range(start, n_frames))
    return start, box, bg_frames, frames, note


def _clamped_background(text: str, indices: list[int], n_frames: int) -> str | None:
    """A note when ``--background N`` or ``A:B`` asked for frames the recording lacks."""
    asked = int(text) if ":" not in text else int(text.split(":")[1]) - int(text.split(":")[0])
    if asked <= len(indices):
        return None
    return (
        f"background: --background {text} asks for {asked} frames, the recording has "
        f"{n_frames}; the median of frames {ranges(indices)}"
    )


def _median_background(frames):
    """The per-pixel median of ``frames`` (``kernels.background.median_background``), or None."""
    if not frames:
        return None
    import jax

    from cpf_jax.kernels.background import median_background

    return jax.jit(median_background)(
        np.stack([f.colour for f in frames]), np.stack([f.depth for f in frames])
    )


def _start_and_box(
    args: argparse.Namespace, source, n_frames: int, auto: bool
) -> tuple[int, np.ndarray | None]:
    """The first frame to track and its box (None: ``--init auto`` finds it), for a
    recording (finite source)."""
    if args.start is not None and not 0 <= args.start < n_frames:
        raise UsageError(f"--start {args.start} is outside 0..{n_frames - 1}")
    if auto or getattr(args, "multi", False):  # the first frame found, or births
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
    multi = getattr(args, "multi", False)
    if args.init is None and not multi:
        raise UsageError(
            f"{where}: a live source has no ground truth; give --init x,y,w,h or --init auto"
        )
    box = None if auto or multi else parse_box(args.init)
    mode = "auto" if args.background == FRAMELESS else args.background  # the finder's
    bg = parse_live_background(mode) if need_bg else (0, 0)
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
    :func:`cpf_jax.detect.find_person_scored` finds someone with confidence at least
    ``AUTO_INIT_MIN_CONFIDENCE``; ``frames`` starts there. Less sure finds are passed
    over (the first one said on stderr); with none sure enough, one error line names the
    best of them."""
    from cpf_jax.detect import find_person_scored

    first, best, skipped = None, None, 0
    for i, frame in frames:
        first = i if first is None else first
        found = find_person_scored(frame, scene)
        if found is None:
            continue
        if found.confidence >= AUTO_INIT_MIN_CONFIDENCE:
            after = f" (passed over {skipped} less sure finds)" if skipped else ""
            print(
                f"--init auto: a person at {_xywh(found.box)} in frame {i}, confidence "
                f"{found.confidence:.2f}{after}",
                file=sys.stderr,
            )
            return found.box, itertools.chain([(i, frame)], frames)
        if skipped == 0:
            print(f"--init auto: passed over {_find(found, i)}", file=sys.stderr)
        skipped += 1
        if best is None or found.confidence > best[0].confidence:
            best = (found, i)
    where = source.describe()
    if first is None:
        raise UsageError(f"--init auto: {where} has no frame to search")
    if best is not None:
        raise UsageError(
            f"--init auto: no one found with confidence >= {AUTO_INIT_MIN_CONFIDENCE} in "
            f"frames {first}..{i} of {where}; the surest was {_find(*best)}; give "
            "--init x,y,w,h"
        )
    raise UsageError(
        f"--init auto: no person-shaped foreground in frames {first}..{i} of {where} "
        "(is the background the empty scene?); give --init x,y,w,h"
    )


def _xywh(box) -> str:
    return ",".join(str(int(v)) for v in box)


def _find(found, i: int) -> str:
    """One find in words: where, how sure and why not surer."""
    doubts = f": {'; '.join(found.doubts)}" if found.doubts else ""
    return f"a blob at {_xywh(found.box)} in frame {i} (confidence {found.confidence:.2f}{doubts})"


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
        f"foreground ({ranges(chosen)}; choose with --background)"
    )
    return [read(i) for i in chosen], note


def ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5, 7, 8]`` -> ``"0-2, 5, 7-8"``."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)


def frame_name(source, i: int) -> str:
    names = getattr(source, "names", None)
    return names[i] if names is not None else f"{source.describe()} frame {i}"


def _calibration(args: argparse.Namespace, source):
    """The calibration in effect: ``--calib``, else the folder's ``calibration.json``.

    A folder's file with intrinsics only (no ``"format"`` or ``"depth"`` entry, see
    docs/recordings.md) says the depth is registered already and registers nothing; any
    other file that is not in the registration format is ignored by the colour model and
    an error for the RGB-D models.
    """
    from cpf_jax.errors import InputWarning
    from cpf_jax.registration import CalibrationError, calibration_from_dict, load_calibration

    if args.calib is not None:
        return load_calibration(args.calib)
    if not getattr(source, "calibration", None):
        return None
    where = f"{source.path}/calibration.json" if source.path is not None else "calibration"
    if not {"format", "depth"} & set(source.calibration):
        if source.intrinsics is None and source.kind == "rgbd":  # its calibration.json
            warnings.warn(
                f"{where}: neither a registration (keys 'format', 'depth', ...) nor "
                "intrinsics ('intrinsics' or 'K'), so it is not used (docs/recordings.md)",
                InputWarning,
                stacklevel=2,
            )
        return None  # intrinsics only: registered depth (io.folders.intrinsics_from_calibration)
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
