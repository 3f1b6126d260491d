"""The README's Python snippets run, in order, as one script (a user copies them)."""

from __future__ import annotations

import re

import pytest
from conftest import ROOT


def readme_python() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_the_readme_has_its_python_snippets():
    blocks = readme_python()
    assert len(blocks) >= 4
    assert any("track_boxes" in b for b in blocks) and any("Context(" in b for b in blocks)


@pytest.mark.slow
def test_the_readme_snippets_run_in_order():
    namespace: dict = {}
    for i, block in enumerate(readme_python()):
        try:
            exec(compile(block, f"README.md python block {i}", "exec"), namespace)
        except Exception as e:  # noqa: BLE001 (name the block that failed)
            raise AssertionError(f"README python block {i} fails: {e!r}\n{block}") from e
    assert namespace["boxes"].shape == (4, 150, 4)
    assert namespace["infos"].points.mean3d.shape[1:] == (5, 3)
