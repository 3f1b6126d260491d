"""Shared test set-up.

JAX's persistent compilation cache is switched on for the test session only (never by the
library): many tests build filters with identical configs, and the cache turns their
repeated XLA compiles into look-ups.

The suite's time is mostly XLA compiling, so the tests compile with cheaper XLA CPU
settings (``TEST_XLA_FLAGS``: no LLVM optimisation, loop fusions emitted the older way):
the same jaxprs run, only code generation differs. The few tests whose running, not
compiling, dominates are marked ``run_bound`` and compile at LLVM level 1
(``RUN_BOUND_OPTIONS``, through ``jax.jit``'s ``compiler_options``; a module-scoped
fixture uses ``run_bound_jit``). Set ``CPF_TEST_XLA_DEFAULTS=1`` to test with XLA's
defaults (what a user gets). The measurements behind these choices are in
``tests/TIMING.md``.
"""

from __future__ import annotations

import os
from pathlib import Path

#: XLA CPU flags for the test session (before JAX starts; appended to the user's own).
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
_FLAGS = os.environ.get("XLA_FLAGS", "")
CHEAP_COMPILES = os.environ.get("CPF_TEST_XLA_DEFAULTS", "") in ("", "0")
if CHEAP_COMPILES and TEST_XLA_FLAGS not in _FLAGS:
    os.environ["XLA_FLAGS"] = f"{_FLAGS} {TEST_XLA_FLAGS}".strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

#: Compile options of the ``run_bound`` tests: LLVM level 1.
RUN_BOUND_OPTIONS = {"xla_backend_optimization_level": 1} if CHEAP_COMPILES else None
_JIT = jax.jit


def run_bound_jit(fun, **kwargs):
    """``jax.jit`` compiling at ``RUN_BOUND_OPTIONS``: for programs that run long enough
    that level 0's slower code costs more than its cheaper compile saves."""
    kwargs.setdefault("compiler_options", RUN_BOUND_OPTIONS)
    return _JIT(fun, **kwargs)


@pytest.fixture(autouse=True)
def _untuned_malloc(monkeypatch):
    """``cpf-track`` tunes glibc's malloc by default (``cpu_tuning.tune_malloc``); the tests
    run it in this process, whose allocator stays as it started."""
    import cpf_jax.cli

    monkeypatch.setattr(cpf_jax.cli, "tune_process", lambda: False)


@pytest.fixture(autouse=True)
def _run_bound_compiles(request, monkeypatch):
    """In a test marked ``run_bound``, every ``jax.jit`` (the test's and the library's,
    looked up as ``jax.jit`` at call time) compiles at ``RUN_BOUND_OPTIONS``."""
    if CHEAP_COMPILES and request.node.get_closest_marker("run_bound") is not None:
        monkeypatch.setattr(jax, "jit", run_bound_jit)


ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

# One cache per pytest-xdist worker: the cache writes its files without a lock, and a
# worker could read an entry another is still writing.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "main")
jax.config.update("jax_compilation_cache_dir", str(ROOT / ".pytest_cache" / "jax" / _WORKER))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


#: Test files heaviest first. ``make test`` runs pytest-xdist with ``--dist loadfile
#: --no-loadscope-reorder``, which hands out whole files in this order, so the workers
#: finish within about a file of each other.
HEAVY_FIRST = (
    "test_cascade.py",
    "test_rgbd.py",
    "test_tuning.py",
    "test_notebooks.py",
    "test_cli.py",
    "test_points.py",
    "test_colour.py",
    "test_rgbd_proposal.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: files stay whole


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
