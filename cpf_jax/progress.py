"""A small dependency-free progress bar for the command line.

On a terminal it redraws one line on stderr (``  37/120 [=====     ]  12.3 fps  ETA 0:07``,
with ``  step 41 ms`` when the caller says how long its steps take)
at most every ``min_interval`` seconds. When the stream is not a terminal (a log
file, CI, a pipe) it prints nothing while running and one summary line at the end,
so logs stay readable. Live sources have no length: pass ``total=None`` and the
bar shows the count and rate only.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import IO, TypeVar

__all__ = ["Progress", "progress", "format_duration"]

T = TypeVar("T")

_BAR_WIDTH = 20
STEP_WINDOW = 30  # steps the shown step time is the median of (a second of a 30 Hz camera)


def format_duration(seconds: float) -> str:
    """``75.4 -> '1:15'``, ``3725 -> '1:02:05'``; negative or non-finite -> ``'?'``."""
    if not seconds >= 0 or seconds == float("inf"):
        return "?"
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """Count steps and report ``i/T``, frames per second and the time left.

    Args:
      total: number of steps, or ``None`` when unknown (live cameras).
      stream: where to write (default ``sys.stderr``).
      label: text put before the counter.
      min_interval: seconds between redraws on a terminal.
      interactive: force terminal (True) or log (False) mode; default asks the stream.
      clock: a monotonic clock in seconds (tests pass a fake one).

    Use as a context manager or call :meth:`close` to print the final line.
    """

    def __init__(
        self,
        total: int | None = None,
        *,
        stream: IO[str] | None = None,
        label: str = "",
        min_interval: float = 0.1,
        interactive: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.label = label
        self.min_interval = min_interval
        if interactive is None:
            isatty = getattr(self.stream, "isatty", None)
            interactive = bool(isatty and isatty())
        self.interactive = interactive
        self._clock = clock
        self.count = 0
        self._start = clock()
        self._last_draw = -float("inf")
        self._closed = False
        self._width = 0
        self._step_ms: list[float] = []  # the last STEP_WINDOW steps' times

    @property
    def elapsed(self) -> float:
        """Seconds since the bar was made."""
        return self._clock() - self._start

    @property
    def rate(self) -> float:
        """Steps per second so far (0 before the first step or with no elapsed time)."""
        elapsed = self.elapsed
        return self.count / elapsed if elapsed > 0 else 0.0

    @property
    def step_ms(self) -> float | None:
        """Median time of the last :data:`STEP_WINDOW` steps given to :meth:`update`, or None."""
        if not self._step_ms:
            return None
        times = sorted(self._step_ms)
        return times[len(times) // 2]

    def line(self) -> str:
        """The status text for the current count (no carriage return)."""
        prefix = f"{self.label} " if self.label else ""
        rate = self.rate
        step = "" if self.step_ms is None else f"  step {self.step_ms:.0f} ms"
        if self.total is None:
            return (
                f"{prefix}{self.count} frames  {rate:.1f} fps  "
                f"{format_duration(self.elapsed)}{step}"
            )
        total = max(self.total, 0)
        frac = min(self.count / total, 1.0) if total else 1.0
        filled = int(round(frac * _BAR_WIDTH))
        bar = "=" * filled + " " * (_BAR_WIDTH - filled)
        eta = (total - self.count) / rate if rate > 0 else float("nan")
        digits = len(str(total))
        return (
            f"{prefix}{self.count:>{digits}}/{total} [{bar}]  {rate:.1f} fps  "
            f"ETA {format_duration(eta)}{step}"
        )

    def update(self, n: int = 1, step_ms: float | None = None) -> None:
        """Record ``n`` more finished steps (the last of them taking ``step_ms``, when
        given); redraw when on a terminal and due."""
        self.count += n
        if step_ms is not None:
            self._step_ms = [*self._step_ms[-(STEP_WINDOW - 1) :], float(step_ms)]
        if not self.interactive:
            return
        now = self._clock()
        done = self.total is not None and self.count >= self.total
        if done or now - self._last_draw >= self.min_interval:
            self._last_draw = now
            self._draw(self.line())

    def _draw(self, text: str) -> None:
        pad = max(self._width - len(text), 0)
        self._width = len(text)
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()

    def clear(self) -> None:
        """Blank the bar's line on a terminal, so that another line can be printed there
        (the next :meth:`update` draws the bar again)."""
        if self.interactive and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0

    def close(self) -> None:
        """Print the final summary line once (in both modes)."""
        if self._closed:
            return
        self._closed = True
        elapsed = self.elapsed
        prefix = f"{self.label} " if self.label else ""
        of = f"/{self.total}" if self.total is not None else ""
        text = f"{prefix}{self.count}{of} frames in {elapsed:.1f} s ({self.rate:.1f} fps)"
        if self.interactive:
            self._draw(text)
            self.stream.write("\n")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress(iterable: Iterable[T], total: int | None = None, **kwargs: object) -> Iterator[T]:
    """Yield from ``iterable`` while showing a :class:`Progress` bar (``total`` from ``len()``)."""
    if total is None:
        try:
            total = len(iterable)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with Progress(total, **kwargs) as bar:  # type: ignore[arg-type]
        for item in iterable:
            yield item
            bar.update()
