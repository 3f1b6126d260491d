"""The multi-person tracker's stages on their own: pixel claims, each slot's depth image,
the detector's mask, births, exclusion, life and re-identification, each against a plain
NumPy loop (plainly, under jit and under vmap where it is a kernel of arrays)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import check_kernel

from cpf_jax.multi import births, claim, tracks
from cpf_jax.multi.config import ACTIVE, FREE, LOST, TENTATIVE, MultiConfig
from cpf_jax.multi.params import default_multi_params

H, W = 24, 32


def _scene(rng):
    depth = rng.integers(1500, 3500, size=(H, W)).astype(np.uint16)
    depth[rng.uniform(size=(H, W)) < 0.1] = 0
    boxes = np.array([[2, 3, 10, 15], [8, 2, 12, 18], [20, 5, 9, 12]], np.float32)
    z = np.array([2000.0, 2200.0, 3000.0], np.float32)
    gate = np.array([400.0, 300.0, 500.0], np.float32)
    claiming = np.array([True, True, False])
    return depth, boxes, z, gate, claiming


def _owner_loop(depth, boxes, z, gate, claiming):
    out = np.full((H, W), -1, np.int32)
    for r in range(H):
        for c in range(W):
            d = float(depth[r, c])
            best, best_cost = -1, np.inf
            for k, (x, y, w, h) in enumerate(boxes):
                inside = x <= c + 0.5 < x + w and y <= r + 0.5 < y + h
                if not (claiming[k] and z[k] > 0 and inside and d > 0):
                    continue
                off = abs(d - z[k])
                if off >= gate[k]:
                    continue
                cost = off / gate[k] + abs(c + 0.5 - (x + w / 2)) / max(w / 2, 1)
                if cost < best_cost:
                    best, best_cost = k, cost
            out[r, c] = best
    return out


def test_claim_owner_against_a_loop():
    rng = np.random.default_rng(0)
    args = _scene(rng)
    other = _scene(np.random.default_rng(1))
    check_kernel(claim.claim_owner, _owner_loop, args, batch=[args, other])


def _slot_depths_loop(depth, owner, z, gate, scene, fake_margins):
    out = np.repeat(depth[None].astype(np.float64), len(z), axis=0)
    for k in range(len(z)):
        fake = max(z[k] - fake_margins * max(400.0, 0.12 * z[k]), 1.0)
        for r in range(H):
            for c in range(W):
                o = owner[r, c]
                if o >= 0 and o != k and z[k] > 0:
                    near = z[o] < z[k] + gate[k]
                    out[k, r, c] = min(depth[r, c], fake) if near else scene[r, c]
    return np.round(out).astype(np.uint16)


def test_slot_depths_turn_others_pixels_into_occluders():
    rng = np.random.default_rng(2)
    depth, boxes, z, gate, claiming = _scene(rng)
    owner = _owner_loop(depth, boxes, z, gate, np.ones(3, bool))
    params = default_multi_params().rgbd  # occlusion margin 400 mm or 12 % of the depth

    scene = np.full((H, W), 4000.0, np.float32)
    scene[:, :3] = 0.0  # no background depth there

    def kernel(depth, owner, z, gate, scene):
        return claim.slot_depths(params, depth, owner, z, gate, 2.0, scene)

    def reference(depth, owner, z, gate, scene):
        return _slot_depths_loop(depth, owner, z, gate, scene, 2.0)

    check_kernel(kernel, reference, (depth, owner, z, gate, scene))
    out = reference(depth, owner, z, gate, scene)
    # A slot's own pixels are as they were; a farther target's are the scene's depth; a
    # nearer one's are in front of the slot's target.
    assert np.all(out[0][owner == 0] == depth[owner == 0])
    assert np.all(out[0][owner == 2] == scene[owner == 2])
    assert np.all(out[2][owner == 0] < z[2])


def _claimed_loop(depth, boxes, z, gate, claiming):
    out = np.zeros((H, W), bool)
    for r in range(H):
        for c in range(W):
            for k, (x, y, w, h) in enumerate(boxes):
                inside = x <= c + 0.5 < x + w and y <= r + 0.5 < y + h
                near = abs(float(depth[r, c]) - z[k]) < gate[k] or depth[r, c] == 0
                out[r, c] |= bool(claiming[k] and z[k] > 0 and inside and near)
    return out


def test_claimed_mask_against_a_loop():
    args = _scene(np.random.default_rng(3))
    check_kernel(
        claim.claimed_mask, _claimed_loop, args, batch=[args, _scene(np.random.default_rng(4))]
    )


def _evidence_loop(foreground, depth, owner, boxes, z, gate, reach=None):
    out = np.zeros(len(z))
    for k, (x, y, w, h) in enumerate(boxes):
        n = 0
        for r in range(H):
            for c in range(W):
                inside = x <= c + 0.5 < x + w and y <= r + 0.5 < y + h
                d = float(depth[r, c])
                mine = owner[r, c] in (-1, k)
                if reach is not None:
                    theirs = any(reach[j, r, c] for j in range(len(z)) if j != k)
                    mine = mine and (reach[k, r, c] or not theirs)
                n += inside and foreground[r, c] and d > 0 and abs(d - z[k]) < gate[k] and mine
        out[k] = n / max(w * h, 1.0) if z[k] > 0 else 0.0
    return out


def test_evidence_counts_own_unclaimed_foreground_at_the_targets_depth():
    def case(seed):
        rng = np.random.default_rng(seed)
        depth, boxes, z, gate, claiming = _scene(rng)
        owner = _owner_loop(depth, boxes, z, gate, claiming)
        foreground = rng.uniform(size=(H, W)) < 0.7
        return foreground, depth, owner, boxes, z, gate

    args = case(5)
    check_kernel(claim.evidence, _evidence_loop, args, batch=[args, case(6)])
    foreground, depth, owner, boxes, z, gate = args
    # Slot 1 shares pixels with slot 0 at its depth: those slot 0 owns are not its evidence.
    alone = claim.evidence(foreground, depth, np.full_like(owner, -1), boxes, z, gate)
    assert float(alone[1]) > float(claim.evidence(*args)[1]) > 0


def _joined_reference(mask, seeds):
    """SciPy's 4-connected components of each mask holding a seed."""
    from scipy import ndimage

    out = np.zeros_like(mask)
    for k in range(mask.shape[0]):
        labels, _ = ndimage.label(mask[k])
        hit = np.unique(labels[seeds[k] & mask[k]])
        out[k] = np.isin(labels, hit[hit > 0])
    return out


