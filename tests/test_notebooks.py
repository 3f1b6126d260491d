"""The worked examples in notebooks/ are executed, so they cannot rot.

``quickstart`` runs in ``make test``. ``body_points`` (the cascade) and ``tuning``
(gradients through the filter) cost 55-70 CPU-seconds each, nearly all compiling programs
that tests/test_cascade.py and tests/test_tuning.py compile in their own forms, so they
run with ``-m slow``. In ``make test`` every notebook is checked without running it:
ruff's pyflakes rules (undefined names, unused imports), and every name it takes from
``cpf_jax`` (``from cpf_jax.x import f``, ``x.f`` on an imported module) must exist, which
catches the usual rot: a renamed or removed function.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.py"))
SLOW = {"body_points.py", "tuning.py"}


def test_every_notebook_passes_pyflakes():
    assert {p.name for p in NOTEBOOKS} >= SLOW | {"quickstart.py"}
    out = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--select", "F", str(NOTEBOOK_DIR)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr


def _library_names(tree: ast.Module):
    """``(module, name)`` for each name a notebook takes from cpf_jax: imported from it,
    or read as an attribute of a cpf_jax module it imported."""
    modules = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cpf_jax"):
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if _is_module(full):
                    modules[alias.asname or alias.name] = full
                else:
                    yield node.module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("cpf_jax"):
                    modules[alias.asname or alias.name] = alias.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.value.id in modules:
                yield modules[node.value.id], node.attr


def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_names_exist_in_the_library(path):
    names = list(_library_names(ast.parse(path.read_text(), str(path))))
    assert names  # the check reads something
    missing = [f"{m}.{n}" for m, n in names if not hasattr(importlib.import_module(m), n)]
    assert not missing, f"{path.name} uses names cpf_jax no longer has: {missing}"


@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p for p in NOTEBOOKS],
    ids=lambda p: p.name,
)
def test_notebook_runs(path, monkeypatch):
    monkeypatch.setenv("CPF_NOTEBOOK_FRAMES", "16")
    monkeypatch.chdir(path.parent)
    ns = runpy.run_path(str(path), run_name="__main__")
    assert "summary" in ns or "result" in ns
    if "summary" in ns:
        assert 0.0 <= ns["summary"]["success_rate"] <= 100.0
    if "point_errors_mm" in ns.get("summary", {}):  # body_points.py; measured 15-64 mm
        assert ns["summary"]["success_rate"] >= 90.0
        assert all(e < 120.0 for e in ns["summary"]["point_errors_mm"].values())
    assert os.environ["CPF_NOTEBOOK_FRAMES"] == "16"
