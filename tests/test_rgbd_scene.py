"""The RGB-D filter without a background model: the scene learnt from the tracked frames
(``RGBDConfig.learn_scene``), on a walker in view from the first frame."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax import synthetic
from cpf_jax.filter import track
from cpf_jax.metrics.single import frame_ious
from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params


@pytest.fixture(scope="module")
def towards():
    seq = synthetic.make_sequence("walk_towards", seed=0)
    return seq, synthetic.stacked_frames(seq)


def _success(config: RGBDConfig, seq, frames) -> float:
    filt = build_rgbd_filter(config)
    run = jax.jit(lambda k, f, b: track(filt, default_rgbd_params(config), k, f, b))
    _, info = run(jax.random.PRNGKey(0), frames, jnp.asarray(seq.boxes[0], jnp.float32))
    ious = np.asarray(frame_ious(info.estimate, jnp.asarray(seq.boxes[1:])))
    return float(np.mean(ious >= 0.5))


def test_the_learnt_scene_tracks_a_walker_every_frame_of_the_recording_holds(towards):
    """walk_towards: the walker is in every frame, so no frame shows the empty room; the
    scene learnt outside him tracks him where every-pixel-foreground loses him."""
    seq, frames = towards
    config = RGBDConfig(n_particles=150)
    learnt = _success(config, seq, frames)
    blind = _success(dataclasses.replace(config, learn_scene=False), seq, frames)
    assert learnt >= 0.9 and blind < 0.5, (learnt, blind)
