"""``cpf-track``'s persistent compilation cache (``cpf_jax.compile_cache``): where it
lives, its size bound, and that a second run looks its programs up instead of
compiling them."""

from __future__ import annotations

import os
import subprocess
import sys

import jax

from cpf_jax import compile_cache
from cpf_jax.cli import main


def test_default_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("CPF_JAX_COMPILE_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.default_dir() == tmp_path / "xdg" / "cpf_jax" / "xla"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compile_cache.default_dir() == tmp_path / "home" / ".cache" / "cpf_jax" / "xla"
    monkeypatch.setenv("CPF_JAX_COMPILE_CACHE", str(tmp_path / "own"))
    assert compile_cache.default_dir() == tmp_path / "own"


def test_prune_removes_the_oldest_files_until_under_the_bound(tmp_path):
    sizes = [300, 200, 100, 400, 50]  # written in this order, oldest first
    for i, size in enumerate(sizes):
        p = tmp_path / f"e{i}"
        p.write_bytes(b"x" * size)
        os.utime(p, (1000 + i, 1000 + i))
    (tmp_path / "sub").mkdir()  # not an entry: left alone
    assert compile_cache.prune(tmp_path, 10_000) == 0
    # 1050 bytes over a 600-byte bound: the oldest go until 550 remain (e0 and e1: 500).
    assert compile_cache.prune(tmp_path, 600) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e2", "e3", "e4", "sub"]
    assert compile_cache.prune(tmp_path, 0) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["sub"]


def test_off_switches_the_cache_off_and_a_bad_directory_is_one_error_line(tmp_path, capsys):
    # The cache is set up before the source is opened: a missing source still switches it off.
    before = jax.config.jax_enable_compilation_cache
    try:
        jax.config.update("jax_enable_compilation_cache", True)
        missing = str(tmp_path / "missing.npz")
        assert main([missing, "--compile-cache", "off", "--no-progress"]) == 2
        assert jax.config.jax_enable_compilation_cache is False
    finally:
        jax.config.update("jax_enable_compilation_cache", before)
    capsys.readouterr()
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    code = main(["walk_across_medium", "--compile-cache", str(blocker / "xla"), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cpf-track: error: --compile-cache {blocker}")


def _cpf_track(*argv: str, env: dict) -> subprocess.CompletedProcess:
    code = f"import sys; from cpf_jax.cli import main; sys.exit(main({list(argv)!r}))"
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600
    )


def test_a_second_run_loads_its_programs_from_the_cache(tmp_path):
    """A fresh process with nothing configured writes to the default directory
    (``$CPF_JAX_COMPILE_CACHE`` here); a second one, whose cache JAX is already given
    by ``JAX_COMPILATION_CACHE_DIR``, keeps that one and finds the programs there."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["CPF_JAX_COMPILE_CACHE"] = str(tmp_path / "default")
    argv = ("walk_across_medium", "--particles", "16", "--max-frames", "3", "--no-progress")
    first = _cpf_track(*argv, env=env)
    assert first.returncode == 0, first.stderr
    entries = sorted(p.name for p in (tmp_path / "default").iterdir())
    assert any(name.startswith("jit_step") for name in entries), entries

    env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "default")
    env["CPF_JAX_COMPILE_CACHE"] = str(tmp_path / "unused")
    env["JAX_LOG_COMPILES"] = "1"
    second = _cpf_track(*argv, env=env)
    assert second.returncode == 0, second.stderr
    assert "Persistent compilation cache hit for 'jit_step'" in second.stderr
    assert not (tmp_path / "unused").exists()
    assert sorted(p.name for p in (tmp_path / "default").iterdir()) == entries
