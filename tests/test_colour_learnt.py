"""The colour layer's learnt discriminative term (colour.correlation) and its camera-motion
stage (colour.camera): each against a reference, and in the filter."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel

from cpf_jax import Frame
from cpf_jax.colour import ColourConfig, CorrelationConfig, build_colour_filter
from cpf_jax.colour import default_colour_params as colour_params
from cpf_jax.colour.camera import camera_init, camera_shift, shift_state
from cpf_jax.colour.correlation import (
    correlation_init,
    correlation_scores,
    correlation_update,
)
from cpf_jax.filter import Cloud
from cpf_jax.kernels import correlation as cf
from cpf_jax.kernels.boxes import iou
from cpf_jax.synthetic import make_sequence

CORR = CorrelationConfig()


@pytest.fixture(scope="module")
def walk():
    return make_sequence("walk_across_medium", seed=4, n_frames=30)


def _frame(seq, t):
    return Frame(jnp.asarray(seq.colour[t]), jnp.asarray(seq.depth[t]))


def test_correlation_scores_read_the_response_around_the_last_estimate(walk):
    box = walk.boxes[0]
    model = correlation_init(CORR, _frame(walk, 0), box)
    centres = np.array(
        [box[:2] + box[2:] / 2 + d for d in ([0, 0], [7.5, -3.0], [-400.0, 0.0])], np.float32
    )

    def reference(colour, estimate, c):
        patch = cf.sample_patch(colour, estimate[:2] + estimate[2:] / 2, 2.5 * estimate[2:], 128)
        resp = np.asarray(cf.response(model.filter, cf.features(patch, 4), CORR.ridge))
        cell = 2.5 * estimate[2:] / 32
        disp = (c - (estimate[:2] + estimate[2:] / 2)) / cell
        return np.asarray(cf.read_response(jnp.asarray(resp), jnp.asarray(disp)))

    later = walk.boxes[3]
    check_kernel(
        lambda colour, e, c: correlation_scores(CORR, model, Frame(colour, None), e, c),
        reference,
        (walk.colour[3], later, centres),
        batch=[(walk.colour[3], later, centres), (walk.colour[5], walk.boxes[5], centres)],
        rtol=1e-4,
        atol=1e-4,
    )
    scores = reference(walk.colour[0], box, centres)
    assert scores[0] > 0.5 > scores[1] > scores[2]  # the target, beside it, off the patch


def _step(config, params, seq, t=1, state=None):
    filt = build_colour_filter(config)
    if state is None:
        state = jax.jit(filt.init)(params, jax.random.PRNGKey(0), _frame(seq, 0), seq.boxes[0])
    return jax.jit(filt.step)(params, jax.random.PRNGKey(t), state, _frame(seq, t))


def test_a_zero_weight_term_leaves_the_weights_and_a_zero_rate_the_filter(walk):
    base = ColourConfig(n_particles=64).with_window(walk.boxes[0, 2:], (424, 512))
    params = colour_params()
    off_state, off = _step(base, params, walk)
    with_term = dataclasses.replace(base, correlation=CORR)
    silent = params._replace(correlation=params.correlation._replace(weight=jnp.float32(0.0)))
    on_state, on = _step(with_term, silent, walk)
    np.testing.assert_allclose(on.box, off.box, rtol=1e-5)
    np.testing.assert_allclose(on_state.cloud.log_weights, off_state.cloud.log_weights, atol=1e-5)
    # It learns at its rate, and not at all at rate 0.
    first = correlation_init(CORR, _frame(walk, 0), walk.boxes[0])
    init = first.filter
    expect = correlation_update(CORR, silent.correlation, first, _frame(walk, 1), on.box, False)
    np.testing.assert_allclose(
        on_state.correlation.filter.denominator, expect.filter.denominator, rtol=1e-4
    )
    assert not np.allclose(on_state.correlation.filter.denominator, init.denominator, rtol=1e-4)
    frozen = silent._replace(correlation=silent.correlation._replace(rate=jnp.float32(0.0)))
    still_state, _ = _step(with_term, frozen, walk)
    np.testing.assert_allclose(
        still_state.correlation.filter.denominator, init.denominator, rtol=1e-5
    )
    # With weight the term changes the weights.
    _, weighed = _step(with_term, params, walk)
    assert not np.allclose(weighed.ess, on.ess)


def test_camera_shift_finds_a_pan_and_ignores_a_still_camera(walk):
    colour = walk.colour[0]
    a, b = colour[8:408, 12:492], colour[0:400, 0:480]  # content moved by (+12, +8)
    box = walk.boxes[0]
    track = camera_init(4, a)
    moved = jax.jit(lambda t, c, e: camera_shift(4, t, c, e, 0.12))(track, b, box)
    np.testing.assert_allclose(moved.shift, [12.0, 8.0], atol=1.5)
    still = camera_shift(4, camera_init(4, walk.colour[0]), walk.colour[1], box, 0.12)
    assert np.abs(np.asarray(still.shift)).max() <= 1.0
    # Frames no shift explains (noise against noise) move nothing.
    rng = np.random.default_rng(0)
    n1, n2 = (rng.integers(0, 255, (200, 240, 3), dtype=np.uint8) for _ in range(2))
    still_box = np.array([100.0, 50.0, 30.0, 60.0], np.float32)
    assert np.all(np.asarray(camera_shift(4, camera_init(4, n1), n2, still_box, 0.12).shift) == 0)


def test_the_target_does_not_pass_its_own_motion_off_as_the_camera_s():
    """A large box moving 8 px a frame over a background that changes every frame: the
    only consistent motion is the target's, which the blanked box leaves out."""
    rng = np.random.default_rng(3)
    frames = []
    for t in range(2):
        img = rng.integers(60, 200, (240, 320, 3), dtype=np.uint8)
        img[40:200, 100 + 8 * t : 180 + 8 * t] = np.array([200, 40, 40], np.uint8)
        img[40:200:8, 100 + 8 * t : 180 + 8 * t] = 30  # stripes: a structure that moves
        frames.append(img)
    box = np.array([100.0, 40.0, 80.0, 160.0], np.float32)
    blind = camera_shift(4, camera_init(4, frames[0]), frames[1], np.zeros(4, np.float32), 0.12)
    assert abs(float(blind.shift[0]) - 8.0) <= 2.0  # without the blank: the target's motion
    seen = camera_shift(4, camera_init(4, frames[0]), frames[1], box, 0.12)
    assert np.all(np.asarray(seen.shift) == 0)


