"""Gradient tuning (cpf_jax.tuning): bijectors, the DIoU loss against NumPy under jit and
vmap, gradients through the filters against finite differences, and the optax loop."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cpf_jax import charts, rgbd, tuning
from cpf_jax.colour import PARAM_CONSTRAINTS, ColourConfig, default_colour_params
from cpf_jax.kernels.background import median_background
from cpf_jax.synthetic import make_sequence


@pytest.fixture(scope="module")
def walk():
    """Two short synthetic walks (14 frames) and a colour config with one window for both:
    the histogram-only model (``ColourConfig.histogram_only``), whose sigma and contrast
    weight carry the likelihood (the default's layout term is checked on its own)."""
    seqs = [make_sequence("walk_across_medium", seed=s, n_frames=14) for s in (100, 101)]
    data = tuning.stack_sequences(seqs)
    w = max(float(s.boxes[:, 2].max()) for s in seqs)
    h = max(float(s.boxes[:, 3].max()) for s in seqs)
    config = ColourConfig(n_particles=40).with_window((w, h), seqs[0].colour.shape[1:3])
    return data, config.histogram_only()


@pytest.mark.parametrize("kind", ["identity", "softplus", "sigmoid"])
def test_bijectors_round_trip_and_map_into_their_domains(kind):
    constrain, unconstrain = tuning.BIJECTORS[kind]
    values = {"identity": [-3.0, 0.0, 2.5], "softplus": [1e-3, 0.15, 28.0, 300.0]}
    x = jnp.asarray(values.get(kind, [1e-3, 0.3, 0.5, 0.999]), jnp.float32)
    np.testing.assert_allclose(np.asarray(constrain(unconstrain(x))), np.asarray(x), rtol=2e-4)
    u = jnp.linspace(-30.0, 30.0, 61)
    y = np.asarray(jax.jit(constrain)(u))
    assert np.all(np.isfinite(y))
    if kind == "softplus":
        assert np.all(y >= 0) and np.all(np.diff(y) > 0)
    if kind == "sigmoid":
        assert np.all((y >= 0) & (y <= 1)) and np.all(np.diff(y) >= 0)


def _tunable(params, constraints):
    """Fields with a constraint whose values are inside its open domain."""
    names = []
    for name in constraints._fields:
        kind = getattr(constraints, name)
        if kind is None:
            continue
        try:
            tuning.to_unconstrained(params, constraints, [name])
        except ValueError:
            continue
        names.append(name)
    return names


@pytest.mark.parametrize("module", ["colour", "rgbd"])
def test_params_round_trip_through_the_free_values(module):
    if module == "colour":
        params, constraints = default_colour_params(), PARAM_CONSTRAINTS
    else:
        params, constraints = rgbd.default_rgbd_params(), rgbd.PARAM_CONSTRAINTS
    names = _tunable(params, constraints)
    assert {"sigma", "tau", "motion"} <= set(names) or {"sigma_rgb", "tau", "motion"} <= set(names)
    free = tuning.to_unconstrained(params, constraints, names)
    back = tuning.to_params(free, params, constraints)
    for a, b in zip(
        jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back), strict=True
    ):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=2e-4, atol=1e-6)


def test_names_that_cannot_be_tuned_raise_one_clear_error():
    p = default_colour_params()
    with pytest.raises(ValueError, match="unknown parameter 'sigmaa'"):
        tuning.to_unconstrained(p, PARAM_CONSTRAINTS, ["sigmaa"])
    with pytest.raises(ValueError, match="'colour' cannot be tuned"):
        tuning.to_unconstrained(rgbd.default_rgbd_params(), rgbd.PARAM_CONSTRAINTS, ["colour"])
    # layout_rate defaults to 0, the boundary of its (0, 1) constraint.
    with pytest.raises(ValueError, match="layout_rate.*boundary"):
        tuning.to_unconstrained(p, PARAM_CONSTRAINTS, ["layout_rate"])


def _diou_numpy(pred, gt, visible):
    out = []
    for p, g in zip(pred.astype(np.float64), gt.astype(np.float64), strict=True):
        ix = max(0.0, min(p[0] + p[2], g[0] + g[2]) - max(p[0], g[0]))
        iy = max(0.0, min(p[1] + p[3], g[1] + g[3]) - max(p[1], g[1]))
        inter = ix * iy
        iou = inter / max(p[2] * p[3] + g[2] * g[3] - inter, 1e-6)
        cp, cg = p[:2] + p[2:] / 2, g[:2] + g[2:] / 2
        lo = np.minimum(p[:2], g[:2])
        hi = np.maximum(p[:2] + p[2:], g[:2] + g[2:])
        out.append(1 - iou + np.sum((cp - cg) ** 2) / np.sum((hi - lo) ** 2))
    out = np.asarray(out)
    return float(np.sum(out * visible) / max(visible.sum(), 1))


