"""The Beta model of foreground ratios (paper eq. 2): its densities, fitting it to training
boxes, and moving its means towards the first box's foreground fill.

The shapes are fitted on synthetic walkers, whose limbs fill about a third of their tight
box; a real person seen from the front, the back or above fills 60-90 %. The initial box
is a ground-truth box, so its fill says which the target is: every Beta mean moves by the
same logit shift towards it (``beta_fill_shift``), each keeping its concentration
``a + b``, once the fill lies beyond a dead zone around the fitted mean (one frame's fill
varies with the gait).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.special import digamma, polygamma

from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.cells import beta_log_density, grid_cells
from cpf_jax.kernels.histogram import box_histograms
from cpf_jax.rgbd.params import BetaParams, BorderParams

__all__ = [
    "FILL_CLIP",
    "box_log_density",
    "fit_beta",
    "clipped_area",
    "cell_foreground_ratios",
    "initial_fill",
    "beta_fill_shift",
    "fill_adapted",
]

#: The initial box's fill is clipped to ``[FILL_CLIP, 1 - FILL_CLIP]`` before the shift.
FILL_CLIP = 0.05


def clipped_area(rects: Array, width: int, height: int) -> Array:
    """Pixels ``[...]`` of integer rects ``[..., 4]`` inside a ``width x height`` frame."""
    r = box_ops.clip_rect(rects, width, height)
    return ((r[..., 2] - r[..., 0]) * (r[..., 3] - r[..., 1])).astype(jnp.float32)


def box_log_density(beta: BetaParams, fg_sum: Array, area_sum: Array) -> Array:
    """The whole-box Beta term of a pooled foreground count over a pooled area (0 for an
    empty area), floored at ``beta.floor``."""
    ratio = jnp.where(area_sum > 0, fg_sum / jnp.maximum(area_sum, 1.0), 0.0)
    lp = beta_log_density(ratio, beta.box_a, beta.box_b)
    return jnp.where(area_sum > 0, jnp.maximum(beta.weight * lp, beta.floor), 0.0)


def fit_beta(
    ratios: Array, weights: Array | None = None, method: str = "moments", iters: int = 50
) -> tuple[Array, Array]:
    """Fit ``Beta(a, b)`` to samples ``ratios [..., M]`` in ``(0, 1)`` along the last axis.

    ``"moments"``: ``a = m k``, ``b = (1 - m) k`` with ``k = m (1 - m) / v - 1``.
    ``"mle"``: Newton's method in log space on ``psi(a) - psi(a + b) = mean log r`` and
    ``psi(b) - psi(a + b) = mean log(1 - r)``, from the moments fit. Samples are clipped
    to ``[1e-3, 1 - 1e-3]``; ``weights [..., M]`` (e.g. 0 for occluded frames) weight
    them. Returns ``(a [...], b [...])``.
    """
    if method not in ("moments", "mle"):
        raise ValueError(f"method must be 'moments' or 'mle', got {method!r}")
    r = jnp.clip(jnp.asarray(ratios, jnp.float32), 1e-3, 1.0 - 1e-3)
    wgt = jnp.ones_like(r) if weights is None else jnp.asarray(weights, jnp.float32)
    tot = jnp.maximum(jnp.sum(wgt, -1), 1e-9)
    m = jnp.sum(wgt * r, -1) / tot
    v = jnp.sum(wgt * (r - m[..., None]) ** 2, -1) / tot
    kk = jnp.maximum(m * (1.0 - m) / jnp.maximum(v, 1e-9) - 1.0, 1e-3)
    a, b = m * kk, (1.0 - m) * kk
    if method == "moments":
        return a, b
    s1 = jnp.sum(wgt * jnp.log(r), -1) / tot
    s2 = jnp.sum(wgt * jnp.log1p(-r), -1) / tot
    x = jnp.stack([jnp.log(a), jnp.log(b)], -1)

    def newton(x, _):
        a, b = jnp.exp(x[..., 0]), jnp.exp(x[..., 1])
        g1 = digamma(a) - digamma(a + b) - s1
        g2 = digamma(b) - digamma(a + b) - s2
        t_ab = polygamma(1, a + b)
        j11 = (polygamma(1, a) - t_ab) * a  # d g1 / d log a
        j12 = -t_ab * b
        j21 = -t_ab * a
        j22 = (polygamma(1, b) - t_ab) * b
        det = j11 * j22 - j12 * j21
        dx0 = (j22 * g1 - j12 * g2) / det
        dx1 = (-j21 * g1 + j11 * g2) / det
        step = jnp.clip(jnp.stack([dx0, dx1], -1), -1.0, 1.0)
        return x - step, None

    x, _ = jax.lax.scan(newton, x, None, length=iters)
    return jnp.exp(x[..., 0]), jnp.exp(x[..., 1])


def cell_foreground_ratios(foreground: Array, boxes_xywh: Array, k: int) -> Array:
    """Foreground ratios ``[T, k*k]`` of the cells of ``boxes [T, 4]`` in masks ``[T, H, W]``:
    the training statistic of eq. 2 (cells clipped to the frame; 0 for an empty cell)."""
    fg = jnp.asarray(foreground, bool)
    height, width = fg.shape[-2:]

    def one(mask, box):
        rects = box_ops.xywh_to_rect(grid_cells(box, k))
        counts = box_histograms(jnp.where(mask, 0, -1), rects, 1)[:, 0]
        area = clipped_area(rects, width, height)
        return jnp.where(area > 0, counts / jnp.maximum(area, 1.0), 0.0)

    return jax.vmap(one)(fg, jnp.asarray(boxes_xywh, jnp.float32))


def initial_fill(foreground: Array, box_xywh: Array) -> Array:
    """Share of foreground pixels in one box (clipped to the frame; 0 for an empty box)."""
    box = jnp.asarray(box_xywh, jnp.float32)
    return cell_foreground_ratios(foreground[None], box[None], 1)[0, 0]


def beta_fill_shift(beta: BetaParams, fill: Array) -> Array:
    """Logit shift of the Beta means towards a foreground ``fill``:
    ``fill_adapt sign(g) max(|g| - fill_deadzone, 0)`` with ``g = logit(fill) - logit(m)``,
    ``m`` the whole-box Beta's mean; 0 when the box holds no foreground."""
    prior = beta.box_a / (beta.box_a + beta.box_b)
    f = jnp.clip(fill, FILL_CLIP, 1.0 - FILL_CLIP)
    gap = jax.scipy.special.logit(f) - jax.scipy.special.logit(prior)
    excess = jnp.sign(gap) * jnp.maximum(jnp.abs(gap) - beta.fill_deadzone, 0.0)
    return jnp.where(fill > 0, beta.fill_adapt * excess, 0.0)


