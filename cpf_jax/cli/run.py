"""``cpf-track``'s tracking loop: one jitted ``init``, then one jitted ``step`` per frame, each
result written as it goes (CSV row, Rerun log). It reads only what every filter's state
and info share (``cpf_jax.filter``), and the body points when the model has them."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

from cpf_jax.cli.inputs import Inputs, frame_name
from cpf_jax.cli.model import Model
from cpf_jax.cli.summary import Results, new_results, point_errors, write_plot
from cpf_jax.errors import CpfJaxError, ViewerUnavailable

__all__ = ["LogThread", "Row", "Sinks", "track"]


class Row(NamedTuple):
    """One tracked frame."""

    box: np.ndarray  # [4] xywh
    lost: bool
    ess: float
    ms: float
    points2d: np.ndarray  # [P, 2] px (NaN: none)
    points3d: np.ndarray  # [P, 3] mm (NaN: none)
    box_used: np.ndarray  # [4] the box layer 2 worked in (the box itself without layer 2)
    surface: np.ndarray | None = None  # [M, 3] mm layer 2's body points (logged runs)
    weighed: Any = None  # the box particles before resampling (logged runs), or None
    hidden: np.ndarray | None = None  # [P] bool, layer 2 reports the point hidden


class LogThread:
    """The Rerun log written on a thread of its own, so that encoding the images (JPEG, PNG)
    overlaps the next step instead of adding to it. Frames go through a queue of
    ``depth`` entries in order (a slower log holds the loop back instead of filling memory);
    the first error a log call raises is raised again by the next ``submit`` or by
    ``close``."""

    def __init__(self, depth: int = 4) -> None:
        import queue
        import threading

        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name="cpf-track log", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            if self._error is None:
                try:
                    job()
                except BaseException as e:  # handed to the loop's thread
                    self._error = e

    def _raise(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def submit(self, job) -> None:
        """Run ``job()`` on the log thread, after every job submitted before it."""
        self._raise()
        self._queue.put(job)

    def close(self) -> None:
        """Wait for the jobs submitted so far; raise the first error one of them raised."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._raise()


class Sinks:
    """Where a run's rows go as it goes: the CSV (``--out``) and the Rerun log (``--rrd``,
    ``--spawn``, ``--connect``)."""

    def __init__(self, args: argparse.Namespace, source, model: Model) -> None:
        from cpf_jax.io import ResultsWriter

        self.source, self.model, self.writer, self.logger, self.surface = (
            source,
            model,
            None,
            None,
            None,
        )
        self.log_thread: LogThread | None = None
        self.init_frame: int | None = None  # the frame init ran on: the first written
        # The logger first: an unreachable viewer fails before any file is written.
        if args.rrd or args.spawn or args.connect:
            import jax

            from cpf_jax.viz import RerunLogger, default_blueprint

            self.logger = RerunLogger(
                args.rrd,
                spawn=args.spawn,
                connect=args.connect,
                raw=args.log_raw,
                blueprint=default_blueprint(points=bool(model.points)),
            )
            self.log_thread = LogThread()
            if model.points:  # layer 2's segmented body, as a 3D point cloud
                from cpf_jax.cascade import body_surface

                self.surface = jax.jit(body_surface, static_argnums=0)
        columns = [
            f"{n}_{c}" for n in model.points for c in ("x", "y", "X_mm", "Y_mm", "Z_mm", "hidden")
        ]
        if args.out:
            self.writer = ResultsWriter(args.out, extra_columns=("ess", "lost", "ms", *columns))

    def write(self, i: int, frame_np, frame, row: Row, state: Any) -> None:
        if self.init_frame is None:
            self.init_frame = i
        if self.writer is not None:
            extras = {}
            for n, name in enumerate(self.model.points):
                for c, v in zip(("x", "y"), row.points2d[n], strict=True):
                    extras[f"{name}_{c}"] = round(float(v), 2)
                if np.all(np.isfinite(row.points3d[n])):
                    for c, v in zip(("X_mm", "Y_mm", "Z_mm"), row.points3d[n], strict=True):
                        extras[f"{name}_{c}"] = round(float(v), 1)
                extras[f"{name}_hidden"] = int(row.hidden[n])
            self.writer.write(
                i, row.box, ess=round(row.ess, 2), lost=int(row.lost), ms=round(row.ms, 3), **extras
            )
        if self.logger is not None:
            self.log_thread.submit(lambda: self._log(i, frame_np, frame, row, state))

    def _log(self, i: int, frame_np, frame, row: Row, state: Any) -> None:
        log, source = self.logger, self.source
        log.log_frame(i, frame_np, source.intrinsics)
        # No labels: the two boxes often coincide, and their labels would overlap; the
        # colour view's name says which colour is which.
        log.log_box(i, row.box)
        if source.gt_boxes is not None and (source.visible is None or source.visible[i]):
            log.log_gt_box(i, source.gt_boxes[i], label=None)
        log.log_cloud(i, state, weighed=row.weighed)
        log.log_scalar(i, "ess", row.ess)
        if i != self.init_frame:  # steps only: the first frame ran init, not a step
            log.log_scalar(i, "ms_per_frame", row.ms)
        if self.model.points:
            names = list(self.model.points)
            log.log_points2d(i, row.points2d, labels=names)
            log.log_points3d(i, row.points3d, labels=names)
            body = row.surface  # the step's own; the first frame's is computed here
            if body is None:
                config, background = self.model.config, self.model.context.background
                body = self.surface(config, frame, row.box_used, background)
            log.log_points3d(i, body, "body/surface", radius=0.004)

    def close(self, failing: bool = False) -> None:
        """Close the CSV and the Rerun log. With ``failing`` (an exception is already on its
        way), a log that fails (a viewer that cannot take it) is one warning line instead
        of an error that would hide the first."""
        if self.writer is not None:
            self.writer.close()
        if self.logger is None:
            return
        try:
            try:
                self.log_thread.close()
            finally:
                self.logger.close()
        except Exception as e:
            if not failing:
                raise
            print(f"cpf-track: warning: {e}", file=sys.stderr)