def test_joined_is_the_seeded_connected_components():
    def case(seed):
        rng = np.random.default_rng(seed)
        mask = rng.uniform(size=(3, H, W)) < 0.6  # near percolation: winding blobs
        mask[0] = False
        mask[0, 4:20, 3:9] = True  # a blob
        mask[0, 4:20, 10:16] = True  # its neighbour, apart from it
        mask[0, 12, 7:9] = False  # and a notch
        seeds = rng.uniform(size=(3, H, W)) < 0.02
        seeds[0] = False
        seeds[0, 10, 4] = True
        return mask, seeds

    args = case(7)
    check_kernel(
        lambda m, s: claim.joined(m, s, max_rounds=H * W),
        _joined_reference,
        args,
        batch=[args, case(8)],
    )
    got = np.asarray(claim.joined(*args))
    assert (got[0, 4:20, 3:9] == args[0][0, 4:20, 3:9]).all() and not got[0, :, 10:16].any()


def _blob_reach_reference(foreground, depth, owner, z, gate):
    d = depth.astype(np.float64)
    near = np.abs(d[None] - z[:, None, None]) < gate[:, None, None]
    mask = (foreground & (d > 0))[None] & near & (z > 0)[:, None, None]
    seeds = owner[None] == np.arange(len(z))[:, None, None]
    return _joined_reference(mask, seeds)


def _evidence_blob_loop(foreground, depth, owner, boxes, z, gate):
    reach = _blob_reach_reference(foreground, depth, owner, z, gate)
    return _evidence_loop(foreground, depth, owner, boxes, z, gate, reach)


