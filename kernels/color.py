"""Colour conversion: RGB -> HSV and hue-saturation bin indices.

Conventions:

* Input images are ``[..., 3] uint8`` in **RGB** order (``cpf_jax.types.Frame``).
* ``rgb_to_hsv_u8`` follows **OpenCV's uint8 convention** exactly
  (``cv2.cvtColor(img, cv2.COLOR_RGB2HSV)`` on ``uint8``): ``H`` in ``0..179``
  (degrees / 2), ``S`` and ``V`` in ``0..255``. It reproduces OpenCV's
  fixed-point arithmetic (``RGB2HSV_b``: 12-bit reciprocal tables rounded to
  nearest, results rounded half-up), so it is bit-exact on every one of the
  256^3 inputs, not merely close.
* ``hs_bin_index`` gives the flat bin ``h_bin * s_bins + s_bin`` of the 2-D
  histogram ``cv2.calcHist([hsv], [0, 1], None, [h_bins, s_bins], [0, 180, 0, 256])``
  (row-major, hue is the slow axis, as in the ``[h_bins, s_bins]`` array OpenCV
  returns). The uniform bin of value ``j`` in range ``[lo, hi)`` is
  ``floor(j * (bins / (hi - lo)))`` evaluated in float64 like OpenCV's
  ``calcHistLookupTables_8u``; this is ``floor(H * h_bins / 180)`` and
  ``floor(S * s_bins / 256)`` up to float64 rounding, which the look-up tables
  built here reproduce exactly (e.g. for ``h_bins = 26`` OpenCV puts ``H = 90``
  in bin 12, not 13, because ``90 * (26 / 180)`` is ``12.999...`` in float64).
* ``rgb_to_hsv_float`` is the smooth path (dm-pix): ``float32`` H, S, V in
  ``[0, 1]`` with finite gradients; it is not used for histograms.
"""

from __future__ import annotations

import dm_pix
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = [
    "rgb_to_hsv_u8",
    "hs_bin_index",
    "hsv_bin_index",
    "hs_bin_luts",
    "rgb_to_hsv_float",
    "grey",
    "ACHROMATIC_S_MIN",
    "ACHROMATIC_V_MIN",
]

# Perez et al. (ECCV 2002): pixels with S < 0.1 or V < 0.2 have no reliable hue.
ACHROMATIC_S_MIN = 26  # 0.1 * 255, rounded
ACHROMATIC_V_MIN = 51  # 0.2 * 255

_HSV_SHIFT = 12
_HALF = 1 << (_HSV_SHIFT - 1)


def grey(rgb: Array) -> Array:
    """``[..., H, W] float32`` luma of ``[..., H, W, 3]`` RGB, ITU-R BT.601 weights (as
    OpenCV's ``COLOR_RGB2GRAY``), in the input's range."""
    return jnp.asarray(rgb, jnp.float32) @ jnp.array([0.299, 0.587, 0.114], jnp.float32)


def _opencv_tables() -> tuple[np.ndarray, np.ndarray]:
    # OpenCV's RGB2HSV_b tables: saturate_cast<int> rounds to nearest; index 0 maps to 0.
    i = np.arange(256, dtype=np.float64)
    with np.errstate(divide="ignore"):
        sdiv = np.where(i > 0, np.rint((255 << _HSV_SHIFT) / i), 0)
        hdiv = np.where(i > 0, np.rint((180 << _HSV_SHIFT) / (6.0 * i)), 0)
    return sdiv.astype(np.int32), hdiv.astype(np.int32)


_SDIV, _HDIV180 = _opencv_tables()


def rgb_to_hsv_u8(rgb: Array) -> Array:
    """``[..., 3] uint8`` RGB -> ``[..., 3] uint8`` HSV, OpenCV convention (H 0..179, S, V 0..255).

    Bit-exact with ``cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)``.
    """
    h, s, v = _hsv_u8_channels(rgb)
    return jnp.stack([h, s, v], axis=-1).astype(jnp.uint8)