def _first_row(inputs: Inputs, model: Model, state: Any, ms: float) -> Row:
    """The initial frame's row: the start box, the points where they start (on the body
    pixel nearest each given point) with their 3D positions."""
    box = np.asarray(inputs.box, np.float32)
    if not model.points:
        return Row(box, False, float(model.n_particles), ms, *NO_POINTS, box)
    from cpf_jax.points import estimate_3d

    p2 = np.array(state.points.estimate, np.float32)
    p3 = np.array(estimate_3d(model.config.points, model.params.points, state.points))
    hidden = np.array(state.points.hidden_prob) > 0.5
    return Row(box, False, float(model.n_particles), ms, p2, p3, box, hidden=hidden)


#: The points of a run without layer 2: one shared pair of empty arrays, not two per frame.
NO_POINTS = (np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32))


def _step_row(model: Model, info: Any, ms: float) -> Row:
    """A step's row from the fields every box filter's info shares (and layer 2's points).

    The values are copied out of JAX's arrays (``np.array``): a view (``np.asarray``) would
    keep each step's device buffer alive for as long as the run keeps its rows."""
    box = np.array(info.box, np.float32)
    if model.points:
        p2, p3 = np.array(info.points.mean), np.array(info.points.mean3d)
        hidden = np.array(info.points.hidden)
        used = np.array(info.box_used)
        surface = info.points.surface
        surface = None if surface is None else np.asarray(surface)
    else:
        (p2, p3), used = NO_POINTS, box
        surface = hidden = None
    weighed = info.weighed_cloud
    weighed = None if weighed is None else type(weighed)(*map(np.asarray, weighed))
    return Row(box, bool(info.lost), float(info.ess), ms, p2, p3, used, surface, weighed, hidden)


def _record(results: Results, i: int, row: Row) -> None:
    results.frames.append(i)
    results.boxes.append(row.box)
    results.lost.append(row.lost)
    results.ess.append(row.ess)
    results.points2d.append(row.points2d)
    results.points3d.append(row.points3d)


