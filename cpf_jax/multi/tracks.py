"""The targets' lives: confirmation, loss, re-identification, death, and exclusion.

Each slot holds a status (``config.FREE``, ``TENTATIVE``, ``ACTIVE``, ``LOST``), an
identity (0 until confirmed), counts of the frames in a row its filter found or missed
its target, and what re-identification remembers of the target: its last box, velocity,
depth and speed in depth, and the body colours of its last unoccluded frame (the RGB-D
filter's body template, ``rgbd.templates``). Counts are in frames; ``LifeParams`` holds
the thresholds.

* A slot's target is found when its filter reports a box and the target's own pixels fill
  at least ``min_evidence`` of the filter's estimate (``claim.evidence``: foreground at its
  depth that no other target claims, nor joins at its depth to its claimed pixels,
  ``claim.blob_reach``, with ``MultiConfig.blob_evidence``); a target whose filter lost
  him behind a nearer one is missed, not found on the floor or on a farther person left
  in its box or on the rest of a person another target holds, so its misses count.
* A confirmed target that its filter misses is still found (with ``hidden_share`` at most
  1; the default, above 1, leaves it missed) when nearer targets claim at
  least ``hidden_share`` of the box it claims (its predicted box grown by
  ``claim.margin``) and its own pixels fill ``min_evidence`` of the rest
  (``claim.visible_part``: his head above the shoulder of the person in front), their body
  colours within ``behind_appearance`` of the remembered ones; it is
  reported with the tight box of what shows of him, and its filter coasts at the
  predicted place, in the columns of what shows (``filter.coasting_box``, ``coast``).
* A tentative target is confirmed after ``confirm`` found frames in a row (and takes an
  identity, ``reid.py``), and dropped after ``tentative_misses`` missed ones.
* A confirmed target missed ``lost_after`` frames in a row is lost: it is no longer
  reported, claims no pixels, and is kept ``forget_after`` missed frames for
  re-identification, then dies (its identity is never used again).
* A target missed ``verify_after`` frames or more is found again by its filter only where
  the body colours of the box it reports are within ``reid.appearance`` of the remembered
  ones (``verified``); a lost target found again for ``confirm`` frames is confirmed again
  under its identity.
* Exclusion: two found targets whose boxes share ``claim.duplicate_overlap`` of the
  narrower one's columns at one depth are one person (``claim.same_place``); the
  confirmed (then the older) keeps him, the other is dropped (a tentative) or lost (a
  confirmed one).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels.histogram import bhattacharyya
from cpf_jax.multi.claim import same_place
from cpf_jax.multi.config import ACTIVE, FREE, LOST, TENTATIVE
from cpf_jax.multi.params import LifeParams, ReidParams
from cpf_jax.multi.reid import reid_cost, reid_match

__all__ = [
    "Tracks",
    "Events",
    "empty_tracks",
    "no_events",
    "verified",
    "count_frames",
    "duplicates",
    "advance",
    "confirm",
    "remember",
]


class Tracks(NamedTuple):
    status: Array  # [K] int32 (config.FREE, TENTATIVE, ACTIVE, LOST)
    ident: Array  # [K] int32 identity, 0 until confirmed
    hits: Array  # [K] int32 frames in a row the target was found
    missed: Array  # [K] int32 frames in a row it was not
    born: Array  # [K] int32 frame index of its birth (older targets win exclusion)
    box: Array  # [K, 4] xywh, its last reported box
    velocity: Array  # [K, 2] px per frame, its box centre's last velocity
    depth: Array  # [K] mm, its last depth (0: unknown)
    appearance: Array  # [K, F] body colours of its last unoccluded frame
    depth_speed: Array  # [K] mm per frame, the speed of its depth when last found


class Events(NamedTuple):
    """What happened to each slot this frame (``[K] bool``), for logs and viewers."""

    started: Array  # a tentative target started (a detection)
    confirmed: Array  # confirmed under a new identity
    reidentified: Array  # confirmed under an old identity (re-identified)
    lost: Array  # a confirmed target was lost
    died: Array  # an identity was forgotten (``died_ident``)
    died_ident: Array  # [K] int32 the identity that died in the slot (0: none)


def empty_tracks(k: int, n_colours: int) -> Tracks:
    """``k`` free slots with body colour memories of ``n_colours`` bins."""
    zi = jnp.zeros((k,), jnp.int32)
    return Tracks(
        zi,
        zi,
        zi,
        zi,
        zi,
        jnp.zeros((k, 4), jnp.float32),
        jnp.zeros((k, 2), jnp.float32),
        jnp.zeros((k,), jnp.float32),
        jnp.zeros((k, n_colours), jnp.float32),
        jnp.zeros((k,), jnp.float32),
    )


def no_events(k: int) -> Events:
    no = jnp.zeros((k,), bool)
    return Events(no, no, no, no, no, jnp.zeros((k,), jnp.int32))


def verified(
    found: Array, tracks: Tracks, seen_distance: Array, after: Array, appearance: Array
) -> Array:
    """``found [K]`` but for confirmed or lost targets missed ``after`` frames or more whose
    reported box's body colours are farther than ``appearance`` from the remembered ones
    (``seen_distance [K]``; no memory yet: no check): a filter that searched for its lost
    target and found someone else has not found him."""
    known = jnp.sum(tracks.appearance, axis=-1) > 0
    searched = ((tracks.status == ACTIVE) | (tracks.status == LOST)) & (
        tracks.missed.astype(jnp.float32) >= after
    )
    return found & ~(searched & known & (seen_distance > appearance))


def count_frames(tracks: Tracks, found: Array) -> Tracks:
    """Hits and misses in a row of the slots' filters (``found [K] bool``)."""
    hits = jnp.where(found, tracks.hits + 1, 0)
    missed = jnp.where(found, 0, tracks.missed + 1)
    return tracks._replace(hits=hits, missed=missed)


