"""One test body, three ways (dm_pix's ``_test_fn``): a kernel against its reference plainly,
under ``jax.jit`` and under ``jax.vmap`` (vmapped under jit, as every filter runs its
kernels: an eager vmap dispatches op by op and costs more than the compile)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

__all__ = ["assert_trees_close", "check_kernel"]


def assert_trees_close(actual: Any, expected: Any, *, rtol: float, atol: float, where: str) -> None:
    """Every leaf of ``actual`` close to the matching leaf of ``expected`` (NaN equals NaN)."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(actual)
    leaves_e, tree_e = jax.tree_util.tree_flatten(expected)
    assert len(leaves_a) == len(leaves_e), f"{where}: {tree_a} against {tree_e}"
    for i, (a, e) in enumerate(zip(leaves_a, leaves_e, strict=True)):
        a, e = np.asarray(a), np.asarray(e)
        assert a.shape == e.shape, f"{where}, output {i}: shape {a.shape} != {e.shape}"
        if a.dtype == bool or e.dtype == bool:
            np.testing.assert_array_equal(a, e, err_msg=f"{where}, output {i}")
        else:
            np.testing.assert_allclose(
                a.astype(np.float64),
                e.astype(np.float64),
                rtol=rtol,
                atol=atol,
                equal_nan=True,
                err_msg=f"{where}, output {i}",
            )


def check_kernel(
    kernel: Callable,
    reference: Callable,
    args: Sequence[Any],
    *,
    batch: Sequence[Sequence[Any]] | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    variants: Sequence[str] = ("plain", "jit", "vmap"),
) -> None:
    """``kernel(*args)`` equals ``reference(*args)`` called plainly and under ``jit``, and
    ``vmap(kernel)`` over ``batch`` (argument tuples of equal shapes; default: ``args``
    and ``args`` again) equals the reference of each element.

    ``kernel`` takes arrays only (close over static arguments with a ``lambda``);
    ``reference`` is a NumPy, SciPy or OpenCV function of the same arguments. Outputs may
    be pytrees; booleans must be equal, numbers close.
    """
    expected = reference(*args)
    for variant in variants:
        if variant == "plain":
            assert_trees_close(kernel(*args), expected, rtol=rtol, atol=atol, where="plain")
        elif variant == "jit":
            out = jax.jit(kernel)(*args)
            assert_trees_close(out, expected, rtol=rtol, atol=atol, where="jit")
        elif variant == "vmap":
            items = list(batch) if batch is not None else [args, args]
            stacked = jax.tree_util.tree_map(lambda *x: np.stack(x), *[tuple(b) for b in items])
            out = jax.jit(jax.vmap(kernel))(*stacked)
            for j, item in enumerate(items):
                got = jax.tree_util.tree_map(lambda x, j=j: x[j], out)
                assert_trees_close(
                    got, reference(*item), rtol=rtol, atol=atol, where=f"vmap, item {j}"
                )
        else:
            raise ValueError(f"unknown variant {variant!r}; expected plain, jit or vmap")
