"""Gradient tuning (cpf_jax.tuning): bijectors, the DIoU loss against NumPy under jit and
vmap, gradients through the filters against finite differences, and the optax loop."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cpf_jax import charts, rgbd, tuning
from cpf_jax import params as pp
from cpf_jax.colour import COLOUR_PROPS, ColourConfig, build_colour_filter, default_colour_params
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
    constrain, unconstrain = pp.BIJECTORS[kind]
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


def _tunable(params, props):
    """Trainable paths whose values lie inside their constraint's open domain, and the
    trainable paths whose values sit on its boundary."""
    inside, boundary = [], []
    for path in pp.paths(props, trainable_only=True):
        try:
            tuning.unconstrained(params, props, [path])
        except ValueError:
            boundary.append(path)
            continue
        inside.append(path)
    return inside, boundary


def _colour_and_rgbd(module):
    if module == "colour":
        return default_colour_params(), COLOUR_PROPS
    return rgbd.default_rgbd_params(), rgbd.rgbd_props()


@pytest.mark.parametrize("module", ["colour", "rgbd"])
def test_params_round_trip_through_the_free_values(module):
    params, props = _colour_and_rgbd(module)
    names, boundary = _tunable(params, props)
    sigma = "histogram.sigma" if module == "colour" else "colour.sigma"
    assert {sigma, "motion.tau", "motion.guided_fraction", "motion.size_velocity_decay"} <= set(
        names
    )
    # Only the colour layer's layout rate starts on a bound (0, of its (0, 1) domain).
    assert boundary == (["layout.rate"] if module == "colour" else [])
    free = tuning.unconstrained(params, props, names)
    assert set(free) == set(names)
    back = pp.constrain(free, params, props)
    for a, b in zip(
        jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back), strict=True
    ):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=2e-4, atol=1e-6)
    # constrain maps the free values back: a moved free value moves the parameter.
    moved = pp.constrain(dict(free, **{sigma: free[sigma] + 1.0}), params, props)
    assert float(pp.get(moved, sigma)) > float(pp.get(params, sigma)) * 1.5


@pytest.mark.parametrize("module", ["colour", "rgbd"])
def test_non_trainable_paths_raise_a_clear_error_when_named(module):
    params, props = _colour_and_rgbd(module)
    trainable = set(pp.paths(props, trainable_only=True))
    fixed = [p for p in pp.paths(props) if p not in trainable]
    if module == "colour":
        assert fixed == []  # every colour parameter is trainable: mark one as not
        props = pp.replace(props, "histogram.lost_distance", pp.Prop("sigmoid", False))
        fixed = ["histogram.lost_distance"]
    else:  # the RGB-D filter's gates, counts and thresholds act only through comparisons
        assert {"occlusion.transition", "occlusion.vote_threshold", "report.margin"} <= set(fixed)
    for path in fixed:
        with pytest.raises(ValueError, match=f"parameter '{path}' is not trainable"):
            tuning.unconstrained(params, props, [path])
        with pytest.raises(ValueError, match=f"parameter '{path}' is not trainable"):
            pp.constrain({path: jnp.float32(0.0)}, params, props)
        with pytest.raises(ValueError, match="not trainable"):
            tuning.tune(lambda p, k, s: s.boxes, params, props, None, [path], steps=0)


def test_names_that_cannot_be_tuned_raise_one_clear_error():
    p = default_colour_params()
    with pytest.raises(ValueError, match="no parameter 'histogram.sigmaa'.*sigma, lost_distance"):
        tuning.unconstrained(p, COLOUR_PROPS, ["histogram.sigmaa"])
    # A term holding a parameter that is not trainable cannot be tuned as a whole ...
    with pytest.raises(ValueError, match="'occlusion.transition' is not trainable"):
        tuning.unconstrained(rgbd.default_rgbd_params(), rgbd.rgbd_props(), ["occlusion"])
    # ... a term of trainable ones can: one free value per field.
    motion = tuning.unconstrained(p, COLOUR_PROPS, ["motion"])["motion"]
    assert motion._fields == p.motion._fields
    # layout.rate defaults to 0, the boundary of its (0, 1) constraint.
    with pytest.raises(ValueError, match="layout.rate.*boundary"):
        tuning.unconstrained(p, COLOUR_PROPS, ["layout.rate"])


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
    [("histogram_only", ("histogram.sigma", "contrast.weight")), ("default", ("layout.weight",))],
)
def test_colour_gradient_matches_finite_differences(walk, model, names):
    """One filter step (the estimate is a smooth weighted mean of fixed particles): the
    gradient of the loss with respect to sigma and the contrast weight (histogram-only
    model) and to the default's layout weight is the numerical one."""
    data, config = walk
    if model == "default":
        config = dataclasses.replace(
            ColourConfig(), n_particles=config.n_particles, window=config.window
        )
    two = jax.tree_util.tree_map(lambda x: x[:, :2], data)
    run = tuning.runner(build_colour_filter(config))
    loss = jax.jit(tuning.make_loss(run, COLOUR_PROPS))
    p = pp.replace(default_colour_params(), "histogram.sigma", jnp.float32(0.3))
    free = tuning.unconstrained(p, COLOUR_PROPS, names)
    key = jax.random.PRNGKey(4)
    grads = jax.jit(jax.grad(tuning.make_loss(run, COLOUR_PROPS)))(free, p, key, two)
    for n in names:
        eps = 0.02
        up = dict(free, **{n: free[n] + eps})
        down = dict(free, **{n: free[n] - eps})
        fd = (float(loss(up, p, key, two)) - float(loss(down, p, key, two))) / (2 * eps)
        assert abs(float(grads[n])) > 1e-4, n  # the check can fail: not a zero gradient
        assert float(grads[n]) == pytest.approx(fd, rel=0.1, abs=2e-5), n