def test_blob_evidence_leaves_out_the_rest_of_a_claimed_persons_blob():
    def case(seed):
        rng = np.random.default_rng(seed)
        depth, boxes, z, gate, claiming = _scene(rng)
        depth = np.where(rng.uniform(size=(H, W)) < 0.5, 2100, depth).astype(np.uint16)
        owner = _owner_loop(depth, boxes, z, gate, claiming)
        foreground = rng.uniform(size=(H, W)) < 0.8
        return foreground, depth, owner, boxes, z, gate

    def kernel(foreground, depth, owner, boxes, z, gate):
        reach = claim.blob_reach(foreground, depth, owner, z, gate)
        return claim.evidence(foreground, depth, owner, boxes, z, gate, reach)

    args = case(9)
    check_kernel(kernel, _evidence_blob_loop, args, batch=[args, case(10)])
    check_kernel(
        claim.blob_reach, _blob_reach_reference, (args[0], args[1], args[2], args[4], args[5])
    )
    # A target that claims nothing (slot 2) beside a blob slot 0 claims at its depth: the
    # blob is slot 0's person, not its evidence.
    foreground = np.ones((H, W), bool)
    depth = np.full((H, W), 3000, np.uint16)
    depth[:, 12:22] = 2000  # one person at 2 m, columns 12-21
    boxes = np.array([[12, 0, 4, H], [0, 0, 2, 2], [17, 0, 5, H]], np.float32)
    z = np.array([2000.0, 0.0, 2000.0], np.float32)
    gate = np.full(3, 300.0, np.float32)
    owner = _owner_loop(depth, boxes, z, gate, np.array([True, False, False]))
    plain = claim.evidence(foreground, depth, owner, boxes, z, gate)
    reach = claim.blob_reach(foreground, depth, owner, z, gate)
    blob = claim.evidence(foreground, depth, owner, boxes, z, gate, reach)
    assert float(plain[2]) == 1.0 and float(blob[2]) == 0.0
    assert float(blob[0]) == float(plain[0]) == 1.0


def _visible_loop(foreground, depth, owner, boxes, z, gate):
    hidden, shown, tight = np.zeros(len(z)), np.zeros(len(z)), np.zeros((len(z), 4))
    for k, (x, y, w, h) in enumerate(boxes):
        front, own = 0, []
        for r in range(H):
            for c in range(W):
                if not (x <= c + 0.5 < x + w and y <= r + 0.5 < y + h):
                    continue
                o = owner[r, c]
                front += bool(o >= 0 and o != k and z[o] < z[k])
                d = float(depth[r, c])
                mine = o in (-1, k) and foreground[r, c] and d > 0 and abs(d - z[k]) < gate[k]
                if mine and z[k] > 0:
                    own.append((r, c))
        area = max(w * h, 1.0)
        hidden[k] = min(front / area, 1.0)
        shown[k] = len(own) / max(area * (1 - hidden[k]), 1.0)
        if own:
            rs, cs = np.array(own).T
            tight[k] = (cs.min(), rs.min(), cs.max() + 1 - cs.min(), rs.max() + 1 - rs.min())
    return claim.Visible(hidden, shown, tight)


def test_visible_part_against_a_loop():
    def case(seed):
        rng = np.random.default_rng(seed)
        depth, boxes, z, gate, claiming = _scene(rng)
        owner = _owner_loop(depth, boxes, z, gate, np.ones(3, bool))
        foreground = rng.uniform(size=(H, W)) < 0.7
        return foreground, depth, owner, boxes, z, gate

    args = case(11)
    check_kernel(claim.visible_part, _visible_loop, args, batch=[args, case(12)], rtol=1e-5)
    # A man at 3 m behind a woman at 2 m who claims the lower part of his box: his head
    # shows above her, fills the rest of the box, and is its tight box.
    foreground = np.ones((H, W), bool)
    depth = np.full((H, W), 5000, np.uint16)
    depth[2:8, 10:16] = 3000  # his head
    depth[8:, 6:20] = 2000  # her, in front of him
    boxes = np.array([[8, 2, 10, 22], [6, 8, 14, 16]], np.float32)
    z = np.array([3000.0, 2000.0], np.float32)
    gate = np.full(2, 300.0, np.float32)
    owner = _owner_loop(depth, boxes, z, gate, np.array([True, True]))
    vis = claim.visible_part(foreground, depth, owner, boxes, z, gate)
    assert float(vis.hidden[0]) == pytest.approx(16 * 10 / 220)
    assert float(vis.evidence[0]) == pytest.approx(36 / 60)
    np.testing.assert_array_equal(np.asarray(vis.box[0]), [10, 2, 6, 6])
    assert float(claim.evidence(foreground, depth, owner, boxes, z, gate)[0]) < 36 / 100


