"""What a compiled filter needs in memory, and whether the device has it free.

XLA's own estimate of a compiled call (``Compiled.memory_analysis()``) is its arguments,
outputs and temporaries, less what the outputs alias: an upper bound, since buffers that
are dead by then share space. A particle count the device cannot hold is then one clear
error before the first frame, not a process killed by the kernel (or a
``RESOURCE_EXHAUSTED`` traceback) while it runs.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import jax

from cpf_jax.errors import MemoryTooSmall

__all__ = ["needed_bytes", "free_bytes", "check_fits"]

# Refuse what needs more than this share of the free memory: the estimate is an upper bound,
# but the rest of the process (frames, the logger) also lives there.
FREE_SHARE = 0.9


def needed_bytes(compiled: Any) -> int | None:
    """Bytes a compiled call (``jax.jit(f).lower(...).compile()``) holds at once by XLA's
    estimate, or None where the backend gives none."""
    try:
        m = compiled.memory_analysis()
    except (AttributeError, NotImplementedError, jax.errors.JaxRuntimeError):
        return None
    if m is None:
        return None
    total = m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
    return int(total - m.alias_size_in_bytes)


def free_bytes(device: Any = None) -> int | None:
    """Free memory of ``device`` (default: JAX's first): the host's available memory for a
    CPU (``/proc/meminfo``'s MemAvailable, else the free pages), an accelerator's limit less
    what it holds; None when unknown."""
    device = jax.devices()[0] if device is None else device
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" not in stats:
            return None
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_fits(needed: int | None, what: str, free: int | None = None) -> None:
    """Raise :class:`MemoryTooSmall` naming ``what`` when ``needed`` bytes exceed the free
    share (:data:`FREE_SHARE`) of ``free`` (default: :func:`free_bytes`); nothing when
    either is unknown."""
    free = free_bytes() if free is None else free
    if needed is None or free is None or needed <= FREE_SHARE * free:
        return
    raise MemoryTooSmall(
        f"{what} needs about {needed / 1e9:.1f} GB by XLA's estimate, and "
        f"{free / 1e9:.1f} GB is free"
    )
