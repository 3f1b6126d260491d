"""cpf_jax.charts: the pixel mapping against the plain formula, and lines, gaps and
legends found where they must be in the drawn image."""

import math

import cv2
import numpy as np
import pytest

from cpf_jax import charts

SIZE = (400, 300)


def _axes(log_x=False):
    return charts.Axes((1.0, 100.0) if log_x else (0.0, 10.0), (0.0, 1.0), 50, 40, 301, 201, log_x)


def test_axes_map_corners_and_midpoints_like_the_plain_formula():
    ax = _axes()
    px, py = ax.to_pixels(np.array([0.0, 10.0, 2.5]), np.array([0.0, 1.0, 0.25]))
    np.testing.assert_allclose(px, [50, 350, 50 + 0.25 * 300])
    np.testing.assert_allclose(py, [240, 40, 40 + 0.75 * 200])
    lx, _ = _axes(log_x=True).to_pixels(np.array([1.0, 10.0, 100.0, 0.0]), np.zeros(4))
    np.testing.assert_allclose(lx[:3], [50, 200, 350])
    assert not np.isfinite(lx[3])  # log of 0: no pixel, so no point is drawn


@pytest.mark.parametrize(
    ("lo", "hi", "log", "want"),
    [
        (0.0, 100.0, False, [0, 20, 40, 60, 80, 100]),
        (0.0, 1.0, False, [0, 0.2, 0.4, 0.6, 0.8, 1.0]),
        (-3.0, 7.0, False, [-2, 0, 2, 4, 6]),
        (20.0, 10000.0, True, [20, 50, 100, 200, 500, 1000, 2000, 5000, 10000]),
        (1.0, 1e6, True, [1, 10, 100, 1000, 1e4, 1e5, 1e6]),
    ],
)
def test_nice_ticks(lo, hi, log, want):
    np.testing.assert_allclose(charts.nice_ticks(lo, hi, log=log), want)


def _plot_area(img):
    # The chart's frame is the black rectangle: its first and last dark rows / columns.
    dark = np.all(img < 40, axis=-1)
    rows = np.flatnonzero(dark.sum(1) > 200)
    cols = np.flatnonzero(dark.sum(0) > 150)
    return rows[0], rows[-1], cols[0], cols[-1]


def _is(img, y, x, colour, tol=40):
    return np.all(np.abs(img[y, x].astype(int) - np.array(colour)) <= tol)


def test_a_line_lands_where_the_axes_put_it():
    img = charts.line_chart(
        {"half": ([0, 10], [0.5, 0.5])}, xlim=(0, 10), ylim=(0, 1), size=SIZE, markers=False
    )
    top, bottom, left, right = _plot_area(img)
    mid = round((top + bottom) / 2)
    blue = charts.PALETTE[0]
    for x in range(left + 5, right - 5, 25):
        assert any(_is(img, y, x, blue) for y in (mid - 1, mid, mid + 1)), x
        assert not _is(img, mid - 8, x, blue) and not _is(img, mid + 8, x, blue)
    # One legend line per series below the plot, in the series colour.
    legend = img[bottom + 30 :]
    assert np.any(np.all(np.abs(legend.astype(int) - blue) <= 10, axis=-1))


def test_non_finite_points_break_the_line_and_lines_stay_inside_the_frame():
    x = np.arange(5.0)
    y = np.array([0.5, 0.5, np.nan, 0.5, 0.5])
    img = charts.line_chart(
        {"gap": (x, y), "off": ([0, 4], [1.12, 1.12])},
        xlim=(0, 4),
        ylim=(0, 1),
        size=SIZE,
        markers=False,
    )
    top, bottom, left, right = _plot_area(img)
    mid = round((top + bottom) / 2)
    blue = charts.PALETTE[0]
    at = lambda v: round(left + v / 4 * (right - left))  # noqa: E731
    row = lambda xx: any(_is(img, y, xx, blue) for y in (mid - 1, mid, mid + 1))  # noqa: E731
    assert row(at(0.5)) and row(at(3.5))
    assert not row(at(1.8)) and not row(at(2.2))  # the segments 1-2 and 2-3 are not drawn
    # ... nor anything else of that colour off the line (a NaN cast to a pixel would be).
    inside = img[top + 2 : bottom - 1, left + 2 : right - 1]
    off_line = np.concatenate([inside[: mid - 5 - top - 2], inside[mid + 5 - top - 2 :]])
    assert not np.any(np.all(np.abs(off_line.astype(int) - blue) <= 40, axis=-1))
    # The second series lies just above ylim: none of it is drawn, inside or outside.
    orange = charts.PALETTE[1]
    plot = img[: bottom + 1]
    assert not np.any(np.all(np.abs(plot.astype(int) - orange) <= 30, axis=-1))


def test_log_axis_places_decades_evenly():
    img = charts.line_chart(
        {"v": ([10, 10], [0, 1])}, xlim=(1, 100), ylim=(0, 1), log_x=True, size=SIZE
    )
    top, bottom, left, right = _plot_area(img)
    centre = round((left + right) / 2)
    blue = charts.PALETTE[0]
    mid = round((top + bottom) / 2)
    assert any(_is(img, mid, x, blue) for x in (centre - 1, centre, centre + 1))
    assert not _is(img, mid, centre - 10, blue)


def test_success_plot_labels_curves_with_their_auc_and_draws_the_curve():
    curve = np.linspace(1.0, 0.0, 21)
    img = charts.success_plot({"ours": curve}, size=SIZE)
    top, bottom, left, right = _plot_area(img)
    blue = charts.PALETTE[0]
    # The diagonal from (0, 1) to (1, 0) passes the plot's centre.
    cy, cx = round((top + bottom) / 2), round((left + right) / 2)
    assert any(_is(img, cy + d, cx, blue) for d in (-2, -1, 0, 1, 2))
    assert not _is(img, top + 10, right - 10, blue)
    with pytest.raises(ValueError, match="thresholds"):
        charts.success_plot({"x": curve}, thresholds=np.linspace(0, 1, 5))


def test_bad_input_gets_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="at least one"):
        charts.line_chart({})
    with pytest.raises(ValueError, match="'a'.*3 x values but 2 y"):
        charts.line_chart({"a": ([1, 2, 3], [1, 2])})
    with pytest.raises(ValueError, match="log x axis"):
        charts.line_chart({"a": ([0, 1], [1, 2])}, log_x=True)
    with pytest.raises(ValueError, match="ylim"):
        charts.line_chart({"a": ([0, 1], [1, 2])}, ylim=(1, 1))
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OSError, match="file"):
        charts.save_png(np.zeros((4, 4, 3), np.uint8), blocker / "x.png")


def test_save_png_round_trips(tmp_path):
    img = charts.line_chart({"a": ([0, 1, 2], [3, math.nan, 5])}, size=SIZE)
    path = charts.save_png(img, tmp_path / "sub" / "chart.png")
    np.testing.assert_array_equal(cv2.imread(str(path)), img)
