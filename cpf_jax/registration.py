"""Depth-to-colour registration: two pinholes, a rigid transform, a z-buffer (SPEC C4, P 2.3).

A depth camera and a colour camera a few centimetres apart see the scene from
slightly different places, so depth pixel ``(u, v)`` is not colour pixel
``(u, v)``. :func:`register_depth` maps every depth pixel into the colour image:

1. back-project with the depth pinhole (0-based pixels, pixel centres at
   integers, ``cpf_jax.types.Intrinsics``)::

       X_d = z (u - cx_d) / fx_d,  Y_d = z (v - cy_d) / fy_d,  Z_d = z

2. move into the colour camera: ``X_c = R X_d + T`` (``T`` in millimetres);
3. project with the colour pinhole and add a constant pixel ``offset``::

       u' = fx_c X_c / Z_c + cx_c + du,  v' = fy_c Y_c / Z_c + cy_c + dv

4. round to the nearest colour pixel and keep, per colour pixel, the
   **nearest** depth that lands on it (z-buffer: a surface hidden from the
   colour camera by a nearer one is not seen). Colour pixels that no depth
   pixel reaches stay 0 (missing), as do out-of-range depths.

The result is ``Z_c`` (depth along the colour camera's axis) in millimetres as
``uint16``: a registered :class:`cpf_jax.types.Frame` in the colour camera's
geometry. Everything is one jittable scatter-min with static shapes.

Calibration file (JSON, :func:`load_calibration` / :func:`save_calibration`)::

    {
      "format": "cpf_jax.calibration/1",
      "depth":  {"intrinsics": {"fx": .., "fy": .., "cx": .., "cy": ..}, "size": [W, H]},
      "colour": {"intrinsics": {"fx": .., "fy": .., "cx": .., "cy": ..}, "size": [W, H]},
      "rotation": [[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]],
      "translation_mm": [tx, ty, tz],
      "offset_px": [du, dv],          # optional, default [0, 0]
      "depth_scale_mm": 1.0,          # optional: millimetres per raw depth unit
      "note": "..."                   # optional, free text
    }

Intrinsics are **0-based** (a MATLAB calibration's ``cx``, ``cy`` minus 1).
``rotation`` / ``translation_mm`` map depth-camera coordinates to
colour-camera coordinates. The colour block has the layout
``cpf_jax.io.folders.intrinsics_from_calibration`` reads, so a recording
folder's ``calibration.json`` in this format also gives the source its colour
intrinsics. A malformed file raises :class:`CalibrationError` with one line
naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.errors import CpfJaxError
from cpf_jax.kernels import alignment
from cpf_jax.types import Frame, Intrinsics

__all__ = [
    "CALIBRATION_FORMAT",
    "Calibration",
    "CalibrationError",
    "calibration_from_dict",
    "calibration_to_dict",
    "load_calibration",
    "save_calibration",
    "register_depth",
    "register_frame",
    "identity_calibration",
    "Alignment",
    "check_alignment",
]

CALIBRATION_FORMAT = "cpf_jax.calibration/1"
_ZMAX = 65535.0  # uint16 ceiling (mm) and the z-buffer's "empty" value


class CalibrationError(CpfJaxError):
    """A calibration file or dict that cannot be used (one line: file and field)."""


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Two pinholes and the rigid transform between them (hashable: a static jit argument).

    ``rotation`` (row-major 3x3) and ``translation_mm`` map depth-camera points to
    colour-camera points. ``offset_px = (du, dv)`` is added after projection
    (an empirical correction, e.g. the +11 px of the IST recordings).
    ``depth_size`` / ``colour_size`` are ``(W, H)``.
    """

    depth: Intrinsics
    colour: Intrinsics
    depth_size: tuple[int, int]
    colour_size: tuple[int, int]
    rotation: tuple[tuple[float, float, float], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_px: tuple[float, float] = (0.0, 0.0)
    depth_scale_mm: float = 1.0
    note: str = ""

    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.rotation, np.float64)

    @property
    def T(self) -> np.ndarray:
        return np.asarray(self.translation_mm, np.float64)


def identity_calibration(intrinsics: Intrinsics, size: tuple[int, int]) -> Calibration:
    """The calibration of an already registered stream (same pinhole, no motion)."""
    return Calibration(intrinsics, intrinsics, tuple(size), tuple(size))


