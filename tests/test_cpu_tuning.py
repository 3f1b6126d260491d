"""cpf_jax.cpu_tuning: opt-in, no import-time effect, glibc detection."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cpf_jax import cpu_tuning


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    return out.stdout.strip()


def test_import_changes_nothing(monkeypatch):
    # Re-import with ctypes.CDLL spied on: importing must not load libc or call mallopt.
    import ctypes
    import importlib

    loaded = []
    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: loaded.append(a) or None)
    importlib.reload(cpu_tuning)
    assert loaded == []
    monkeypatch.undo()
    importlib.reload(cpu_tuning)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc check")
def test_tune_malloc_on_glibc_in_fresh_process():
    libc = cpu_tuning.load_glibc()
    if libc is None:
        pytest.skip("not glibc")
    # A fresh process: mallopt is process-wide and must not leak into the test session.
    assert _run("from cpf_jax.cpu_tuning import tune_malloc; print(tune_malloc())") == "True"
    assert (
        _run("from cpf_jax.cpu_tuning import tune_malloc; print(tune_malloc(disable_mmap=False))")
        == "True"
    )
    with pytest.raises(ValueError):
        cpu_tuning.tune_malloc(1 << 40)  # would overflow C int: refused before any call


class _FakeLibc:
    """Records mallopt calls; refuses mmap thresholds above ``cap``."""

    def __init__(self, cap):
        self.cap, self.calls = cap, []
        self.mallopt = self._mallopt

    def _mallopt(self, param, value):
        self.calls.append((param, value))
        return 0 if (param == -3 and value > self.cap) else 1


def test_tune_malloc_settings_and_capped_glibc(monkeypatch):
    fake = _FakeLibc(cap=1 << 40)
    monkeypatch.setattr(cpu_tuning, "load_glibc", lambda: fake)
    assert cpu_tuning.tune_malloc() is True
    assert fake.calls == [(-3, 1 << 30), (-1, 1 << 30), (-4, 0), (-8, 1)]
    # An older glibc capping the threshold at 32 MiB: the cap is used instead.
    fake = _FakeLibc(cap=32 << 20)
    monkeypatch.setattr(cpu_tuning, "load_glibc", lambda: fake)
    assert cpu_tuning.tune_malloc(disable_mmap=False, single_arena=False) is True
    assert fake.calls == [(-3, 1 << 30), (-3, 32 << 20), (-1, 1 << 30)]
    # A refused setting is reported as False, not raised.
    fake = _FakeLibc(cap=0)
    monkeypatch.setattr(cpu_tuning, "load_glibc", lambda: fake)
    assert cpu_tuning.tune_malloc() is False


def test_tune_malloc_returns_false_without_glibc(monkeypatch):
    monkeypatch.setattr(cpu_tuning, "load_glibc", lambda: None)
    assert cpu_tuning.tune_malloc() is False


def test_xla_cpu_flags_only_returns_a_string(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert cpu_tuning.xla_cpu_flags() == ""
    flags = cpu_tuning.xla_cpu_flags(single_threaded=True, extra="--xla_dump_to=/tmp/x")
    assert flags == "--xla_cpu_multi_thread_eigen=false --xla_dump_to=/tmp/x"
    import os

    assert "XLA_FLAGS" not in os.environ


#: Compiles a sqrt-multiply-reduce (the colour step's per-chunk reduction) and binds
#: ``ynn`` to the number of YNNPACK fusions in it.
_YNN_PROBE = (
    "import jax, jax.numpy as jnp\n"
    "f = jax.jit(lambda c, q: jnp.sum(jnp.sqrt(c) * q, axis=-1))\n"
    "c = jnp.ones((4096, 2, 72)); q = jnp.ones((2, 72))\n"
    "ynn = f.lower(c, q).compile().as_text().count('__ynn_fusion')\n"
)


def test_library_fusions_flag_is_accepted_and_removes_ynn_fusions():
    # This jaxlib must know the flag (XLA aborts on an unknown flag or value), and the
    # compiled program of a sqrt-multiply-reduce (the colour step's per-chunk
    # reduction) must then hold no YNNPACK fusion.
    flags = cpu_tuning.xla_cpu_flags(library_fusions=False)
    assert flags == cpu_tuning.YNN_OFF_FLAG
    code = (
        "import os; os.environ['XLA_FLAGS'] = "
        + repr(flags)
        + "\n"
        + _YNN_PROBE
        + "print(float(f(c, q)[0, 0]), ynn)\n"
    )
    value, ynn = _run(code).split()
    assert float(value) == 72.0
    assert int(ynn) == 0


def test_importing_the_library_starts_no_jax_backend():
    # cpu_tuning's switches (XLA_FLAGS, tune_malloc) only apply if JAX has not created
    # its CPU client yet; importing cpf_jax (any module) must not create it, as a
    # module-level jnp constant would.
    code = (
        "import importlib, os, pkgutil\n"
        "import cpf_jax, cpf_jax.io, cpf_jax.kernels\n"
        "for pkg in (cpf_jax, cpf_jax.io, cpf_jax.kernels):\n"
        "    for m in pkgutil.iter_modules(pkg.__path__):\n"
        "        importlib.import_module(pkg.__name__ + '.' + m.name)\n"
        "os.environ['XLA_FLAGS'] = '--xla_force_host_platform_device_count=3 '"
        " + cpf_jax.cpu_tuning.xla_cpu_flags(library_fusions=False)\n"
        + _YNN_PROBE
        + "print(len(jax.devices('cpu')), ynn)\n"
    )
    devices, ynn = _run(code).split()
    assert int(devices) == 3
    assert int(ynn) == 0
