"""Motion models: deterministic parts against the thesis equations, noise statistics, guidance."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel

from cpf_jax.dynamics import MODELS, MOTION, RNGS, THESIS_TAU, height_scale, propagate
from cpf_jax.kernels import fastrand
from cpf_jax.params import values

ZERO_TAU = jnp.zeros(8)
STATE = jnp.array([[100.0, 80.0, 3.0, -2.0, 40.0, 90.0, 0.5, 1.0]])
PREV = jnp.array([[96.0, 81.0, 2.0, -1.0, 39.0, 88.0, 0.0, 0.5]])
KEY = jax.random.PRNGKey(0)
#: The library's motion spec with undamped size velocities (the thesis's model).
MP = values(MOTION)._replace(size_velocity_decay=jnp.float32(1.0))


def motion(tau, base=MP, **changes):
    """``base`` with the noise scales ``tau`` and any other fields replaced (float32)."""
    changes = {k: jnp.float32(v) for k, v in changes.items()}
    return base._replace(tau=jnp.asarray(tau, jnp.float32), **changes)


def test_library_motion_spec_is_the_documented_one():
    """``values(MOTION)``: DEFAULT_TAU, guided 0.5, gain 2, speed 4, gx 0.5, gy 0.5,
    correlation 0.8, hold 0, decay 0.9 (the numbers the tests below were set with)."""
    from cpf_jax.dynamics import DEFAULT_TAU

    mp = values(MOTION)
    np.testing.assert_array_equal(np.asarray(mp.tau), np.float32(DEFAULT_TAU))
    got = [float(x) for x in mp[1:]]
    np.testing.assert_allclose(got, [0.5, 2.0, 4.0, 0.5, 0.5, 0.8, 0.0, 0.9], rtol=1e-7)


def test_ar1_matches_thesis_equations_without_noise():
    out = np.asarray(propagate(KEY, STATE, PREV, motion(ZERO_TAU), model="ar1"))[0]
    # eqs. 3.14-3.17: x += x', x' unchanged, w += w', w' unchanged
    np.testing.assert_allclose(out, [103, 78, 3, -2, 40.5, 91, 0.5, 1.0], rtol=1e-6)


def test_ar2_matches_eq_3_26_without_noise():
    out = np.asarray(propagate(KEY, STATE, PREV, motion(ZERO_TAU), model="ar2"))[0]
    s, d = np.asarray(STATE)[0], np.asarray(STATE - PREV)[0]
    a = np.array([[0.5, 0, 0.5, 0], [0, 0.5, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]])
    ref = np.concatenate([s[:4] + a @ d[:4], s[4:] + a @ d[4:]])
    np.testing.assert_allclose(out, ref, rtol=1e-6)


def _noiseless_reference(model: str, decay: float):
    """NumPy: every model's deterministic step (thesis eqs. 3.14-3.28, 3.33), size
    velocities then multiplied by ``decay``."""
    a = np.array([[0.5, 0, 0.5, 0], [0, 0.5, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]])

    def ref(particles, previous):
        s, p = np.asarray(particles, np.float64), np.asarray(previous, np.float64)
        if model.startswith("ar1"):
            out = s.copy()
            out[:, 0:2] += s[:, 2:4]
            out[:, 4:6] += s[:, 6:8]
        elif model.startswith("ar2"):
            d = s - p
            out = np.concatenate([s[:, :4] + d[:, :4] @ a.T, s[:, 4:] + d[:, 4:] @ a.T], 1)
        else:  # random walk: nothing moves without noise, velocities zero
            out = s.copy()
            out[:, [2, 3, 6, 7]] = 0.0
        if model.endswith("_fixed"):
            out[:, 4:6] = s[:, 4:6]
            out[:, 6:8] = 0.0
        out[:, 6:8] *= decay
        return out

    return ref


@pytest.mark.parametrize("model", MODELS)
def test_noiseless_step_of_every_model_matches_numpy_plain_jit_and_vmap(model):
    """With zero noise every model is its deterministic equation (guidance only shapes
    noise, the hold is off), plainly, under jit and vmapped over particle sets."""
    rng = np.random.default_rng(1)
    mp = motion(ZERO_TAU, size_velocity_decay=0.7)

    def cloud():
        s = rng.normal([100, 80, 0, 0, 40, 90, 0, 0], [20, 20, 3, 3, 5, 5, 1, 1], (6, 8))
        return s.astype(np.float32), (s - rng.normal(0, 2, s.shape)).astype(np.float32)

    batch = [cloud(), cloud(), cloud()]
    check_kernel(
        lambda s, p: propagate(
            KEY, jnp.asarray(s), jnp.asarray(p), mp, model=model, hierarchical=True
        ),
        _noiseless_reference(model, 0.7),
        batch[0],
        batch=batch,
        rtol=1e-5,
        atol=1e-4,
    )


@pytest.mark.parametrize("model", ["ar1", "ar2"])
def test_size_velocity_decay_scales_only_the_new_size_velocities(model):
    plain = np.asarray(propagate(KEY, STATE, PREV, motion(ZERO_TAU), model=model))[0]
    damped = np.asarray(
        propagate(KEY, STATE, PREV, motion(ZERO_TAU, size_velocity_decay=0.5), model=model)
    )[0]
    # w'_t = decay * (w' + n): positions, sizes and position velocities as undamped.
    np.testing.assert_array_equal(damped[:6], plain[:6])
    np.testing.assert_allclose(damped[6:], 0.5 * plain[6:], rtol=1e-6)
    assert np.all(plain[6:] != 0)


def test_size_velocity_decay_is_a_traced_parameter():
    state = jnp.tile(STATE, (64, 1))

    def draw(decay):
        mp = motion(THESIS_TAU)._replace(size_velocity_decay=decay)
        return propagate(KEY, state, state, mp, model="ar1")

    decays = jnp.array([1.0, 0.9, 0.0])
    batched = jax.jit(jax.vmap(draw))(decays)
    for i, d in enumerate(np.asarray(decays)):
        one = np.asarray(draw(jnp.float32(d)))
        np.testing.assert_allclose(np.asarray(batched[i]), one, rtol=1e-6, atol=1e-6)
    assert np.all(np.asarray(batched[2])[:, 6:] == 0)
    # The gradient reaches the decay (a tuning target): d(sum w') / d decay = sum(w' + n).
    g = jax.grad(lambda d: jnp.sum(draw(d)[:, 6:8]))(jnp.float32(0.9))
    np.testing.assert_allclose(float(g), float(jnp.sum(draw(jnp.float32(1.0))[:, 6:8])), rtol=1e-5)


@pytest.mark.parametrize("model", ["ar1_fixed", "ar2_fixed"])
def test_fixed_models_keep_size(model):
    tau = jnp.asarray(THESIS_TAU) * 5
    out = np.asarray(
        propagate(
            KEY,
            jnp.tile(STATE, (100, 1)),
            jnp.tile(PREV, (100, 1)),
            motion(tau),
            model=model,
            hierarchical=True,
        )
    )
    np.testing.assert_allclose(out[:, 4:6], np.tile([40.0, 90.0], (100, 1)))
    assert np.all(out[:, 6:] == 0)
    assert out[:, 0].std() > 1.0


def test_random_walk_has_no_velocity():
    out = np.asarray(
        propagate(
            KEY,
            jnp.tile(STATE, (500, 1)),
            jnp.tile(PREV, (500, 1)),
            motion(THESIS_TAU),
            model="random_walk",
        )
    )
    assert np.all(out[:, [2, 3, 6, 7]] == 0)
    np.testing.assert_allclose(out[:, 0].mean(), 100.0, atol=1.5)  # no drift from x'
    np.testing.assert_allclose(out[:, 0].std(), 10.0, rtol=0.1)


@pytest.mark.parametrize("rng", RNGS)
def test_random_walk_moves_by_the_full_draws_position_and_size_normals(rng):
    """The random walk draws only the normals it uses (positions and sizes): they are
    the ones of the full ``[N, 8]`` draw, so every step is the same as drawing all."""
    n = 300
    independent = motion(THESIS_TAU, size_correlation=0.0)
    state = jnp.tile(STATE, (n, 1))
    tau = jnp.asarray(THESIS_TAU)
    out = np.asarray(propagate(KEY, state, state, independent, model="random_walk", rng=rng))
    k_noise, _ = jax.random.split(KEY)
    if rng == "hash":
        z = fastrand.normal(k_noise, (n, 8))
    else:
        z = jax.random.normal(k_noise, (n, 8), jnp.float32)
    want = np.asarray(state + z * tau)
    cols = [0, 1, 4, 5]
    np.testing.assert_array_equal(out[:, cols], want[:, cols])
    assert np.all(out[:, [2, 3, 6, 7]] == 0)


@pytest.mark.parametrize("rng", RNGS)
def test_ar1_noise_scales_are_tau(rng):
    n = 20_000
    independent = motion(THESIS_TAU, size_correlation=0.0)
    out = np.asarray(
        propagate(
            KEY,
            jnp.tile(STATE, (n, 1)),
            jnp.tile(PREV, (n, 1)),
            independent,
            model="ar1",
            rng=rng,
        )
    )
    # position gets n1 (tau=10) only; velocity n3 (tau=1)
    np.testing.assert_allclose(out.std(axis=0), THESIS_TAU, rtol=0.03)
    still = propagate(KEY, STATE, PREV, motion(ZERO_TAU, independent), model="ar1", rng=rng)
    np.testing.assert_allclose(out.mean(axis=0), np.asarray(still[0]), atol=0.25)
    # the components' noises are uncorrelated
    c = np.corrcoef(out.T)
    assert np.max(np.abs(c - np.eye(8))) < 0.04


def test_unknown_rng_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown rng"):
        propagate(KEY, STATE, PREV, motion(THESIS_TAU), rng="mersenne")


def test_correlated_size_noise_scales_width_and_height_together():
    n = 20_000
    mp = motion([1.0, 1, 1, 1, 2, 2, 0.5, 0.5], size_correlation=0.8)
    state = jnp.tile(jnp.array([[100.0, 80.0, 0.0, 0.0, 41.0, 100.0, 0.0, 0.0]]), (n, 1))
    out = np.asarray(propagate(KEY, state, state, mp, model="ar1"))
    dw, dh = out[:, 4] - 41.0, out[:, 5] - 100.0
    assert abs(np.corrcoef(dw, dh)[0, 1] - 0.8) < 0.02
    np.testing.assert_allclose([dw.std(), dh.std()], [2.0, 2.0], rtol=0.03)  # aspect 0.41
    np.testing.assert_allclose(np.corrcoef(out[:, 6], out[:, 7])[0, 1], 0.8, atol=0.02)


def test_guidance_stretches_along_motion_and_keeps_stationary_isotropic():
    n = 20_000
    mp = motion(THESIS_TAU, guided_fraction=1.0)
    moving = jnp.tile(jnp.array([[100.0, 100.0, 8.0, 0.0, 40.0, 90.0, 0.0, 0.0]]), (n, 1))
    out = np.asarray(propagate(KEY, moving, moving, mp, model="ar1", hierarchical=True))
    sx, sy = out[:, 0].std(), out[:, 1].std()
    assert sx > 1.5 * 10 and sy < 10 / 1.5
    assert abs(out[:, 0].mean() - 108.0) < 0.5  # still centred on the AR1 prediction
    # size-velocity noise is damped by fast motion along x
    assert out[:, 6].std() < 0.1 * 0.5
    still = moving.at[:, 2].set(0.0)
    out = np.asarray(propagate(KEY, still, still, mp, model="ar1", hierarchical=True))
    np.testing.assert_allclose([out[:, 0].std(), out[:, 1].std()], [10, 10], rtol=0.05)


def test_guided_fraction_zero_equals_plain():
    mp = motion(THESIS_TAU, guided_fraction=0.0)
    p = jnp.tile(STATE, (64, 1))
    a = propagate(KEY, p, p, mp, model="ar1", hierarchical=True)
    b = propagate(KEY, p, p, mp, model="ar1", hierarchical=False)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b))
    # ... which the guided share would change (so the comparison above can fail)
    half = propagate(KEY, p, p, mp._replace(guided_fraction=jnp.float32(0.5)), hierarchical=True)
    assert np.abs(np.asarray(half) - np.asarray(b)).max() > 0.1


def test_guided_random_walk_drifts_its_share_by_the_estimated_velocity():
    n = 40_000
    mp = motion(THESIS_TAU, guided_fraction=0.5)
    still = jnp.tile(jnp.array([[100.0, 100.0, 0.0, 0.0, 40.0, 90.0, 0.0, 0.0]]), (n, 1))
    v = jnp.array([8.0, 0.0])
    rw = dict(model="random_walk", hierarchical=True)
    out = np.asarray(propagate(KEY, still, still, mp, guide=v, **rw))
    dx, dy = out[:, 0] - 100.0, out[:, 1] - 100.0
    # a two-component mixture: half around +8 px (stretched along x), half around 0
    stretch = 1.0 + 2.0 * 8.0 / (8.0 + 4.0)  # default guide_gain / guide_speed
    assert abs(dx.mean() - 4.0) < 0.3 and abs(dy.mean()) < 0.2
    var_x = 0.5 * 100.0 + 0.5 * (10.0 * stretch) ** 2 + 0.25 * 64.0
    var_y = 0.5 * 100.0 + 0.5 * (10.0 / stretch) ** 2
    np.testing.assert_allclose([dx.var(), dy.var()], [var_x, var_y], rtol=0.04)
    mp1 = mp._replace(guided_fraction=jnp.float32(1.0))
    one = np.asarray(propagate(KEY, still, still, mp1, guide=v, **rw))
    np.testing.assert_allclose(one[:, 0].mean(), 108.0, atol=0.3)
    np.testing.assert_allclose(
        [one[:, 0].std(), one[:, 1].std()], [10.0 * stretch, 10.0 / stretch], rtol=0.03
    )
    np.testing.assert_allclose(one[:, 4:6].std(axis=0), [0.1 * 40 / 90 / 0.41, 0.1], rtol=0.05)
    assert (one[:, 2:4] == 0).all() and (one[:, 6:8] == 0).all()  # still a random walk
    # no guide, plain sampling, or a zero velocity with nothing guided: the plain walk
    plain = np.asarray(propagate(KEY, still, still, mp, model="random_walk"))
    np.testing.assert_array_equal(np.asarray(propagate(KEY, still, still, mp, **rw)), plain)
    mp0 = mp._replace(guided_fraction=jnp.float32(0.0))
    np.testing.assert_allclose(
        np.asarray(propagate(KEY, still, still, mp0, guide=v, **rw)), plain, atol=1e-5
    )


@pytest.mark.parametrize("model", MODELS)
def test_jit_and_vmap_over_keys_draw_what_plain_calls_draw(model):
    """The noisy step under jit equals the plain call, and vmapped over keys each key's
    plain call (the keys draw different particles, so a shared draw would fail)."""
    p = jnp.tile(STATE, (16, 1))
    mp = motion(THESIS_TAU)

    def draw(k, p):
        return propagate(k, p, p, mp, model=model, hierarchical=True)

    f = jax.jit(draw)
    np.testing.assert_allclose(np.asarray(f(KEY, p)), np.asarray(draw(KEY, p)), rtol=1e-5)
    keys = jax.random.split(KEY, 3)
    b = np.asarray(jax.vmap(f, in_axes=(0, None))(keys, p))
    assert b.shape == (3, 16, 8) and np.isfinite(b).all()
    for i in range(3):
        np.testing.assert_allclose(b[i], np.asarray(draw(keys[i], p)), rtol=1e-5, atol=1e-4)
    assert np.abs(b[0] - b[1]).max() > 0.1


def test_unknown_model_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown motion model"):
        propagate(KEY, STATE, PREV, motion(ZERO_TAU), model="ar3")


def test_size_hold_damps_the_size_velocity_of_guided_particles_moving_across():
    """``size_hold``: guided particles keep ``1 - h (1 - min(r, 1))`` of their size
    velocity (r the size-noise scale); positions and the plain share are unchanged."""
    n = 20_000
    g = 0.5
    mp = motion(THESIS_TAU, guided_fraction=g)
    # moving along x at 8 px/frame, the box growing by 2 px/frame
    state = jnp.tile(jnp.array([[100.0, 100.0, 8.0, 0.0, 40.0, 90.0, 2.0, 2.0]]), (n, 1))

    @jax.jit
    def run(hold, state):
        m = mp._replace(size_hold=hold)
        return propagate(KEY, state, state, m, model="ar1", hierarchical=True)

    off = np.asarray(run(jnp.float32(0.0), state))
    on = np.asarray(run(jnp.float32(1.0), state))
    np.testing.assert_array_equal(on[:, :4], off[:, :4])  # positions untouched
    r = 1.0 / (1.0 + 0.5 * 8.0)  # default size_gain_x 0.5, |y'| = 0
    shift = on[:, 4:] - off[:, 4:]  # (w, h, w', h') each lose (1 - keep) * 2 px
    held = np.abs(shift[:, 0] + (1.0 - r) * 2.0) < 1e-4
    assert abs(held.mean() - g) < 0.02  # the guided share
    np.testing.assert_allclose(shift[held], -(1.0 - r) * 2.0, atol=1e-4)
    np.testing.assert_allclose(shift[~held], 0.0, atol=1e-5)
    # traced and vmapped over the hold: the mean size velocity is linear in it
    holds = jnp.array([0.0, 0.5, 1.0], jnp.float32)
    vw = np.asarray(jax.vmap(run, in_axes=(0, None))(holds, state))[:, :, 6].mean(axis=1)
    want = (1 - g) * 2.0 + g * 2.0 * (1.0 - np.asarray(holds) * (1.0 - r))
    np.testing.assert_allclose(vw, want, atol=0.01)
    # still, or moving along y (r >= 1): nothing to hold
    for v in ((0.0, 0.0), (0.0, 8.0)):
        s = state.at[:, 2].set(v[0]).at[:, 3].set(v[1])
        np.testing.assert_allclose(np.asarray(run(jnp.float32(1.0), s)), np.asarray(run(0.0, s)))


def test_height_scale_is_the_height_over_the_reference_height():
    particles = jnp.concatenate([STATE, STATE.at[:, 5].set(300.0)])
    np.testing.assert_allclose(np.asarray(height_scale(particles, 200.0)), [0.45, 1.5])
    assert height_scale(particles, None) is None
    # The same multipliers as the noise it scales: propagate with it equals tau scaled.
    tau = np.asarray(THESIS_TAU)
    scaled = propagate(KEY, STATE, PREV, motion(tau), model="ar1", scale=height_scale(STATE, 45.0))
    plain = propagate(KEY, STATE, PREV, motion(2.0 * tau), model="ar1")
    np.testing.assert_allclose(np.asarray(scaled), np.asarray(plain), rtol=1e-5)