def test_coast_moves_hidden_clouds_to_the_predicted_box():
    from cpf_jax.filter import Cloud
    from cpf_jax.multi.filter import coast

    class Slots(NamedTuple):
        cloud: Cloud
        estimate: np.ndarray

    rng = np.random.default_rng(13)
    particles = rng.normal(size=(2, 5, 8)).astype(np.float32)
    slots = Slots(Cloud(particles, particles - 1, np.zeros((2, 5))), np.ones((2, 4), np.float32))
    slots = jax.tree_util.tree_map(jnp.asarray, slots)
    box = np.array([[10, 20, 4, 6], [30, 40, 2, 2]], np.float32)
    out = coast(slots, np.array([True, False]), box)
    # Centred on the box, its own size.
    np.testing.assert_allclose(out.estimate[0], [11.5, 22.5, 1, 1], atol=1e-6)
    np.testing.assert_allclose(
        out.cloud.particles[0, :, :2] - particles[0, :, :2], [[10.5, 21.5]] * 5
    )
    np.testing.assert_allclose(out.cloud.previous[0, :, 2:], particles[0, :, 2:] - 1)
    np.testing.assert_array_equal(out.cloud.particles[1], particles[1])


def test_coasting_box_takes_the_columns_of_what_shows():
    from cpf_jax.multi.filter import coasting_box

    predicted = np.array([[100, 30, 90, 240], [10, 10, 20, 40]], np.float32)
    shown = np.array([[140, 30, 40, 60], [0, 0, 0, 0]], np.float32)
    got = np.asarray(coasting_box(jnp.asarray(predicted), jnp.asarray(shown)))
    np.testing.assert_allclose(got[0], [115, 30, 90, 240])  # centred on column 160


def _same_place_loop(a, za, ga, b, zb, gb, share):
    out = np.zeros((len(a), len(b)), bool)
    for i in range(len(a)):
        for j in range(len(b)):
            x0, x1 = max(a[i, 0], b[j, 0]), min(a[i, 0] + a[i, 2], b[j, 0] + b[j, 2])
            narrow = max(min(a[i, 2], b[j, 2]), 1.0)
            near = abs(za[i] - zb[j]) < max(ga[i], gb[j]) and za[i] > 0 and zb[j] > 0
            out[i, j] = max(x1 - x0, 0.0) / narrow >= share and near
    return out


def test_same_place_against_a_loop():
    rng = np.random.default_rng(5)

    def case():
        a = np.column_stack([rng.uniform(0, 50, (4, 2)), rng.uniform(5, 30, (4, 2))])
        b = np.column_stack([rng.uniform(0, 50, (3, 2)), rng.uniform(5, 30, (3, 2))])
        za = rng.choice([0.0, 2000.0, 2300.0], 4)
        zb = rng.choice([2000.0, 2600.0], 3)
        ga, gb = np.full(4, 300.0), np.full(3, 350.0)
        return tuple(np.asarray(x, np.float32) for x in (a, za, ga, b, zb, gb)) + (np.float32(0.5),)

    check_kernel(claim.same_place, _same_place_loop, case(), batch=[case(), case()])


@pytest.mark.parametrize("on_device", [False, True])
def test_host_candidates_and_the_step_agree(on_device):
    import jax

    mask = np.zeros((120, 160), bool)
    depth = np.full((120, 160), 4000, np.uint16)
    mask[20:100, 20:45] = True  # a person at 2 m
    depth[20:100, 20:45] = 2000
    mask[30:90, 100:118] = True  # a farther one at 3 m
    depth[30:90, 100:118] = 3000
    config = MultiConfig().detect
    boxes, conf, z = births.host_candidates(config, 3, mask, depth)
    np.testing.assert_allclose(boxes[0], [20, 20, 25, 80])
    np.testing.assert_allclose(boxes[1], [100, 30, 18, 60])
    assert np.all(boxes[2] == 0) and conf[2] == 0
    np.testing.assert_allclose(z[:2], [2000, 3000])
    assert conf[0] > 0.5 and conf[1] > 0.5
    got = jax.jit(lambda m, d: births.detect_candidates(config, 3, m, d, on_device))(mask, depth)
    np.testing.assert_allclose(np.asarray(got.box), boxes)
    np.testing.assert_allclose(np.asarray(got.depth), z)
    many = jax.jit(jax.vmap(lambda m, d: births.detect_candidates(config, 3, m, d, on_device)))(
        np.stack([mask, np.zeros_like(mask)]), np.stack([depth, depth])
    )
    np.testing.assert_allclose(np.asarray(many.box[0]), boxes)
    assert np.all(np.asarray(many.confidence[1]) == 0)


