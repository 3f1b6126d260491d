"""The body's anchor at the target's depth (``PointConfig.joined_anchor = "depth"``) against a
SciPy reference, under jit and vmap, and on a scene where someone passes in front."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cpf_jax.points import PointConfig
from cpf_jax.points import body as pb

CFG = PointConfig(
    min_component_fraction=0.05,
    joined_max_dz_mm=160.0,
    joined_anchor="depth",
    anchor_max_dz_mm=300.0,
)


def _labels(d: np.ndarray, body: np.ndarray, max_dz: float) -> np.ndarray:
    """SciPy's components of ``body``, 8 neighbours joined when ``|dz| < max_dz``."""
    h, w = d.shape
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for r in range(h):
        for c in range(w):
            for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
                r2, c2 = r + dr, c + dc
                if not (0 <= r2 < h and 0 <= c2 < w):
                    continue
                if body[r, c] and body[r2, c2] and abs(d[r, c] - d[r2, c2]) < max_dz:
                    rows.append(idx[r, c])
                    cols.append(idx[r2, c2])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(h * w, h * w))
    return connected_components(graph, directed=False)[1].reshape(h, w)


def _reference(d: np.ndarray, body: np.ndarray, target: float, cfg: PointConfig) -> np.ndarray:
    """The groups of ``body`` (8 neighbours joined when ``|dz| < joined_max_dz_mm``) whose mean
    depth is within ``anchor_max_dz_mm`` of ``target``; else the group of the body pixel
    nearest the centre (ties: the first in row-major order)."""
    h, w = d.shape
    labels = _labels(d, body, cfg.joined_max_dz_mm)
    out = np.zeros_like(body)
    for lab in np.unique(labels[body]):
        g = body & (labels == lab)
        if abs(d[g].mean() - target) <= cfg.anchor_max_dz_mm:
            out |= g
    if target > 0 and out.any():
        return out
    rr, cc = np.nonzero(body)
    k = np.argmin((rr - (h - 1) / 2) ** 2 + (cc - (w - 1) / 2) ** 2)
    return body & (labels == labels[rr[k], cc[k]])


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[24, 32]`` mm of blocks at random depths over a wall, and its foreground."""
    rng = np.random.default_rng(seed)
    d = np.full((24, 32), 5000.0, np.float32)
    for _ in range(6):
        r, c = rng.integers(0, 20), rng.integers(0, 28)
        d[r : r + rng.integers(3, 10), c : c + rng.integers(3, 10)] = rng.uniform(1500, 4000)
    d += rng.normal(0, 20, d.shape).astype(np.float32)
    return d, d < 4500


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joined_at_depth_matches_scipy_under_jit_and_vmap(seed):
    d, body = _scene(seed)
    ones = jnp.ones(d.shape, jnp.float32)
    # the target at the depth of a block, between blocks, and unknown (the centre's group)
    inside = d[body]
    targets = np.float32([inside[0], inside.mean(), 0.0])
    run = jax.jit(lambda z, b, t: pb._joined_at_depth(CFG, z, b, ones, t))
    for t in targets:
        want = _reference(d, body, float(t), CFG)
        np.testing.assert_array_equal(np.asarray(run(jnp.asarray(d), jnp.asarray(body), t)), want)
    got = jax.vmap(lambda t: pb._joined_at_depth(CFG, jnp.asarray(d), jnp.asarray(body), ones, t))(
        jnp.asarray(targets)
    )
    for k, t in enumerate(targets):
        np.testing.assert_array_equal(np.asarray(got[k]), _reference(d, body, float(t), CFG))


def test_the_person_behind_not_the_one_passing_in_front_at_the_centre():
    # The tracked person at 3000 mm fills the window; someone at 2000 mm passes in front of
    # its centre and splits him in two. The centre's group is the passer-by; at the target's
    # depth both halves of the tracked person are the body, and no pixel of the passer-by.
    d = np.full((20, 30), 6000.0, np.float32)
    d[1:19, 4:26] = 3000
    d[0:20, 12:18] = 2000
    fg = d < 5000
    him = fg & (d > 2500)
    ones = jnp.ones(d.shape, jnp.float32)
    centre = pb._joined_to_centre(CFG, jnp.asarray(d), jnp.asarray(fg), ones)
    np.testing.assert_array_equal(np.asarray(centre), fg & (d < 2500))
    got = pb._joined_at_depth(CFG, jnp.asarray(d), jnp.asarray(fg), ones, jnp.float32(3100.0))
    np.testing.assert_array_equal(np.asarray(got), him)
    # unknown depth (0) or no group near it: the centre's group
    for t in (0.0, 4500.0):
        got = pb._joined_at_depth(CFG, jnp.asarray(d), jnp.asarray(fg), ones, jnp.float32(t))
        np.testing.assert_array_equal(np.asarray(got), np.asarray(centre))


def test_segment_uses_the_depth_anchor_only_when_given():
    d = np.full((20, 30), 6000.0, np.float32)
    d[1:19, 4:26] = 3000
    d[0:20, 12:18] = 2000
    fg = jnp.asarray(d < 5000)
    roi = jnp.ones(d.shape, bool)
    ones = jnp.ones(d.shape, jnp.float32)
    cfg = dataclasses.replace(CFG, background_margin_mm=None)
    without = pb._segment(cfg, jnp.asarray(d), roi, fg, ones)
    with_z = pb._segment(cfg, jnp.asarray(d), roi, fg, ones, jnp.float32(3000.0))
    assert np.asarray(without)[10, 15] and not np.asarray(without)[10, 5]
    assert np.asarray(with_z)[10, 5] and not np.asarray(with_z)[10, 15]
    centre = pb._segment(
        dataclasses.replace(cfg, joined_anchor="centre"),
        jnp.asarray(d),
        roi,
        fg,
        ones,
        jnp.float32(3000.0),
    )
    np.testing.assert_array_equal(np.asarray(centre), np.asarray(without))


def test_anchor_settings_are_checked():
    with pytest.raises(ValueError, match="joined_anchor"):
        PointConfig(joined_anchor="head")
    with pytest.raises(ValueError, match="anchor_max_dz_mm"):
        PointConfig(anchor_max_dz_mm=0.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_largest_at_depth_matches_scipy_under_jit_and_vmap(seed):
    d, valid = _scene(seed)
    labels = np.asarray(
        pb.gk.connected_components(pb.gk.pixel_graph(jnp.asarray(d), jnp.asarray(valid), 25.0))
    )
    size = np.asarray(pb._component_sizes(jnp.asarray(labels), jnp.asarray(valid)))
    ref = _labels(d, valid, 25.0)
    sizes = {lab: (ref == lab)[valid].sum() for lab in np.unique(ref[valid])}
    means = {lab: d[valid & (ref == lab)].mean() for lab in sizes}
    targets = np.float32([d[valid][0], 2500.0, 0.0])

    def want(t):
        at = [sizes[k] for k in sizes if abs(means[k] - t) <= CFG.anchor_max_dz_mm]
        return max(at) if at else max(sizes.values())

    args = (jnp.asarray(d), jnp.asarray(labels), jnp.asarray(valid), jnp.asarray(size))
    run = jax.jit(lambda t: pb._largest_at_depth(CFG, *args, t))
    for t in targets:
        assert float(run(t)) == want(float(t))
    both = jax.vmap(lambda t: pb._largest_at_depth(CFG, *args, t))(jnp.asarray(targets))
    np.testing.assert_array_equal(np.asarray(both), [want(float(t)) for t in targets])


def test_a_mostly_hidden_target_keeps_his_small_pieces_with_sizes_at_depth():
    # Someone at 2000 mm fills the window; of the target at 3000 mm only a strip at the
    # side shows, under 5 % of the one in front: "sizeable" against the largest component
    # drops the strip, against the largest at the target's depth keeps it.
    d = np.full((40, 40), 6000.0, np.float32)
    d[:, 2:40] = 2000
    d[10:30, 0:2] = 3000
    fg = jnp.asarray(d < 5000)
    roi = jnp.ones(d.shape, bool)
    ones = jnp.ones(d.shape, jnp.float32)
    cfg = dataclasses.replace(CFG, background_margin_mm=None)
    strip = (d > 2500) & (d < 5000)
    z = jnp.float32(3000.0)
    plain = np.asarray(pb._segment(cfg, jnp.asarray(d), roi, fg, ones, z))
    sized = np.asarray(
        pb._segment(
            dataclasses.replace(cfg, anchor_sizeable=True), jnp.asarray(d), roi, fg, ones, z
        )
    )
    assert not (plain & strip).any()
    np.testing.assert_array_equal(sized, strip)


def test_the_cascade_gives_layer2_layer1s_target_depth():
    """Layer 2's frame carries the depth layer 1 reads from its templates: the walker's."""
    from cpf_jax.cascade import CascadeConfig, layer1_target_depth, layer2_from_layer1
    from cpf_jax.colour import ColourConfig
    from cpf_jax.rgbd import RGBDConfig, build_rgbd_filter, default_rgbd_params
    from cpf_jax.synthetic import make_sequence
    from cpf_jax.types import Frame

    seq = make_sequence("walk_towards", seed=0, n_frames=2, fps=30.0)
    box = RGBDConfig(n_particles=50).with_window(
        tuple(float(v) for v in seq.boxes[0, 2:]), seq.colour.shape[1:3]
    )
    config = CascadeConfig(box=box, points=PointConfig(), foreground=True)
    frame = Frame(jnp.asarray(seq.colour[0]), jnp.asarray(seq.depth[0]))
    b = jnp.asarray(seq.boxes[0])
    s1 = build_rgbd_filter(box).init(default_rgbd_params(box), jax.random.PRNGKey(0), frame, b)
    inp = jax.jit(lambda s, f: layer2_from_layer1(config, None, s, f, b))(s1, frame)
    walker = np.median(seq.depth[0][seq.mask[0]])
    assert abs(float(inp.target_depth) - walker) < 150
    assert inp.foreground is not None
    assert layer1_target_depth(ColourConfig(), None) is None
