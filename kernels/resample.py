"""Resampling schemes, effective sample size and ESS-triggered resampling.

Every scheme has one signature::

    scheme(key, log_weights: [N] float, num: int | None = None) -> [num] int32

taking unnormalised log-weights (log-sum-exp normalisation happens inside) and
returning ancestor indices. ``num`` defaults to ``N`` and is static.

Degenerate weights: if every log-weight is ``-inf`` (or NaN), all particles are
treated as equally likely, so the result is a uniform resample rather than NaN
indices. Filters report that case separately (see ``all_weights_invalid``).

Schemes (Douc & Cappe 2005; blackjax/smc/resampling.py):

* ``systematic``: one uniform offset, ``num`` evenly spaced positions; lowest
  variance in practice. O(N) without a search: a histogram of the number of
  positions below each particle's cumulative weight, and its prefix sum.
* ``stratified``: one uniform per stratum, O(N log N) by ``searchsorted`` on the
  cumulative weights.
* ``multinomial``: ``num`` independent draws (sorted uniforms), by ``searchsorted``.
* ``residual``: ``floor(num w_i)`` copies deterministically, the remainder drawn
  multinomially from the residual weights.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import Array

__all__ = [
    "normalise_log_weights",
    "all_weights_invalid",
    "effective_sample_size",
    "reweight",
    "systematic",
    "stratified",
    "multinomial",
    "residual",
    "SCHEMES",
    "resample_if",
]

Resampler = Callable[[Array, Array, "int | None"], Array]


def all_weights_invalid(log_weights: Array) -> Array:
    """True when no log-weight is finite (all ``-inf`` or NaN): the filter has no information."""
    return ~jnp.any(jnp.isfinite(log_weights))


def normalise_log_weights(log_weights: Array) -> Array:
    """Return ``log w_i - logsumexp(log w)`` as float32; all-invalid -> uniform ``-log N``.

    NaN entries count as ``-inf`` (zero weight), so one bad particle cannot
    poison the population.
    """
    lw = jnp.asarray(log_weights, jnp.float32)
    lw = jnp.where(jnp.isnan(lw), -jnp.inf, lw)
    n = lw.shape[-1]
    invalid = ~jnp.any(jnp.isfinite(lw), axis=-1, keepdims=True)
    lw = jnp.where(invalid, 0.0, lw)
    # Shift by the finite max before exponentiating (safe even with -inf entries).
    m = jnp.max(lw, axis=-1, keepdims=True)
    lse = m + jnp.log(jnp.sum(jnp.exp(lw - m), axis=-1, keepdims=True))
    out = lw - lse
    return jnp.where(invalid, -jnp.log(jnp.float32(n)), out)


def effective_sample_size(log_weights: Array) -> Array:
    """ESS = 1 / sum w_i^2 of the normalised weights, in [1, N]."""
    lw = normalise_log_weights(log_weights)
    return 1.0 / jnp.sum(jnp.exp(2.0 * lw), axis=-1)


def reweight(log_weights: Array, log_lik: Array) -> tuple[Array, Array, Array, Array]:
    """One importance-weight update: ``(log_weights [N], invalid, ess, log_evidence)``.

    Non-finite ``log_lik`` entries count as zero likelihood. ``log_weights`` come
    back normalised (uniform when every weight is invalid); ``log_evidence`` is the
    log mean likelihood under the previous weights (incremental evidence).
    """
    log_lik = jnp.where(jnp.isfinite(log_lik), log_lik, -jnp.inf)
    invalid = all_weights_invalid(log_weights + log_lik)
    lw = normalise_log_weights(log_weights + log_lik)
    log_evidence = jax.nn.logsumexp(log_weights + jnp.where(invalid, 0.0, log_lik))
    return lw, invalid, effective_sample_size(lw), log_evidence


def _weights(log_weights: Array) -> Array:
    """Normalised weights ``[N]`` (uniform when every log-weight is invalid)."""
    return jnp.exp(normalise_log_weights(log_weights))


def _search(weights: Array, positions: Array) -> Array:
    """Index ``i`` with ``cumsum[i-1] <= u < cumsum[i]`` for each position ``u`` in ``[0, 1)``."""
    cdf = jnp.cumsum(weights)
    # float32 cumulative sums can end slightly below 1: clip the indices.
    idx = jnp.searchsorted(cdf, positions, side="right")
    return jnp.clip(idx, 0, weights.shape[0] - 1).astype(jnp.int32)


def systematic(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Systematic resampling: positions ``(u + j) / num`` with one ``u ~ U[0, 1)``.

    O(N) without a search: particle ``i`` covers the positions below its
    cumulative weight ``c_i``, i.e. ``j < k_i`` with ``k_i = ceil(c_i num - u)``
    (corrected by one where float rounding disagrees with the positions'
    own float values), so slot ``j`` takes ``#{i : k_i <= j}``: a histogram of
    the ``k_i`` and its cumulative sum. Identical, slot for slot, to
    ``searchsorted(c, positions, side="right")`` (tested), without its
    ``log N`` search per position.
    """
    n = log_weights.shape[0]
    num = n if num is None else num
    u = jax.random.uniform(key, (), jnp.float32)
    cdf = jnp.cumsum(_weights(log_weights))

    def position(j: Array) -> Array:
        return (u + j.astype(jnp.float32)) / num

    k = jnp.clip(jnp.ceil(cdf * num - u), 0, num).astype(jnp.int32)
    k = jnp.where((k > 0) & (position(k - 1) >= cdf), k - 1, k)
    k = jnp.where((k < num) & (position(k) < cdf), k + 1, k)
    hist = jnp.zeros(num + 1, jnp.int32).at[k].add(1)
    # Integer prefix sum: exact in any order, so associative_scan may replace the
    # reduce_window that jnp.cumsum lowers to on CPU.
    idx = jax.lax.associative_scan(jnp.add, hist[:num])
    # float32 cumulative sums can end slightly below 1: clip the indices.
    return jnp.clip(idx, 0, n - 1).astype(jnp.int32)