def test_allocate_takes_free_slots_then_the_oldest_lost():
    status = np.array([ACTIVE, FREE, LOST, LOST, TENTATIVE, FREE], np.int32)
    missed = np.array([0, 0, 30, 90, 0, 0], np.int32)
    ok = np.array([True, False, True, True, True])
    got = np.asarray(births.allocate(ok, status, missed, np.float32(100.0)))
    # Candidates 0, 2, 3, 4 take slots 1, 5 (free), 3 (lost longest), 2.
    np.testing.assert_array_equal(got, [-1, 0, 4, 3, -1, 2])
    got = np.asarray(births.allocate(np.array([True]), status, missed, np.float32(100.0)))
    np.testing.assert_array_equal(got, [-1, 0, -1, -1, -1, -1])


def _tracks(status, ident=None, hits=None, missed=None, born=None):
    k = len(status)
    t = tracks.empty_tracks(k, 4)
    z = np.zeros(k, np.int32)
    return t._replace(
        status=np.asarray(status, np.int32),
        ident=np.asarray(ident if ident is not None else z, np.int32),
        hits=np.asarray(hits if hits is not None else z, np.int32),
        missed=np.asarray(missed if missed is not None else z, np.int32),
        born=np.asarray(born if born is not None else z, np.int32),
    )


def test_duplicates_keep_the_confirmed_then_the_older():
    boxes = np.array(
        [[10, 10, 20, 60], [12, 40, 18, 30], [60, 10, 20, 60], [14, 10, 20, 60]], np.float32
    )
    z = np.array([2000, 2100, 2000, 3500], np.float32)
    gate = np.full(4, 300.0, np.float32)
    tr = _tracks([TENTATIVE, ACTIVE, ACTIVE, ACTIVE], born=[5, 9, 0, 0])
    found = np.ones(4, bool)
    lose = np.asarray(tracks.duplicates(np.float32(0.5), tr, found, boxes, z, gate))
    # 0 and 1 are one person at one depth: the confirmed one keeps him; 3 is behind.
    np.testing.assert_array_equal(lose, [True, False, False, False])
    tr = _tracks([ACTIVE, ACTIVE, ACTIVE, ACTIVE], born=[5, 9, 0, 0])
    lose = np.asarray(tracks.duplicates(np.float32(0.5), tr, found, boxes, z, gate))
    np.testing.assert_array_equal(lose, [False, True, False, False])


