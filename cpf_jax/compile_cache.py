"""A persistent XLA compilation cache for ``cpf-track``, and for scripts and notebooks with
one call, ``cpf_jax.enable_compile_cache()``.

Compiling is much of a short run's time. JAX can keep compiled programs on disk and look
them up by a hash of the program, the XLA flags and the device, so a second run with the
same model and sizes skips the compile and gives the same output. The library never switches
this on by itself on import (a process-wide JAX setting); the command line does, in
:func:`default_dir` unless told otherwise (``--compile-cache DIR|off``), and leaves a
cache the user or a notebook has already configured (``JAX_COMPILATION_CACHE_DIR``,
``jax.config``) alone.

JAX bounds its cache's size only with the optional ``filelock`` package, which is not a
dependency here, so :func:`prune` keeps the directory under ``max_bytes`` itself,
removing the least recently written entries first.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DEFAULT_MAX_BYTES", "configured", "default_dir", "enable", "prune"]

#: Size bound of the cache directory (an entry is 0.5-5 MB).
DEFAULT_MAX_BYTES = 1 << 30


def default_dir() -> Path:
    """``$CPF_JAX_COMPILE_CACHE``, else ``$XDG_CACHE_HOME/cpf_jax/xla`` (``~/.cache`` when
    ``XDG_CACHE_HOME`` is unset)."""
    own = os.environ.get("CPF_JAX_COMPILE_CACHE")
    if own:
        return Path(own).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "cpf_jax" / "xla"


def prune(path: str | os.PathLike, max_bytes: int = DEFAULT_MAX_BYTES) -> int:
    """Delete the oldest files (by modification time) until the files directly in
    ``path`` take at most ``max_bytes``; returns how many were deleted. Files that
    vanish or cannot be removed meanwhile (another process) are skipped."""
    entries = []
    for p in Path(path).iterdir():
        try:
            st = p.stat()
        except OSError:
            continue
        if p.is_file():
            entries.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in entries)
    removed = 0
    for _, size, p in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        try:
            p.unlink()
        except OSError:
            continue
        total -= size
        removed += 1
    return removed


def enable(path: str | os.PathLike | None = None, max_bytes: int = DEFAULT_MAX_BYTES) -> Path:
    """Point JAX's persistent compilation cache at ``path`` (default :func:`default_dir`,
    the one ``cpf-track`` uses; created if missing), after pruning it to ``max_bytes``;
    returns the directory. Programs that compile in under a second are not kept. This is
    ``cpf_jax.enable_compile_cache``, the one call a notebook or script makes to skip the
    compile on its next run. Raises ``OSError`` when the directory cannot be created or
    written."""
    import jax

    path = Path(default_dir() if path is None else path).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    if not os.access(path, os.W_OK | os.X_OK):
        raise PermissionError(f"{path} is not writable")
    prune(path, max_bytes)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    jax.config.update("jax_enable_compilation_cache", True)
    return path


def configured() -> str | None:
    """The cache directory JAX already uses (environment or ``jax.config``), or None."""
    import jax

    if not jax.config.jax_enable_compilation_cache:
        return None
    return jax.config.jax_compilation_cache_dir or None
