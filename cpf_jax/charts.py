"""Line charts drawn with OpenCV: the experiments' figures, and success plots for users.

Usage::

    from cpf_jax import charts

    img = charts.line_chart(
        {"ours": (n_particles, success), "thesis": (n_particles, thesis)},
        title="Table 3.1", xlabel="particles N", ylabel="success rate (%)", ylim=(0, 100),
    )
    charts.save_png(img, "experiments/results/table_3_1.png")
    # OTB success plots from per-frame IoUs (cpf_jax.metrics.success_curve):
    img = charts.success_plot({"default": curve_a, "layout": curve_b}, title="Crossing")

Images are ``[H, W, 3] uint8`` in OpenCV's BGR order. Nothing here needs a plotting
library: opencv-python-headless is already a dependency, and the figures are plain
axes, ticks, polylines with markers and a legend below the plot. Non-finite points
(NaN, inf) leave a gap in their line. Everything is NumPy at the edge; no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ["PALETTE", "Axes", "nice_ticks", "line_chart", "success_plot", "save_png"]

#: Okabe-Ito colours (readable by colour-blind viewers), BGR; series take them in order.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (178, 114, 0),  # blue
    (0, 94, 213),  # vermillion
    (115, 158, 0),  # bluish green
    (0, 159, 230),  # orange
    (167, 121, 204),  # reddish purple
    (233, 180, 86),  # sky blue
    (66, 228, 240),  # yellow
    (0, 0, 0),  # black
)

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_TEXT = 0.4  # font scale of labels
_LINE_H = 16  # px per legend line
_INK = (0, 0, 0)
_GRID = (225, 225, 225)


@dataclass(frozen=True)
class Axes:
    """Maps data coordinates to pixels of the plot area (``width x height`` from ``left, top``).

    ``y`` grows upwards in data and downwards in pixels; with ``log_x`` the x axis is
    logarithmic (``xlim`` must then be positive).
    """

    xlim: tuple[float, float]
    ylim: tuple[float, float]
    left: int
    top: int
    width: int
    height: int
    log_x: bool = False

    def to_pixels(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(px, py)`` float pixel coordinates of data points ``x, y`` (any shape)."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        x0, x1 = self.xlim
        if self.log_x:
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (np.log10(x) - math.log10(x0)) / (math.log10(x1) - math.log10(x0))
        else:
            u = (x - x0) / (x1 - x0)
        v = (y - self.ylim[0]) / (self.ylim[1] - self.ylim[0])
        return self.left + u * (self.width - 1), self.top + (1.0 - v) * (self.height - 1)


def nice_ticks(lo: float, hi: float, target: int = 5, log: bool = False) -> list[float]:
    """Tick values inside ``[lo, hi]``: steps of 1, 2 or 5 x 10^k giving about ``target``
    ticks, or every power of ten (and 2x, 5x when there are few decades) for ``log``."""
    if log:
        ticks = []
        decades = math.log10(hi) - math.log10(lo)
        mults = (1, 2, 5) if decades <= 3 else (1,)
        for k in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1):
            ticks += [
                m * 10.0**k for m in mults if lo * (1 - 1e-9) <= m * 10.0**k <= hi * (1 + 1e-9)
            ]
        return ticks
    raw = (hi - lo) / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    n = int(math.floor((hi - first) / step + 1e-9)) + 1
    return [round(first + i * step, 12) for i in range(n)]


def _format(v: float) -> str:
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
        return f"{v:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{v:g}"


def _limits(values: list[np.ndarray], given, log: bool, name: str) -> tuple[float, float]:
    if given is not None:
        lo, hi = float(given[0]), float(given[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"{name} must be two finite numbers with lo < hi, got {given}")
        if log and lo <= 0:
            raise ValueError(f"{name} of a log axis must be positive, got {given}")
        return lo, hi
    finite = np.concatenate([v[np.isfinite(v)] for v in values]) if values else np.zeros(0)
    if log:
        finite = finite[finite > 0]
    if finite.size == 0:
        return (1.0, 10.0) if log else (0.0, 1.0)
    lo, hi = float(finite.min()), float(finite.max())
    if log:
        return (lo / 2, hi * 2) if lo == hi else (lo / 1.2, hi * 1.2)
    if lo == hi:
        return lo - 1.0, hi + 1.0
    pad = 0.05 * (hi - lo)
    return lo - pad, hi + pad


def _series_arrays(series, log_x: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{label: (x, y)}`` as flat float64 arrays, checked (see :func:`line_chart`)."""
    if not series:
        raise ValueError("line_chart needs at least one series")
    data = {}
    for label, pair in series.items():
        if len(pair) != 2:
            raise ValueError(f"series {label!r} must be an (x, y) pair")
        x = np.asarray(pair[0], np.float64).reshape(-1)
        y = np.asarray(pair[1], np.float64).reshape(-1)
        if x.shape != y.shape:
            raise ValueError(f"series {label!r}: {x.size} x values but {y.size} y values")
        if log_x and np.any(np.isfinite(x) & (x <= 0)):
            raise ValueError(f"series {label!r} has x <= 0 on a log x axis")
        data[label] = (x, y)
    return data