def test_a_small_frame_s_noise_is_not_taken_for_the_camera_s_motion():
    """160 x 120 frames (a 40 x 30 grid) of fresh noise each frame: the largest of the
    surface's noise values clears the fixed peak but not the noise floor, so nothing moves;
    a real shift of the same size of frame still does."""
    rng = np.random.default_rng(1)
    noise = [rng.integers(90, 110, (120, 160, 3), dtype=np.uint8) for _ in range(30)]
    box = np.array([60.0, 35.0, 20.0, 50.0], np.float32)
    shift = jax.jit(lambda t, c: camera_shift(4, t, c, box, 0.12).shift)
    moved = [
        np.asarray(shift(camera_init(4, a), b)) for a, b in zip(noise[:-1], noise[1:], strict=True)
    ]
    assert np.all(np.stack(moved) == 0)
    scene = rng.integers(0, 255, (15, 20, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1)
    a, b = scene[8:, 12:][:112, :148], scene[:112, :148]  # content moved by (+12, +8)
    np.testing.assert_allclose(shift(camera_init(4, a), b), [12.0, 8.0], atol=1.5)


def test_shift_state_moves_positions_and_keeps_velocities():
    particles = jnp.arange(24.0).reshape(3, 8)
    state = _State(Cloud(particles, particles - 1.0, jnp.zeros(3)), jnp.array([1.0, 2, 3, 4]))
    out = shift_state(state, jnp.array([5.0, -2.0]))
    expect = np.asarray(particles).copy()
    expect[:, 0] += 5
    expect[:, 1] -= 2
    np.testing.assert_allclose(out.cloud.particles, expect)
    np.testing.assert_allclose(out.cloud.previous, expect - 1.0)
    np.testing.assert_allclose(out.estimate, [6.0, 0.0, 3.0, 4.0])


class _State(tuple):
    """A stand-in box-filter state with the two fields ``shift_state`` reads."""

    def __new__(cls, cloud, estimate):
        return super().__new__(cls, (cloud, estimate))

    cloud = property(lambda self: self[0])
    estimate = property(lambda self: self[1])

    def _replace(self, **kw):
        return _State(kw.get("cloud", self.cloud), kw.get("estimate", self.estimate))


def test_following_the_camera_keeps_the_box_through_a_camera_jump(walk):
    """The whole frame jumps 110 px left and 20 px down (a camera knocked sideways): with
    the camera stage the first step's box is on the walker, without it the cloud is left
    where the walker was."""
    colour = walk.colour[0]
    jumped = np.roll(colour, (20, -110), axis=(0, 1))
    box = walk.boxes[0]
    truth = box + np.array([-110.0, 20.0, 0.0, 0.0], np.float32)
    seq = walk._replace(colour=np.stack([colour, jumped]), depth=walk.depth[:2])
    config = ColourConfig(n_particles=150).with_window(box[2:], (424, 512))
    ious = {}
    for name, factor in (("plain", None), ("camera", 4)):
        _, info = _step(dataclasses.replace(config, camera_motion=factor), colour_params(), seq)
        ious[name] = float(iou(jnp.asarray(info.box), jnp.asarray(truth)))
    assert ious["camera"] > 0.8 and ious["plain"] < 0.5, ious