def test_diou_loss_matches_numpy_under_jit_and_vmap():
    rng = np.random.default_rng(0)
    gt = np.concatenate([rng.uniform(0, 300, (2, 6, 2)), rng.uniform(10, 120, (2, 6, 2))], -1)
    pred = gt + rng.normal(0, 25, gt.shape)
    pred[..., 2:] = np.abs(pred[..., 2:]) + 1
    pred[0, 0] = [900, 900, 20, 20]  # far from its ground truth: no overlap
    visible = np.ones((2, 6), bool)
    visible[1, 2] = False
    got = jax.jit(jax.vmap(tuning.diou_loss))(pred, gt, visible)
    want = [_diou_numpy(pred[i], gt[i], visible[i]) for i in range(2)]
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)
    assert float(tuning.diou_loss(gt[0], gt[0])) == pytest.approx(0.0, abs=1e-6)
    # A box on its target has a finite gradient (no sqrt of a zero centre distance).
    assert np.all(np.isfinite(np.asarray(jax.grad(tuning.diou_loss)(jnp.asarray(gt[0]), gt[0]))))
    # Without overlap the loss exceeds 1 and still has a gradient towards the target.
    g = jax.grad(lambda b: tuning.diou_loss(b[None], gt[0, :1]))(jnp.asarray(pred[0, 0]))
    assert np.all(np.asarray(g[:2]) > 0)  # moving the far box up-left lowers the loss
    assert float(tuning.diou_loss(jnp.zeros((0, 4)), jnp.zeros((0, 4)), jnp.zeros(0))) == 0.0


@pytest.mark.parametrize(
    "model, names",
    [("histogram_only", ("sigma", "contrast_weight")), ("default", ("layout_weight",))],
)
def test_colour_gradient_matches_finite_differences(walk, model, names):
    """One filter step (the estimate is a smooth weighted mean of fixed particles): the
    gradient of the loss with respect to sigma and contrast_weight (histogram-only
    model) and to the default's layout weight is the numerical one."""
    data, config = walk
    if model == "default":
        config = dataclasses.replace(
            ColourConfig(), n_particles=config.n_particles, window=config.window
        )
    two = jax.tree_util.tree_map(lambda x: x[:, :2], data)
    loss = jax.jit(tuning.make_loss(tuning.colour_runner(config), PARAM_CONSTRAINTS))
    p = default_colour_params()._replace(sigma=jnp.float32(0.3))
    free = tuning.to_unconstrained(p, PARAM_CONSTRAINTS, names)
    key = jax.random.PRNGKey(4)
    grads = jax.jit(jax.grad(tuning.make_loss(tuning.colour_runner(config), PARAM_CONSTRAINTS)))(
        free, p, key, two
    )
    for n in names:
        eps = 0.02
        up = dict(free, **{n: free[n] + eps})
        down = dict(free, **{n: free[n] - eps})
        fd = (float(loss(up, p, key, two)) - float(loss(down, p, key, two))) / (2 * eps)
        assert abs(float(grads[n])) > 1e-4, n  # the check can fail: not a zero gradient
        assert float(grads[n]) == pytest.approx(fd, rel=0.1, abs=2e-5), n


@pytest.mark.run_bound
def test_tune_lowers_the_training_loss_and_stays_in_the_domain(walk):
    data, config = walk
    run = tuning.colour_runner(config)
    start = default_colour_params()._replace(
        sigma=jnp.float32(1.0), contrast_weight=jnp.float32(2.0)
    )
    names = ("sigma", "contrast_weight")
    seen = []
    result = tuning.tune(
        run,
        start,
        PARAM_CONSTRAINTS,
        data,
        names,
        optimizer=optax.adam(0.3),
        steps=8,
        key=jax.random.PRNGKey(1),
        callback=seen.append,
    )
    assert len(result.history) == 8 and seen == result.history
    assert not any(e["skipped"] for e in result.history)
    assert float(result.params.sigma) > 0 and float(result.params.contrast_weight) > 0
    # Every other field is untouched.
    for name in set(start._fields) - set(names):
        for a, b in zip(
            jax.tree_util.tree_leaves(getattr(start, name)),
            jax.tree_util.tree_leaves(getattr(result.params, name)),
            strict=True,
        ):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    loss = jax.jit(tuning.make_loss(run, PARAM_CONSTRAINTS, keys=4))
    key = jax.random.PRNGKey(99)

    def value(p):
        return float(loss(tuning.to_unconstrained(p, PARAM_CONSTRAINTS, names), p, key, data))

    assert value(result.params) < value(start) - 0.1  # measured: 0.60 -> 0.31-0.33


