"""The test session's own set-up (``tests/conftest.py``): cheap compiles for most tests,
LLVM level 1 for the ``run_bound`` ones."""

from __future__ import annotations

import os

import conftest
import jax
import jax.numpy as jnp
import pytest


def test_the_session_compiles_at_llvm_level_0():
    if not conftest.CHEAP_COMPILES:
        pytest.skip("CPF_TEST_XLA_DEFAULTS is set: the session compiles with XLA's defaults")
    assert conftest.TEST_XLA_FLAGS in os.environ["XLA_FLAGS"]
    assert "--xla_backend_optimization_level=0" in conftest.TEST_XLA_FLAGS
    assert jax.jit is conftest._JIT  # unmarked tests: jax.jit untouched


@pytest.mark.run_bound
def test_run_bound_tests_jit_at_level_1():
    if not conftest.CHEAP_COMPILES:
        assert jax.jit is conftest._JIT
        return
    assert jax.jit is conftest.run_bound_jit
    assert conftest.RUN_BOUND_OPTIONS == {"xla_backend_optimization_level": 1}

    @jax.jit
    def f(x):
        return jnp.cumsum(x) * 2

    assert f(jnp.arange(4.0)).tolist() == [0.0, 2.0, 6.0, 12.0]
    # The options reach the compile: an unknown option is refused by XLA.
    bad = conftest.run_bound_jit(lambda x: x + 1, compiler_options={"no_such_xla_option": 1})
    with pytest.raises(Exception, match="no_such_xla_option"):
        bad(1.0)