def _loop(args, source, inputs: Inputs, model: Model, sinks: Sinks, results: Results) -> None:
    """Init on the first frame, step on the others; every row recorded and written."""
    import jax
    import jax.numpy as jnp

    from cpf_jax.progress import Progress
    from cpf_jax.types import Frame

    key = jax.random.PRNGKey(args.seed)
    bar = Progress(
        inputs.n_frames, label="tracking", interactive=False if args.no_progress else None
    )
    first = inputs.first
    box = jnp.asarray(inputs.box)
    frame = Frame(jnp.asarray(first.colour), jnp.asarray(first.depth))
    init, step = _compiled(args, model, key, frame, box, bar)
    state = None
    for i, frame_np in inputs.frames:
        frame = Frame(jnp.asarray(frame_np.colour), jnp.asarray(frame_np.depth))
        key, k = jax.random.split(key)
        t0 = time.perf_counter()
        if state is None:
            state = jax.block_until_ready(init(model.params, k, frame, box, model.context))
            row = _first_row(inputs, model, state, (time.perf_counter() - t0) * 1000.0)
        else:
            state, info = jax.block_until_ready(step(model.params, k, state, frame))
            row = _step_row(model, info, (time.perf_counter() - t0) * 1000.0)
            results.windowed.append(bool(info.windowed))
        if not np.all(np.isfinite(row.box)):  # never write a NaN box
            raise CpfJaxError(f"{frame_name(source, i)}: the filter produced a non-finite box")
        _record(results, i, row)
        sinks.write(i, frame_np, frame, row, state)
        bar.update(step_ms=row.ms)
    bar.close()  # the final progress line only for a completed run


def _compiled(args, model: Model, key, frame, box, bar):
    """``init`` and ``step`` compiled ahead of the first frame (each with its "compiling"
    line), and refused with one error line when they need more memory than is free
    (:mod:`cpf_jax.memory`)."""
    import jax

    from cpf_jax.errors import MemoryTooSmall
    from cpf_jax.memory import FREE_SHARE, check_fits, free_bytes, needed_bytes

    filt, params, context = model.filt, model.params, model.context
    with _compiling("init", bar):
        lowered = jax.jit(filt.init).lower(params, key, frame, box, context)
        init = lowered.compile()
    state = lowered.out_info  # the state's shapes, without tracing init again
    with _compiling("step", bar):
        step = jax.jit(filt.step).lower(params, key, state, frame).compile()
    needs = [n for n in (needed_bytes(init), needed_bytes(step)) if n is not None]
    free = free_bytes()
    h, w = frame.colour.shape[:2]
    try:
        check_fits(max(needs, default=None), f"--particles {args.particles} on {w}x{h}", free)
    except MemoryTooSmall as e:
        fit = int(args.particles * FREE_SHARE * free / max(needs))
        raise MemoryTooSmall(f"{e}; about {fit:,} particles fit") from None
    return init, step


@contextlib.contextmanager
def _compiling(what: str, bar) -> Iterator[None]:
    """One stderr line around compiling ``init`` or ``step`` (or loading it from the disk
    cache), with its time."""
    bar.clear()
    print(f"cpf-track: compiling {what} ...", end="", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    try:
        yield
    finally:
        print(f" {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)


def track(args: argparse.Namespace, source, inputs: Inputs, model: Model):
    """Track every frame of ``inputs``; returns ``(results, viewer_error)``. An error or
    Ctrl-C closes the outputs first (the CSV keeps its rows, the ``.rrd`` is completed,
    an interrupted run still writes its ``--plot``)."""
    sinks = Sinks(args, source, model)
    results = new_results()
    try:
        _loop(args, source, inputs, model, sinks, results)
    except BaseException as exc:
        sinks.close(failing=True)
        if isinstance(exc, KeyboardInterrupt) and args.plot and results.frames:
            try:
                errors = point_errors(args, source, model.points, results)
                write_plot(args, source, results, model.n_particles, errors)
            except CpfJaxError as e:  # the interrupt, not the plot, is what happened
                print(f"cpf-track: warning: {e}", file=sys.stderr)
        raise
    # A viewer that went away fails the run (exit 2), but only after the results it did
    # produce (CSV, .rrd, plot, summary) are written and printed.
    try:
        sinks.close()
    except ViewerUnavailable as e:
        return results, e
    return results, None
