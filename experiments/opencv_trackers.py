"""OpenCV's CSRT and KCF on one sequence, run by the opencv-contrib environment.

This file imports only NumPy and OpenCV (not cpf_jax): opencv-contrib-python-headless,
which holds the two trackers, cannot share an environment with opencv-python-headless.
`experiments/unseen.py` writes each sequence to an ``.npz`` (``colour`` ``[T, H, W, 3]``
uint8 RGB, ``box`` ``[4]`` xywh) and runs

    .venv-contrib/bin/python experiments/opencv_trackers.py IN.npz OUT.npz

which writes ``csrt`` and ``kcf`` ``[T, 4]`` xywh (frame 0 the start box, NaN where the
tracker reports a failure).
"""

from __future__ import annotations

import sys

import cv2
import numpy as np

TRACKERS = {"csrt": cv2.TrackerCSRT.create, "kcf": cv2.TrackerKCF.create}


def run(make, colour: np.ndarray, box: np.ndarray) -> np.ndarray:
    """``[T, 4]`` boxes of one tracker over ``colour`` from ``box``."""
    out = np.full((len(colour), 4), np.nan, np.float32)
    out[0] = box
    tracker = make()
    tracker.init(cv2.cvtColor(colour[0], cv2.COLOR_RGB2BGR), tuple(int(round(v)) for v in box))
    for t in range(1, len(colour)):
        ok, rect = tracker.update(cv2.cvtColor(colour[t], cv2.COLOR_RGB2BGR))
        if ok:
            out[t] = rect
    return out


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: opencv_trackers.py IN.npz OUT.npz", file=sys.stderr)
        return 2
    data = np.load(argv[0])
    colour, box = data["colour"], data["box"].astype(np.float32)
    np.savez(argv[1], **{name: run(make, colour, box) for name, make in TRACKERS.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