def _start():
    """The defaults with a too-wide sigma and a too-small contrast weight."""
    start = pp.replace(default_colour_params(), "histogram.sigma", jnp.float32(1.0))
    return pp.replace(start, "contrast.weight", jnp.float32(2.0))


@pytest.mark.run_bound
def test_tune_lowers_the_training_loss_and_stays_in_the_domain(walk):
    data, config = walk
    run = tuning.runner(build_colour_filter(config))
    start = _start()
    names = ("histogram.sigma", "contrast.weight")
    seen = []
    result = tuning.tune(
        run,
        start,
        COLOUR_PROPS,
        data,
        names,
        optimizer=optax.adam(0.3),
        steps=8,
        key=jax.random.PRNGKey(1),
        callback=seen.append,
    )
    assert len(result.history) == 8 and seen == result.history
    assert not any(e["skipped"] for e in result.history)
    assert float(result.params.histogram.sigma) > 0 and float(result.params.contrast.weight) > 0
    assert float(result.params.histogram.sigma) != pytest.approx(1.0)  # it moved
    # Every other field is untouched.
    others = [path for path in pp.paths(COLOUR_PROPS) if path not in names]
    assert len(others) == len(list(pp.paths(COLOUR_PROPS))) - 2
    for path in others:
        for a, b in zip(
            jax.tree_util.tree_leaves(pp.get(start, path)),
            jax.tree_util.tree_leaves(pp.get(result.params, path)),
            strict=True,
        ):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    loss = jax.jit(tuning.make_loss(run, COLOUR_PROPS, keys=4))
    key = jax.random.PRNGKey(99)

    def value(p):
        return float(loss(tuning.unconstrained(p, COLOUR_PROPS, names), p, key, data))

    assert value(result.params) < value(start) - 0.1  # measured: 0.60 -> 0.31-0.33


def test_tune_skips_steps_whose_gradient_is_not_finite(walk):
    data, _ = walk

    def broken(params, key, seq):  # a NaN box whenever sigma is involved
        return seq.boxes * (params.histogram.sigma * jnp.nan)

    start = default_colour_params()
    result = tuning.tune(broken, start, COLOUR_PROPS, data, ("histogram.sigma",), steps=2)
    assert len(result.history) == 2 and all(e["skipped"] for e in result.history)
    assert float(result.params.histogram.sigma) == pytest.approx(float(start.histogram.sigma))


def test_rgbd_gradients_are_finite_and_reach_the_likelihood():
    seq = make_sequence("occlusion_box", seed=100, n_frames=10)
    bg = median_background(
        jnp.asarray(seq.meta["background_colour"])[None],
        jnp.asarray(seq.meta["background_depth"])[None],
    )
    data = tuning.stack_sequences([seq], [bg])
    w, h = (float(v) for v in seq.boxes[:, 2:].max(0))
    config = rgbd.RGBDConfig(n_particles=64).with_window((w, h), seq.colour.shape[1:3])
    params, props = rgbd.default_rgbd_params(config), rgbd.rgbd_props(config)
    names = (
        "colour.sigma",
        "depth.sigma",
        "occlusion.log_occluded",
        "occlusion.p_occlude",
        "beta.a",
    )
    free = tuning.unconstrained(params, props, names)
    loss = tuning.make_loss(tuning.runner(rgbd.build_rgbd_filter(config)), props)
    value, grads = jax.jit(jax.value_and_grad(loss))(free, params, jax.random.PRNGKey(0), data)
    assert np.isfinite(float(value))
    flat = {n: np.asarray(g) for n, g in grads.items()}
    assert set(flat) == set(names)
    assert all(np.all(np.isfinite(g)) for g in flat.values()), flat
    assert np.abs(flat["depth.sigma"]).max() > 0 and np.abs(flat["beta.a"]).max() > 0, flat


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
    run = tuning.runner(build_colour_filter(config))
    start = _start()
    key = jax.random.PRNGKey(5)
    result = tuning.tune(
        run,
        start,
        COLOUR_PROPS,
        train,
        ("histogram.sigma",),
        optimizer=optax.adam(0.4),
        steps=6,
        key=key,
        validation=val,
        validate_every=2,
    )
    checked = [e for e in result.history if "validation" in e]
    assert [e["step"] for e in checked] == [1, 3, 5]
    loss = tuning.make_loss(run, COLOUR_PROPS)
    free0 = tuning.unconstrained(start, COLOUR_PROPS, ("histogram.sigma",))
    v0 = float(jax.jit(loss)(free0, start, jax.random.fold_in(key, 1), val))
    assert result.start_validation == pytest.approx(v0, rel=1e-5)
    candidates = [(v0, float(start.histogram.sigma))]
    candidates += [(e["validation"], e["histogram.sigma"]) for e in checked]
    best_sigma = min(candidates)[1]
    assert float(result.params.histogram.sigma) == pytest.approx(best_sigma, rel=1e-5)
    assert min(candidates)[0] < v0  # the check can fail: tuning helped on validation


def test_progress_prints_each_step(capsys):
    show = tuning.progress("run", ("colour.sigma", "beta.a"))
    show({"step": 3, "loss": 0.25, "colour.sigma": 0.125, "beta.a": [1.0, 3.0], "skipped": False})
    show({"step": 4, "loss": 0.2, "colour.sigma": 0.1, "beta.a": [2.0, 2.0], "validation": 0.3})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "run step   3 loss 0.2500 colour.sigma 0.125 beta.a 2.000"
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
