"""Synthetic scenes with several people, and their ground truth with identities.

Each scene is a :class:`cpf_jax.synthetic.ScenarioSpec` whose walker is person 1 and whose
``kind="person"`` occluders are the others (``Occluder.identity``, default ``2 + k``;
occluders that share an identity are one person who leaves and comes back). Rendered by
:func:`cpf_jax.synthetic.make_sequence`, so frames, noise and the background are those of
every synthetic sequence::

    seq = make_people_sequence("two_crossing", seed=0)
    gt = people_truth(seq)        # [K, 9] rows (frame, id, x, y, w, h, 1, 1, visibility)

Ground-truth boxes are tight around each person's visible pixels (occluders, other people
and the frame's edge cut them), in the convention of ``cpf_jax.kernels.boxes``; frames and
pixels count from 0, as :func:`cpf_jax.io.mot.read_mot` returns them. ``visibility`` is the
share of the person's pixels (inside the frame, in front of the room) that nothing else
hides. Lengths in metres, times in seconds, as in ``ScenarioSpec``.
"""

from __future__ import annotations

import numpy as np

from cpf_jax.synthetic import Clothing, Occluder, ScenarioSpec, SyntheticSequence, make_sequence

__all__ = ["PEOPLE_SCENARIOS", "make_people_sequence", "people_truth", "person_ids"]

_BLUE = Clothing(shirt=(50, 72, 140), trousers=(40, 40, 46), hair=(45, 35, 28))
_BLUE_2 = Clothing(shirt=(56, 78, 150), trousers=(44, 44, 50), hair=(60, 45, 35))
_BLUE_3 = Clothing(shirt=(46, 66, 128), trousers=(38, 38, 44), hair=(35, 28, 22))
_GREEN = Clothing(shirt=(45, 120, 75), trousers=(60, 55, 50), hair=(70, 50, 35))
_YELLOW = Clothing(shirt=(205, 160, 50), trousers=(50, 50, 60), hair=(30, 25, 22))
_GREY = Clothing(shirt=(120, 120, 125), trousers=(40, 40, 45), hair=(70, 55, 40))
_WHITE = Clothing(shirt=(215, 215, 210), trousers=(55, 65, 100), hair=(50, 40, 30))


def _walker(z: float, x0: float, x1: float, t0: float, speed: float, clothing, **kw) -> Occluder:
    """A person walking across at depth ``z`` from ``x0`` to ``x1`` at ``speed`` from ``t0``,
    placed relative to the walker's first direction (``mirror_x``)."""
    return Occluder(
        size_m=(0.5, kw.pop("height", 1.78), 0.3),
        start_xz=(x0, z),
        end_xz=(x1, z),
        t0_s=t0,
        t1_s=t0 + abs(x1 - x0) / speed,
        kind="person",
        mirror_x=True,
        clothing=clothing,
        **kw,
    )