def test_tune_skips_steps_whose_gradient_is_not_finite(walk):
    data, _ = walk

    def broken(params, key, seq):  # a NaN box whenever sigma is involved
        return seq.boxes * (params.sigma * jnp.nan)

    start = default_colour_params()
    result = tuning.tune(broken, start, PARAM_CONSTRAINTS, data, ("sigma",), steps=2)
    assert all(e["skipped"] for e in result.history)
    assert float(result.params.sigma) == pytest.approx(float(start.sigma))


def test_rgbd_gradients_are_finite_and_reach_the_likelihood():
    seq = make_sequence("occlusion_box", seed=100, n_frames=10)
    bg = median_background(
        jnp.asarray(seq.meta["background_colour"])[None],
        jnp.asarray(seq.meta["background_depth"])[None],
    )
    data = tuning.stack_sequences([seq], [bg])
    w, h = (float(v) for v in seq.boxes[:, 2:].max(0))
    config = rgbd.RGBDConfig(n_particles=64).with_window((w, h), seq.colour.shape[1:3])
    params = rgbd.default_rgbd_params(config)
    names = ("sigma_rgb", "sigma_depth", "log_occluded", "p_occlude", "beta_a")
    free = tuning.to_unconstrained(params, rgbd.PARAM_CONSTRAINTS, names)
    loss = tuning.make_loss(tuning.rgbd_runner(config), rgbd.PARAM_CONSTRAINTS)
    value, grads = jax.jit(jax.value_and_grad(loss))(free, params, jax.random.PRNGKey(0), data)
    assert np.isfinite(float(value))
    flat = {n: np.asarray(g) for n, g in grads.items()}
    assert all(np.all(np.isfinite(g)) for g in flat.values()), flat
    assert np.abs(flat["sigma_depth"]).max() > 0 and np.abs(flat["beta_a"]).max() > 0, flat


def test_stack_sequences_rejects_mixed_lengths():
    a = make_sequence("walk_across_medium", seed=0, n_frames=4)
    b = a._replace(colour=a.colour[:3], depth=a.depth[:3])
    with pytest.raises(ValueError, match="differ in length or frame size"):
        tuning.stack_sequences([a, b])


@pytest.mark.run_bound
def test_tune_with_validation_returns_the_best_validated_parameters(walk):
    data, config = walk
    train = jax.tree_util.tree_map(lambda x: x[:1], data)
    val = jax.tree_util.tree_map(lambda x: x[1:], data)
    run = tuning.colour_runner(config)
    start = default_colour_params()._replace(
        sigma=jnp.float32(1.0), contrast_weight=jnp.float32(2.0)
    )
    key = jax.random.PRNGKey(5)
    result = tuning.tune(
        run,
        start,
        PARAM_CONSTRAINTS,
        train,
        ("sigma",),
        optimizer=optax.adam(0.4),
        steps=6,
        key=key,
        validation=val,
        validate_every=2,
    )
    checked = [e for e in result.history if "validation" in e]
    assert [e["step"] for e in checked] == [1, 3, 5]
    loss = tuning.make_loss(run, PARAM_CONSTRAINTS)
    free0 = tuning.to_unconstrained(start, PARAM_CONSTRAINTS, ("sigma",))
    v0 = float(jax.jit(loss)(free0, start, jax.random.fold_in(key, 1), val))
    assert result.start_validation == pytest.approx(v0, rel=1e-5)
    candidates = [(v0, float(start.sigma))] + [(e["validation"], e["sigma"]) for e in checked]
    best_sigma = min(candidates)[1]
    assert float(result.params.sigma) == pytest.approx(best_sigma, rel=1e-5)
    assert min(candidates)[0] < v0  # the check can fail: tuning helped on validation


def test_progress_prints_each_step(capsys):
    show = tuning.progress("run", ("sigma", "beta_a"))
    show({"step": 3, "loss": 0.25, "sigma": 0.125, "beta_a": [1.0, 3.0], "skipped": False})
    show({"step": 4, "loss": 0.2, "sigma": 0.1, "beta_a": [2.0, 2.0], "validation": 0.3})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "run step   3 loss 0.2500 sigma 0.125 beta_a 2.000"
    assert lines[1].endswith("validation 0.3000")


def test_history_chart_draws_training_and_validation_losses():
    history = [
        {"step": 0, "loss": 0.5},
        {"step": 1, "loss": 0.4, "validation": 0.45},
        {"step": 2, "loss": 0.3},
    ]
    one = tuning.history_chart({"a": history[:1] + [history[2]]})
    both = tuning.history_chart({"a": history})
    assert one.ndim == 3 and one.dtype == np.uint8
    # One legend line per series: the validation loss is a second series.
    assert both.shape[0] - one.shape[0] == 16
    # Training in the first palette colour, validation in the second.
    for colour in charts.PALETTE[:2]:
        assert np.any(np.all(np.abs(both.astype(int) - colour) <= 10, axis=-1))
    assert not np.any(np.all(np.abs(one.astype(int) - charts.PALETTE[1]) <= 10, axis=-1))