# ----------------------------------------------------------------------------- JSON


def _where(source: str | None) -> str:
    return f"{source}: " if source else "calibration: "


def _numbers(value: Any, shape: tuple[int, ...], field: str, source: str | None) -> np.ndarray:
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)):
        want = "x".join(str(s) for s in shape)
        raise CalibrationError(
            f"{_where(source)}field '{field}' must be {want} finite numbers, got {value!r}"
        )
    return arr


def _camera(d: dict[str, Any], name: str, source: str | None) -> tuple[Intrinsics, tuple[int, int]]:
    node = d.get(name)
    if node is None and name == "colour":
        node = d.get("color", d.get("rgb"))
    if not isinstance(node, dict):
        raise CalibrationError(
            f"{_where(source)}missing field '{name}' (an object with intrinsics)"
        )
    intr = node.get("intrinsics")
    if isinstance(intr, dict):
        vals = []
        for k in ("fx", "fy", "cx", "cy"):
            if k not in intr:
                raise CalibrationError(f"{_where(source)}missing field '{name}.intrinsics.{k}'")
            vals.append(_numbers(intr[k], (), f"{name}.intrinsics.{k}", source))
        fx, fy, cx, cy = (float(v) for v in vals)
    elif "K" in node:
        k = _numbers(node["K"], (3, 3), f"{name}.K", source)
        fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    else:
        raise CalibrationError(f"{_where(source)}missing field '{name}.intrinsics'")
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"{_where(source)}field '{name}.intrinsics' needs fx, fy > 0")
    if "size" not in node:
        raise CalibrationError(f"{_where(source)}missing field '{name}.size' ([width, height])")
    size = _numbers(node["size"], (2,), f"{name}.size", source)
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise CalibrationError(
            f"{_where(source)}field '{name}.size' must be two positive integers, "
            f"got {node['size']!r}"
        )
    return Intrinsics(fx, fy, cx, cy), (int(size[0]), int(size[1]))


# Two cameras' centres lie at least this far apart; a shorter non-zero baseline is a
# translation in metres (a Kinect's 25 mm read as 0.025).
MIN_BASELINE_MM = 1.0


def calibration_from_dict(d: Any, source: str | None = None) -> Calibration:
    """Parse the JSON layout of the module docstring; ``source`` names the file in errors."""
    if not isinstance(d, dict):
        raise CalibrationError(f"{_where(source)}expected a JSON object at the top level")
    fmt = d.get("format", CALIBRATION_FORMAT)
    if fmt != CALIBRATION_FORMAT:
        raise CalibrationError(
            f"{_where(source)}field 'format' is {fmt!r}, expected {CALIBRATION_FORMAT!r}"
        )
    depth, depth_size = _camera(d, "depth", source)
    colour, colour_size = _camera(d, "colour", source)
    if "rotation" not in d:
        raise CalibrationError(f"{_where(source)}missing field 'rotation' (3x3)")
    r = _numbers(d["rotation"], (3, 3), "rotation", source)
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) <= 0:
        raise CalibrationError(f"{_where(source)}field 'rotation' is not a rotation matrix")
    if "translation_mm" not in d:
        raise CalibrationError(f"{_where(source)}missing field 'translation_mm' (3 numbers, mm)")
    t = _numbers(d["translation_mm"], (3,), "translation_mm", source)
    if 0 < np.linalg.norm(t) < MIN_BASELINE_MM:
        raise CalibrationError(
            f"{_where(source)}field 'translation_mm' is {np.linalg.norm(t):.3g} mm long, "
            f"nearer than two cameras sit ({MIN_BASELINE_MM:g} mm): metres? Give millimetres"
        )
    off = _numbers(d.get("offset_px", [0.0, 0.0]), (2,), "offset_px", source)
    scale = float(_numbers(d.get("depth_scale_mm", 1.0), (), "depth_scale_mm", source))
    if not scale > 0:
        raise CalibrationError(f"{_where(source)}field 'depth_scale_mm' must be > 0")
    note = d.get("note", "")
    return Calibration(
        depth=depth,
        colour=colour,
        depth_size=depth_size,
        colour_size=colour_size,
        rotation=tuple(tuple(float(x) for x in row) for row in r),
        translation_mm=tuple(float(x) for x in t),
        offset_px=(float(off[0]), float(off[1])),
        depth_scale_mm=scale,
        note=str(note),
    )


