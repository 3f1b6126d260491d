"""docs/recordings.md as executed: its example folder is built by its own code and tracked,
and its calibration.json examples are read by the code that reads them."""

from __future__ import annotations

import json
import re

import numpy as np
from conftest import ROOT

from cpf_jax.cli import main
from cpf_jax.io import open_source, read_results
from cpf_jax.io.folders import intrinsics_from_calibration
from cpf_jax.registration import calibration_from_dict

DOC = ROOT / "docs" / "recordings.md"


def _blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_calibration_examples_are_read_as_documented():
    intrinsics_only, registration = (json.loads(b) for b in _blocks("json"))
    k = intrinsics_from_calibration(intrinsics_only)
    assert (k.fx, k.cx, k.cy) == (365.0, 255.0, 205.0)
    calib = calibration_from_dict(registration, source="docs/recordings.md")
    assert tuple(calib.depth_size) == (640, 480) and calib.colour.cx == 308.6


def test_the_alignment_example_finds_the_shift_it_says(capsys):
    (example,) = [b for b in _blocks("python") if "check_alignment" in b]
    exec(compile(example, "docs/recordings.md", "exec"), {})
    assert capsys.readouterr().out.startswith("(8, 0) True depth edges lie 8 px left of")


def test_the_minimal_example_folder_is_tracked(tmp_path, monkeypatch, capsys):
    (example,) = [b for b in _blocks("python") if "example_recording" in b]
    monkeypatch.chdir(tmp_path)
    exec(compile(example, "docs/recordings.md", "exec"), {})
    source = open_source("example_recording")
    assert source.kind == "rgbd" and len(source) == 3 and source.first_visible == 1
    assert source.intrinsics.cx == 159.5 and source.occlusion == ["none"] * 3
    np.testing.assert_array_equal(source.gt_boxes[1], [60, 60, 50, 140])  # 0-based
    argv = ["example_recording", "--model", "rgbd", "--background", "1", "--particles", "16"]
    assert main([*argv, "--out", "boxes.csv", "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in err  # registered depth, intrinsics given, millimetres
    assert "scored 2 of 2 tracked frames (1-2" in out
    res = read_results("boxes.csv")
    np.testing.assert_array_equal(res["frame"], [1, 2])
