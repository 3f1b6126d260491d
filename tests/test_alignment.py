"""Depth-to-colour alignment: edge maps and their scores over shifts, against NumPy."""

from __future__ import annotations

import numpy as np
import pytest

from cpf_jax.kernels import alignment as al
from tests.checks import check_kernel


def _scene(h: int, w: int, shift: tuple[int, int], seed: int = 0):
    """Colour rectangles on a flat wall, and the same rectangles in depth moved by
    ``-shift`` (the depth lies ``shift`` px left of and above the colour)."""
    rng = np.random.default_rng(seed)
    colour = np.full((h, w, 3), 90, np.uint8)
    depth = np.full((h, w), 4000, np.uint16)
    dx, dy = shift
    for _ in range(4):
        x, y = int(rng.integers(4, w - 20)), int(rng.integers(4, h - 20))
        bw, bh = int(rng.integers(6, 14)), int(rng.integers(6, 14))
        colour[y : y + bh, x : x + bw] = rng.integers(150, 250, 3)
        depth[max(y - dy, 0) : y - dy + bh, max(x - dx, 0) : x - dx + bw] = int(
            rng.integers(1000, 2500)
        )
    depth[rng.random((h, w)) < 0.02] = 0  # missing pixels
    return colour, depth


def _scores_ref(colour, depth, s):
    c = np.asarray(al.colour_edges(colour), np.float64)  # edge maps have their own test
    d = np.asarray(al.depth_edges(depth), np.float64)
    h, w = d.shape
    pad = np.zeros((h + 2 * s, w + 2 * s))
    pad[s : s + h, s : s + w] = c
    out = np.zeros((2 * s + 1, 2 * s + 1))
    for dy in range(-s, s + 1):
        for dx in range(-s, s + 1):
            out[dy + s, dx + s] = np.sum(d * pad[s + dy : s + dy + h, s + dx : s + dx + w])
    return out / max(d.sum(), 1.0)


def _edges_ref(colour, depth):
    grey = colour.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    gx, gy = np.zeros_like(grey), np.zeros_like(grey)
    gx[:, 1:-1] = grey[:, 2:] - grey[:, :-2]
    gy[1:-1] = grey[2:] - grey[:-2]
    mag = np.hypot(gx, gy)
    ce = np.clip(mag / (3 * mag.mean() + 1e-6), 0, 1)
    z = depth.astype(np.float64)
    de = np.zeros(z.shape, bool)
    for a, b, sl in ((z[:, :-1], z[:, 1:], np.s_[:, :-1]), (z[:-1], z[1:], np.s_[:-1])):
        step = np.maximum(al.DEPTH_STEP_MM, al.DEPTH_STEP_REL * np.minimum(a, b))
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > step)
        de[sl] |= jump
        de[(np.s_[:, 1:] if sl == np.s_[:, :-1] else np.s_[1:])] |= jump
    return ce, de.astype(np.float64)


def test_edge_maps_match_numpy():
    a, b = _scene(40, 48, (3, 1), seed=1), _scene(40, 48, (0, 0), seed=2)
    check_kernel(
        lambda c, d: (al.colour_edges(c), al.depth_edges(d)),
        _edges_ref,
        a,
        batch=[a, b],
        rtol=1e-4,
        atol=1e-5,
    )


def test_shift_scores_match_every_shift_by_brute_force():
    a, b = _scene(40, 48, (3, -2), seed=3), _scene(40, 48, (-4, 0), seed=4)
    check_kernel(
        lambda c, d: al.edge_shift_scores(c, d, 5),
        lambda c, d: _scores_ref(c, d, 5),
        a,
        batch=[a, b],
        rtol=1e-4,
        atol=1e-5,
    )


@pytest.mark.parametrize("shift", [(0, 0), (7, -3), (-5, 4)])
def test_the_best_shift_is_the_one_the_depth_was_moved_by(shift):
    colour, depth = _scene(96, 128, shift, seed=5)
    scores = np.asarray(al.edge_shift_scores(colour, depth, 10))
    dy, dx = np.unravel_index(np.argmax(scores), scores.shape)
    assert (dx - 10, dy - 10) == shift


def test_no_depth_edges_scores_zero():
    colour, _ = _scene(40, 48, (0, 0))
    flat = np.full((40, 48), 3000, np.uint16)
    assert np.all(np.asarray(al.edge_shift_scores(colour, flat, 4)) == 0)
