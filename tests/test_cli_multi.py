"""cpf-track --multi on a recorded folder: MOTChallenge lines as it goes, the scores against
a MOTChallenge ground truth, the Rerun log's people and events, and the options that do
not go with it."""

from __future__ import annotations

import cv2
import pytest

from cpf_jax.cli import main
from cpf_jax.io.mot import read_mot
from cpf_jax.synthetic_multi import make_people_sequence, people_truth

EMPTY = 3  # empty frames before the people: the background (--background 0:3)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    seq = make_people_sequence("two_crossing", 6, n_frames=16)
    root = tmp_path_factory.mktemp("crossing")
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    bg_colour, bg_depth = seq.meta["background_colour"], seq.meta["background_depth"]
    colour = [bg_colour] * EMPTY + list(seq.colour)
    depth = [bg_depth] * EMPTY + list(seq.depth)
    for t, (c, d) in enumerate(zip(colour, depth, strict=True)):
        cv2.imwrite(str(root / "rgb" / f"{t:06d}.png"), cv2.cvtColor(c, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{t:06d}.png"), d)
    gt = people_truth(seq)
    with open(root / "gt.txt", "w") as fh:
        for f, i, x, y, w, h, _, _, v in gt:
            fh.write(f"{int(f) + EMPTY + 1},{int(i)},{x + 1:g},{y + 1:g},{w:g},{h:g},1,1,{v:.2f}\n")
    return root


def test_multi_writes_mot_lines_and_scores_them(folder, tmp_path, capsys):
    mot, rrd = tmp_path / "out.txt", tmp_path / "run.rrd"
    code = main(
        [
            str(folder),
            "--multi",
            "--mot",
            str(mot),
            "--mot-gt",
            str(folder / "gt.txt"),
            "--rrd",
            str(rrd),
            "--background",
            f"0:{EMPTY}",
            "--particles",
            "64",
            "--max-people",
            "3",
            "--no-progress",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    lines = mot.read_text().splitlines()
    assert lines and all(len(line.split(",")) == 10 for line in lines)
    assert all(line.endswith(",-1,-1,-1") for line in lines)
    rows = read_mot(mot)
    assert rows[:, 0].min() >= EMPTY  # nobody in the empty frames
    assert "MOTA" in out and "id switches" in out
    mota = float(out.split("MOTA ")[1].split(" %")[0])
    assert mota > 50.0, out
    from test_viz import read_rrd

    log = read_rrd(str(rrd))
    assert "/world/camera/people" in log and "/events" in log
    texts = [str(r["TextLog:text"][0]) for r in log["/events"]["rows"]]
    assert any(t.endswith("born") for t in texts), texts


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--multi", "--init", "1,2,3,4"], "do not go with --multi"),
        (["--multi", "--background", "learn"], "--background expects"),
        (["--mot", "x.txt"], "go with --multi"),
        (["--multi", "--max-people", "0"], "--max-people"),
    ],
)
def test_multi_option_errors(folder, capsys, extra, message):
    assert main([str(folder), *extra]) == 2
    assert message in capsys.readouterr().err


def test_multi_reads_the_quiet_frames_under_the_default_background(folder):
    # --background none (each frame its own scene) is the single-person default; --multi
    # takes --background auto's quiet frames unless told --background none.
    from cpf_jax.cli.inputs import open_inputs
    from cpf_jax.cli.multi import check_multi_options
    from cpf_jax.cli.options import build_parser
    from cpf_jax.io import open_source

    args = build_parser().parse_args([str(folder), "--multi", "--no-progress"])
    assert args.background is None
    check_multi_options(args)
    with open_source(folder) as source:
        inputs = open_inputs(args, source)
        assert inputs.background is not None
        assert inputs.start == 0
    single = build_parser().parse_args(
        [str(folder), "--model", "grid-occlusion", "--init", "1,1,9,9"]
    )
    with open_source(folder) as source:
        assert open_inputs(single, source).background is None


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    """Two people standing apart in every frame (``two_crossing``'s frame 30, ten times):
    a scene never seen empty."""
    seq = make_people_sequence("two_crossing", 6, n_frames=31)
    root = tmp_path_factory.mktemp("crowded")
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    truth = people_truth(seq)
    truth = truth[truth[:, 0] == 30]
    with open(root / "gt.txt", "w") as fh:
        for t in range(10):
            cv2.imwrite(
                str(root / "rgb" / f"{t:06d}.png"), cv2.cvtColor(seq.colour[30], cv2.COLOR_RGB2BGR)
            )
            cv2.imwrite(str(root / "depth" / f"{t:06d}.png"), seq.depth[30])
            for _, i, x, y, w, h, _, _, v in truth:
                fh.write(f"{t + 1},{int(i)},{x + 1:g},{y + 1:g},{w:g},{h:g},1,1,{v:.2f}\n")
    return root


def _mota(folder, tmp_path, capsys, background: str) -> float:
    argv = [str(folder), "--multi", "--mot", str(tmp_path / f"{background}.txt")]
    argv += ["--mot-gt", str(folder / "gt.txt"), "--background", background]
    assert main([*argv, "--particles", "64", "--max-people", "3", "--no-progress"]) == 0
    return float(capsys.readouterr().out.split("MOTA ")[1].split(" %")[0])


def test_multi_without_background_frames_reads_each_frames_scene(crowded, tmp_path, capsys):
    # Nobody ever moves: the quiet frames (--background auto, what --multi read before
    # --background none) hold the people, and births against them find nobody; each
    # frame's own scene (--background none) finds both.
    framed = _mota(crowded, tmp_path, capsys, "none")
    quiet = _mota(crowded, tmp_path, capsys, "auto")
    assert framed > 50.0 and framed > quiet + 20.0, (framed, quiet)