def calibration_to_dict(calib: Calibration) -> dict[str, Any]:
    """The JSON layout of the module docstring (inverse of :func:`calibration_from_dict`)."""

    def cam(intr: Intrinsics, size: tuple[int, int]) -> dict[str, Any]:
        return {"intrinsics": dict(intr._asdict()), "size": list(size)}

    out: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "depth": cam(calib.depth, calib.depth_size),
        "colour": cam(calib.colour, calib.colour_size),
        "rotation": [list(row) for row in calib.rotation],
        "translation_mm": list(calib.translation_mm),
        "offset_px": list(calib.offset_px),
        "depth_scale_mm": calib.depth_scale_mm,
    }
    if calib.note:
        out["note"] = calib.note
    return out


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration JSON file; errors name the file and the field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read calibration ({e.strerror or e})") from None
    try:
        data = json.loads(text)
    except ValueError as e:
        raise CalibrationError(f"{path}: not valid JSON ({e})") from None
    return calibration_from_dict(data, source=str(path))


def save_calibration(calib: Calibration, path: str | os.PathLike) -> None:
    """Write ``calib`` as JSON (round-trips through :func:`load_calibration`)."""
    Path(path).write_text(json.dumps(calibration_to_dict(calib), indent=2) + "\n", encoding="utf-8")


# ----------------------------------------------------------------------------- registration


def register_depth(depth: Array, calib: Calibration, splat: int = 1) -> Array:
    """``[Hd, Wd] uint16`` raw depth -> ``[Hc, Wc] uint16`` mm depth in the colour camera.

    ``calib`` and ``splat`` are static (hashable). ``splat = s`` writes each
    depth sample into an ``s x s`` block of colour pixels (its rounded pixel
    and the ones right of and below it) to close one-pixel cracks when the
    colour image samples the scene more densely than the depth image; the
    z-buffer still keeps the nearest surface per pixel. 0 = missing, in and out.
    """
    if splat < 1:
        raise ValueError(f"splat must be >= 1, got {splat}")
    depth = jnp.asarray(depth)
    hd, wd = depth.shape
    if (wd, hd) != tuple(calib.depth_size):
        raise ValueError(
            f"depth image is {wd}x{hd} but the calibration's depth size is "
            f"{calib.depth_size[0]}x{calib.depth_size[1]}"
        )
    wc, hc = calib.colour_size
    d, c = calib.depth, calib.colour
    r = jnp.asarray(calib.R, jnp.float32)
    t = jnp.asarray(calib.T, jnp.float32)
    z = depth.astype(jnp.float32) * jnp.float32(calib.depth_scale_mm)
    v, u = jnp.meshgrid(
        jnp.arange(hd, dtype=jnp.float32), jnp.arange(wd, dtype=jnp.float32), indexing="ij"
    )
    x = z * (u - d.cx) / d.fx
    y = z * (v - d.cy) / d.fy
    xc = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
    yc = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
    zc = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
    ok = (z > 0) & (zc > 0)
    safe = jnp.where(ok, zc, 1.0)
    uc = jnp.floor(c.fx * xc / safe + c.cx + calib.offset_px[0] + 0.5).astype(jnp.int32)
    vc = jnp.floor(c.fy * yc / safe + c.cy + calib.offset_px[1] + 0.5).astype(jnp.int32)
    zval = jnp.where(ok, jnp.minimum(jnp.round(zc), _ZMAX - 1), _ZMAX)
    out = jnp.full((hc * wc,), _ZMAX, jnp.float32)
    for dy in range(splat):
        for dx in range(splat):
            uu, vv = uc + dx, vc + dy
            inside = ok & (uu >= 0) & (uu < wc) & (vv >= 0) & (vv < hc)
            # Out-of-image and invalid samples get an index past the end: dropped.
            flat = jnp.where(inside, vv * wc + uu, hc * wc)
            out = out.at[flat.reshape(-1)].min(zval.reshape(-1), mode="drop")
    out = jnp.where(out >= _ZMAX, 0.0, out)
    return out.reshape(hc, wc).astype(jnp.uint16)


