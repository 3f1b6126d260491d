"""Resampling schemes: statistical properties over many keys, degenerate weights, jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import resample as rs

WEIGHTS = np.array([0.05, 0.0, 0.3, 0.15, 0.4, 0.1], np.float32)
N = WEIGHTS.size


def _counts(indices, n):
    return np.stack([np.bincount(np.asarray(i), minlength=n) for i in indices])


@pytest.fixture(scope="module")
def draws():
    """20,000 resamples per scheme (vmapped over keys, jitted once per scheme)."""
    keys = jax.random.split(jax.random.PRNGKey(0), 20_000)
    lw = jnp.log(jnp.asarray(WEIGHTS))
    return {
        name: np.asarray(jax.jit(jax.vmap(lambda k, f=f: f(k, lw)))(keys))
        for name, f in rs.SCHEMES.items()
    }


@pytest.mark.parametrize("name", list(rs.SCHEMES))
def test_unbiased_offspring_counts(draws, name):
    counts = _counts(draws[name], N)
    mean = counts.mean(axis=0)
    expected = N * WEIGHTS
    # standard error of a count's mean is at most sqrt(N w (1-w) / 20000) < 0.01
    np.testing.assert_allclose(mean, expected, atol=0.03)
    assert counts[:, 1].max() == 0, "a zero-weight particle was selected"
    assert (counts.sum(axis=1) == N).all()


@pytest.mark.parametrize("name", ["systematic", "stratified", "residual"])
def test_low_variance_schemes_keep_floor_copies(draws, name):
    counts = _counts(draws[name], N)
    floor = np.floor(N * WEIGHTS)
    if name == "systematic":
        # systematic: every count is floor or ceil of N w_i
        assert ((counts >= floor) & (counts <= np.ceil(N * WEIGHTS))).all()
    if name == "residual":
        assert (counts >= floor).all()


def test_variance_ordering(draws):
    """Systematic and stratified resampling have lower offspring variance than multinomial."""
    var = {k: _counts(v, N).var(axis=0).sum() for k, v in draws.items()}
    assert var["systematic"] < var["multinomial"]
    assert var["stratified"] < var["multinomial"]
    assert var["residual"] < var["multinomial"]


@pytest.mark.parametrize("name", list(rs.SCHEMES))
def test_all_invalid_weights_give_uniform_defined_result(name):
    f = rs.SCHEMES[name]
    keys = jax.random.split(jax.random.PRNGKey(1), 2000)
    for bad in (jnp.full((N,), -jnp.inf), jnp.full((N,), jnp.nan)):
        idx = np.asarray(jax.vmap(lambda k, b=bad: f(k, b))(keys))
        assert idx.min() >= 0 and idx.max() < N
        mean = _counts(idx, N).mean(axis=0)
        np.testing.assert_allclose(mean, np.ones(N), atol=0.1)
    assert bool(rs.all_weights_invalid(jnp.full((N,), -jnp.inf)))
    assert not bool(rs.all_weights_invalid(jnp.array([-jnp.inf, 0.0])))


def test_nan_entry_counts_as_zero_weight():
    lw = jnp.array([0.0, jnp.nan, 0.0, -jnp.inf])
    w = np.exp(np.asarray(rs.normalise_log_weights(lw)))
    np.testing.assert_allclose(w, [0.5, 0.0, 0.5, 0.0], atol=1e-6)
    idx = np.asarray(rs.systematic(jax.random.PRNGKey(0), lw))
    assert set(idx.tolist()) <= {0, 2}


def test_num_differs_from_n_and_huge_log_weights():
    lw = jnp.array([1e4, 1e4 - 1.0, -1e4], jnp.float32)  # would overflow exp without the shift
    idx = rs.systematic(jax.random.PRNGKey(3), lw, 1000)
    assert idx.shape == (1000,)
    counts = np.bincount(np.asarray(idx), minlength=3)
    p0 = 1 / (1 + np.exp(-1.0))
    assert abs(counts[0] / 1000 - p0) < 0.002 and counts[2] == 0


def test_effective_sample_size():
    n = 128
    assert float(rs.effective_sample_size(jnp.zeros(n))) == pytest.approx(n, rel=1e-5)
    one_hot = jnp.full(n, -jnp.inf).at[7].set(0.0)
    assert float(rs.effective_sample_size(one_hot)) == pytest.approx(1.0)
    w = np.random.default_rng(0).random(n).astype(np.float32)
    ref = w.sum() ** 2 / (w**2).sum()
    assert float(rs.effective_sample_size(jnp.log(w))) == pytest.approx(ref, rel=1e-4)
    assert float(rs.effective_sample_size(jnp.full(n, -jnp.inf))) == pytest.approx(n, rel=1e-5)


def test_resample_if_threshold_and_jit_vmap():
    particles = {"x": jnp.arange(6.0), "v": jnp.arange(6.0) * 10}
    lw = jnp.log(jnp.asarray(WEIGHTS))
    key = jax.random.PRNGKey(0)
    p0, lw0, did0 = rs.resample_if(key, lw, particles, 0.0)
    assert not bool(did0)
    np.testing.assert_allclose(np.exp(np.asarray(lw0)), WEIGHTS, rtol=1e-5)
    jitted = jax.jit(lambda k, l: rs.resample_if(k, l, particles, 1.0))
    p1, lw1, did1 = jitted(key, lw)
    assert bool(did1)
    np.testing.assert_allclose(np.asarray(lw1), np.full(6, -np.log(6)), rtol=1e-6)
    # ancestors are resampled jointly across the pytree
    np.testing.assert_allclose(np.asarray(p1["v"]), np.asarray(p1["x"]) * 10)
    # batched over keys
    keys = jax.random.split(key, 8)
    pb, lwb, didb = jax.vmap(lambda k: rs.resample_if(k, lw, particles, 1.0))(keys)
    assert pb["x"].shape == (8, 6) and bool(jnp.all(didb))


def test_resample_if_clips_a_custom_schemes_out_of_range_indices():
    """A scheme of the same signature that returns indices outside [0, N) gets them
    clipped (the first and last particle), never NaN or a silent wrap-around."""
    particles = jnp.arange(6.0)[:, None] * jnp.ones((1, 8))

    def wild(key, log_weights, num):
        return jnp.array([-3, 0, 2, 5, 6, 40], jnp.int32)

    lw = jnp.log(jnp.asarray(WEIGHTS))
    p, _, did = jax.jit(lambda k: rs.resample_if(k, lw, particles, 1.0, wild))(
        jax.random.PRNGKey(0)
    )
    assert bool(did)
    np.testing.assert_array_equal(np.asarray(p[:, 0]), [0, 0, 2, 5, 5, 5])


def test_reweight_matches_numpy_and_handles_invalid_likelihoods():
    lw0 = np.log(np.array([0.1, 0.2, 0.3, 0.4], np.float32))
    lik = np.array([-1.0, np.nan, 0.5, -np.inf], np.float32)
    lw, invalid, ess, ev = jax.jit(rs.reweight)(jnp.asarray(lw0), jnp.asarray(lik))
    w = np.exp(lw0) * np.exp(np.where(np.isfinite(lik), lik, -np.inf))
    np.testing.assert_allclose(np.exp(np.asarray(lw)), w / w.sum(), rtol=1e-5)
    np.testing.assert_allclose(float(ev), np.log(w.sum()), rtol=1e-5)
    np.testing.assert_allclose(float(ess), 1 / np.sum((w / w.sum()) ** 2), rtol=1e-5)
    assert not bool(invalid)
    lw, invalid, ess, ev = rs.reweight(jnp.asarray(lw0), jnp.full(4, jnp.nan))
    assert bool(invalid) and np.isfinite(np.asarray(lw)).all() and np.isfinite(float(ev))


@pytest.mark.parametrize("num", [None, 37, 5000])
def test_systematic_equals_a_search_of_its_positions(num):
    # The O(N) histogram form against the textbook search of the same positions
    # (searchsorted on the same cumulative weights), slot for slot, on peaked,
    # flat and partly -inf weights, under jit and vmap.
    n = 3000
    m = n if num is None else num

    def searched(key, lw):
        # The textbook form: the first particle whose cumulative weight exceeds each
        # position, clipped because float32 cumulative sums can end slightly below 1.
        u = jax.random.uniform(key, (), jnp.float32)
        positions = (u + jnp.arange(m, dtype=jnp.float32)) / m
        cdf = jnp.cumsum(jnp.exp(rs.normalise_log_weights(lw)))
        idx = jnp.searchsorted(cdf, positions, side="right")
        return jnp.clip(idx, 0, n - 1).astype(jnp.int32)

    both = jax.jit(lambda k, lw: (rs.systematic(k, lw, num), searched(k, lw)))
    keys = jax.random.split(jax.random.key(5), 8)
    for i, key in enumerate(keys):
        lw = jax.random.normal(jax.random.fold_in(key, 1), (n,)) * (0.1, 3.0, 30.0, 1.0)[i % 4]
        if i % 4 == 3:
            lw = lw.at[::3].set(-jnp.inf)
        idx, ref = (np.asarray(a) for a in both(key, lw))
        np.testing.assert_array_equal(idx, ref)
        # and the search itself is NumPy's, up to float32 rounding of the sums
        assert (
            np.mean(
                idx
                == np.clip(
                    np.searchsorted(
                        np.cumsum(np.exp(np.asarray(rs.normalise_log_weights(lw), np.float64))),
                        (np.float64(jax.random.uniform(key, ())) + np.arange(m)) / m,
                        side="right",
                    ),
                    0,
                    n - 1,
                )
            )
            > 0.99
        )
    batched = jax.vmap(lambda k: rs.systematic(k, jnp.zeros(n)))(keys)
    assert batched.shape == (8, n)
    np.testing.assert_array_equal(np.asarray(batched[0]), np.arange(n))


@pytest.mark.parametrize("name", ["systematic", "multinomial"])
def test_resample_if_carries_unbiased_gradients(name):
    """After resampling, the log-weights are -log N in value but carry the ancestors'
    derivatives (Scibior and Wood 2021): the gradient of the resampled mean of x,
    averaged over keys, is the gradient of the weighted mean sum_i w_i(theta) x_i."""
    x = jnp.asarray([1.0, -2.0, 0.5, 3.0, -1.0, 2.0])
    s = jnp.asarray([0.2, -1.0, 0.7, 1.5, 0.0, -0.4])

    def resampled_mean(theta, key):
        lw = rs.normalise_log_weights(theta * s)
        p, lw1, did = rs.resample_if(key, lw, x, 1.0, rs.SCHEMES[name])
        return jnp.sum(jnp.exp(lw1) * p), lw1

    keys = jax.random.split(jax.random.PRNGKey(3), 20_000)
    grad_fn = jax.jit(jax.vmap(jax.grad(lambda t, k: resampled_mean(t, k)[0]), (None, 0)))
    grads = np.asarray(grad_fn(jnp.float32(0.8), keys))
    w = jax.nn.softmax(0.8 * s)
    exact = float(jnp.sum(w * x * (s - jnp.sum(w * s))))  # d/dtheta sum_i w_i x_i
    se = grads.std() / np.sqrt(grads.size)
    assert abs(grads.mean() - exact) < 4 * se + 1e-4, (grads.mean(), exact, se)
    assert abs(exact) > 10 * se  # the check can fail: the gradient is far from 0
    # The forward pass is unchanged: uniform log-weights exactly.
    _, lw1 = jax.jit(resampled_mean)(jnp.float32(0.8), keys[0])
    np.testing.assert_array_equal(np.asarray(lw1), np.full(6, -np.log(np.float32(6)), np.float32))
