"""The correlation filter (kernels.correlation) against NumPy references, and what it is
for: the response to a shifted patch peaks at the shift."""

from __future__ import annotations

import colorsys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import correlation as cf
from cpf_jax.synthetic import make_sequence
from tests.checks import check_kernel


def _sample_ref(image, centre, size, pixels):
    img = np.asarray(image, np.float64)
    h, w = img.shape[:2]
    t = (np.arange(pixels) + 0.5) / pixels - 0.5
    out = np.zeros((pixels, pixels, img.shape[2]))
    for i, y in enumerate(centre[1] + t * size[1]):
        for j, x in enumerate(centre[0] + t * size[0]):
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0
            acc = 0.0
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    yy, xx = min(max(y0 + dy, 0), h - 1), min(max(x0 + dx, 0), w - 1)
                    acc = acc + wy * wx * img[yy, xx]
            out[i, j] = acc
    return out


def _features_ref(patch, cell):
    p = np.asarray(patch, np.float64)
    luma = (p @ np.array([0.299, 0.587, 0.114])) / 255.0
    pad = np.pad(luma, 1, mode="edge")
    gx = 0.5 * (pad[1:-1, 2:] - pad[1:-1, :-2])
    gy = 0.5 * (pad[2:, 1:-1] - pad[:-2, 1:-1])
    mag = np.hypot(gx, gy)
    ang = np.mod(np.arctan2(gy, gx), np.pi) * 9 / np.pi
    n = p.shape[0] // cell
    hog = np.zeros((n, n, 9))
    colour = np.zeros((n, n, 3))
    for r in range(p.shape[0]):
        for c in range(p.shape[1]):
            lo = int(np.floor(ang[r, c]))
            frac = ang[r, c] - lo
            hog[r // cell, c // cell, lo % 9] += mag[r, c] * (1 - frac)
            hog[r // cell, c // cell, (lo + 1) % 9] += mag[r, c] * frac
            h, s, _ = colorsys.rgb_to_hsv(*(np.clip(p[r, c], 0, 255) / 255.0))
            v = (luma[r, c] - 0.5, s * np.cos(2 * np.pi * h), s * np.sin(2 * np.pi * h))
            colour[r // cell, c // cell] += np.array(v) / cell**2
    energy = np.sqrt((hog**2).sum(-1, keepdims=True) + 1e-4)
    return np.concatenate([hog / energy, colour], axis=-1)


def _window_ref(n):
    w = 0.5 - 0.5 * np.cos(2 * np.pi * (np.arange(n) + 0.5) / n)
    return np.outer(w, w)


def _label_ref(n, sigma):
    d = np.arange(n)
    d = np.minimum(d, n - d)
    return np.fft.rfft2(np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma**2)))


def _fit_ref(feats, label):
    x = np.fft.rfft2(np.moveaxis(np.asarray(feats, np.float64), -1, 0) * _window_ref(len(feats)))
    return np.conj(label)[None] * x, np.sum(np.abs(x) ** 2, axis=0)


def _response_ref(num, den, feats, lam):
    n = len(feats)
    z = np.fft.rfft2(np.moveaxis(np.asarray(feats, np.float64), -1, 0) * _window_ref(n))
    r = np.fft.irfft2(np.sum(np.conj(num) * z, axis=0) / (den + lam), s=(n, n))
    return np.roll(r, (n // 2, n // 2), axis=(0, 1))


@pytest.fixture(scope="module")
def frame():
    seq = make_sequence("walk_across_medium", seed=2, n_frames=1)
    return seq.colour[0], seq.boxes[0]


def test_sample_patch_matches_bilinear_sampling(frame):
    image, box = frame
    centre = np.array([box[0] + box[2] / 2 + 0.3, box[1] + box[3] / 2 - 0.7], np.float32)
    other = np.array([5.0, 410.0], np.float32)  # off the frame's corner: repeats its border
    size = np.array([2.5 * box[2], 2.5 * box[3]], np.float32)
    check_kernel(
        lambda im, c, s: cf.sample_patch(im, c, s, 24),
        lambda im, c, s: _sample_ref(im, c, s, 24),
        (image, centre, size),
        batch=[(image, centre, size), (image, other, size)],
        rtol=1e-4,
        atol=1e-3,
    )


def test_features_match_their_definition(frame):
    image, box = frame
    patch = np.asarray(cf.sample_patch(image, box[:2] + box[2:] / 2, 2.0 * box[2:], 32))
    flat = np.full_like(patch, 128.0)  # no gradient: HOG channels 0
    check_kernel(
        lambda p: cf.features(p, 4),
        lambda p: _features_ref(p, 4),
        (patch,),
        batch=[(patch,), (flat,)],
        rtol=1e-3,
        atol=2e-4,
    )


def test_fit_and_response_match_the_fourier_ridge_regression(frame):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(16, 16, 5)).astype(np.float32)
    b = rng.normal(size=(16, 16, 5)).astype(np.float32)
    label = cf.label_spectrum(16, 1.5)
    np.testing.assert_allclose(np.asarray(label), _label_ref(16, 1.5), atol=1e-4)

    def kernel(x, z):
        return cf.response(cf.fit(x, label), z, 0.01)

    def reference(x, z):
        num, den = _fit_ref(x, _label_ref(16, 1.5))
        return _response_ref(num, den, z, 0.01)

    check_kernel(kernel, reference, (a, b), batch=[(a, b), (b, a)], rtol=1e-3, atol=1e-4)


def test_blend_is_the_running_average():
    rng = np.random.default_rng(1)
    f1 = cf.fit(rng.normal(size=(8, 8, 3)).astype(np.float32), cf.label_spectrum(8, 1.0))
    f2 = cf.fit(rng.normal(size=(8, 8, 3)).astype(np.float32), cf.label_spectrum(8, 1.0))
    out = jax.jit(cf.blend)(f1, f2, jnp.float32(0.25))
    np.testing.assert_allclose(out.numerator, 0.75 * f1.numerator + 0.25 * f2.numerator, atol=1e-5)
    np.testing.assert_allclose(
        out.denominator, 0.75 * f1.denominator + 0.25 * f2.denominator, rtol=1e-6
    )


def test_read_response_is_bilinear_and_floors_outside():
    resp = np.arange(36, dtype=np.float32).reshape(6, 6) ** 1.5
    disp = np.array([[0.0, 0.0], [1.25, -0.5], [-3.0, -3.0], [2.0, 2.0], [2.5, 0.0], [0, -3.2]])

    def reference(r, d):
        out = []
        for dx, dy in d:
            x, y = dx + 3, dy + 3
            if not (0 <= x <= 5 and 0 <= y <= 5):
                out.append(r.min())
                continue
            x0, y0 = min(int(np.floor(x)), 4), min(int(np.floor(y)), 4)
            fx, fy = x - x0, y - y0
            out.append(
                (1 - fy) * ((1 - fx) * r[y0, x0] + fx * r[y0, x0 + 1])
                + fy * ((1 - fx) * r[y0 + 1, x0] + fx * r[y0 + 1, x0 + 1])
            )
        return np.array(out, np.float32)

    check_kernel(cf.read_response, reference, (resp, disp.astype(np.float32)), rtol=1e-5)


def test_the_response_peaks_where_the_target_moved(frame):
    """Trained on the walker, the filter finds him shifted by (5, -3) cells in a patch
    that was not centred on him, and scores the untrained background low."""
    image, box = frame
    cell, n = 4, 32
    size = 2.5 * box[2:]
    centre = box[:2] + box[2:] / 2
    step = size / n  # pixels per cell
    label = cf.label_spectrum(n, 0.1 * n / 2.5)

    @jax.jit
    def run(image, centre, offset):
        feats = cf.features(cf.sample_patch(image, centre, size, n * cell), cell)
        filt = cf.fit(feats, label)
        moved = cf.features(cf.sample_patch(image, centre - offset * step, size, n * cell), cell)
        return cf.response(filt, moved, 1e-2)

    resp = np.asarray(run(image, centre, jnp.array([5.0, -3.0])))
    peak = np.unravel_index(np.argmax(resp), resp.shape)
    assert (peak[1] - n // 2, peak[0] - n // 2) == (5, -3)
    assert resp.max() > 0.5 and np.median(resp) < 0.2 * resp.max()
