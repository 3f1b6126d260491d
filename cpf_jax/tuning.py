"""Gradient-based tuning of filter parameters with optax (SPEC C7).

Usage::

    from cpf_jax import tuning
    from cpf_jax.colour import COLOUR_PROPS, build_colour_filter, default_colour_params

    data = tuning.stack_sequences([make_sequence("walk_across_medium", seed=s, n_frames=60)
                                   for s in (100, 101, 102)])
    run = tuning.runner(build_colour_filter(config))   # (params, key, sequence) -> [T, 4]
    result = tuning.tune(run, default_colour_params(), COLOUR_PROPS, data,
                         names=("histogram.sigma", "contrast.weight"), steps=40)
    result.params, result.history           # tuned parameters, loss per step

What is differentiated
----------------------
The loss is the mean DIoU loss (``diou_loss``; Zheng et al. 2020: ``1 - IoU`` plus the
squared centre distance over the squared diagonal of the smallest box enclosing both,
so it still has a gradient when the boxes do not overlap) of the filter's boxes against
the ground truth, over the sequences of a ``TuningData`` batch and ``keys`` filter seeds
each. The filters' estimates are weighted means of their particles, so the gradient
reaches every parameter of the likelihood through the importance weights
(``sigma``, ``contrast_weight``, ``layout_weight``, the aspect prior; in the RGB-D
filter the per-cell terms, floors, the occlusion prior and the flag transitions).
Across frames the gradient passes resampling by the estimator of Scibior and Wood
(2021), built into ``kernels.resample.resample_if``: the forward pass is unchanged
(every filter computes exactly what it computes untuned) and the resampled log-weights
carry their ancestors' derivatives.

What is not: the histogram and cell counts are exact integer counts over pixel
rects, piecewise constant in a box's coordinates, so the likelihood has no
derivative with respect to where a particle is. Parameters that act only by moving
particles (the motion noise ``tau``, the sampling shape ``motion``) get the part of
their gradient that flows through the weighted mean of the moved particles, not the
part through the likelihood of where they land: a biased gradient. Tune them by
search, or with care. Discrete choices (grid size, bins, motion model) live in the
static configs and are not tuned here.

Parameters are optimised unconstrained: each parameter's ``Prop`` (``cpf_jax.params``)
names its bijector (``"softplus"`` for positive, ``"sigmoid"`` for ``(0, 1)``,
``"identity"``) and whether it is trainable; parameters are named by dotted paths
(``"histogram.sigma"``, ``"motion.tau"``). A step whose loss or gradient is not finite is
skipped (the parameters keep their last finite values and the history records it), so a
tuning run never ends on NaN parameters.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array

from cpf_jax import charts
from cpf_jax import params as pp
from cpf_jax.filter import Context, Filter, track
from cpf_jax.kernels import boxes as box_ops
from cpf_jax.types import Frame

__all__ = [
    "TuningData",
    "TuneResult",
    "stack_sequences",
    "diou_loss",
    "runner",
    "make_loss",
    "unconstrained",
    "tune",
    "progress",
    "history_chart",
]


class TuningData(NamedTuple):
    """A batch of ``S`` sequences of equal length ``T`` and frame size (stacked on axis 0)."""

    frames: Frame  # [S, T, ...]
    boxes: Array  # [S, T, 4] ground-truth xywh; the filters start from boxes[:, 0]
    visible: Array  # [S, T] bool: frames that count in the loss
    background: Any = None  # per-sequence Background ([S, ...]) for the context, or None


class TuneResult(NamedTuple):
    params: Any  # the tuned parameters (the last finite step, or the best on validation)
    history: list  # one dict per step: step, loss, skipped, seconds, and each tuned value
    start_validation: float | None = None  # validation loss of the starting parameters


def stack_sequences(sequences: Sequence, backgrounds: Sequence | None = None) -> TuningData:
    """``TuningData`` from sequences with ``colour``, ``depth``, ``boxes`` and ``visible``
    (``cpf_jax.synthetic.SyntheticSequence``, ``cpf_jax.io`` recordings), all of one
    length and frame size (cut them with ``make_sequence(..., n_frames=T)``)."""
    if not sequences:
        raise ValueError("stack_sequences needs at least one sequence")
    shapes = {(np.shape(s.colour), np.shape(s.depth)) for s in sequences}
    if len(shapes) != 1:
        raise ValueError(
            f"sequences differ in length or frame size {sorted(shapes)}: "
            "cut them to one length (make_sequence(..., n_frames=T))"
        )
    frames = Frame(
        jnp.asarray(np.stack([s.colour for s in sequences])),
        jnp.asarray(np.stack([s.depth for s in sequences])),
    )
    boxes = jnp.asarray(np.stack([s.boxes for s in sequences]), jnp.float32)
    visible = jnp.asarray(np.stack([s.visible for s in sequences]), bool)
    background = None
    if backgrounds is not None:
        if len(backgrounds) != len(sequences):
            raise ValueError(f"{len(backgrounds)} backgrounds for {len(sequences)} sequences")
        background = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *backgrounds)
    return TuningData(frames, boxes, visible, background)


def diou_loss(pred: Array, gt: Array, visible: Array | None = None) -> Array:
    """Mean DIoU loss of ``[T, 4]`` xywh boxes over the ``visible`` frames.

    Per frame ``1 - IoU + |c_pred - c_gt|^2 / d^2``, with ``d`` the diagonal of the
    smallest box enclosing both (Zheng et al., AAAI 2020): 0 for equal boxes, up to
    2 for distant ones, with a gradient even without overlap. No visible frame: 0.
    """
    pred = jnp.asarray(pred, jnp.float32)
    gt = jnp.asarray(gt, jnp.float32)
    p0, p1 = pred[..., :2], pred[..., :2] + pred[..., 2:]
    g0, g1 = gt[..., :2], gt[..., :2] + gt[..., 2:]
    # Squared centre distance written out: the derivative of centre_distance's sqrt is
    # infinite where the boxes share a centre.
    centre = jnp.sum(((p0 + p1) - (g0 + g1)) ** 2, axis=-1) / 4.0
    diag = jnp.sum((jnp.maximum(p1, g1) - jnp.minimum(p0, g0)) ** 2, axis=-1)
    per_frame = 1.0 - box_ops.iou(pred, gt) + centre / jnp.maximum(diag, 1e-6)
    if visible is None:
        return jnp.mean(per_frame, axis=-1)
    w = jnp.asarray(visible, jnp.float32)
    return jnp.sum(per_frame * w, axis=-1) / jnp.maximum(jnp.sum(w, axis=-1), 1.0)


def runner(filt: Filter, box: str = "estimate") -> Callable:
    """``run(params, key, sequence) -> [T, 4]`` boxes of any box filter over one element of
    a ``TuningData`` (its background, if any, goes into the context).

    ``box="estimate"`` (default): the state estimate (``info.estimate``, a weighted mean),
    through which the gradient reaches the likelihood. ``"box"``: the box the filter
    reports (what the tables score), the estimate where it reports none (``lost``); the
    RGB-D filter's tight pixel box has no derivative with respect to any parameter.
    """
    if box not in ("estimate", "box"):
        raise ValueError(f"box must be 'estimate' or 'box', got {box!r}")

    def run(params, key: Array, seq: TuningData) -> Array:
        context = Context(background=seq.background)
        _, infos = track(filt, params, key, seq.frames, seq.boxes[0], context)
        boxes = infos.estimate
        if box == "box":
            boxes = jnp.where(infos.lost[:, None], infos.estimate, infos.box)
        return jnp.concatenate([seq.boxes[:1], boxes], axis=0)

    return run


def make_loss(run: Callable, props: NamedTuple, keys: int = 1) -> Callable:
    """``loss(free, params, key, data) -> scalar``: the mean ``diou_loss`` over the
    sequences of ``data`` (``lax.map``: one at a time, bounded memory) and ``keys``
    filter seeds each, with ``params`` updated from the free values ``free``."""

    def loss(free: dict, params, key: Array, data: TuningData) -> Array:
        p = pp.constrain(free, params, props)
        n_seq = data.boxes.shape[0]
        split = jax.random.split(key, n_seq * keys)  # raw [n, 2] or typed [n] keys
        seq_keys = split.reshape(n_seq, keys, *split.shape[1:])

        def one(xs):
            seq, ks = xs
            # lax.map, not vmap, over seeds too: memory stays that of one run (the
            # backward pass keeps every step's residuals), and the filters' other
            # lax.conds (resampling, lost-target draws) stay branches.
            per_key = jax.lax.map(lambda k: diou_loss(run(p, k, seq), seq.boxes, seq.visible), ks)
            return jnp.mean(per_key)

        return jnp.mean(jax.lax.map(one, (data, seq_keys)))

    return loss


def unconstrained(params: NamedTuple, props: NamedTuple, names: Sequence[str]) -> dict:
    """``{path: free value}`` of the named parameters; a value on the boundary of its
    domain (0 for ``"softplus"``, 0 or 1 for ``"sigmoid"``) has no finite free value and
    is one clear ``ValueError`` (start it inside, e.g. 1e-3, to tune it)."""
    free = pp.unconstrain(params, props, list(names))
    for n, u in free.items():
        if not all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(u)):
            value = np.asarray(jax.tree_util.tree_leaves(pp.get(params, n))).ravel().tolist()
            raise ValueError(
                f"parameter {n!r} = {value} is on the boundary of its constraint: start it "
                "inside to tune it"
            )
    return free


def _guarded_update(optimizer: optax.GradientTransformation, loss: Callable) -> Callable:
    """A jitted optimiser step on ``loss(free, params, key, data)`` that keeps the last
    values (and optimiser state) when the loss or a gradient is not finite. The parameters
    and data are arguments, not closed-over constants: XLA would otherwise embed every
    frame in the compiled program."""

    @jax.jit
    def update(free, opt_state, key, params, data):
        value, grads = jax.value_and_grad(loss)(free, params, key, data)
        leaves = jax.tree_util.tree_leaves(grads)
        ok = jnp.isfinite(value) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(g)) for g in leaves]))
        updates, new_opt = optimizer.update(grads, opt_state, free)
        new_free = optax.apply_updates(free, updates)

        def keep(new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)

        return keep(new_free, free), keep(new_opt, opt_state), value, ~ok

    return update


def tune(
    run: Callable,
    params: NamedTuple,
    props: NamedTuple,
    data: TuningData,
    names: Sequence[str],
    *,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 40,
    keys: int = 1,
    key: Array | None = None,
    callback: Callable[[dict], None] | None = None,
    validation: TuningData | None = None,
    validate_every: int = 5,
) -> TuneResult:
    """Tune the fields ``names`` of ``params`` by ``steps`` optimiser steps on ``data``.

    ``run(params, key, sequence) -> [T, 4]`` (``runner`` or your own); ``props``: the
    parameters' ``Prop`` tree (``COLOUR_PROPS``, ``rgbd_props(config)``); ``names``:
    dotted paths of trainable parameters; ``optimizer``: any
    optax transformation (default ``optax.adam(0.05)``) on the free values divided by
    ``max(|free value at the start|, 1)``, so that its steps are relative for large
    values (a learning rate of 0.05 moves a weight of 28 by about 1.4). Every
    step draws fresh filter seeds (``keys`` per sequence), so the loss is a
    stochastic estimate: compare results on held-out sequences and seeds. One
    compile, then each step runs one jitted forward and backward pass. ``callback``
    gets each step's history entry (e.g. to print progress).

    ``validation`` (other sequences than ``data``): its loss, with one fixed key, is
    computed at the start and every ``validate_every`` steps (history entries get
    ``"validation"``), and the result is the parameters with the lowest validation
    loss seen (early stopping), not the last ones.
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if not names:
        raise ValueError("names: give at least one parameter to tune")
    if validate_every < 1:
        raise ValueError(f"validate_every must be >= 1, got {validate_every}")
    optimizer = optimizer or optax.adam(0.05)
    key = jax.random.PRNGKey(0) if key is None else key
    free = unconstrained(params, props, names)
    # The optimiser's variables are the free values divided by max(|u0|, 1): a step of
    # size lr changes a parameter whose free value is large (a weight of 28, a floor of
    # -12, a depth width of 100 mm) by about lr of itself, not by lr in absolute terms.
    scales = jax.tree_util.tree_map(lambda u: jnp.maximum(jnp.abs(u), 1.0), free)
    loss = make_loss(run, props, keys)

    def unscale(v):
        return jax.tree_util.tree_map(jnp.multiply, v, scales)

    def scaled_loss(v, params, key, data):
        return loss(unscale(v), params, key, data)

    free = jax.tree_util.tree_map(jnp.divide, free, scales)
    opt_state = optimizer.init(free)

    update = _guarded_update(optimizer, scaled_loss)

    if validation is not None:
        val_key = jax.random.fold_in(key, 1)
        val_loss = jax.jit(lambda v, params, data: scaled_loss(v, params, val_key, data))
        start_validation = float(val_loss(free, params, validation))
        best = (start_validation, free)
    history = []
    for step in range(steps):
        t0 = time.perf_counter()
        key, k = jax.random.split(key)
        free, opt_state, value, skipped = update(free, opt_state, k, params, data)
        tuned = pp.constrain(unscale(free), params, props)
        entry = {"step": step, "loss": float(value), "skipped": bool(skipped)}
        entry["seconds"] = time.perf_counter() - t0
        entry.update({n: np.asarray(pp.get(tuned, n)).tolist() for n in names})
        if validation is not None and ((step + 1) % validate_every == 0 or step == steps - 1):
            entry["validation"] = float(val_loss(free, params, validation))
            if entry["validation"] < best[0]:
                best = (entry["validation"], free)
        history.append(entry)
        if callback is not None:
            callback(entry)
    start = None
    if validation is not None:
        start = start_validation
        free = best[1]
    return TuneResult(pp.constrain(unscale(free), params, props), history, start)


