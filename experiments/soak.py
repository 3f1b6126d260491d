"""A long run as a user makes it: ``cpf-track`` on a 10,000-frame video, its memory sampled.

The video is the synthetic ``walk_across_medium`` (colour, 512 x 424) played forwards and
backwards until it is ``--frames`` long, written as Motion-JPEG to a temporary file.
``cpf-track VIDEO --init BOX --out rows.csv`` then runs in a process of its own with the
defaults (colour layer, N = 200, no Rerun log), once with ``--no-tune-malloc`` (glibc's
default allocator) and once as shipped. While it runs, the process's resident memory
(``/proc/PID/status`` VmRSS) is read every ``--every`` seconds together with the number of
rows its CSV holds (rows are written as the run goes), which gives the memory at each
frame. A leak grows with the frames; an allocator's fragmentation grows, then levels off.

Writes ``experiments/results/soak.json`` and ``soak.md`` (memory at frames 1,000 and
10,000, growth per 1,000 frames over the second half, frames/s).

    python experiments/soak.py [--frames 10000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE))

import host  # noqa: E402

SCENARIO = "walk_across_medium"
CHECKPOINTS = (1_000, 10_000)


def write_video(path: Path, n_frames: int) -> np.ndarray:
    """``n_frames`` of the scenario, forwards then backwards, as Motion-JPEG at ``path``;
    returns the first frame's ground-truth box (x, y, w, h)."""
    from cpf_jax.synthetic import make_sequence

    seq = make_sequence(SCENARIO, seed=0)
    t = len(seq.colour)
    order = np.concatenate([np.arange(t), np.arange(t - 2, 0, -1)])  # a ping-pong cycle
    h, w = seq.colour.shape[1:3]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    if not out.isOpened():
        sys.exit(f"soak: cannot write {path} (OpenCV has no Motion-JPEG writer)")
    for i in range(n_frames):
        out.write(np.ascontiguousarray(seq.colour[order[i % len(order)]][..., ::-1]))
    out.release()
    return np.asarray(seq.boxes[0], np.float64)


def rss_mb(pid: int) -> float | None:
    """Resident memory of ``pid`` in MB, or None once it has gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def rows_written(csv: Path) -> int:
    """Data rows in the CSV so far (the header is one line)."""
    try:
        with open(csv, "rb") as f:
            return max(sum(1 for _ in f) - 1, 0)
    except OSError:
        return 0


def run(video: Path, box: np.ndarray, tmp: Path, every: float, extra: list[str]) -> dict:
    """One ``cpf-track`` run on ``video``: ``{"samples": [[frame, MB], ...], "fps", ...}``."""
    csv = tmp / f"rows{len(extra)}.csv"
    init = ",".join(f"{v:g}" for v in box)
    cmd = [sys.executable, "-m", "cpf_jax.cli", str(video), "--init", init, "--out", str(csv)]
    cmd += ["--no-progress", *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    samples: list[list[float]] = []
    while proc.poll() is None:
        mb = rss_mb(proc.pid)
        if mb is not None:
            samples.append([rows_written(csv), round(mb, 1)])
        time.sleep(every)
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"soak: {' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr.read()}")
    frames = rows_written(csv)
    return {"command": cmd[2:], "samples": samples, "frames": frames, "fps": frames / elapsed}


def memory_at(samples: list[list[float]], frame: int) -> float | None:
    """The resident memory (MB) sampled nearest ``frame`` once tracking reached it."""
    after = [mb for f, mb in samples if f >= frame]
    return after[0] if after else None


def growth_per_1000(samples: list[list[float]], n_frames: int) -> float:
    """Least-squares slope of memory against frame over the run's second half, MB per 1,000."""
    pts = np.array([(f, mb) for f, mb in samples if f >= n_frames / 2], np.float64)
    if len(pts) < 3:
        return float("nan")
    return float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0] * 1000.0)


def summary(runs: dict, n_frames: int) -> dict:
    out = {"host": host.describe(), "frames": n_frames, "scenario": SCENARIO}
    for name, r in runs.items():
        out[name] = {
            "fps": round(r["fps"], 1),
            **{f"rss_mb_at_{c}": memory_at(r["samples"], min(c, n_frames)) for c in CHECKPOINTS},
            "peak_mb": max(mb for _, mb in r["samples"]),
            "growth_mb_per_1000_frames_second_half": round(
                growth_per_1000(r["samples"], n_frames), 2
            ),
            "command": " ".join(r["command"]),
            "samples": r["samples"],
        }
    return out


def markdown(s: dict) -> str:
    lines = [
        "# A long run's memory (soak)",
        "",
        f"`cpf-track` on a {s['frames']:,}-frame Motion-JPEG video of `{s['scenario']}` "
        "(512 x 424, played forwards and backwards), the defaults (colour layer, N = 200, "
        "CSV rows, no Rerun log), resident memory read from /proc while it runs. "
        f"Host: {s['host']}. Regenerate: `python experiments/soak.py`.",
        "",
        "| allocator | frames/s | MB at frame 1,000 | MB at frame 10,000 | peak MB "
        "| MB per 1,000 frames, second half |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, label in (
        ("default_malloc", "glibc default (`--no-tune-malloc`)"),
        ("tuned_malloc", "as shipped (`tune_malloc`)"),
    ):
        r = s[name]
        lines.append(
            f"| {label} | {r['fps']:.1f} | {r['rss_mb_at_1000']} | {r['rss_mb_at_10000']} | "
            f"{r['peak_mb']} | {r['growth_mb_per_1000_frames_second_half']:+.2f} |"
        )
    lines.append("")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--frames", type=int, default=10_000, help="length of the video")
    p.add_argument("--every", type=float, default=0.5, help="seconds between memory samples")
    p.add_argument("--no-write", action="store_true", help="print, do not write results")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        video = tmp / "soak.avi"
        box = write_video(video, args.frames)
        runs = {
            "default_malloc": run(video, box, tmp, args.every, ["--no-tune-malloc"]),
            "tuned_malloc": run(video, box, tmp, args.every, []),
        }
    s = summary(runs, args.frames)
    text = markdown(s)
    print(text)
    if not args.no_write:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "soak.json").write_text(json.dumps(s, indent=1) + "\n")
        (RESULTS / "soak.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
