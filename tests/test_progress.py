"""Tests for cpf_jax.progress (fake clock, in-memory streams)."""

from __future__ import annotations

import io

from cpf_jax.progress import Progress, format_duration, progress


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_format_duration():
    assert format_duration(0) == "0:00"
    assert format_duration(75.4) == "1:15"
    assert format_duration(3725) == "1:02:05"
    assert format_duration(float("nan")) == "?"
    assert format_duration(float("inf")) == "?"


def test_terminal_mode_redraws_with_count_rate_and_eta():
    clock, out = FakeClock(), FakeTTY()
    bar = Progress(10, stream=out, clock=clock, min_interval=0.0)
    assert bar.interactive
    for _ in range(4):
        clock.t += 0.5
        bar.update()
    text = out.getvalue()
    assert text.startswith("\r")
    last = text.split("\r")[-1]
    assert " 4/10 [" in last and "2.0 fps" in last and "ETA 0:03" in last
    bar.close()
    assert out.getvalue().endswith("\n")
    assert out.getvalue().split("\r")[-1].rstrip() == "4/10 frames in 2.0 s (2.0 fps)"


def test_terminal_mode_throttles_redraws():
    clock, out = FakeClock(), FakeTTY()
    bar = Progress(100, stream=out, clock=clock, min_interval=1.0)
    for _ in range(50):
        clock.t += 0.1
        bar.update()
    assert 4 <= out.getvalue().count("\r") <= 6


def test_log_mode_prints_only_the_final_line():
    clock, out = FakeClock(), io.StringIO()
    with Progress(3, stream=out, clock=clock, label="Crossing") as bar:
        for _ in range(3):
            clock.t += 1.0
            bar.update()
            assert out.getvalue() == ""
    assert out.getvalue() == "Crossing 3/3 frames in 3.0 s (1.0 fps)\n"
    bar.close()  # idempotent
    assert out.getvalue().count("\n") == 1


def test_unknown_total_and_iterable_wrapper():
    clock, out = FakeClock(), FakeTTY()
    bar = Progress(None, stream=out, clock=clock, min_interval=0.0)
    clock.t = 2.0
    bar.update(4)
    assert "4 frames  2.0 fps" in out.getvalue()

    def live():  # no len(): like a camera
        yield from range(5)

    out2 = io.StringIO()
    assert list(progress(live(), stream=out2)) == list(range(5))
    assert out2.getvalue().startswith("5 frames in")
    out3 = io.StringIO()
    assert list(progress([1, 2], stream=out3)) == [1, 2]
    assert out3.getvalue().startswith("2/2 frames")


def test_the_line_shows_the_median_step_time_when_given():
    clock, out = FakeClock(), FakeTTY()
    bar = Progress(None, stream=out, clock=clock, min_interval=0.0)
    for ms in (900.0, 12.0, 11.0, 13.0, 10.0):  # the first step (compiled init) is an outlier
        clock.t += 0.1
        bar.update(step_ms=ms)
    assert bar.step_ms == 12.0 and out.getvalue().rstrip().endswith("step 12 ms")
    for _ in range(40):  # a window of the last 30
        bar.update(step_ms=20.0)
    assert bar.step_ms == 20.0
