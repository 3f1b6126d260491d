"""Batch runs spread over devices (SPEC C8): many seeds, sequences or settings at once.

Usage::

    from cpf_jax.batch import run_sharded, track_sharded

    boxes, lost = track_sharded(filt, params, keys, frames, box)  # [K, T, 4]; keys spread
    # anything else: batch a pytree and share the rest, e.g. many sequences at once
    one = lambda item: track_boxes(filt, params, *item)
    boxes, lost = run_sharded(one, (keys, frames_batch, boxes0))

``run_sharded(fn, batched, *shared)`` applies ``fn(item, *shared)`` to every item
along the leading axis of the pytree ``batched``. The items are split into equal
blocks, one per device of a one-axis mesh (``batch_mesh``, every device by default),
with ``jax.shard_map``; the ``shared`` arguments are replicated. Within a device the
items run one after another under ``lax.map`` (``inner="map"``, the default: memory
stays that of one item, and every ``lax.cond`` stays a real branch; the histogram
kernel's fallback does so under ``vmap`` too, ``kernels.histogram.batch_all``)
or all at once under ``vmap`` (``inner="vmap"``: one batched program, the better
choice on a GPU when a block fits in memory). A batch that does not divide evenly is
padded with copies of its last item, and the padding is cut from the result. The
whole call is one jitted program per ``fn``, shapes and mesh.

On one CPU the mesh has one device. Several CPU devices for testing:
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` before JAX starts (each
device then gets a share of the host's cores). On several GPUs the same code runs on
``jax.devices()``.

Several processes (hosts, or processes on one machine): each calls
:func:`start_distributed` (``jax.distributed.initialize`` with the coordinator's
address, the number of processes and its own index) before anything else touches JAX,
then runs the same ``run_sharded`` call on the same whole batch. The mesh then spans every
process's devices; each process feeds its devices their blocks of the batch
(``jax.make_array_from_callback``) and the outputs are gathered back whole on every
process (``multihost_utils.process_allgather``), so every process returns what one
process would.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cpf_jax.filter import Filter, track_boxes

__all__ = ["AXIS", "INNER", "batch_mesh", "run_sharded", "start_distributed", "track_sharded"]

AXIS = "batch"
INNER = ("map", "vmap")


def batch_mesh(devices: Sequence[Any] | None = None, axis: str = AXIS) -> Mesh:
    """A one-axis ``Mesh`` named ``axis`` over ``devices`` (default: ``jax.devices()``)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("batch_mesh needs at least one device")
    return Mesh(np.asarray(devices, dtype=object), (axis,))


def _batch_size(batched: Any) -> int:
    leaves = jax.tree_util.tree_leaves(batched)
    if not leaves:
        raise ValueError("run_sharded: 'batched' has no arrays")
    sizes = {int(np.shape(x)[0]) if np.ndim(x) else -1 for x in leaves}
    if -1 in sizes:
        raise ValueError("run_sharded: every array in 'batched' needs a leading batch axis")
    if len(sizes) != 1:
        raise ValueError(
            f"run_sharded: the arrays in 'batched' differ in batch size: {sorted(sizes)}"
        )
    (n,) = sizes
    if n < 1:
        raise ValueError("run_sharded: the batch is empty")
    return n


def _pad(batched: Any, n: int, to: int) -> Any:
    if to == n:
        return batched

    def pad(x):
        x = jnp.asarray(x)
        last = jnp.broadcast_to(x[-1:], (to - n, *x.shape[1:]))
        return jnp.concatenate([x, last], axis=0)

    return jax.tree_util.tree_map(pad, batched)


def start_distributed(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join this process to a run over ``num_processes`` JAX processes whose process 0
    listens at ``coordinator`` (``"host:port"``), as ``process_id``: CPU collectives over
    gloo (the CPU backend has none of its own), then ``jax.distributed.initialize``. Call
    it first, before JAX starts a backend; the process-wide switch is the caller's."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=coordinator, num_processes=num_processes, process_id=process_id
    )


def _global(tree: Any, mesh: Mesh, spec: PartitionSpec) -> Any:
    """``tree``'s arrays as global arrays of ``mesh`` laid out by ``spec``, each process
    filling its own devices' blocks from its whole copy (None leaves stay None)."""
    sharding = NamedSharding(mesh, spec)

    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])

    return jax.tree_util.tree_map(one, tree)


@functools.lru_cache(maxsize=64)  # bounded: a notebook may pass a new lambda each call
def _program(fn: Callable, mesh: Mesh, axis: str, inner: str, n_shared: int) -> Callable:
    def block(batched, *shared):
        if inner == "vmap":
            return jax.vmap(lambda item: fn(item, *shared))(batched)
        return jax.lax.map(lambda item: fn(item, *shared), batched)

    spec = PartitionSpec(axis)
    in_specs = (spec, *([PartitionSpec()] * n_shared))
    mapped = jax.shard_map(block, mesh=mesh, in_specs=in_specs, out_specs=spec, check_vma=False)
    return jax.jit(mapped)


def run_sharded(
    fn: Callable,
    batched: Any,
    *shared: Any,
    mesh: Mesh | None = None,
    inner: str = "map",
) -> Any:
    """``fn(item, *shared)`` for every item of ``batched``, spread over ``mesh``'s devices.

    ``batched``: a pytree of arrays with one leading batch axis ``[B, ...]``.
    ``shared``: arguments every item sees whole (replicated on every device).
    ``mesh``: a one-axis mesh (``batch_mesh()`` by default). ``inner``: ``"map"`` or
    ``"vmap"`` (module docstring). Returns ``fn``'s outputs stacked ``[B, ...]``.
    ``fn`` should be one function object per program (a lambda made anew on each call
    compiles anew).
    """
    if inner not in INNER:
        raise ValueError(f"inner must be one of {INNER}, got {inner!r}")
    mesh = batch_mesh() if mesh is None else mesh
    if len(mesh.axis_names) != 1:
        raise ValueError(f"run_sharded needs a one-axis mesh, got axes {mesh.axis_names}")
    (axis,) = mesh.axis_names
    n = _batch_size(batched)
    d = mesh.devices.size
    padded = _pad(batched, n, -(-n // d) * d)
    program = _program(fn, mesh, axis, inner, len(shared))
    if jax.process_count() > 1:  # the mesh spans processes: global arrays in and out
        from jax.experimental import multihost_utils

        out = program(
            _global(padded, mesh, PartitionSpec(axis)),
            *_global(shared, mesh, PartitionSpec()),
        )
        out = multihost_utils.process_allgather(out, tiled=True)
    else:
        out = program(padded, *shared)
    return jax.tree_util.tree_map(lambda x: x[:n], out)


@functools.lru_cache(maxsize=64)
def _keyed(filt: Filter) -> Callable:
    """One function object per filter (``run_sharded`` compiles one program per ``fn``)."""

    def one(key, params, frames, box, context):
        return track_boxes(filt, params, key, frames, box, context)

    return one


def track_sharded(
    filt: Filter,
    params: Any,
    keys: Any,
    frames: Any,
    box: Any,
    context: Any = None,
    *,
    mesh: Mesh | None = None,
    inner: str = "map",
):
    """``track_boxes`` of any box filter for every key of ``keys [K]``, spread over the
    devices of ``mesh``: ``([K, T, 4] boxes, [K, T] lost)``; the parameters, frames, box
    and context are shared."""
    return run_sharded(_keyed(filt), keys, params, frames, box, context, mesh=mesh, inner=inner)
