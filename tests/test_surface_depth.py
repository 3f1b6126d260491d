"""``points.body.surface_depth`` against a plain loop, under jit and vmap: the depth under a
position on the body, the nearest body pixel's off it (its search skipped by a ``lax.cond``
when every position is on the body), 0 without a body."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import depth as dk
from cpf_jax.points import PointConfig
from cpf_jax.points import body as pb

SHAPE = (24, 16)
CONFIG = PointConfig(window=SHAPE)


def _body_model(body: np.ndarray, depth: np.ndarray, origin=(3.0, 5.0), scale=1.5):
    window = dk.Window(jnp.asarray(origin, jnp.float32), jnp.float32(scale))
    empty = pb.BodyModel(*([None] * len(pb.BodyModel._fields)))
    return empty._replace(window=window, body=jnp.asarray(body), depth=jnp.asarray(depth))


def _reference(body, depth, xy, origin=(3.0, 5.0), scale=1.5):
    out = []
    rows, cols = np.nonzero(body)
    for x, y in np.asarray(xy, np.float64):
        j, i = (x - origin[0]) / scale, (y - origin[1]) / scale
        r, c = int(np.floor(i)), int(np.floor(j))
        if 0 <= r < SHAPE[0] and 0 <= c < SHAPE[1] and body[r, c]:
            out.append(depth[r, c])
        elif rows.size:
            k = np.argmin((rows - i) ** 2 + (cols - j) ** 2)  # first of ties, row-major
            out.append(depth[rows[k], cols[k]])
        else:
            out.append(0.0)
    return np.asarray(out, np.float32)


def _scene(seed: int):
    rng = np.random.default_rng(seed)
    body = np.zeros(SHAPE, bool)
    body[4:18, 3:12] = True
    body &= rng.random(SHAPE) > 0.2
    depth = rng.uniform(1500.0, 3000.0, SHAPE).astype(np.float32)
    return body, depth


def _positions(body, seed: int, on_body: bool):
    """Frame positions ``[6, 2]``: pixel centres on the body, or a mix with some off it
    (outside the window and on holes)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(body)
    pick = rng.choice(rows.size, 6, replace=False)
    ji = np.stack([cols[pick], rows[pick]], -1) + rng.uniform(0.1, 0.9, (6, 2))
    if not on_body:
        ji[0] = (-3.0, 2.5)  # left of the window
        holes = np.argwhere(~body[4:18, 3:12])[:2] + (4, 3)
        ji[1 : 1 + len(holes)] = holes[:, ::-1] + 0.5
        ji[5] = (30.0, 40.0)  # beyond the bottom-right corner
    return (ji * 1.5 + (3.0, 5.0)).astype(np.float32)


@pytest.mark.parametrize("on_body", [True, False])
def test_surface_depth_matches_a_loop_under_jit_and_vmap(on_body):
    scenes = [_scene(s) for s in (0, 1)]
    xys = [_positions(b, s + 7, on_body) for s, (b, _) in enumerate(scenes)]
    want = [_reference(b, d, xy) for (b, d), xy in zip(scenes, xys, strict=True)]
    one = jax.jit(lambda bm, xy: pb.surface_depth(CONFIG, bm, xy))
    for (b, d), xy, w in zip(scenes, xys, want, strict=True):
        np.testing.assert_array_equal(np.asarray(one(_body_model(b, d), jnp.asarray(xy))), w)
    both = jax.vmap(lambda body, depth, xy: pb.surface_depth(CONFIG, _body_model(body, depth), xy))
    got = jax.jit(both)(
        jnp.asarray(np.stack([b for b, _ in scenes])),
        jnp.asarray(np.stack([d for _, d in scenes])),
        jnp.asarray(np.stack(xys)),
    )
    np.testing.assert_array_equal(np.asarray(got), np.stack(want))


def test_surface_depth_is_zero_without_a_body():
    body, depth = np.zeros(SHAPE, bool), np.full(SHAPE, 2000.0, np.float32)
    xy = jnp.asarray([[10.0, 12.0], [-5.0, 3.0]])
    got = jax.jit(lambda bm, p: pb.surface_depth(CONFIG, bm, p))(_body_model(body, depth), xy)
    np.testing.assert_array_equal(np.asarray(got), [0.0, 0.0])
