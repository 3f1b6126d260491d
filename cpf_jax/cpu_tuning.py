"""Opt-in CPU tuning switches. Nothing here runs at import time.

``tune_malloc()``
    XLA on CPU allocates its large temporaries (integral-histogram tables of
    10-50 MB) on every call. glibc serves blocks above its mmap threshold with
    fresh ``mmap`` pages, returns them to the kernel on ``free`` and trims the
    heap top, so every frame pays the page faults again (visible as system
    time). Raising ``M_MMAP_THRESHOLD`` (``mallopt`` parameter -3; 1 GiB
    requested, 32 MiB where glibc caps it) and ``M_TRIM_THRESHOLD`` (-1, 1 GiB)
    keeps freed memory in the process and reuses it. By default ``M_MMAP_MAX``
    (-4) is also set to 0 so that no block is served by a fresh ``mmap``
    (``disable_mmap=False`` keeps glibc's mmap for huge blocks). The cost: the
    process keeps its peak heap size.

    ``M_ARENA_MAX`` (-8) is set to 1 too (``single_arena=False`` leaves it): one
    heap for every thread. XLA's worker threads allocate from per-thread
    arenas, whose extra heaps glibc unmaps as soon as one is empty, whatever
    the trim threshold; a temporary that fills such a heap is faulted in anew on
    every call. Same effect as ``GLIBC_TUNABLES=glibc.malloc.arena_max=1``, which
    must be set before the process starts.

    Call it **before JAX allocates anything** (first thing in a script or
    benchmark, before the first jitted call): glibc applies the thresholds to
    later allocations, and chunks already mapped stay mapped. It is a process-wide
    change, hence opt-in. Returns ``True`` when glibc accepted both settings and
    ``False`` (no warning, no exception) on other C libraries (macOS, musl,
    Windows).

``xla_cpu_flags(...)``
    Builds an ``XLA_FLAGS`` string for the CPU backend (single-threaded Eigen
    kernels; no YNNPACK library fusions); it only returns the string. Set it in
    the environment yourself, before the first JAX computation, if you want it:
    the library never changes it. Importing ``cpf_jax`` does not start JAX's
    backend, so setting it after the import works (tested); once JAX has run
    anything, XLA has read its flags.

    ``library_fusions=False`` stops XLA:CPU (jax 0.10) from handing elementwise
    chains and reductions to YNNPACK (``__ynn_fusion`` in the compiled HLO). In
    the colour step, the per-chunk ``sqrt(counts) . sqrt(q)`` reduction runs as
    such a fusion without XLA's outer-dimension split across the cores. Between
    processes the gain is within a shared host's noise, so other programs may gain
    or lose: time yours.

    In jax 0.10, ``--xla_cpu_use_multi_output_fusion``,
    ``--xla_cpu_enable_experimental_deallocation`` and
    ``--xla_cpu_small_while_loop_byte_threshold`` are unknown flags and abort the
    process.

The measurements behind these settings, and the other XLA:CPU flags timed against them,
are dated entries of ``docs/decisions.md``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["load_glibc", "tune_malloc", "xla_cpu_flags"]

# glibc <malloc.h> parameter numbers.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
# Requested mmap threshold; glibc versions that cap it (at HEAP_MAX / 2 = 32 MiB
# on 64-bit) refuse larger values, and then the cap is used.
_MMAP_THRESHOLD = 1 << 30
_MMAP_THRESHOLD_CAP = 32 * 1024 * 1024
_TRIM_THRESHOLD = 1 << 30
#: XLA flag enabling no YNNPACK fusion type (an empty list).
YNN_OFF_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def load_glibc() -> ctypes.CDLL | None:
    """The C library as a ``ctypes`` handle when it is glibc, else None (loaded on call)."""
    if os.name != "posix":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    # mallopt and gnu_get_libc_version both exist only in glibc.
    if not hasattr(libc, "mallopt") or not hasattr(libc, "gnu_get_libc_version"):
        return None
    return libc


def tune_malloc(
    mmap_threshold: int = _MMAP_THRESHOLD,
    trim_threshold: int = _TRIM_THRESHOLD,
    *,
    disable_mmap: bool = True,
    single_arena: bool = True,
) -> bool:
    """Raise glibc's mmap and trim thresholds and use one arena (``mallopt``); ``False``
    if not glibc.

    Must run before JAX allocates its buffers (see the module docstring).
    Returns ``True`` when glibc accepted every setting.
    """
    for value in (mmap_threshold, trim_threshold):
        if not -(2**31) <= int(value) < 2**31:
            raise ValueError(f"mallopt value {value} does not fit a C int")
    libc = load_glibc()
    if libc is None:
        return False
    if hasattr(libc.mallopt, "argtypes"):
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.mallopt.restype = ctypes.c_int
    ok = libc.mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
    if not ok and mmap_threshold > _MMAP_THRESHOLD_CAP:
        ok = libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_CAP) == 1
    ok &= libc.mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)) == 1
    if disable_mmap:
        ok &= libc.mallopt(_M_MMAP_MAX, 0) == 1
    if single_arena:
        ok &= libc.mallopt(_M_ARENA_MAX, 1) == 1
    return bool(ok)


def xla_cpu_flags(
    *, single_threaded: bool = False, library_fusions: bool = True, extra: str = ""
) -> str:
    """An ``XLA_FLAGS`` value for the CPU backend; returned, never applied.

    ``single_threaded=True`` turns off XLA's multi-threaded Eigen kernels
    (``--xla_cpu_multi_thread_eigen=false``), e.g. to run one process per core.
    XLA's CPU intra-op pool otherwise uses every core. ``library_fusions=False``
    enables no YNNPACK fusion type (``--xla_cpu_experimental_ynn_fusion_type=``;
    see the module docstring). ``extra`` is appended as is. Set the result as
    ``os.environ["XLA_FLAGS"]`` before the first JAX computation.
    """
    flags = []
    if single_threaded:
        flags.append("--xla_cpu_multi_thread_eigen=false")
    if not library_fusions:
        flags.append(YNN_OFF_FLAG)
    if extra:
        flags.append(extra)
    return " ".join(flags)
