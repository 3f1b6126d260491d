"""Every Python example of the README and of docs/*.md runs as written, each block alone in
a fresh namespace (a user copies one)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from conftest import ROOT, TEST_XLA_FLAGS

DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def python_blocks(path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_the_readme_has_its_python_snippets():
    blocks = python_blocks(ROOT / "README.md")
    assert len(blocks) >= 4
    assert any("track_boxes" in b for b in blocks) and any("Context(" in b for b in blocks)


# Each block in its own namespace and its own empty working folder; what some leave behind.
_RUN_EACH = """
import os, re, sys, tempfile
checks = {
    "README.md": {0: "namespace['boxes'].shape == (150, 4)",
                  3: "namespace['infos'].points.mean3d.shape[1:] == (5, 3)",
                  4: "namespace['boxes'].shape == (4, 150, 4)"},
}
for path in sys.argv[1:]:
    name = os.path.basename(path)
    for i, block in enumerate(re.findall(r"```python\\n(.*?)```", open(path).read(), flags=re.S)):
        namespace = {}
        os.chdir(tempfile.mkdtemp())
        try:
            exec(compile(block, f"{name} python block {i}", "exec"), namespace)
        except Exception as e:
            raise SystemExit(f"{name} python block {i} fails alone: {e!r}\\n{block}")
        check = checks.get(name, {}).get(i)
        if check is not None and not eval(check):
            raise SystemExit(f"{name} python block {i}: not {check}")
        print(f"{name} python block {i}: ran", flush=True)
"""


@pytest.mark.slow
def test_every_documented_python_example_runs_alone():
    """In a fresh process with the user's XLA flags, not the test session's cheap
    compiles (their slower code makes the README's tuning run take many times longer)."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace(TEST_XLA_FLAGS, "").strip()
    run = subprocess.run(
        [sys.executable, "-c", _RUN_EACH, *map(str, DOCUMENTS)],
        capture_output=True,
        text=True,
        env=env,
        timeout=1800,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    n_blocks = sum(len(python_blocks(p)) for p in DOCUMENTS)
    assert run.stdout.count(": ran") == n_blocks, run.stdout