def duplicates(
    share: Array, tracks: Tracks, found: Array, boxes: Array, depth: Array, gate: Array
) -> Array:
    """``[K] bool``: found targets that are one person with a found target of higher
    priority: boxes ``[K, 4]`` sharing ``share`` of their columns at one depth
    (``claim.same_place``). Confirmed targets go before tentative ones, then those found
    in more frames in a row (a target that finds someone after missing its own is the
    likelier mistake), then the older, then the lower slot."""
    k = tracks.status.shape[0]
    live = found & ((tracks.status == ACTIVE) | (tracks.status == TENTATIVE))
    pair = same_place(boxes, depth, gate, boxes, depth, gate, share)
    pair = pair & live[:, None] & live[None] & ~jnp.eye(k, dtype=bool)
    return jnp.any(pair & _goes_before(tracks), axis=1)


def _goes_before(tracks: Tracks) -> Array:
    """``[K, K] bool``: slot ``j`` (columns) goes before slot ``i`` (rows) in exclusion."""
    key = (
        (tracks.status == ACTIVE).astype(jnp.int32),
        tracks.hits,
        -tracks.born,
        -jnp.arange(tracks.status.shape[0], dtype=jnp.int32),
    )
    before = jnp.zeros((len(tracks.hits),) * 2, bool)
    tied = jnp.ones_like(before)
    for v in key:  # lexicographic: the first key that differs decides
        before = before | (tied & (v[None] > v[:, None]))
        tied = tied & (v[None] == v[:, None])
    return before


