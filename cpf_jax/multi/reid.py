"""Re-identification: a newly confirmed target taken for a lost or hidden one.

When a tentative target is confirmed, it is matched against the pool of confirmed targets
not seen now (lost, or confirmed and missed in the last frames) by one minimum-cost
assignment (``kernels.assignment.linear_assignment``, in the jitted step)::

    cost = d_app + weight_depth (dz / sz)^2 + weight_reach (dc / sc)^2

with ``d_app`` the Bhattacharyya distance of the body colours (the new target's body
template against the one remembered from the old target's last unoccluded frames), ``dz``
the depth difference against ``sz = depth + (depth_speed + |v_z|) m`` (``v_z`` the old
target's depth velocity when last seen: out of sight, a fast walker may be that much
farther, or nearer once he turns, for every frame; the depth is not extrapolated) and
``dc`` the distance of the box centres (the old box moved by its velocity for at most
``EXTRAPOLATE`` frames) against ``sc = (reach + reach_speed m) h``, ``m`` the old target's
missed frames and ``h`` its box height. A pair beyond any of the three gates (``d_app >
appearance``, ``dz > sz``, ``dc > sc``) is forbidden. A matched new target takes the old
identity; the others get new ones.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels.assignment import linear_assignment
from cpf_jax.kernels.histogram import bhattacharyya
from cpf_jax.multi.params import ReidParams

__all__ = ["EXTRAPOLATE", "reid_cost", "reid_match"]

#: Frames of constant velocity an old target's box is moved by at most (a person out of
#: sight may stop or turn round).
EXTRAPOLATE = 10.0


def reid_cost(
    params: ReidParams,
    appearance: Array,
    depth: Array,
    box: Array,
    rows: Array,
    memory,
    pool: Array,
) -> Array:
    """``[K, K]`` cost of taking new target ``i`` (``rows [K] bool``; body colours
    ``appearance [K, F]``, ``depth [K]`` mm, ``box [K, 4]`` xywh) for old target ``j``
    (``pool [K] bool``, remembered in ``memory``: a ``tracks.Tracks``), ``inf`` where
    forbidden (module docstring)."""
    d_app = bhattacharyya(appearance[:, None], memory.appearance[None])  # [K, K]
    missed = memory.missed.astype(jnp.float32)[None]
    dz = jnp.abs(depth[:, None] - memory.depth[None])
    sz = params.depth + (params.depth_speed + memory.depth_speed[None]) * missed
    centre = box[:, :2] + 0.5 * box[:, 2:]
    old = memory.box[:, :2] + 0.5 * memory.box[:, 2:]
    old = (
        old + memory.velocity * jnp.minimum(memory.missed.astype(jnp.float32), EXTRAPOLATE)[:, None]
    )
    dc = jnp.linalg.norm(centre[:, None] - old[None], axis=-1)
    sc = (params.reach + params.reach_speed * missed) * jnp.maximum(memory.box[None, :, 3], 1.0)
    cost = d_app + params.weight_depth * (dz / sz) ** 2 + params.weight_reach * (dc / sc) ** 2
    known = (depth[:, None] > 0) & (memory.depth[None] > 0)
    allowed = (d_app <= params.appearance) & ((dz <= sz) | ~known) & (dc <= sc)
    allowed = allowed & rows[:, None] & pool[None]
    return jnp.where(allowed, cost, jnp.inf)


def reid_match(cost: Array) -> Array:
    """``[K] int32``: the old target each new one takes, -1 for none (a minimum-cost
    assignment of ``cost [K, K]``)."""
    return linear_assignment(cost).row_to_col
