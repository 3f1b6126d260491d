"""Box geometry against plain NumPy references, under jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax.kernels import boxes as B


def _np_iou(a, b):
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def _random_boxes(n, seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50, 300, (n, 2))
    wh = rng.uniform(0, 120, (n, 2))
    return np.concatenate([xy, wh], 1).astype(np.float32)


def test_iou_matches_numpy_and_transforms():
    a, b = _random_boxes(500, 0), _random_boxes(500, 1)
    b[:50] = a[:50]  # identical pairs
    ref = np.array([_np_iou(x, y) for x, y in zip(a, b, strict=True)])
    for f in (B.iou, jax.jit(B.iou), jax.vmap(B.iou)):
        np.testing.assert_allclose(np.asarray(f(a, b)), ref, atol=1e-5)
    same = np.asarray(B.iou(a[:50], b[:50]))
    np.testing.assert_allclose(same[a[:50, 2] * a[:50, 3] > 0], 1.0, atol=1e-5)


def test_iou_empty_boxes_are_zero_not_nan():
    z = jnp.zeros((3, 4))
    out = B.iou(z, z)
    assert np.all(np.asarray(out) == 0)
    assert not np.isnan(np.asarray(B.iou(z, jnp.array([1.0, 1, 5, 5])))).any()


def test_conversions_roundtrip_and_broadcast():
    a = _random_boxes(100, 2)
    c = B.xywh_to_cxcywh(a)
    np.testing.assert_allclose(np.asarray(c[:, :2]), a[:, :2] + a[:, 2:] / 2, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(B.cxcywh_to_xywh(c)), a, atol=1e-4)
    batched = jax.vmap(B.xywh_to_cxcywh)(a.reshape(10, 10, 4))
    np.testing.assert_allclose(np.asarray(batched).reshape(100, 4), np.asarray(c), atol=1e-5)


def test_rect_rounding_and_clipping():
    boxes = jnp.array(
        [
            [10.0, 20.0, 30.0, 40.0],
            [10.4, 20.5, 30.2, 39.4],
            [-5.0, -5.0, 10.0, 10.0],
            [500.0, 10.0, 20.0, 20.0],
        ]
    )
    rects = B.xywh_to_rect(boxes)
    np.testing.assert_array_equal(np.asarray(rects[:2]), [[10, 20, 40, 60], [10, 21, 41, 60]])
    clipped = np.asarray(B.clip_rect(rects, 320, 240))
    np.testing.assert_array_equal(clipped[2], [0, 0, 5, 5])
    assert clipped[3][0] == clipped[3][2] == 320  # fully outside: empty
    cb = np.asarray(B.clip_xywh(boxes, 320.0, 240.0))
    np.testing.assert_allclose(cb[2], [0, 0, 5, 5])
    assert cb[3][2] == 0


def test_centre_distance():
    a = jnp.array([0.0, 0, 10, 10])
    b = jnp.array([3.0, 4, 10, 10])
    assert float(B.centre_distance(a, b)) == 5.0
