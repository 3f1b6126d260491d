"""Contact sheets of the hand annotations of IST images1, for checking them by eye.

Reads ``ist_images1_people.txt`` (MOTChallenge ground truth, 1-based frames and pixels)
and ``ist_images1_points.csv`` next to this script, and the recording from
``../shared/data/ist_piv_rgbd/images1`` (read-only). Draws every person's box with its
id and visibility on frames 27-102, and the target's head, hands and shoulder-centre on
crops around his box in frames 52-90. Writes
``experiments/results/ist_images1_annotations_people_{1..4}.png`` and
``ist_images1_annotations_points_{1,2}.png``. Without the recording it says so and exits
with status 0, writing nothing.

    python experiments/annotations/draw_annotations.py [--data DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
DATA = ROOT.parent / "shared" / "data" / "ist_piv_rgbd" / "images1"
RESULTS = ROOT / "experiments" / "results"
PEOPLE = HERE / "ist_images1_people.txt"
POINTS = HERE / "ist_images1_points.csv"

#: BGR colour of each identity (1 = the target of groundtruth_rect.txt).
ID_COLOURS = {
    1: (0, 255, 255),
    2: (0, 0, 255),
    3: (0, 200, 0),
    4: (255, 0, 255),
    5: (255, 90, 0),
    6: (0, 140, 255),
}
#: BGR colour and marker of each body point.
PART_STYLE = {
    "head": ((0, 0, 255), cv2.MARKER_CROSS),
    "left_hand": ((0, 200, 0), cv2.MARKER_TILTED_CROSS),
    "right_hand": ((255, 0, 255), cv2.MARKER_TILTED_CROSS),
    "torso": ((255, 128, 0), cv2.MARKER_DIAMOND),
}
PEOPLE_FRAMES = range(27, 103)
POINT_FRAMES = range(52, 91)
THUMB = (288, 216)  # people sheets: 0.45 of a 640x480 frame
CELL = (180, 270)  # points sheets: crop around the target, fitted into this cell
COLS = 5
POINT_COLS = 10
PAD = 25  # px of context around the target's box in the point crops


def read_people(path: Path) -> dict[int, list[tuple[int, int, int, int, int, float]]]:
    """``{frame: [(id, x, y, w, h, visibility), ...]}`` with 1-based frames and pixels."""
    out: dict[int, list[tuple[int, int, int, int, int, float]]] = {}
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        f = line.split(",")
        if len(f) != 9:
            raise SystemExit(f"{path}:{n}: expected 9 fields 'frame,id,x,y,w,h,1,1,vis'")
        frame, pid, x, y, w, h = (int(float(v)) for v in f[:6])
        out.setdefault(frame, []).append((pid, x, y, w, h, float(f[8])))
    return out


def read_points(path: Path) -> dict[int, dict[str, tuple[int, int] | None]]:
    """``{frame: {part: (x, y) or None when hidden}}``, 1-based pixels."""
    out: dict[int, dict[str, tuple[int, int] | None]] = {}
    with path.open(encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            xy = (int(row["x"]), int(row["y"])) if row["visible"] == "1" else None
            out.setdefault(int(row["frame"]), {})[row["part"]] = xy
    return out


def frame_image(data: Path, frame: int) -> np.ndarray:
    """Colour frame ``frame`` (1-based) as BGR uint8."""
    path = data / "rgb" / f"images{frame:08d}.jpg"
    img = cv2.imread(str(path))
    if img is None:
        raise SystemExit(f"{path}: cannot read the colour frame")
    return img


def label(img: np.ndarray, text: str, org: tuple[int, int], colour, scale: float = 0.5) -> None:
    """Text with a black outline so it reads on any background."""
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def draw_people(img: np.ndarray, people, scale: float = 1.0) -> None:
    """Each box (1-based, inclusive extent ``x .. x+w-1``) with ``id`` and visibility, on
    ``img`` resized by ``scale`` from the 640x480 frame."""
    for pid, x, y, w, h, vis in people:
        c = ID_COLOURS.get(pid, (255, 255, 255))
        p0 = (round((x - 1) * scale), round((y - 1) * scale))
        p1 = (round((x + w - 2) * scale), round((y + h - 2) * scale))
        cv2.rectangle(img, p0, p1, c, 2 if pid == 1 else 1)
        label(img, f"{pid}:{vis:.2f}", (p0[0] + 2, p0[1] + 12), c, 0.4)


def draw_points(img: np.ndarray, parts, origin=(0, 0), scale: float = 1.0) -> None:
    """Each visible point (1-based pixels) as its marker on ``img``, a crop of the frame
    whose top-left 0-based pixel is ``origin``, resized by ``scale``."""
    for part, xy in parts.items():
        if xy is None:
            continue
        c, marker = PART_STYLE[part]
        p = (round((xy[0] - 1 - origin[0]) * scale), round((xy[1] - 1 - origin[1]) * scale))
        cv2.circle(img, p, 5, (0, 0, 0), 2)
        cv2.drawMarker(img, p, c, marker, 12, 2)


def grid(tiles: list[np.ndarray], cols: int) -> np.ndarray:
    """Tiles of one size in rows of ``cols``, white where a row is short."""
    h, w = tiles[0].shape[:2]
    rows = []
    for i in range(0, len(tiles), cols):
        row = tiles[i : i + cols]
        row += [np.full((h, w, 3), 255, np.uint8)] * (cols - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def legend(width: int, items: list[tuple[str, tuple[int, int, int]]]) -> np.ndarray:
    """A white strip naming each colour."""
    strip = np.full((26, width, 3), 255, np.uint8)
    x = 8
    for text, c in items:
        cv2.rectangle(strip, (x, 7), (x + 14, 19), c, -1)
        cv2.putText(strip, text, (x + 20, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        x += 30 + 9 * len(text)
    return strip


def compact(img: np.ndarray) -> np.ndarray:
    """The sheet through JPEG (quality 80) and 5-bit colour, so the PNG stays small."""
    ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    return cv2.imdecode(jpeg, cv2.IMREAD_COLOR) & 0xF8


def write(img: np.ndarray, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), compact(img), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise SystemExit(f"{path}: cannot write the sheet")
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")


def people_sheets(data: Path, people, out: Path) -> None:
    """Frames 27-102, 20 a sheet, every box with id and visibility."""
    frames = list(PEOPLE_FRAMES)
    names = {1: "1 target", 2: "2", 3: "3", 4: "4", 5: "5", 6: "6"}
    for k, start in enumerate(range(0, len(frames), 20), start=1):
        tiles = []
        for frame in frames[start : start + 20]:
            img = cv2.resize(frame_image(data, frame), THUMB, interpolation=cv2.INTER_AREA)
            draw_people(img, people.get(frame, []), THUMB[0] / 640)
            label(img, f"frame {frame}", (THUMB[0] - 92, 14), (255, 255, 255), 0.45)
            tiles.append(img)
        sheet = grid(tiles, COLS)
        items = [(f"id {names[i]}", c) for i, c in ID_COLOURS.items()]
        sheet = np.concatenate([legend(sheet.shape[1], items), sheet], axis=0)
        write(sheet, out / f"ist_images1_annotations_people_{k}.png")


def point_tile(data: Path, frame: int, box, parts) -> np.ndarray:
    """Crop around the target's box, points drawn, fitted into ``CELL`` with a frame label."""
    img = frame_image(data, frame)
    if box is not None:
        _, x, y, w, h, _ = box
        cv2.rectangle(img, (x - 1, y - 1), (x + w - 2, y + h - 2), ID_COLOURS[1], 1)
        x0, y0 = max(0, x - 1 - PAD), max(0, y - 1 - PAD)
        x1, y1 = min(640, x + w - 1 + PAD), min(480, y + h - 1 + PAD)
    else:
        x0, y0, x1, y1 = 0, 0, 640, 480
    crop = img[y0:y1, x0:x1]
    s = min(CELL[0] / crop.shape[1], (CELL[1] - 18) / crop.shape[0])
    crop = cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    draw_points(crop, parts, (x0, y0), s)
    tile = np.full((CELL[1], CELL[0], 3), 255, np.uint8)
    tile[18 : 18 + crop.shape[0], : crop.shape[1]] = crop
    hidden = [p.replace("_hand", "") for p, xy in parts.items() if xy is None]
    text = f"{frame}" + (f" hid: {','.join(hidden)}" if hidden else "")
    cv2.putText(tile, text, (2, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 1)
    return tile


def point_sheets(data: Path, people, points, out: Path) -> None:
    """Frames 52-90: the target's head, hands and shoulder-centre on crops around him."""
    frames = list(POINT_FRAMES)
    half = (len(frames) + 1) // 2
    for k, chunk in enumerate((frames[:half], frames[half:]), start=1):
        tiles = []
        for frame in chunk:
            box = next((p for p in people.get(frame, []) if p[0] == 1), None)
            tiles.append(point_tile(data, frame, box, points.get(frame, {})))
        sheet = grid(tiles, POINT_COLS)
        items = [(p, c) for p, (c, _) in PART_STYLE.items()]
        sheet = np.concatenate([legend(sheet.shape[1], items), sheet], axis=0)
        write(sheet, out / f"ist_images1_annotations_points_{k}.png")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="the images1 folder (rgb/)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder for the sheets")
    args = ap.parse_args(argv)
    if not (args.data / "rgb").is_dir():
        print(f"skipped: the recording is not available at {args.data} (read-only shared data)")
        return 0
    people = read_people(PEOPLE)
    points = read_points(POINTS)
    people_sheets(args.data, people, args.out)
    point_sheets(args.data, people, points, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
