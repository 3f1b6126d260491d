"""The test session's own set-up (``tests/conftest.py``): cheap compiles for most tests,
LLVM level 1 for the ``run_bound`` ones."""

from __future__ import annotations

import conftest
import jax
import jax.numpy as jnp
import pytest
from jaxlib import xla_client


def _session_optimization_level() -> int:
    """The LLVM level XLA compiles at by default in this process: the debug options it
    parsed from ``XLA_FLAGS``, which every ``jax.jit`` compile starts from."""
    options = xla_client.CompileOptions().executable_build_options.debug_options
    return options.xla_backend_optimization_level


def test_the_session_compiles_at_llvm_level_0():
    if not conftest.CHEAP_COMPILES:
        pytest.skip("CPF_TEST_XLA_DEFAULTS is set: the session compiles with XLA's defaults")
    assert _session_optimization_level() == 0
    assert jax.jit is conftest._JIT  # unmarked tests: jax.jit untouched


@pytest.mark.run_bound
def test_run_bound_tests_jit_at_level_1(monkeypatch):
    if not conftest.CHEAP_COMPILES:
        assert jax.jit is conftest._JIT
        return
    assert jax.jit is conftest.run_bound_jit
    # A higher level than the session's, and one XLA accepts.
    assert conftest.RUN_BOUND_OPTIONS["xla_backend_optimization_level"] > (
        _session_optimization_level()
    )

    @jax.jit
    def f(x):
        return jnp.cumsum(x) * 2

    assert f(jnp.arange(4.0)).tolist() == [0.0, 2.0, 6.0, 12.0]
    # A plain jax.jit in a run_bound test compiles with RUN_BOUND_OPTIONS (read when it
    # is called): replaced by an unknown option, XLA refuses the compile.
    monkeypatch.setattr(conftest, "RUN_BOUND_OPTIONS", {"no_such_xla_option": 1})
    bad = jax.jit(lambda x: x + 1)
    with pytest.raises(Exception, match="no_such_xla_option"):
        bad(1.0)
    # Options given explicitly win over the default.
    assert jax.jit(lambda x: x + 2, compiler_options={})(1.0) == 3.0