def test_advance_drops_loses_finds_and_forgets():
    life = default_multi_params().life  # confirm 3, tentative 2, lost 15, forget 100
    tr = _tracks(
        [TENTATIVE, ACTIVE, LOST, LOST, LOST, ACTIVE],
        ident=[0, 4, 5, 6, 7, 8],
        hits=[0, 0, 3, 3, 0, 5],
        missed=[2, 15, 0, 0, 100, 0],
    )
    found = np.array([False, False, True, True, False, True])
    loser = np.array([False, False, False, False, False, True])
    dist = np.array([0, 0, 0.2, 0.9, 0, 0], np.float32)
    new, ev = tracks.advance(life, tr, found, loser, dist, np.float32(0.5))
    np.testing.assert_array_equal(np.asarray(new.status), [FREE, LOST, ACTIVE, LOST, FREE, LOST])
    np.testing.assert_array_equal(np.asarray(new.ident), [0, 4, 5, 6, 0, 8])
    np.testing.assert_array_equal(np.asarray(ev.lost), [0, 1, 0, 0, 0, 1])
    np.testing.assert_array_equal(np.asarray(ev.reidentified), [0, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(np.asarray(ev.died_ident), [0, 0, 0, 0, 7, 0])


def test_confirm_reidentifies_by_appearance_and_names_the_rest():
    params = default_multi_params()
    app = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    tr = _tracks(
        [TENTATIVE, TENTATIVE, LOST, LOST],
        ident=[0, 0, 7, 9],
        hits=[3, 3, 0, 0],
        missed=[0, 0, 20, 20],
    )
    # Lost target 7 wore colours 0, target 9 colours 3; the new ones show 3 and 1.
    tr = tr._replace(
        appearance=app[[0, 0, 0, 3]],
        box=np.tile(np.array([50, 20, 30, 90], np.float32), (4, 1)),
        depth=np.full(4, 2500.0, np.float32),
    )
    seen = app[[3, 1, 0, 0]]
    z = np.full(4, 2500.0, np.float32)
    box = np.tile(np.array([60, 20, 30, 90], np.float32), (4, 1))
    new, next_id, fresh, old = tracks.confirm(
        params.life, params.reid, tr, np.int32(12), seen, z, box
    )
    np.testing.assert_array_equal(np.asarray(new.ident), [9, 12, 7, 0])
    np.testing.assert_array_equal(np.asarray(new.status), [ACTIVE, ACTIVE, LOST, FREE])
    np.testing.assert_array_equal(np.asarray(fresh), [False, True, False, False])
    np.testing.assert_array_equal(np.asarray(old), [True, False, False, False])
    assert int(next_id) == 13


def _reid_loop(params, appearance, depth, box, rows, memory, pool):
    k = len(rows)
    out = np.full((k, k), np.inf)
    for i in range(k):
        for j in range(k):
            p = np.float64(appearance[i]) / appearance[i].sum()
            q = np.float64(memory.appearance[j]) / memory.appearance[j].sum()
            d_app = np.sqrt(max(1 - np.sum(np.sqrt(p * q)), 0.0))
            m = float(memory.missed[j])
            dz = abs(depth[i] - memory.depth[j])
            sz = float(params.depth) + (float(params.depth_speed) + memory.depth_speed[j]) * m
            c = box[i, :2] + box[i, 2:] / 2
            o = memory.box[j, :2] + memory.box[j, 2:] / 2 + memory.velocity[j] * min(m, 10.0)
            dc = np.linalg.norm(c - o)
            sc = (float(params.reach) + float(params.reach_speed) * m) * max(memory.box[j, 3], 1)
            if rows[i] and pool[j] and d_app <= float(params.appearance) and dz <= sz and dc <= sc:
                out[i, j] = (
                    d_app
                    + float(params.weight_depth) * (dz / sz) ** 2
                    + float(params.weight_reach) * (dc / sc) ** 2
                )
    return out


def test_reid_cost_against_a_loop():
    from cpf_jax.multi.reid import reid_cost

    params = default_multi_params().reid
    rng = np.random.default_rng(7)
    k = 4
    memory = _tracks([LOST] * k, missed=[0, 5, 20, 3])._replace(
        appearance=rng.uniform(0.1, 1, (k, 4)).astype(np.float32),
        box=np.column_stack([rng.uniform(0, 100, (k, 2)), rng.uniform(30, 90, (k, 2))]).astype(
            np.float32
        ),
        velocity=rng.normal(0, 2, (k, 2)).astype(np.float32),
        depth=rng.uniform(2000, 3000, k).astype(np.float32),
        depth_speed=np.array([0.0, 150.0, 20.0, 60.0], np.float32),
    )
    appearance = memory.appearance[[1, 0, 2, 3]] + rng.uniform(0, 0.2, (k, 4)).astype(np.float32)
    # New target 0 is 1.2 m from old target 1, within its gate only through its speed.
    depth = memory.depth[[1, 0, 2, 3]] + np.array([1200, 100, 100, 100], np.float32)
    box = memory.box[[1, 0, 2, 3]] + np.float32(5)
    rows = np.array([True, True, False, True])
    pool = np.array([True, True, True, False])
    got = np.asarray(reid_cost(params, appearance, depth, box, rows, memory, pool))
    want = _reid_loop(params, appearance, depth, box, rows, memory, pool)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    assert np.isfinite(got).sum() >= 2
    assert np.isfinite(got[0, 1])


@pytest.mark.parametrize("bad", ["births", "slots"])
def test_config_errors(bad):
    with pytest.raises(ValueError, match="max_births|max_targets"):
        if bad == "births":
            MultiConfig(max_births=0)
        else:
            MultiConfig(max_targets=0)


def test_duplicates_prefer_the_target_found_longer():
    boxes = np.array([[10, 10, 20, 60], [12, 12, 20, 60]], np.float32)
    z = np.array([2000, 2050], np.float32)
    gate = np.full(2, 300.0, np.float32)
    # Slot 0 is older but just found someone after missing its own target.
    tr = _tracks([ACTIVE, ACTIVE], hits=[1, 30], born=[0, 20])
    lose = np.asarray(tracks.duplicates(np.float32(0.5), tr, np.ones(2, bool), boxes, z, gate))
    np.testing.assert_array_equal(lose, [True, False])


def test_verified_needs_the_remembered_colours_after_a_search():
    tr = _tracks([ACTIVE, ACTIVE, LOST, ACTIVE], missed=[6, 6, 9, 1])
    tr = tr._replace(appearance=np.array([[1, 0, 0, 0]] * 3 + [[0, 0, 0, 0]], np.float32))
    found = np.ones(4, bool)
    seen = np.array([0.2, 0.8, 0.9, 0.9], np.float32)
    got = np.asarray(tracks.verified(found, tr, seen, np.float32(5.0), np.float32(0.5)))
    # Like its memory; unlike after 6 misses; unlike after 9; no memory yet, 1 miss.
    np.testing.assert_array_equal(got, [True, False, False, True])


def test_box_depths_against_numpy():
    from cpf_jax.kernels.cells import depth_bin_index
    from cpf_jax.rgbd.observe import Observation

    config = MultiConfig().rgbd
    rng = np.random.default_rng(8)
    depth = rng.uniform(1500, 3000, (H, W)).astype(np.uint16)
    fg = rng.uniform(size=(H, W)) < 0.6
    bins = np.asarray(depth_bin_index(depth, fg, config.depth_bins, *config.depth_range))
    obs = Observation(np.zeros((H, W), np.int32), bins, fg)
    boxes = np.array([[2, 3, 10, 15], [8, 2, 12, 18]], np.float32)
    got = np.asarray(claim.box_depths(config, obs, boxes))
    for k, (x, y, w, h) in enumerate(boxes.astype(int)):
        sel = fg[y : y + h, x : x + w]
        want = np.median(depth[y : y + h, x : x + w][sel])
        # The median of log-spaced 64-bin histograms over 0.4-10 m: within half a bin.
        assert abs(got[k] - want) < 0.03 * want, (got[k], want)


def test_every_parameter_has_its_prop_beside_it():
    import jax

    from cpf_jax.multi import multi_props

    params, props = default_multi_params(), multi_props()
    leaves = jax.tree_util.tree_structure(params, is_leaf=lambda x: x is None)
    assert leaves == jax.tree_util.tree_structure(
        jax.tree_util.tree_map(lambda p: 0, props, is_leaf=lambda x: hasattr(x, "constraint")),
        is_leaf=lambda x: x is None,
    )


def test_reanchor_takes_the_rest_of_a_person_within_the_grown_box():
    # A target 35 px wide found on part of a person at 3 m; the rest of him is a sliver
    # 20 px wide beside the box at his depth, and a second sliver stands at 4 m.
    box = np.array([[100, 50, 35, 150]], np.float32)
    z, gate, found = np.array([3000.0], np.float32), np.array([300.0], np.float32), np.array([True])
    cand = births.Candidates(
        box=np.array([[135, 50, 20, 150], [135, 50, 20, 150]], np.float32),
        confidence=np.array([0.9, 0.9], np.float32),
        depth=np.array([3000.0, 4000.0], np.float32),
    )
    ok = np.array([True, True])

    def widen(margin):
        grown = claim.grow(box, np.float32(margin))
        return births.reanchor(cand, ok, box, grown, z, gate, found, 0.5, np.float32(1.3))

    grows, union = widen(0.5)  # columns 82.5-152.5 hold 17.5 of the sliver's 20
    assert bool(grows[0])
    np.testing.assert_allclose(np.asarray(union[0]), [100, 50, 55, 150])
    grows, _ = widen(0.2)  # columns 93-142: 7 of 20, under half
    assert not bool(grows[0])
    far = births.Candidates(cand.box[1:], cand.confidence[1:], cand.depth[1:])
    grown = claim.grow(box, np.float32(0.5))
    grows, _ = births.reanchor(far, ok[1:], box, grown, z, gate, found, 0.5, np.float32(1.3))
    assert not bool(grows[0]), "a blob at another depth is someone else"