def _moved(a: Array, b: Array, shift: Array, on: Array | bool = True) -> tuple[Array, Array]:
    """Beta shapes with the mean moved by ``shift`` logits and ``a + b`` kept; no shift
    keeps them bit for bit (the round trip through the logit does not)."""
    k = a + b
    m = jax.nn.sigmoid(jax.scipy.special.logit(a / k) + jnp.where(on, shift, 0.0))
    same = (shift == 0.0) | ~jnp.asarray(on)
    return jnp.where(same, a, m * k), jnp.where(same, b, (1.0 - m) * k)


def fill_adapted(
    beta: BetaParams, border: BorderParams, shift: Array
) -> tuple[BetaParams, BorderParams]:
    """The cells', the whole box's and the inner border strips' Betas moved by ``shift``
    logits (the outer strips stay: nothing of a person lies outside his tight box)."""
    beta_a, beta_b = _moved(beta.a, beta.b, shift)
    box_a, box_b = _moved(beta.box_a, beta.box_b, shift)
    inner = jnp.arange(border.a.shape[-1]) < 4
    border_a, border_b = _moved(border.a, border.b, shift, inner)
    return (
        beta._replace(a=beta_a, b=beta_b, box_a=box_a, box_b=box_b),
        border._replace(a=border_a, b=border_b),
    )
