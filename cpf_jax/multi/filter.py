"""The multi-person tracker: one RGB-D box filter per slot, in the library's one filter shape.

::

    config = MultiConfig()
    filt = build_multi_filter(config)
    params = default_multi_params(config)
    state = filt.init(params, key, frame, None, Context(background=bg))  # or [M, 4] boxes
    state, info = filt.step(params, key, state, frame)  # info.box [K, 4], info.ident [K]

A fixed number of slots (``MultiConfig.max_targets``) each hold an RGB-D box filter state
(``cpf_jax.rgbd``), stacked ``[K, ...]``; static shapes throughout, so a sequence is one
``lax.scan`` and many are a ``vmap`` or ``batch.run_sharded``. One ``step`` is::

    claim      who owns each pixel, and each slot's depth image          (claim.py)
    track      every slot's RGB-D step on its own depth image (vmap)    (cpf_jax.rgbd)
    judge      hits (own pixels), misses, exclusion, drops, losses, deaths (claim, tracks)
    confirm    tentative targets confirmed, re-identified or named       (tracks.py, reid.py)
    remember   box, velocity, depth and body colours of found targets    (tracks.py)
    birth      the detector on unclaimed foreground, new tentative slots (births.py)

``info.box`` is each slot's reported box and ``info.lost`` whether it is not reported
this frame: only confirmed targets that their filter found are reported, under
``info.ident``. ``init`` needs ``Context.background`` (the scene without people: the
detector and every slot's foreground are taken against it); it starts the given boxes
as confirmed targets (identities 1, 2, ...) and runs the birth stage on the first frame.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.filter import Context, Filter, memoised_build
from cpf_jax.kernels.background import Background
from cpf_jax.multi import births, claim, tracks
from cpf_jax.multi.config import ACTIVE, FREE, TENTATIVE, MultiConfig
from cpf_jax.multi.params import MultiParams
from cpf_jax.rgbd.depth import depth_tolerance, mean_known_depth
from cpf_jax.rgbd.filter import build_rgbd_filter
from cpf_jax.rgbd.observe import as_background, body_histogram, observe
from cpf_jax.types import Frame, check_frame

__all__ = [
    "MultiState",
    "MultiInfo",
    "multi_init",
    "multi_step",
    "build_multi_filter",
    "step_slots",
    "add_births",
    "union",
    "behind",
    "coasting_box",
    "coast",
    "people_rows",
    "track_people",
]


class MultiState(NamedTuple):
    slots: object  # RGBDState, every leaf stacked [K, ...]
    tracks: tracks.Tracks
    next_id: Array  # int32, the next new identity
    frame: Array  # int32, frames seen (the first is 0)
    background: Background  # the scene without people


class MultiInfo(NamedTuple):
    box: Array  # [K, 4] xywh, each slot's reported box
    lost: Array  # [K] bool: not reported this frame (not confirmed, or not found)
    ess: Array  # [K]
    log_evidence: Array  # [K]
    estimate: Array  # [K, 4] xywh, each slot's weighted-mean box
    windowed: Array  # [K] bool
    ident: Array  # [K] int32 identity of each slot (0: none)
    status: Array  # [K] int32 (config.FREE, TENTATIVE, ACTIVE, LOST)
    found: Array  # [K] bool: the slot's filter found its target (any status)
    evidence: Array  # [K] share of its estimate its own unclaimed pixels fill (claim.evidence)
    events: tracks.Events


def _slot_filter(config: MultiConfig) -> Filter:
    return build_rgbd_filter(config.rgbd)


def _colours(config: MultiConfig, obs, boxes: Array) -> Array:
    """``[K, F]`` foreground colour histograms of ``boxes [K, 4]`` in one observation."""
    return jax.vmap(lambda b: body_histogram(config.rgbd, obs, b)[0])(boxes)


def _target_depths(slots) -> Array:
    return mean_known_depth(slots.depth.depth)


def _where_slots(mask: Array, new, old):
    """Per slot ``mask [K]``: the leaves of ``new`` where True, of ``old`` elsewhere."""

    def pick(a, b):
        m = mask.reshape(mask.shape + (1,) * (a.ndim - 1))
        return jnp.where(m, a, b)

    return jax.tree_util.tree_map(pick, new, old)


def _init_slots(config, params: MultiParams, key, frame: Frame, boxes: Array, background):
    """RGB-D states ``[D, ...]`` started on ``boxes [D, 4]`` of ``frame``."""
    filt = _slot_filter(config)
    keys = jax.random.split(key, boxes.shape[0])
    context = Context(background=background)
    return jax.vmap(lambda k, b: filt.init(params.rgbd, k, frame, b, context))(keys, boxes)


def step_slots(
    config: MultiConfig, params: MultiParams, keys: Array, slots, colour, depths, live: Array
):
    """Every slot's RGB-D step on ``Frame(colour, depths[k])``: ``(slots, infos)`` stacked
    ``[K, ...]``. Under ``lax.map`` (``MultiConfig.slot_loop``) a slot that is not ``live
    [K]`` is not stepped (its info says lost); under ``vmap`` every slot is."""
    filt = _slot_filter(config)

    def one(key, state, depth):
        return filt.step(params.rgbd, key, state, Frame(colour, depth))

    if config.slot_loop == "vmap":
        return jax.vmap(one)(keys, slots, depths)
    first = jax.tree_util.tree_map(lambda a: a[0], (keys, slots, depths))
    shapes = jax.eval_shape(one, *first)[1]

    def idle(key, state, depth):
        info = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        return state, info._replace(lost=jnp.ones((), bool))

    def slot(args):
        go, key, state, depth = args
        return jax.lax.cond(go, one, idle, key, state, depth)

    return jax.lax.map(slot, (live, keys, slots, depths))


def union(a: Array, b: Array) -> Array:
    """The smallest ``[..., 4]`` xywh boxes holding both ``a`` and ``b``."""
    x0 = jnp.minimum(a[..., 0], b[..., 0])
    y0 = jnp.minimum(a[..., 1], b[..., 1])
    x1 = jnp.maximum(a[..., 0] + a[..., 2], b[..., 0] + b[..., 2])
    y1 = jnp.maximum(a[..., 1] + a[..., 3], b[..., 1] + b[..., 3])
    return jnp.stack([x0, y0, x1 - x0, y1 - y0], axis=-1)


def add_births(
    config: MultiConfig,
    params: MultiParams,
    key: Array,
    state: MultiState,
    frame: Frame,
    obs,
    found: Array,
    boxes: Array,
) -> tuple[MultiState, tuple[Array, Array]]:
    """The birth stage (``births.py``): the detector on the foreground that no confirmed or
    tentative target explains; new tentative targets in free slots, and found targets
    started again on a larger box when a candidate is the rest of one of them
    (``births.reanchor``). ``found [K]``: the slots whose filter found its target this
    frame, ``boxes [K, 4]`` where (the estimate and the reported box). Returns the state,
    which slots started a target ``[K]`` and which of those evicted a lost target
    ``[K]``."""
    slots, tr = state.slots, state.tracks
    z = _target_depths(slots)
    gate = depth_tolerance(params.rgbd, z)
    tracked = found & ((tr.status == ACTIVE) | (tr.status == TENTATIVE))
    grown = claim.grow(boxes, params.claim.margin)
    mine = claim.claimed_mask(frame.depth, grown, z, gate, tracked)
    # Is a blob part of a tracked person? Both depths measured on this frame.
    seen_z = claim.box_depths(config.rgbd, obs, boxes)
    seen_gate = depth_tolerance(params.rgbd, seen_z)
    cand = births.detect_candidates(
        config.detect, config.max_births, obs.foreground & ~mine, frame.depth, config.device_births
    )
    sure = (cand.confidence >= params.life.birth_confidence) & (cand.box[:, 2] >= 1.0)
    aspect = cand.box[:, 2] / jnp.maximum(cand.box[:, 3], 1.0)
    share = params.claim.duplicate_overlap
    widen, wider = births.reanchor(
        cand,
        sure & (aspect >= params.claim.reanchor_aspect),
        boxes,
        claim.grow(boxes, params.claim.reanchor_margin),
        seen_z,
        seen_gate,
        tracked,
        share,
        params.claim.reanchor_growth,
    )
    ok = sure & (aspect >= params.life.birth_aspect)
    ok = ok & ~births.part_of_found(cand, grown, seen_z, seen_gate, tracked, share)
    take = births.allocate(ok, tr.status, tr.missed, params.life.forget_after)
    started = take >= 0
    restart = started | widen
    start_box = jnp.where(started[:, None], cand.box[jnp.maximum(take, 0)], wider)

    def start(slots):
        # The new boxes' templates see no depth where another tracked person is.
        others = claim.claimed_mask(frame.depth, grown, z, gate, tracked & ~widen)
        depth = jnp.where(others, 0, frame.depth).astype(frame.depth.dtype)
        fresh = _init_slots(
            config, params, key, Frame(frame.colour, depth), start_box, state.background
        )
        return _where_slots(restart, fresh, slots)

    slots = jax.lax.cond(jnp.any(restart), start, lambda s: s, slots)
    evicted = started & (tr.status != 0) & (tr.ident > 0)
    k = tr.status.shape[0]
    new_tracks = tracks.empty_tracks(k, tr.appearance.shape[1])._replace(
        status=jnp.full((k,), TENTATIVE, jnp.int32),
        hits=jnp.ones((k,), jnp.int32),
        born=jnp.full((k,), state.frame, jnp.int32),
        box=start_box,
        depth=cand.depth[jnp.maximum(take, 0)],
    )
    tr = _where_slots(started, new_tracks, tr)
    return state._replace(slots=slots, tracks=tr), (started, evicted)


def multi_init(
    config: MultiConfig,
    params: MultiParams,
    key: Array,
    frame: Frame,
    boxes: Array | None = None,
    context: Context | None = None,
) -> MultiState:
    """Slots on ``frame``: ``boxes [M, 4]`` (``M <= max_targets``; None: none) as confirmed
    targets with identities ``1..M``, then the birth stage on the rest of the frame."""
    check_frame(frame, needs_depth=True)
    if config.scene_width is not None:
        background = births.frame_scene(config, frame)
    elif context is None or context.background is None:
        raise ValueError(
            "the multi-person tracker needs Context(background=...): the scene without "
            "people, against which it finds them (kernels.background.median_background), "
            "or MultiConfig.scene_width to read it in each frame"
        )
    else:
        background = as_background(context.background, frame)
    k = config.max_targets
    height, width = frame.colour.shape[:2]
    m = 0 if boxes is None else int(np.shape(boxes)[0])
    if m > k:
        raise ValueError(f"{m} initial boxes but max_targets is {k}")
    k_slots, k_birth = jax.random.split(key)
    # Free slots hold a small box in the middle of the frame: under vmap every slot takes
    # the fast histogram path only when every slot's cloud fits its window.
    dummy = jnp.array([width / 2 - 8, height / 2 - 16, 16, 32], jnp.float32)
    start = jnp.tile(dummy, (k, 1))
    if m:
        start = start.at[:m].set(jnp.asarray(boxes, jnp.float32).reshape(m, 4))
    slots = _init_slots(config, params, k_slots, frame, start, background)
    n_colours = slots.body.histogram.shape[-1]
    given = jnp.arange(k) < m
    tr = tracks.empty_tracks(k, n_colours)._replace(
        status=jnp.where(given, ACTIVE, 0).astype(jnp.int32),
        ident=jnp.where(given, jnp.arange(1, k + 1), 0).astype(jnp.int32),
        box=jnp.where(given[:, None], start, 0.0),
        depth=jnp.where(given, _target_depths(slots), 0.0),
        appearance=jnp.where(given[:, None], slots.body.histogram, 0.0),
    )
    state = MultiState(slots, tr, jnp.int32(m + 1), jnp.int32(0), background)
    obs = observe(config.rgbd, params.rgbd.foreground, frame, background)
    state, _ = add_births(config, params, k_birth, state, frame, obs, given, slots.estimate)
    return state


def behind(
    life, status: Array, seen_now: Array, visible: claim.Visible, looks: Array | None = None
) -> Array:
    """``[K] bool``: confirmed targets not seen by their filters but seen behind nearer
    targets (``tracks`` module docstring): at least ``life.hidden_share`` of the box it
    claims (``visible``: ``claim.visible_part`` of it) is claimed by nearer targets, the
    target's own pixels fill ``min_evidence`` of the rest, and the body colours of what
    shows are within ``life.behind_appearance`` of the remembered ones (``looks [K]``, the
    Bhattacharyya distance; None: not checked)."""
    shown = (visible.evidence >= life.min_evidence) & (visible.box[:, 3] > 0)
    if looks is not None:
        shown = shown & (looks <= life.behind_appearance)
    return (status == ACTIVE) & ~seen_now & (visible.hidden >= life.hidden_share) & shown


def seen_behind(
    config: MultiConfig,
    life,
    obs,
    depth: Array,
    owner: Array,
    reach: Array | None,
    tr,
    grown: Array,
    z: Array,
    gate: Array,
    seen_now: Array,
) -> tuple[Array, Array]:
    """``([K] bool, [K, 4] xywh)``: the targets seen behind nearer ones (``behind``, on
    ``claim.visible_part`` of their ``grown`` predicted boxes) and the tight box of what
    shows of each; it runs only when ``life.hidden_share`` can be reached (at most 1)."""
    visible = claim.visible_part(obs.foreground, depth, owner, grown, z, gate, reach)
    looks = tracks.seen_distance(_colours(config, obs, visible.box), tr)
    looks = jnp.where(jnp.sum(tr.appearance, axis=-1) > 0, looks, 0.0)
    return behind(life, tr.status, seen_now, visible, looks), visible.box


def coasting_box(predicted: Array, shown: Array) -> Array:
    """``[K, 4]`` xywh: where a target seen behind another is, its ``predicted`` box moved
    to the columns of what shows of him (``shown``): the head above an occluder's shoulder
    is over the middle of the body, while the prediction carries the motion of frames
    before he turned."""
    cx = shown[:, 0] + 0.5 * shown[:, 2]
    return predicted.at[:, 0].set(cx - 0.5 * predicted[:, 2])


def coast(slots, mask: Array, box: Array):
    """The slots' clouds ``mask [K]`` moved so that their estimate is centred on ``box [K,
    4]`` (xywh): a filter whose target is hidden finds only the occluder or the floor, so
    it is held at the predicted place."""
    shift = (box[:, :2] + 0.5 * box[:, 2:]) - (slots.estimate[:, :2] + 0.5 * slots.estimate[:, 2:])
    shift = jnp.where(mask[:, None], shift, 0.0)
    cloud = slots.cloud._replace(
        particles=slots.cloud.particles.at[..., :2].add(shift[:, None]),
        previous=slots.cloud.previous.at[..., :2].add(shift[:, None]),
    )
    return slots._replace(cloud=cloud, estimate=slots.estimate.at[:, :2].add(shift))


def _judge(
    config, params: MultiParams, state: MultiState, infos, obs, boxes, seen_now, hidden
) -> tuple:
    """Hits and misses, exclusion, and the status changes but confirmation; ``boxes [K,
    4]``: where each slot's target is (the estimate and the reported box); ``seen_now
    [K]``: the slots whose filter reports a box that its target's own pixels fill enough
    of (``claim.evidence``); ``hidden [K]``: the targets seen only behind nearer ones
    (``behind``)."""
    tr = state.tracks
    # The templates' depths: a box's measured depth is the occluder's while one passes.
    z = _target_depths(state.slots)
    gate = depth_tolerance(params.rgbd, z)
    seen = tracks.seen_distance(_colours(config, obs, infos.box), tr)
    appearance = params.reid.appearance
    found = tracks.verified(seen_now, tr, seen, params.life.verify_after, appearance) | hidden
    tr = tracks.count_frames(tr, found)
    loser = tracks.duplicates(params.claim.duplicate_overlap, tr, found, boxes, z, gate)
    tr, events = tracks.advance(params.life, tr, found, loser, seen, appearance)
    return tr, events, found & ~loser


def multi_step(
    config: MultiConfig, params: MultiParams, key: Array, state: MultiState, frame: Frame
) -> tuple[MultiState, MultiInfo]:
    """One frame: claim, track, judge, confirm, remember, birth (module docstring)."""
    check_frame(frame, needs_depth=True)
    k = config.max_targets
    k_slots, k_birth = jax.random.split(key)
    tr = state.tracks
    if config.scene_width is not None:
        state = state._replace(background=births.frame_scene(config, frame))
    # claim
    pred = claim.predict_targets(params.rgbd, state.slots)
    claiming = (tr.status == ACTIVE) | (tr.status == TENTATIVE)
    grown = claim.grow(pred.box, params.claim.margin)
    owner = claim.claim_owner(frame.depth, grown, pred.depth, pred.gate, claiming)
    depths = claim.slot_depths(
        params.rgbd,
        frame.depth,
        owner,
        pred.depth,
        pred.gate,
        params.claim.fake_margins,
        state.background.depth,
    )
    # track
    keys = jax.random.split(k_slots, k)
    live = tr.status != FREE
    slots, infos = step_slots(config, params, keys, state.slots, frame.colour, depths, live)
    state = state._replace(slots=slots)
    obs = observe(config.rgbd, params.rgbd.foreground, frame, state.background)
    # judge
    reach = None
    if config.blob_evidence:
        reach = claim.blob_reach(obs.foreground, frame.depth, owner, pred.depth, pred.gate)
    evidence = claim.evidence(
        obs.foreground, frame.depth, owner, infos.estimate, pred.depth, pred.gate, reach
    )
    seen_now = ~infos.lost & (evidence >= params.life.min_evidence)
    hidden, shown = jax.lax.cond(
        params.life.hidden_share <= 1.0,
        functools.partial(seen_behind, config, params.life, obs, frame.depth, owner, reach, tr),
        lambda *_: (jnp.zeros_like(seen_now), jnp.zeros_like(grown)),
        grown,
        pred.depth,
        pred.gate,
        seen_now,
    )
    # A target seen behind another is reported with what shows of him, and coasts.
    infos = infos._replace(box=jnp.where(hidden[:, None], shown, infos.box))
    slots = coast(slots, hidden, coasting_box(pred.box, shown))
    state = state._replace(slots=slots)
    boxes = jnp.where(hidden[:, None], shown, union(infos.estimate, infos.box))
    tr, events, found = _judge(config, params, state, infos, obs, boxes, seen_now, hidden)
    # confirm
    z = _target_depths(slots)
    tr, next_id, new, old = tracks.confirm(
        params.life, params.reid, tr, state.next_id, slots.body.histogram, z, infos.box
    )
    events = events._replace(confirmed=new, reidentified=events.reidentified | old)
    # remember
    w = jnp.exp(slots.cloud.log_weights)
    velocity = jnp.einsum("kn,knd->kd", w, slots.cloud.particles[..., 2:4])
    unoccluded = (jnp.max(infos.vote, axis=-1) < 0.1) & ~hidden
    tr = tracks.remember(
        tr, found, unoccluded, infos.box, velocity, z, slots.body.histogram, slots.depth.velocity
    )
    # birth
    state = state._replace(tracks=tr, next_id=next_id)
    state, (started, evicted) = add_births(config, params, k_birth, state, frame, obs, found, boxes)
    events = events._replace(
        started=started,
        died=events.died | evicted,
        died_ident=jnp.where(evicted, tr.ident, events.died_ident),
    )
    tr = state.tracks
    reported = found & (tr.status == ACTIVE) & ~started
    info = MultiInfo(
        box=infos.box,
        lost=~reported,
        ess=infos.ess,
        log_evidence=infos.log_evidence,
        estimate=infos.estimate,
        windowed=infos.windowed,
        ident=tr.ident,
        status=tr.status,
        found=found,
        evidence=evidence,
        events=events,
    )
    return state._replace(frame=state.frame + 1), info


@memoised_build
def build_multi_filter(config: MultiConfig) -> Filter:
    """The multi-person tracker's ``Filter(init, step)`` for a static ``config``; ``init``
    takes ``[M, 4]`` boxes (or None) and reads ``context.background``."""

    def init(params, key, frame, boxes=None, context=None):
        return multi_init(config, params, key, frame, boxes, context)

    def step(params, key, state, frame):
        return multi_step(config, params, key, state, frame)

    return Filter(init, step)


def people_rows(infos: MultiInfo, first_frame: int = 1) -> np.ndarray:
    """``[R, 7]`` rows ``(frame, id, x, y, w, h, conf)`` of the reported boxes of stacked
    infos ``[T, K, ...]`` (frame ``first_frame + t``), the form of ``cpf_jax.io.mot``."""
    box = np.asarray(infos.box)
    lost = np.asarray(infos.lost)
    ident = np.asarray(infos.ident)
    t, k = np.nonzero(~lost)
    rows = np.column_stack([t + first_frame, ident[t, k], box[t, k], np.ones(len(t))]).astype(
        np.float64
    )
    return rows.reshape(-1, 7)


def track_people(
    filt: Filter, params, key: Array, frames: Frame, context: Context, boxes=None
) -> tuple[MultiState, MultiInfo]:
    """The tracker over ``frames [T, ...]`` as one ``lax.scan`` (``filter.track`` with the
    multi-person ``init``): ``(final state, infos [T - 1, K, ...])`` of frames ``1..T-1``."""
    from cpf_jax.filter import track

    return track(filt, params, key, frames, boxes, context)
