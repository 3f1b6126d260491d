"""The worked examples in notebooks/ are executed, so they cannot rot."""

from __future__ import annotations

import os
import runpy
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
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
