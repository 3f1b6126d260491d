"""Depth-to-colour registration: NumPy z-buffer reference (jit, vmap), calibration JSON."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import shared_data

from cpf_jax.registration import (
    Calibration,
    CalibrationError,
    calibration_from_dict,
    calibration_to_dict,
    identity_calibration,
    load_calibration,
    register_depth,
    register_frame,
    save_calibration,
)
from cpf_jax.types import Frame, Intrinsics

ROOT = Path(__file__).resolve().parents[1]
IST_CALIB = ROOT / "experiments" / "calib" / "ist_piv.json"

HD, WD = 48, 64


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.array([rx, ry, rz], np.float64))
    return r


CALIB = Calibration(
    depth=Intrinsics(60.0, 61.0, 31.2, 23.7),
    colour=Intrinsics(55.0, 55.5, 33.0, 24.4),
    depth_size=(WD, HD),
    colour_size=(70, 52),
    rotation=tuple(map(tuple, _rotation(0.01, -0.02, 0.005))),
    translation_mm=(-26.0, 3.0, -1.0),
    offset_px=(2.0, -1.0),
)


def _reference(depth: np.ndarray, c: Calibration, splat: int = 1) -> np.ndarray:
    """Plain NumPy forward warp with a z-buffer (np.minimum.at), float64."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = depth.astype(np.float64) * c.depth_scale_mm
    x = z * (u - c.depth.cx) / c.depth.fx
    y = z * (v - c.depth.cy) / c.depth.fy
    pts = np.stack([x, y, z], -1) @ c.R.T + c.T
    ok = (z > 0) & (pts[..., 2] > 0)
    zc = np.where(ok, pts[..., 2], 1.0)
    uc = np.floor(c.colour.fx * pts[..., 0] / zc + c.colour.cx + c.offset_px[0] + 0.5).astype(int)
    vc = np.floor(c.colour.fy * pts[..., 1] / zc + c.colour.cy + c.offset_px[1] + 0.5).astype(int)
    wc, hc = c.colour_size
    out = np.full((hc, wc), np.inf)
    for dy in range(splat):
        for dx in range(splat):
            uu, vv = uc + dx, vc + dy
            inside = ok & (uu >= 0) & (uu < wc) & (vv >= 0) & (vv < hc)
            np.minimum.at(out, (vv[inside], uu[inside]), np.round(pts[..., 2][inside]))
    return np.where(np.isfinite(out), out, 0).astype(np.uint16)


