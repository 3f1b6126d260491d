"""Opt-in CPU tuning switches. Nothing here runs at import time.

``tune_malloc()``
    XLA on CPU allocates its large temporaries (integral-histogram tables of
    10-50 MB) on every call. glibc serves blocks above its mmap threshold with
    fresh ``mmap`` pages, returns them to the kernel on ``free`` and trims the
    heap top, so every frame pays the page faults again (visible as system
    time: 12,000 faults, 15 ms, per N = 100k colour step). Raising
    ``M_MMAP_THRESHOLD`` (``mallopt`` parameter -3; 1 GiB requested, 32 MiB
    where glibc caps it) and ``M_TRIM_THRESHOLD`` (-1, 1 GiB) keeps freed
    memory in the process and reuses it. By default ``M_MMAP_MAX`` (-4) is also
    set to 0 so that no block is served by a fresh ``mmap``
    (``disable_mmap=False`` keeps glibc's mmap for huge blocks). The cost: the
    process keeps its peak heap size.

    ``M_ARENA_MAX`` (-8) is set to 1 too (``single_arena=False`` leaves it): one
    heap for every thread. XLA's worker threads allocate from per-thread
    arenas, whose extra heaps glibc unmaps as soon as one is empty, whatever
    the trim threshold; a temporary that fills such a heap is faulted in anew on
    every call. Measured on the 2-core Intel Xeon host (2026-11-28, N = 100k
    colour step, 40 steps after warm-up, ``getrusage``): 7,100 minor faults and
    14-17 ms of system time per step with the thresholds alone, 20-60 faults
    and 1.3-2.5 ms with one arena; wall time 65-70 -> 61 ms per step. Same
    effect as ``GLIBC_TUNABLES=glibc.malloc.arena_max=1``, which must be set
    before the process starts.

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
    the colour step, the per-chunk ``sqrt(counts) . sqrt(q)`` reduction ran as
    such a fusion without XLA's outer-dimension split across the cores.
    Measured on the 2-core AMD EPYC host (``experiments/bench_colour.py``,
    2026-11-27T22:01, medians of 50 steps, the second in a fresh process): N =
    1k 9.0 -> 6.3 ms, N = 10k 12.4 -> 9.6 ms, N = 100k 46.3 -> 37.6 ms; in
    separate processes timed back to back, N = 10k about 1 ms faster. In the
    runs of 2026-11-28 the fresh process without the flag was sometimes the
    faster one (01:20: 6.7 / 10.1 / 31.7 ms against 7.9 / 11.8 / 39.5; 04:30:
    4.8 / 8.5 / 31.8 against 5.3 / 8.3 / 29.8; 04:50: 6.2 / 9.8 / 36.9 against
    6.9 / 9.9 / 38.5): between processes the difference is within this host's
    noise. Until 2026-11-27 the benchmark set the flag after importing
    ``cpf_jax``, which had already started JAX, so XLA never saw it. Other
    programs may gain or lose: time yours.

    Other XLA:CPU flags did not help the colour step. On 2026-11-28 (10:00-10:18,
    a slow spell), the N = 100k default step was timed in fresh processes taking
    turns, each with ``library_fusions=False``'s flag plus one more. Figures are medians
    of 40 steps.

    - Baseline, 5 processes: 41.9-60.9 ms (median 54.7).
    - ``--xla_cpu_use_xnnpack=true``: 41.6-50.9 ms (48.2).
    - ``--xla_cpu_enable_concurrency_optimized_scheduler=true``: 39.3-53.9 ms (48.1).
    - Both together: 43.1-58.3 ms (50.6).
    - ``--xla_cpu_prefer_vector_width=512``, 3 processes: 40.3-54.5 ms.
    - ``--xla_cpu_parallel_codegen_split_count=1``, 3 processes: 44.5-48.7 ms.

    All of these gave bit-identical particles, and every difference is within the
    baseline's own spread of 19 ms. ``--xla_cpu_prefer_vector_width=128`` was
    slower (48.1-65.0 ms) and changed the particles. In jax 0.10,
    ``--xla_cpu_use_multi_output_fusion``,
    ``--xla_cpu_enable_experimental_deallocation`` and
    ``--xla_cpu_small_while_loop_byte_threshold`` are unknown flags and abort the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["tune_malloc", "xla_cpu_flags"]

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


def _glibc():
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
    libc = _glibc()
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
