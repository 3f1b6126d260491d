"""The Rerun recording as a user sees it: Rerun's own viewer, headless, on a cascade run.

Tracks ``walk_towards`` with the cascade (``--model grid-occlusion --points joints
--background empty``), as ``cpf-track`` writes it with ``--rrd``, opens the recording in
the viewer that ships with rerun-sdk (``rerun --headless``, through
``rerun.experimental.ViewerClient``), pauses at one frame, and checks what the viewer
reports: every view of ``cpf_jax.viz.default_blueprint`` present, with its origin, and no
view reporting an entity it failed to draw. Saves the viewer's screenshot and a table.

The headless viewer renders with Vulkan: on a machine without a GPU it needs a software
driver (Debian: ``apt-get install mesa-vulkan-drivers``, Mesa's llvmpipe); without one the
script says so and exits with status 2.

Writes ``experiments/results/viewer_check.md`` and ``viewer_check.png``.

    python experiments/viewer_check.py [--rrd RUN.rrd] [--frame 20]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
RUN = ["walk_towards", "--model", "grid-occlusion", "--points", "joints", "--background", "empty"]
PORT = 9877  # not the viewer's default 9876, which a user's own viewer may hold


def expected_views() -> dict[str, str]:
    """``{view name: origin}`` of the blueprint a cascade run sends."""
    from cpf_jax.viz import default_blueprint

    bp = default_blueprint(points=True)
    views: dict[str, str] = {}

    def walk(node) -> None:
        for child in getattr(node, "contents", None) or []:
            walk(child)
        if hasattr(node, "origin") and hasattr(node, "name"):
            views[str(node.name)] = str(node.origin).strip("/")

    walk(bp.root_container)
    return views


def fail(message: str, code: int = 2) -> None:
    """Stop with one line on stderr."""
    print(f"viewer_check: {message}", file=sys.stderr)
    sys.exit(code)


def record(rrd: Path) -> None:
    """Write the cascade run's recording with ``cpf-track``, as a user would."""
    cmd = [sys.executable, "-m", "cpf_jax.cli", *RUN, "--rrd", str(rrd), "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        fail(f"cpf-track failed ({done.returncode}):\n{done.stderr}", 1)


def inspect(rrd: Path, frame: int, shot: Path) -> list[tuple[str, str, str, str]]:
    """Open ``rrd`` in a headless viewer at ``frame``, save its screenshot to ``shot`` and
    return ``(view, class, origin, reports)`` per view the viewer shows."""
    import rerun.experimental as rx

    from cpf_jax.viz import viewer_executable

    exe = viewer_executable()
    if exe is None:
        fail("no `rerun` viewer executable (rerun-sdk's rerun_cli) found")
    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp())
    try:
        viewer = rx.ViewerClient.spawn(
            headless=True, port=PORT, hide_welcome_screen=True, executable_path=exe
        )
    except RuntimeError as e:
        fail(f"the headless viewer did not start: {str(e).splitlines()[0]}")
    try:
        viewer.open(str(rrd))
        viewer.set_time("frame", sequence=frame, play_state="paused")
        time.sleep(2.0)  # the views load their chunks and paint
        viewer.save_screenshot(str(shot))
        state = viewer.get_state()
    except RuntimeError as e:  # the viewer died: most often no Vulkan adapter
        fail(
            f"the headless viewer stopped answering ({str(e).splitlines()[0]}); without a "
            "GPU it needs a software Vulkan driver (Debian: apt-get install mesa-vulkan-drivers)"
        )
    finally:
        viewer.quit()
    return [
        (v.name, v.view_class, v.origin.strip("/"), "; ".join(map(str, v.reports)))
        for v in state.views
    ]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--rrd", type=Path, help="a recording to open (default: record the cascade)")
    p.add_argument("--frame", type=int, default=20, help="frame to pause at")
    args = p.parse_args()
    RESULTS.mkdir(exist_ok=True)
    shot = RESULTS / "viewer_check.png"
    with tempfile.TemporaryDirectory() as tmp:
        rrd = args.rrd
        if rrd is None:
            rrd = Path(tmp) / "cascade.rrd"
            record(rrd)
        size = rrd.stat().st_size
        rows = inspect(rrd.resolve(), args.frame, shot)
    expected = expected_views()
    shown = {name: origin for name, _, origin, _ in rows}
    problems = [f"view {n!r} missing" for n in expected if n not in shown]
    problems += [
        f"view {n!r} at {shown[n]!r}, not {o!r}"
        for n, o in expected.items()
        if n in shown and shown[n] != o
    ]
    problems += [f"view {n!r} reports: {r}" for n, _, _, r in rows if r]
    image = cv2.imread(str(shot))
    if image is None or float(np.std(image)) < 5.0:
        problems.append("the screenshot is missing or blank")
    lines = [
        "# The recording in Rerun's viewer (headless)",
        "",
        f"`cpf-track {' '.join(RUN)} --rrd RUN.rrd` ({size / 1e6:.1f} MB), opened in the viewer "
        f"that ships with rerun-sdk (`rerun --headless`, software Vulkan), paused at frame "
        f"{args.frame}. Screenshot: `viewer_check.png`. Regenerate: "
        "`python experiments/viewer_check.py`.",
        "",
        "| view | kind | origin | what it failed to draw |",
        "|---|---|---|---|",
        *(f"| {n} | {c} | `{o}` | {r or 'nothing'} |" for n, c, o, r in sorted(rows)),
        "",
        "Result: "
        + (
            "every view of the blueprint is shown and draws everything."
            if not problems
            else "; ".join(problems)
        ),
        "",
    ]
    (RESULTS / "viewer_check.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