def stratified(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Stratified resampling: positions ``(u_i + i) / num`` with independent ``u_i``."""
    num = log_weights.shape[0] if num is None else num
    u = jax.random.uniform(key, (num,), jnp.float32)
    positions = (u + jnp.arange(num, dtype=jnp.float32)) / num
    return _search(_weights(log_weights), positions)


def multinomial(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Multinomial resampling: ``num`` independent draws from the weights."""
    num = log_weights.shape[0] if num is None else num
    u = jnp.sort(jax.random.uniform(key, (num,), jnp.float32))
    return _search(_weights(log_weights), u)


def residual(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Residual resampling: ``floor(num * w_i)`` copies of i, the rest multinomial on the residuals.

    Static shapes: the deterministic copies are laid out with a cumulative
    count and ``searchsorted``; the remaining slots are filled from a
    multinomial draw over the normalised residual weights.
    """
    n = log_weights.shape[0]
    num = n if num is None else num
    w = _weights(log_weights)
    scaled = w * num
    copies = jnp.floor(scaled).astype(jnp.int32)
    n_det = jnp.sum(copies)
    ends = jnp.cumsum(copies)
    slots = jnp.arange(num, dtype=jnp.int32)
    det_idx = jnp.clip(jnp.searchsorted(ends, slots, side="right"), 0, n - 1)
    resid = scaled - copies
    resid_log = jnp.where(resid > 0, jnp.log(jnp.where(resid > 0, resid, 1.0)), -jnp.inf)
    # Independent (unsorted) draws from the residual weights fill the remaining
    # slots; sorted draws would bias the first slots towards low indices.
    u = jax.random.uniform(key, (num,), jnp.float32)
    rand_idx = _search(_weights(resid_log), u)
    rand_for_slot = rand_idx[jnp.clip(slots - n_det, 0, num - 1)]
    return jnp.where(slots < n_det, det_idx, rand_for_slot).astype(jnp.int32)


SCHEMES: dict[str, Resampler] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def resample_if(
    key: Array,
    log_weights: Array,
    particles,
    threshold: float | Array,
    scheme: Resampler = systematic,
):
    """Resample a particle pytree when ``ESS < threshold * N`` (under ``lax.cond``).

    Returns ``(particles, log_weights, resampled)``: after resampling the
    log-weights are uniform; otherwise the normalised log-weights are kept.
    ``threshold = 1`` resamples every frame (SIR, thesis 2.1) except when the
    weights are exactly uniform; ``threshold = 0`` never resamples. A custom
    ``scheme`` (same signature as ``systematic``) that returns indices outside
    ``[0, N)`` has them clipped to the first and last particle.

    Gradients: the uniform log-weights after resampling are ``-log N + l_a -
    stop_gradient(l_a)``, with ``l_a`` each particle's ancestor's log-weight
    (Scibior and Wood 2021, "Differentiable particle filtering without modifying
    the forward pass"). The value is exactly ``-log N``; the derivative is that of
    ``l_a``, so gradients of weighted estimates at later frames reach the
    likelihoods of earlier ones (``cpf_jax.tuning``) instead of stopping at the
    discrete ancestor draw. The indices themselves carry no gradient.
    """
    n = log_weights.shape[0]
    lw = normalise_log_weights(log_weights)
    ess = effective_sample_size(lw)
    do = ess < threshold * n

    def _resample(_):
        # Clipped (the schemes here already are; a custom one may not be), then taken
        # without jnp.take's default fill mode, whose select would run over every
        # gathered element of the particles.
        idx = jnp.clip(scheme(key, lw, n), 0, n - 1)

        def take(x):
            return x.at[idx].get(mode="promise_in_bounds", wrap_negative_indices=False)

        taken = jax.tree_util.tree_map(take, particles)
        ancestor = take(lw)
        # 0 in value (an ancestor is never drawn with weight 0 unless all are invalid,
        # when lw is uniform and finite); the guard keeps -inf - -inf out anyway.
        carried = jnp.where(jnp.isfinite(ancestor), ancestor - jax.lax.stop_gradient(ancestor), 0.0)
        return taken, jnp.full_like(lw, -jnp.log(jnp.float32(n))) + carried

    def _keep(_):
        return particles, lw

    new_particles, new_lw = jax.lax.cond(do, _resample, _keep, None)
    return new_particles, new_lw, do