def register_frame(frame: Frame, calib: Calibration, splat: int = 1) -> Frame:
    """The frame with its depth registered to its colour image (:func:`register_depth`)."""
    hc, wc = frame.colour.shape[:2]
    if (wc, hc) != tuple(calib.colour_size):
        raise ValueError(
            f"colour image is {wc}x{hc} but the calibration's colour size is "
            f"{calib.colour_size[0]}x{calib.colour_size[1]}"
        )
    return Frame(frame.colour, register_depth(frame.depth, calib, splat))


class Alignment(NamedTuple):
    """How well registered depth lines up with its colour (:func:`check_alignment`)."""

    shift: tuple[int, int]  # (dx, dy) px: colour edges lie this far from the depth edges
    score: float  # mean colour edge under the depth edges moved by ``shift``, in [0, 1]
    score_at_zero: float  # the same without a shift
    edge_pixels: int  # depth edge pixels the scores rest on
    score_mirrored: float  # the best score of the depth flipped left-right

    @property
    def mirrored(self) -> bool:
        """Depth that lines up far better flipped left-right (a driver that mirrors one
        stream): 15 % above the best unflipped score, on enough edge pixels."""
        return (
            self.edge_pixels >= MIN_EDGE_PIXELS
            and self.score_mirrored > ALIGNMENT_MARGIN * self.score
        )

    @property
    def misaligned(self) -> bool:
        """A clear best shift other than none: 15 % above the unshifted score, on at least
        ``MIN_EDGE_PIXELS`` depth edge pixels."""
        return (
            self.shift != (0, 0)
            and self.edge_pixels >= MIN_EDGE_PIXELS
            and self.score > ALIGNMENT_MARGIN * self.score_at_zero
        )

    def describe(self) -> str:
        dx, dy = self.shift
        parts = [f"{abs(dx)} px {'left of' if dx > 0 else 'right of'}"] if dx else []
        parts += [f"{abs(dy)} px {'above' if dy > 0 else 'below'}"] if dy else []
        where = " and ".join(parts) or "on"
        return (
            f"depth edges lie {where} the colour edges (best of shifts up to the "
            f"search's bound: score {self.score:.2f} against {self.score_at_zero:.2f} "
            "unshifted)"
        )


# Alignment.misaligned's evidence: depth edge pixels, and the best shift's margin.
MIN_EDGE_PIXELS = 200
ALIGNMENT_MARGIN = 1.15


@functools.partial(jax.jit, static_argnums=2)
def _summed_scores(colour: Array, depth: Array, max_shift: int) -> tuple[Array, Array]:
    """Per-frame shift scores summed with each frame's depth edge pixels as its weight."""
    edges = jax.vmap(alignment.depth_edges)(depth)  # once: the scores and their weights
    colour_edges = jax.vmap(alignment.colour_edges)(colour)
    scores = jax.vmap(alignment.shift_scores, in_axes=(0, 0, None))(colour_edges, edges, max_shift)
    weights = jnp.sum(edges, axis=(1, 2))
    total = jnp.sum(scores * weights[:, None, None], 0) / jnp.maximum(jnp.sum(weights), 1.0)
    return total, jnp.sum(weights)


def check_alignment(colour: Array, depth: Array, max_shift: int | None = None) -> Alignment:
    """The shift between depth edges and colour edges over ``K`` frames (``colour [K, H, W,
    3] uint8``, registered ``depth [K, H, W]`` mm): ``kernels.alignment``'s scores, summed
    over the frames by their depth edge pixels, searched up to ``max_shift`` px (default
    a 32nd of the width, at least 8), and the same for the depth flipped left-right.
    Registered depth shows ``shift == (0, 0)``."""
    colour, depth = np.asarray(colour), np.asarray(depth)
    if colour.ndim == 3:
        colour, depth = colour[None], depth[None]
    s = max(8, colour.shape[2] // 32) if max_shift is None else int(max_shift)
    total, n = _summed_scores(jnp.asarray(colour), jnp.asarray(depth), s)
    flipped, _ = _summed_scores(jnp.asarray(colour), jnp.asarray(depth[:, :, ::-1]), s)
    total = np.asarray(total)
    dy, dx = np.unravel_index(int(np.argmax(total)), total.shape)
    best, zero, mirrored = float(total.max()), float(total[s, s]), float(np.max(flipped))
    return Alignment((int(dx) - s, int(dy) - s), best, zero, int(n), mirrored)
