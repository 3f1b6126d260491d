"""The README's Python snippets run, in order, as one script (a user copies them)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from conftest import ROOT, TEST_XLA_FLAGS


def readme_python() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_the_readme_has_its_python_snippets():
    blocks = readme_python()
    assert len(blocks) >= 4
    assert any("track_boxes" in b for b in blocks) and any("Context(" in b for b in blocks)


_RUN_IN_ORDER = """
import re, sys
text = open(sys.argv[1]).read()
namespace = {}
for i, block in enumerate(re.findall(r"```python\\n(.*?)```", text, flags=re.S)):
    try:
        exec(compile(block, f"README.md python block {i}", "exec"), namespace)
    except Exception as e:
        raise SystemExit(f"README python block {i} fails: {e!r}\\n{block}")
assert namespace["boxes"].shape == (4, 150, 4), namespace["boxes"].shape
assert namespace["infos"].points.mean3d.shape[1:] == (5, 3)
"""


@pytest.mark.slow
def test_the_readme_snippets_run_in_order():
    """In a fresh process with the user's XLA flags, not the test session's cheap
    compiles (their slower code makes the README's tuning run take many times longer)."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace(TEST_XLA_FLAGS, "").strip()
    run = subprocess.run(
        [sys.executable, "-c", _RUN_IN_ORDER, str(ROOT / "README.md")],
        capture_output=True,
        text=True,
        env=env,
        timeout=1800,
    )
    assert run.returncode == 0, run.stderr[-3000:]
