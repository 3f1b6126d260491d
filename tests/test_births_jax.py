"""The person detector in JAX (``kernels.blobs``, ``births.device_candidates``) against the
host detector (``detect.clean_mask`` + ``detect.mask_person_boxes``, OpenCV), under jit
and vmap, on synthetic foreground masks."""

from __future__ import annotations

import cv2
import jax
import numpy as np
import pytest
from checks import check_kernel

from cpf_jax.detect import DetectConfig, person_confidence
from cpf_jax.kernels import blobs
from cpf_jax.multi import births

CONFIG = DetectConfig()
N = 3


def _morph(op):
    def reference(mask, size):
        kernel = np.ones((size, size), np.uint8)
        return cv2.morphologyEx(np.asarray(mask, np.uint8), op, kernel).astype(bool)

    return reference


@pytest.mark.parametrize("size", [3, 4, 7])
def test_opening_and_closing_are_opencvs(size):
    rng = np.random.default_rng(size)
    masks = [rng.random((40, 50)) < p for p in (0.3, 0.6, 0.8)]
    masks[2][:, :3] = True  # the frame's edge neither erodes nor dilates
    for kernel, op in ((blobs.opening, cv2.MORPH_OPEN), (blobs.closing, cv2.MORPH_CLOSE)):
        check_kernel(
            lambda m, kernel=kernel: kernel(m, size),
            lambda m, op=op: _morph(op)(m, size),
            (masks[0],),
            batch=[(masks[1],), (masks[2],)],
        )


