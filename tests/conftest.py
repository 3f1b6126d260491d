"""Shared test set-up.

JAX's persistent compilation cache is switched on for the test session only
(never by the library): many tests build filters with identical configs, and
the cache turns their repeated XLA compiles into look-ups.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

# One cache per pytest-xdist worker: the cache writes its files without a lock, and a
# worker could read an entry another is still writing.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "main")
jax.config.update("jax_compilation_cache_dir", str(ROOT / ".pytest_cache" / "jax" / _WORKER))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data, skipping the test with a clear reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real recording not available: {path} is absent (read-only shared data)")
    return path


def figure_joints(arm: float) -> dict[str, tuple[float, float]]:
    """Joints of the depth tests' capsule figure: ``(x, y)`` mm at adult size around
    the pelvis (y down), the left arm raised by ``arm`` rad."""
    return {
        "head": (0, -760),
        "neck": (0, -560),
        "pelvis": (0, 0),
        "ls": (-180, -480),
        "rs": (180, -480),
        "lh": (-200 - 500 * np.sin(arm), -480 + 500 * np.cos(arm)),
        "rh": (330, 0),
        "lf": (-150, 850),
        "rf": (160, 850),
    }


#: The figure's capsules: (joint, joint, radius mm at adult size).
FIGURE_SEGMENTS = (
    ("head", "head", 100),
    ("neck", "pelvis", 150),
    ("ls", "rs", 70),
    ("ls", "lh", 45),
    ("rs", "rh", 45),
    ("pelvis", "lf", 75),
    ("pelvis", "rf", 75),
)