def _chart_axes(data, xlim, ylim, log_x: bool, size: tuple[int, int]) -> Axes:
    """The plot area inside fixed margins (tick labels left, axis label below, title
    above), with limits from the data where not given."""
    xs = [x[np.isfinite(y)] for x, y in data.values()]
    ys = [y[np.isfinite(x)] for x, y in data.values()]
    xlim = _limits(xs, xlim, log_x, "xlim")
    ylim = _limits(ys, ylim, False, "ylim")
    width, height = int(size[0]), int(size[1])
    left, right, top, bottom = 58, 16, 48, 44
    if width < left + right + 20 or height < top + bottom + 20:
        raise ValueError(f"size {size} is too small for a chart")
    return Axes(xlim, ylim, left, top, width - left - right, height - top - bottom, log_x)


def _ends(axes: Axes) -> tuple[int, int]:
    """Last pixel column and row of the plot area."""
    return axes.left + axes.width - 1, axes.top + axes.height - 1


def _draw_ticks(img: np.ndarray, axes: Axes) -> None:
    """Grid lines, tick marks and tick labels of both axes, and the plot frame."""
    x_end, y_end = _ends(axes)
    xlim, ylim = axes.xlim, axes.ylim
    for t in nice_ticks(*ylim):
        _, py = axes.to_pixels(np.array(xlim[0]), np.array(t))
        py = int(round(float(py)))
        cv2.line(img, (axes.left, py), (x_end, py), _GRID, 1)
        cv2.line(img, (axes.left - 4, py), (axes.left, py), _INK, 1)
        text = _format(t)
        (tw, _), _ = cv2.getTextSize(text, _FONT, _TEXT, 1)
        cv2.putText(img, text, (axes.left - 7 - tw, py + 4), _FONT, _TEXT, _INK, 1, cv2.LINE_AA)
    for t in nice_ticks(*xlim, target=6, log=axes.log_x):
        px, _ = axes.to_pixels(np.array(t), np.array(ylim[0]))
        px = int(round(float(px)))
        cv2.line(img, (px, axes.top), (px, y_end), _GRID, 1)
        cv2.line(img, (px, y_end), (px, y_end + 4), _INK, 1)
        text = _format(t)
        (tw, _), _ = cv2.getTextSize(text, _FONT, _TEXT, 1)
        cv2.putText(img, text, (px - tw // 2, y_end + 17), _FONT, _TEXT, _INK, 1, cv2.LINE_AA)
    cv2.rectangle(img, (axes.left, axes.top), (x_end, y_end), _INK, 1)


def _draw_series(canvas: np.ndarray, axes: Axes, x, y, colour, markers: bool) -> None:
    """One series as anti-aliased polylines with 4 fractional bits; consecutive finite
    points form one polyline and a non-finite point breaks it."""
    px, py = axes.to_pixels(x, y)
    ok = np.isfinite(px) & np.isfinite(py)
    pts = np.stack([px, py], -1)
    run: list[np.ndarray] = []
    for j in range(len(x) + 1):
        if j < len(x) and ok[j]:
            run.append(pts[j])
            continue
        if len(run) > 1:
            line = np.round(np.array(run) * 16).astype(np.int32)
            cv2.polylines(canvas, [line], False, colour, 2, cv2.LINE_AA, shift=4)
        run = []
    if markers:
        for p in pts[ok]:
            centre = (int(round(p[0] * 16)), int(round(p[1] * 16)))
            cv2.circle(canvas, centre, 3 * 16, colour, -1, cv2.LINE_AA, shift=4)


def _draw_legend_entry(img: np.ndarray, axes: Axes, height: int, i: int, label, colour) -> None:
    """Line ``i`` of the legend below the plot block of ``height`` pixels."""
    ly = height + _LINE_H * i + 10
    cv2.line(img, (axes.left, ly), (axes.left + 24, ly), colour, 2, cv2.LINE_AA)
    cv2.putText(img, label, (axes.left + 32, ly + 4), _FONT, _TEXT, _INK, 1, cv2.LINE_AA)


def _draw_labels(img: np.ndarray, axes: Axes, title: str, xlabel: str, ylabel: str) -> None:
    """Title above the plot, y label above the y axis, x label centred below the x axis."""
    _, y_end = _ends(axes)
    cv2.putText(img, title, (axes.left, 20), _FONT, 0.5, _INK, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, axes.top - 12), _FONT, _TEXT, _INK, 1, cv2.LINE_AA)
    (tw, _), _ = cv2.getTextSize(xlabel, _FONT, _TEXT, 1)
    origin = (axes.left + (axes.width - tw) // 2, y_end + 36)
    cv2.putText(img, xlabel, origin, _FONT, _TEXT, _INK, 1, cv2.LINE_AA)


def line_chart(
    series: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
    log_x: bool = False,
    size: tuple[int, int] = (640, 360),
    markers: bool = True,
    colours: Mapping[str, tuple[int, int, int]] | None = None,
) -> np.ndarray:
    """One line per series, ``{label: (x, y)}``, on shared axes; returns a BGR image.

    Args:
      series: label -> (x values, y values) of equal length; non-finite points leave
        gaps. Series are drawn in order, in ``PALETTE`` colours unless ``colours``
        names one.
      title, xlabel, ylabel: text above the plot, below the x axis, above the y axis.
      xlim, ylim: axis ranges (default: the finite data, padded by 5 %).
      log_x: logarithmic x axis (every x must then be positive or non-finite).
      size: (width, height) in pixels of the plot block; the legend adds one line per
        series below it.
      markers: a small circle on every finite point.

    Raises:
      ValueError: no series, a series whose x and y lengths differ, non-positive x on
        a log axis, or unusable limits.
    """
    data = _series_arrays(series, log_x)
    axes = _chart_axes(data, xlim, ylim, log_x, size)
    width, height = int(size[0]), int(size[1])
    img = np.full((height + _LINE_H * len(data) + 6, width, 3), 255, np.uint8)
    _draw_ticks(img, axes)
    # Lines are clipped to the plot area: draw them on a copy and paste the area back.
    canvas = img.copy()
    for i, (label, (x, y)) in enumerate(data.items()):
        colour = (colours or {}).get(label, PALETTE[i % len(PALETTE)])
        _draw_series(canvas, axes, x, y, colour, markers)
        _draw_legend_entry(img, axes, height, i, label, colour)
    x_end, y_end = _ends(axes)
    inner = (slice(axes.top + 1, y_end), slice(axes.left + 1, x_end))
    img[inner] = canvas[inner]
    _draw_labels(img, axes, title, xlabel, ylabel)
    return img


def success_plot(
    curves: Mapping[str, Sequence[float]],
    *,
    title: str = "",
    thresholds: Sequence[float] | None = None,
    size: tuple[int, int] = (640, 360),
) -> np.ndarray:
    """OTB success plot: for each label, the fraction of frames with ``IoU > t`` against
    the overlap threshold ``t`` (``cpf_jax.metrics.success_curve``, default thresholds
    0, 0.05, ..., 1), labelled with its AUC (the curve's mean, in percent)."""
    if not curves:
        raise ValueError("success_plot needs at least one curve")
    series = {}
    for label, curve in curves.items():
        c = np.asarray(curve, np.float64).reshape(-1)
        t = np.linspace(0.0, 1.0, c.size) if thresholds is None else np.asarray(thresholds)
        if t.shape != c.shape:
            raise ValueError(f"curve {label!r}: {c.size} values but {t.size} thresholds")
        series[f"{label} (AUC {100 * np.mean(c):.1f})"] = (t, c)
    return line_chart(
        series,
        title=title,
        xlabel="overlap threshold (IoU)",
        ylabel="success rate",
        xlim=(0.0, 1.0),
        ylim=(0.0, 1.0),
        size=size,
        markers=False,
    )


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write ``image`` (BGR) to ``path`` as PNG, creating parent folders; returns the path.

    Raises:
      OSError: naming the path, when it cannot be written.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(path), np.ascontiguousarray(image))
    except (OSError, cv2.error) as exc:
        raise OSError(f"{path}: cannot write the image ({exc})") from exc
    if not ok:
        raise OSError(f"{path}: cannot write the image (OpenCV refused it)")
    return path