def advance(
    params: LifeParams,
    tracks: Tracks,
    found: Array,
    loser: Array,
    seen_distance: Array,
    reid_appearance: Array,
) -> tuple[Tracks, Events]:
    """The status changes of the module docstring but confirmation: tentative targets
    dropped, confirmed ones lost, lost ones found again (``seen_distance [K]``: the body
    colours in the reported box against the remembered ones) or forgotten."""
    s, m = tracks.status, tracks.missed.astype(jnp.float32)
    hits = tracks.hits.astype(jnp.float32)
    drop = (s == TENTATIVE) & ((m >= params.tentative_misses) | loser)
    lose = (s == ACTIVE) & ((m >= params.lost_after) | loser)
    back = (s == LOST) & found & ~loser & (hits >= params.confirm)
    back = back & (seen_distance <= reid_appearance)
    die = (s == LOST) & ~back & (m >= params.forget_after)
    status = jnp.where(drop | die, FREE, jnp.where(lose, LOST, jnp.where(back, ACTIVE, s)))
    # A confirmed target that loses a duplicate counts as missed since it was lost.
    missed = jnp.where(
        lose & loser, jnp.maximum(tracks.missed, params.lost_after.astype(jnp.int32)), tracks.missed
    )
    ident = jnp.where(drop | die, 0, tracks.ident)
    events = no_events(s.shape[0])._replace(
        reidentified=back, lost=lose, died=die, died_ident=jnp.where(die, tracks.ident, 0)
    )
    return tracks._replace(status=status.astype(jnp.int32), ident=ident, missed=missed), events


def confirm(
    life: LifeParams,
    reid: ReidParams,
    tracks: Tracks,
    next_id: Array,
    appearance: Array,
    depth: Array,
    box: Array,
) -> tuple[Tracks, Array, Array, Array]:
    """Confirm the tentative targets found ``confirm`` frames in a row: each takes the
    identity of the lost or hidden target it is re-identified as (``reid.py``; that slot
    is freed) or a new one. Returns the tracks, the next free identity and which slots
    were confirmed ``[K]`` under a new and under an old identity."""
    s = tracks.status
    ready = (s == TENTATIVE) & (tracks.hits.astype(jnp.float32) >= life.confirm)
    pool = (s == LOST) | ((s == ACTIVE) & (tracks.missed > 0))
    match = reid_match(reid_cost(reid, appearance, depth, box, ready, tracks, pool))
    old = ready & (match >= 0)
    new = ready & ~old
    rank = jnp.cumsum(new.astype(jnp.int32)) - 1
    ident = jnp.where(old, tracks.ident[jnp.maximum(match, 0)], tracks.ident)
    ident = jnp.where(new, next_id + rank, ident)
    k = s.shape[0]
    taken = jnp.zeros((k,), bool).at[jnp.where(old, match, k)].set(True, mode="drop")
    status = jnp.where(ready, ACTIVE, jnp.where(taken, FREE, s))
    ident = jnp.where(taken & ~ready, 0, ident)
    tracks = tracks._replace(status=status.astype(jnp.int32), ident=ident.astype(jnp.int32))
    # The re-identified keep the old memory until their own first unoccluded frame.
    src = jnp.where(old, match, jnp.arange(k))
    tracks = tracks._replace(appearance=tracks.appearance[src])
    return tracks, next_id + jnp.sum(new.astype(jnp.int32)), new, old


def remember(
    tracks: Tracks,
    found: Array,
    unoccluded: Array,
    box: Array,
    velocity: Array,
    depth: Array,
    appearance: Array,
    depth_velocity: Array,
) -> Tracks:
    """What re-identification remembers of each confirmed target found this frame: its
    box, velocity, depth and speed in depth (``depth_velocity [K]`` mm per frame), and its
    body colours when no cell is occluded."""
    ok = found & (tracks.status == ACTIVE)
    colours = ok & unoccluded
    return tracks._replace(
        box=jnp.where(ok[:, None], box, tracks.box),
        velocity=jnp.where(ok[:, None], velocity, tracks.velocity),
        depth=jnp.where(ok & (depth > 0), depth, tracks.depth),
        depth_speed=jnp.where(ok, jnp.abs(depth_velocity), tracks.depth_speed),
        appearance=jnp.where(colours[:, None], appearance, tracks.appearance),
    )


def seen_distance(appearance_now: Array, tracks: Tracks) -> Array:
    """``[K]`` Bhattacharyya distance of the body colours seen now to the remembered ones."""
    return bhattacharyya(appearance_now, tracks.appearance)