def _depth(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(600, 5000, (HD, WD)).astype(np.uint16)
    d[rng.uniform(size=d.shape) < 0.2] = 0  # missing pixels
    d[10:30, 20:40] = 900  # a near object in front of the rest: the z-buffer matters
    return d


REG = jax.jit(register_depth, static_argnums=(1, 2))


@pytest.mark.parametrize("splat", [1, 2])
def test_register_matches_numpy_zbuffer(splat):
    d = _depth(0)
    got = np.asarray(REG(jnp.asarray(d), CALIB, splat))
    want = _reference(d, CALIB, splat)
    assert got.dtype == np.uint16 and got.shape == (52, 70)
    # float32 vs float64 projections may round a few samples to neighbouring pixels.
    assert (got == want).mean() > 0.995
    assert (got > 0).sum() == pytest.approx((want > 0).sum(), rel=0.01)


def test_register_under_vmap_equals_per_frame():
    batch = np.stack([_depth(s) for s in range(3)])
    out = jax.vmap(lambda d: register_depth(d, CALIB))(jnp.asarray(batch))
    for i in range(3):
        one = np.asarray(REG(batch[i], CALIB, 1)).astype(int)
        got = np.asarray(out[i]).astype(int)
        # Same pixels; depths equal up to float32 rounding of the last millimetre.
        assert ((got > 0) == (one > 0)).mean() > 0.999
        both = (got > 0) & (one > 0)
        assert np.abs(got[both] - one[both]).max() <= 1


def test_identity_calibration_is_identity():
    d = _depth(1)
    ident = identity_calibration(Intrinsics(60.0, 60.0, 31.5, 23.5), (WD, HD))
    np.testing.assert_array_equal(np.asarray(REG(jnp.asarray(d), ident, 1)), d)


def test_zbuffer_keeps_the_nearest_surface():
    # Colour camera with half the focal length: 2x2 depth pixels land on one colour pixel.
    c = Calibration(
        depth=Intrinsics(60.0, 60.0, 32.0, 24.0),
        colour=Intrinsics(30.0, 30.0, 16.0, 12.0),
        depth_size=(WD, HD),
        colour_size=(WD // 2, HD // 2),
    )
    d = np.full((HD, WD), 3000, np.uint16)
    d[::2, ::2] = 1000  # one sample of every 2x2 block is near
    out = np.asarray(REG(jnp.asarray(d), c, 1))
    inner = out[2:-2, 2:-2]
    assert (inner == 1000).all()


def test_offset_shifts_columns():
    d = _depth(2)
    base = Calibration(
        Intrinsics(60.0, 60.0, 32.0, 24.0), Intrinsics(60.0, 60.0, 32.0, 24.0), (WD, HD), (WD, HD)
    )
    shifted = dataclasses.replace(base, offset_px=(11.0, 0.0))
    a = np.asarray(REG(jnp.asarray(d), base, 1))
    b = np.asarray(REG(jnp.asarray(d), shifted, 1))
    np.testing.assert_array_equal(b[:, 11:], a[:, :-11])
    assert (b[:, :11] == 0).all()


def test_register_frame_checks_sizes():
    d = _depth(0)
    frame = Frame(np.zeros((52, 70, 3), np.uint8), d)
    out = register_frame(frame, CALIB)
    assert out.depth.shape == (52, 70)
    with pytest.raises(ValueError, match="calibration's depth size"):
        register_depth(jnp.zeros((10, 10), jnp.uint16), CALIB)
    with pytest.raises(ValueError, match="calibration's colour size"):
        register_frame(Frame(np.zeros((10, 10, 3), np.uint8), d), CALIB)


# -- calibration files -------------------------------------------------------------------


def test_json_round_trip(tmp_path):
    path = tmp_path / "calib.json"
    save_calibration(CALIB, path)
    assert load_calibration(path) == CALIB
    assert calibration_from_dict(calibration_to_dict(CALIB)) == CALIB


def test_ist_calibration_file():
    c = load_calibration(IST_CALIB)
    # SOURCE.md values, principal points moved to 0-based, T in mm, +11 px offset.
    assert c.depth.cx == pytest.approx(312.1240 - 1) and c.depth.cy == pytest.approx(242.5695 - 1)
    assert c.colour.cx == pytest.approx(309.5674 - 1) and c.colour.fx == pytest.approx(534.2856)
    assert c.translation_mm == pytest.approx((-26.30589, 0.28027, -0.77569))
    assert c.offset_px == (11.0, 0.0)
    assert c.depth_size == c.colour_size == (640, 480)
    # Folder sources read the colour intrinsics from this layout too.
    from cpf_jax.io.folders import intrinsics_from_calibration

    assert intrinsics_from_calibration(json.loads(IST_CALIB.read_text())) == c.colour


def _broken(tmp_path, mutate) -> Path:
    d = calibration_to_dict(CALIB)
    mutate(d)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d.pop("rotation"), "rotation"),
        (lambda d: d.__setitem__("rotation", [[1, 0], [0, 1]]), "rotation"),
        (lambda d: d.__setitem__("rotation", [[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "rotation"),
        (lambda d: d.__setitem__("translation_mm", [1, "a", 3]), "translation_mm"),
        (lambda d: d.__setitem__("translation_mm", [-0.026, 0, 0]), "translation_mm"),  # metres
        (lambda d: d["depth"]["intrinsics"].pop("fx"), "depth.intrinsics.fx"),
        (lambda d: d["colour"].__setitem__("size", [640]), "colour.size"),
        (lambda d: d.__setitem__("offset_px", [1, 2, 3]), "offset_px"),
        (lambda d: d.__setitem__("format", "other/2"), "format"),
        (lambda d: d.pop("depth"), "depth"),
    ],
)
def test_malformed_calibration_names_file_and_field(tmp_path, mutate, field):
    p = _broken(tmp_path, mutate)
    with pytest.raises(CalibrationError) as e:
        load_calibration(p)
    msg = str(e.value)
    assert str(p) in msg and f"'{field}'" in msg and "\n" not in msg


def test_unreadable_calibration(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(p)
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "missing.json")


# -- real recording ----------------------------------------------------------------------


@pytest.mark.shared_data
def test_ist_offset_aligns_depth_and_colour_edges():
    """With the +11 px offset, depth edges fall closer to colour edges than without it."""
    folder = shared_data("ist_piv_rgbd", "images1")
    from cpf_jax.io import open_source

    src = open_source(folder)
    c = load_calibration(IST_CALIB)
    plain = dataclasses.replace(c, offset_px=(0.0, 0.0))
    scores = {}
    for name, calib in (("offset", c), ("plain", plain)):
        hits = total = 0
        for i in (84, 85):
            f = src.read(i)
            d = np.asarray(REG(jnp.asarray(f.depth), calib, 1)).astype(np.float32)
            de = cv2.Canny(cv2.convertScaleAbs(d, alpha=255 / 8000.0), 30, 90) > 0
            gray = cv2.cvtColor(f.colour, cv2.COLOR_RGB2GRAY)
            ce = cv2.dilate(cv2.Canny(gray, 50, 150), np.ones((5, 5), np.uint8)) > 0
            hits += int((de & ce).sum())
            total += int(de.sum())
        scores[name] = hits / total
    assert scores["offset"] > scores["plain"]