def progress(label: str, names: Sequence[str]) -> Callable[[dict], None]:
    """A ``tune(callback=...)`` that prints each step: its loss, the tuned values (the
    mean of a vector) and, when computed, the validation loss."""

    def show(entry: dict) -> None:
        vals = " ".join(f"{n} {float(np.mean(entry[n])):.3f}" for n in names)
        val = f" validation {entry['validation']:.4f}" if "validation" in entry else ""
        step, loss = entry["step"], entry["loss"]
        print(f"{label} step {step:3d} loss {loss:.4f} {vals}{val}", flush=True)

    return show


def history_chart(runs: Mapping[str, Sequence[dict]], title: str = "") -> np.ndarray:
    """Loss curves of tuning runs, ``{label: TuneResult.history}`` -> a BGR image
    (``cpf_jax.charts``): the training loss of every step, and the validation loss where
    it was computed (points joined across the steps without one)."""
    series = {}
    for label, history in runs.items():
        steps = [e["step"] for e in history]
        series[f"{label}: training loss"] = (steps, [e["loss"] for e in history])
        val = [(e["step"], e["validation"]) for e in history if "validation" in e]
        if val:
            series[f"{label}: validation loss"] = ([v[0] for v in val], [v[1] for v in val])
    return charts.line_chart(series, title=title, xlabel="optax step", ylabel="loss")