def _median_loop(groups, values, weights, n_groups):
    out = np.zeros(n_groups)
    for g in range(n_groups):
        v = np.repeat(values[groups == g], weights[groups == g])
        out[g] = np.sort(v)[(len(v) - 1) // 2] if len(v) else 0.0
    return out


def test_group_median_is_the_weighted_lower_median():
    rng = np.random.default_rng(0)

    def case(seed):
        r = np.random.default_rng(seed)
        g = r.integers(0, 5, 60).astype(np.int32)
        return g, np.round(r.random(60) * 4000).astype(np.float32), r.integers(0, 4, 60)

    check_kernel(
        lambda g, v, w: blobs.group_median(g, v, w, 6),
        lambda g, v, w: _median_loop(g, v, w, 6),
        case(1),
        batch=[case(2), case(3)],
        atol=0.1,
    )
    v = np.round(rng.random(30) * 4000).astype(np.float32)
    w = rng.integers(0, 3, (2, 30))
    got = np.asarray(jax.jit(blobs.weighted_median)(v, w))
    want = [_median_loop(np.zeros(30, int), v, row, 1)[0] for row in w]
    np.testing.assert_allclose(got, want, atol=0.1)


def _person(mask, depth, x, y, w, h, z):
    """A person-shaped blob: a head on a trunk, at ``z`` mm, tight box ``(x, y, w, h)``."""
    head = w // 3
    mask[y : y + head, x + head : x + 2 * head] = True
    depth[y : y + head, x + head : x + 2 * head] = z
    mask[y + head : y + h, x : x + w] = True
    depth[y + head : y + h, x : x + w] = z


def scenes(hw):
    """Foreground masks ``[S, H, W] bool`` and depths ``[S, H, W] uint16`` mm of four
    scenes drawn on a 120 x 160 plan scaled by ``H // 120`` (so not always a multiple of
    the detector's block): two people side by side at
    different depths, a person touching a chair, speckle around a person, a head and
    shoulders at the frame's top-left corner."""
    h, w = hw
    s = h // 120
    rng = np.random.default_rng(0)
    masks = np.zeros((4, h, w), bool)
    depths = np.zeros((4, h, w), np.uint16)
    # Two people side by side, touching, at 2 m and 3 m.
    _person(masks[0], depths[0], 30 * s, 15 * s, 27 * s, 90 * s, 2000)
    _person(masks[0], depths[0], 57 * s, 25 * s, 24 * s, 75 * s, 3000)
    # A person touching a chair 0.7 m behind him (seat and back).
    _person(masks[1], depths[1], 60 * s, 10 * s, 30 * s, 100 * s, 2500)
    masks[1, 70 * s : 110 * s, 90 * s : 125 * s] = True
    depths[1, 70 * s : 110 * s, 90 * s : 125 * s] = 3200
    # Speckle (and a few depth holes) around a person.
    _person(masks[2], depths[2], 100 * s, 20 * s, 27 * s, 84 * s, 2200)
    speck = rng.random((h, w)) < 0.01
    masks[2] |= speck
    depths[2][speck & (depths[2] == 0)] = 1500
    depths[2][rng.random((h, w)) < 0.02] = 0
    # A head and shoulders cut by the frame's top-left corner.
    masks[3, : 40 * s, : 45 * s] = True
    depths[3, : 40 * s, : 45 * s] = 1200
    masks[3, 40 * s : 55 * s, : 20 * s] = True
    depths[3, 40 * s : 55 * s, : 20 * s] = 1200
    noise = rng.normal(0, 15, (4, h, w)).round().astype(np.int32)
    depths = np.where(depths > 0, depths + noise, 0).astype(np.uint16)
    return masks, depths


def _host(masks, depths):
    rows = [births.host_candidates(CONFIG, N, m, d) for m, d in zip(masks, depths, strict=True)]
    return [np.stack(a) for a in zip(*rows, strict=True)]


def _assert_agree(got, want, box_px):
    box, conf, z = want
    np.testing.assert_allclose(np.asarray(got.box), box, atol=box_px)
    np.testing.assert_allclose(np.asarray(got.confidence), conf, atol=0.1)
    np.testing.assert_allclose(np.asarray(got.depth), z, atol=40.0)


@pytest.mark.parametrize("hw", [(120, 160), (240, 320), (424, 512)])
def test_the_kernel_finds_the_host_detectors_people(hw):
    masks, depths = scenes(hw)
    box, conf, z = want = _host(masks, depths)
    # The host finds what the scenes hold: both people, the person and the chair apart,
    # the person among speckle, the corner's head and shoulders (with low confidence).
    assert [int(np.sum(c > 0)) for c in conf] == [2, 2, 1, 1]
    assert box[1, 0, 2] == 30 * (hw[0] // 120) and conf[3, 0] < 0.5
    block = blobs.detector_block(hw[1])
    assert block == -(-hw[1] // 160)
    one = jax.jit(lambda m, d: births.device_candidates(CONFIG, N, m, d))
    for i in range(len(masks)):
        got = one(masks[i], depths[i])
        _assert_agree(got, [a[i] for a in want], block - 1)
    many = jax.jit(jax.vmap(lambda m, d: births.device_candidates(CONFIG, N, m, d)))
    _assert_agree(many(masks, depths), want, block - 1)


def test_the_kernel_keeps_the_host_rules_on_confidence():
    # One formula: the host's person_confidence is the kernel's on the same box and area.
    box, area = np.float32([[0, 0, 60, 55], [30, 15, 27, 90]]), np.array([2400, 2000])
    got = np.asarray(jax.jit(lambda b, a: blobs.person_confidence(b, a, (120, 160)))(box, area))
    want = [person_confidence(b, int(a), (120, 160))[0] for b, a in zip(box, area, strict=True)]
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # By hand: the corner box fills its box and is a third of the frame tall, but it is
    # 55 / 60 as tall as wide and the left and top edges cut it.
    np.testing.assert_allclose(got[0], (55 / 60 - 0.9) / 0.9 * 0.6**2, rtol=1e-5)


def test_an_empty_or_tiny_mask_gives_nobody():
    mask = np.zeros((120, 160), bool)
    mask[5:8, 5:8] = True
    depth = np.full((120, 160), 2000, np.uint16)
    got = jax.jit(lambda m, d: births.device_candidates(CONFIG, N, m, d))(mask, depth)
    assert not np.any(np.asarray(got.box)) and not np.any(np.asarray(got.confidence))