#: The multi-person scenes (10 frames/s, Kinect v2 view; the walker paces two lanes
#: ``lane_gap_m`` apart around ``distance_m`` from a seed-dependent start).
PEOPLE_SCENARIOS: dict[str, ScenarioSpec] = {
    # A second person in other clothes crosses the view nearer than the walker, the other
    # way: the two meet and the near one passes in front of the far one.
    "two_crossing": ScenarioSpec(
        n_frames=80,
        distance_m=3.2,
        clutter=4,
        occluders=(_walker(2.1, 2.1, -2.1, 0.5, 0.9, _GREY),),
    ),
    # Three people in look-alike blue tops: one crosses in front of the walker, one behind;
    # colour cannot tell them apart, depth and motion must.
    "three_walkers": ScenarioSpec(
        n_frames=100,
        distance_m=3.0,
        room_depth_m=5.2,
        clothing=_BLUE,
        clutter=4,
        occluders=(
            _walker(2.0, 2.1, -2.1, 0.5, 0.8, _BLUE_2),
            _walker(4.1, -3.2, 3.2, 2.5, 0.9, _BLUE_3, height=1.72),
        ),
    ),
    # A person crosses in front of the walker and out of view, then comes back the way he
    # left two and a half seconds later: one identity over two walks.
    "leave_return": ScenarioSpec(
        n_frames=110,
        distance_m=3.4,
        clutter=4,
        clothing=_BLUE,
        occluders=(
            _walker(2.2, -1.0, 2.2, 0.0, 0.9, _GREEN, identity=2),
            _walker(2.3, 2.2, -2.2, 6.0, 0.9, _GREEN, identity=2),
        ),
    ),
    # Three people enter together from one side, staggered in depth, and cross the view
    # in front of the walker: four people at once.
    "group_enter": ScenarioSpec(
        n_frames=90,
        distance_m=3.7,
        room_depth_m=5.0,
        clutter=4,
        clothing=_BLUE,
        occluders=(
            _walker(2.0, -2.1, 2.4, 1.0, 0.8, _GREEN),
            _walker(2.5, -2.5, 2.4, 1.0, 0.8, _YELLOW, height=1.7),
            _walker(3.0, -2.9, 2.4, 1.0, 0.8, _WHITE, height=1.84),
        ),
    ),
}


def make_people_sequence(
    name: str | ScenarioSpec, seed: int = 0, n_frames: int | None = None, **overrides
) -> SyntheticSequence:
    """Render a scene of :data:`PEOPLE_SCENARIOS` (or any spec) with
    :func:`cpf_jax.synthetic.make_sequence`; the result's ``name`` is the scene's."""
    if isinstance(name, str):
        if name not in PEOPLE_SCENARIOS:
            raise KeyError(f"unknown people scenario {name!r}; known: {sorted(PEOPLE_SCENARIOS)}")
        seq = make_sequence(PEOPLE_SCENARIOS[name], seed, n_frames, **overrides)
        return seq._replace(name=name)
    return make_sequence(name, seed, n_frames, **overrides)


def person_ids(seq: SyntheticSequence) -> np.ndarray:
    """The identities of a sequence's people, ascending: 1 (the walker) and those of its
    ``kind="person"`` occluders."""
    spec: ScenarioSpec = seq.meta["spec"]
    ident = seq.meta["occluder_identity"]
    return np.unique(
        [1, *(int(i) for i, oc in zip(ident, spec.occluders, strict=True) if oc.kind == "person")]
    )


def people_truth(seq: SyntheticSequence, min_pixels: int = 1) -> np.ndarray:
    """``[K, 9] float64`` rows ``(frame, id, x, y, w, h, 1, 1, visibility)`` of every person
    with at least ``min_pixels`` visible pixels in a frame, ordered by frame and id (module
    docstring). Occluders that share an identity in one frame give the union of their boxes."""
    spec: ScenarioSpec = seq.meta["spec"]
    rows = []
    n = len(seq.boxes)
    counts = seq.mask.reshape(n, -1).sum(axis=1)
    for t in range(n):
        if counts[t] >= min_pixels:
            vis = float(seq.meta["visible_fraction"][t])
            rows.append((t, 1, *seq.boxes[t], 1, 1, vis))
        per_id: dict[int, list] = {}
        for k, oc in enumerate(spec.occluders):
            if oc.kind != "person" or seq.meta["occluder_pixels"][t, k] < min_pixels:
                continue
            ident = int(seq.meta["occluder_identity"][k])
            per_id.setdefault(ident, []).append(k)
        for ident in sorted(per_id):
            ks = per_id[ident]
            b = seq.meta["occluder_boxes"][t, ks]
            x0, y0 = b[:, 0].min(), b[:, 1].min()
            x1, y1 = (b[:, 0] + b[:, 2]).max(), (b[:, 1] + b[:, 3]).max()
            vis = float(seq.meta["occluder_visible_fraction"][t, ks].max())
            rows.append((t, ident, x0, y0, x1 - x0, y1 - y0, 1, 1, vis))
    return np.asarray(rows, np.float64).reshape(-1, 9)