def _hsv_u8_channels(rgb: Array) -> tuple[Array, Array, Array]:
    """int32 H (0..179), S (0..255), V (0..255) planes of OpenCV's uint8 RGB -> HSV."""
    rgb = jnp.asarray(rgb).astype(jnp.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    v = jnp.maximum(jnp.maximum(r, g), b)
    diff = v - jnp.minimum(jnp.minimum(r, g), b)
    # OpenCV's reciprocal tables round((255 << 12) / v) and round((180 << 12) / (6 diff)),
    # computed arithmetically: float32 division then rounding reproduces every table
    # entry (checked once below, and exhaustively by the tests), and vectorises
    # where a table look-up (gather) does not.
    s = (diff * _reciprocal(v, 255 << _HSV_SHIFT) + _HALF) >> _HSV_SHIFT
    # Same branch order as OpenCV: red wins ties with green, green wins ties with blue.
    h = jnp.where(v == r, g - b, jnp.where(v == g, b - r + 2 * diff, r - g + 4 * diff))
    # Arithmetic right shift = floor division, as in C++ for negative h.
    h = (h * _reciprocal(diff, (180 << _HSV_SHIFT) // 6) + _HALF) >> _HSV_SHIFT
    h = jnp.where(h < 0, h + 180, h)
    return h, s, v


def _reciprocal(x: Array, numerator: int) -> Array:
    """``round(numerator / x)`` as int32 for ``x`` in 1..255, 0 for ``x == 0``."""
    pos = x > 0
    q = jnp.float32(numerator) / jnp.where(pos, x, 1).astype(jnp.float32)
    return jnp.where(pos, jnp.round(q).astype(jnp.int32), 0)


def _check_reciprocals() -> None:
    i = np.arange(1, 256, dtype=np.float32)
    for numerator, table in ((255 << _HSV_SHIFT, _SDIV), ((180 << _HSV_SHIFT) // 6, _HDIV180)):
        q = np.rint(np.float32(numerator) / i).astype(np.int32)
        assert (q == table[1:]).all(), "float32 reciprocal differs from OpenCV's table"


_check_reciprocals()


def hs_bin_luts(h_bins: int, s_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's uniform-bin look-up tables for H in ``[0, 180)`` and S in ``[0, 256)``.

    Returns ``(h_lut [180] int32, s_lut [256] int32)``; built with float64 like
    ``calcHistLookupTables_8u`` (bin = ``floor(j * (bins / range))``, clamped).
    """
    h_lut = np.floor(np.arange(180, dtype=np.float64) * (h_bins / 180.0))
    s_lut = np.floor(np.arange(256, dtype=np.float64) * (s_bins / 256.0))
    h_lut = np.clip(h_lut, 0, h_bins - 1).astype(np.int32)
    s_lut = np.clip(s_lut, 0, s_bins - 1).astype(np.int32)
    return h_lut, s_lut


def hs_bin_index(colour: Array, h_bins: int, s_bins: int) -> Array:
    """``colour [..., 3] uint8`` RGB -> ``[...] int32`` flat H-S bin in ``[0, h_bins * s_bins)``.

    ``bin = h_bin * s_bins + s_bin`` with OpenCV's uniform binning of
    ``calcHist(..., [h_bins, s_bins], [0, 180, 0, 256])`` on the uint8 HSV image.
    ``h_bins`` and ``s_bins`` are static.
    """
    h, s, _ = _hsv_u8_channels(colour)
    return _lut_or_formula(h, hs_bin_luts(h_bins, s_bins)[0], h_bins, 180) * s_bins + (
        _lut_or_formula(s, hs_bin_luts(h_bins, s_bins)[1], s_bins, 256)
    )


def hsv_bin_index(
    colour: Array,
    h_bins: int,
    s_bins: int,
    v_bins: int,
    s_min: int = ACHROMATIC_S_MIN,
    v_min: int = ACHROMATIC_V_MIN,
) -> Array:
    """H-S bins for chromatic pixels plus ``v_bins`` value bins for achromatic ones.

    The colour model of Perez et al. (ECCV 2002): a pixel with ``S >= s_min``
    and ``V >= v_min`` (uint8 OpenCV HSV) gets its H-S bin
    ``h_bin * s_bins + s_bin``; any other pixel (black, grey, white, whose hue
    is noise) gets ``h_bins * s_bins + floor(V * v_bins / 256)``. So dark hair,
    a black coat, a shadowed pavement and a white wall fall in different bins
    instead of random hue bins. Returns ``[...] int32`` in
    ``[0, h_bins * s_bins + v_bins)``; ``v_bins = 0`` is ``hs_bin_index``.
    """
    if v_bins == 0:
        return hs_bin_index(colour, h_bins, s_bins)
    h, s, v = _hsv_u8_channels(colour)
    luts = hs_bin_luts(h_bins, s_bins)
    hs = _lut_or_formula(h, luts[0], h_bins, 180) * s_bins + _lut_or_formula(
        s, luts[1], s_bins, 256
    )
    achromatic = (s < s_min) | (v < v_min)
    return jnp.where(achromatic, h_bins * s_bins + v * v_bins // 256, hs).astype(jnp.int32)


def _lut_or_formula(x: Array, lut: np.ndarray, bins: int, span: int) -> Array:
    """``lut[x]``, computed as ``x * bins // span`` when that equals OpenCV's table.

    The integer formula (a multiply and a shift or constant division) is much
    cheaper than a gather; for bin counts where float64 rounding makes OpenCV's
    table differ from it (e.g. 26 hue bins), the table is used.
    """
    if (np.arange(len(lut)) * bins // span == lut).all():
        return x * bins // span
    return jnp.asarray(lut)[x]


def rgb_to_hsv_float(colour: Array) -> Array:
    """``[..., 3]`` RGB (uint8, or float in ``[0, 1]``) -> ``[..., 3] float32`` HSV in ``[0, 1]``.

    Smooth path through ``dm_pix.rgb_to_hsv`` (hue = OpenCV float hue / 360 to
    about 3e-5); gradients are finite. Not bit-compatible with the uint8 path.
    """
    colour = jnp.asarray(colour)
    if colour.dtype == jnp.uint8:
        colour = colour.astype(jnp.float32) / 255.0
    return dm_pix.rgb_to_hsv(colour.astype(jnp.float32))
