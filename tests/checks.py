"""One test body, three ways (dm_pix's ``_test_fn``): a kernel against its reference plainly,
under ``jax.jit`` and under ``jax.vmap`` (vmapped under jit, as every filter runs its
kernels: an eager vmap dispatches op by op and costs more than the compile)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

__all__ = ["assert_trees_close", "check_kernel", "check_weighed_cloud"]


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
            wide = np.complex128 if np.iscomplexobj(a) or np.iscomplexobj(e) else np.float64
            np.testing.assert_allclose(
                a.astype(wide),
                e.astype(wide),
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


def check_weighed_cloud(filt_plain, filt_reporting, params, state, frames, where: str) -> None:
    """A filter whose config has ``report_weights`` steps as the plain one (from the same
    state, to float rounding: the extra output may change XLA's fusions) and reports the
    particles before resampling: its state's particles are drawn from them, their weights
    give the info's ESS, and they are not the uniform weights after it."""
    import jax.numpy as jnp

    plain_step, reporting_step = jax.jit(filt_plain.step), jax.jit(filt_reporting.step)
    plain = state
    for t, frame in enumerate(frames):
        key = jax.random.PRNGKey(100 + t)
        reporting, info = reporting_step(params, key, plain, frame)
        plain, plain_info = plain_step(params, key, plain, frame)
        assert plain_info.weighed_cloud is None, where
        assert_trees_close(reporting, plain, rtol=1e-5, atol=1e-4, where=f"{where}, step {t}")
        weighed = info.weighed_cloud
        n = weighed.log_weights.shape[0]
        w = np.exp(np.asarray(weighed.log_weights, np.float64))
        np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-5, err_msg=where)
        np.testing.assert_allclose(1.0 / np.sum(w**2), float(info.ess), rtol=1e-3, err_msg=where)
        assert np.ptp(w) > 0, f"{where}: the reported weights are uniform"
        drawn = np.asarray(reporting.cloud.particles)[:, None, :]
        hits = np.all(drawn == np.asarray(weighed.particles)[None], axis=-1).any(axis=1)
        assert bool(info.resampled) and hits.all(), f"{where}: resampled particles not drawn"
        assert float(jnp.max(jnp.abs(reporting.cloud.log_weights + np.log(n)))) < 1e-5
