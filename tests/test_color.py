"""cpf_jax.kernels.color against OpenCV: exact uint8 HSV, exact calcHist binning."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.kernels import color

BIN_SETTINGS = [(8, 8), (16, 16), (26, 8), (30, 32)]

_hsv_u8 = jax.jit(color.rgb_to_hsv_u8)
_bin_index = jax.jit(color.hs_bin_index, static_argnums=(1, 2))


@pytest.fixture(scope="module")
def all_colours() -> np.ndarray:
    """Every 24-bit RGB colour once, as a 4096 x 4096 image."""
    a = np.arange(256**3, dtype=np.uint32)
    rgb = np.stack([(a >> 16) & 255, (a >> 8) & 255, a & 255], axis=-1).astype(np.uint8)
    return rgb.reshape(4096, 4096, 3)


@pytest.fixture(scope="module")
def textured() -> np.ndarray:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    # Smooth patches too, so that grey (S = 0) and saturated pixels both occur.
    img[:20, :30] = 128
    img[20:40, 40:] = (255, 0, 0)
    return img


def test_rgb_to_hsv_u8_matches_opencv_on_all_colours(all_colours):
    ref = cv2.cvtColor(all_colours, cv2.COLOR_RGB2HSV)
    out = np.asarray(_hsv_u8(all_colours))
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, ref)
    assert out[..., 0].max() == 179


def _opencv_bin_luts(h_bins: int, s_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Bin of every H and S value as cv2.calcHist assigns it (one tiny calcHist per value)."""
    h_lut = np.empty(180, np.int64)
    for h in range(180):
        img = np.zeros((1, 1, 3), np.uint8)
        img[..., 0] = h
        hist = cv2.calcHist([img], [0, 1], None, [h_bins, s_bins], [0, 180, 0, 256])
        h_lut[h] = np.argwhere(hist)[0, 0]
    s_lut = np.empty(256, np.int64)
    for s in range(256):
        img = np.zeros((1, 1, 3), np.uint8)
        img[..., 1] = s
        hist = cv2.calcHist([img], [0, 1], None, [h_bins, s_bins], [0, 180, 0, 256])
        s_lut[s] = np.argwhere(hist)[0, 1]
    return h_lut, s_lut


@pytest.mark.parametrize("h_bins,s_bins", BIN_SETTINGS)
def test_hs_bin_index_matches_calchist_per_pixel(all_colours, h_bins, s_bins):
    # A 1/16 sample of all colours (every H and S value occurs), checked pixel by pixel.
    img = all_colours[::4, ::4]
    hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
    h_lut, s_lut = _opencv_bin_luts(h_bins, s_bins)
    ref = h_lut[hsv[..., 0]] * s_bins + s_lut[hsv[..., 1]]
    out = np.asarray(_bin_index(img, h_bins, s_bins))
    assert out.dtype == np.int32
    np.testing.assert_array_equal(out, ref)
    # And as a histogram: bincount of the indices is cv2.calcHist of the image.
    hist = cv2.calcHist([hsv], [0, 1], None, [h_bins, s_bins], [0, 180, 0, 256]).ravel()
    np.testing.assert_array_equal(np.bincount(out.ravel(), minlength=h_bins * s_bins), hist)


def test_float_lut_differs_from_integer_formula_where_opencv_does():
    # OpenCV bins in float64: H=90 with 26 hue bins lands in bin 12, not floor(90*26/180)=13.
    h_lut, _ = color.hs_bin_luts(26, 8)
    assert h_lut[90] == 12
    assert h_lut[90] == _opencv_bin_luts(26, 8)[0][90]


def test_hs_bin_index_under_vmap(textured):
    frames = np.stack([textured, textured[::-1], 255 - textured])
    batched = np.asarray(jax.vmap(lambda f: color.hs_bin_index(f, 8, 8))(frames))
    for frame, out in zip(frames, batched, strict=True):
        np.testing.assert_array_equal(out, np.asarray(_bin_index(frame, 8, 8)))


def test_rgb_to_hsv_float_close_to_opencv_and_differentiable(textured):
    ref = cv2.cvtColor(textured.astype(np.float32) / 255.0, cv2.COLOR_RGB2HSV)
    ref = ref / np.array([360.0, 1.0, 1.0], np.float32)
    out = np.asarray(jax.jit(color.rgb_to_hsv_float)(textured))
    # Hue wraps at 1: compare on the circle.
    dh = np.abs(out[..., 0] - ref[..., 0])
    np.testing.assert_array_less(np.minimum(dh, 1 - dh), 1e-4)
    np.testing.assert_allclose(out[..., 1:], ref[..., 1:], atol=1e-5)
    grad = jax.grad(lambda x: color.rgb_to_hsv_float(x).sum())(
        jnp.asarray(textured, jnp.float32) / 255.0
    )
    assert np.isfinite(np.asarray(grad)).all()


def test_hsv_bin_index_matches_opencv_reference_jit_and_vmap():
    """Chromatic pixels get OpenCV's H-S bin; achromatic ones (S < 26 or V < 51) a value bin."""
    import cv2

    from cpf_jax.kernels.color import hsv_bin_index

    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (2, 48, 64, 3), dtype=np.uint8)
    img[:, :8] = rng.integers(0, 40, (2, 8, 64, 3))  # dark pixels
    img[:, 8:16] = rng.integers(120, 140, (2, 8, 64, 1))  # greys
    ref = []
    for frame in img:
        hsv = cv2.cvtColor(frame, cv2.COLOR_RGB2HSV).astype(np.int64)
        h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
        hs = (h * 8 // 180) * 8 + s * 8 // 256
        ref.append(np.where((s < 26) | (v < 51), 64 + v * 8 // 256, hs))
    ref = np.stack(ref)
    assert (ref >= 64).any() and (ref < 64).any()
    out = jax.jit(jax.vmap(lambda f: hsv_bin_index(f, 8, 8, 8)))(jnp.asarray(img))
    np.testing.assert_array_equal(np.asarray(out), ref)
    # v_bins = 0 is the plain H-S index
    np.testing.assert_array_equal(
        np.asarray(hsv_bin_index(img[0], 8, 8, 0)), np.asarray(color.hs_bin_index(img[0], 8, 8))
    )
