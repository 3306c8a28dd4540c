"""Progress of long work (making a dataset, training, a sweep), on a terminal and in a log.

On a terminal, :func:`bar` is tqdm's bar. Anywhere else (output to a file, a pipe, a CI job,
``nohup``) a bar is either nothing (tqdm's ``disable=None``) or one endless line of carriage
returns, so :func:`bar` writes plain lines instead: one when the work starts (what it is, how much,
and the estimate when one is given), one every :data:`LOG_SECONDS` (done so far, rate, time
left), and one when it ends (how long it took). :func:`say` writes a single stage line.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TextIO

from tqdm.auto import tqdm

from eabc.timing import duration

LOG_SECONDS = float(os.environ.get("EABC_PROGRESS_SECONDS", 60.0))
"""Seconds between two progress lines when the output is not a terminal
(``EABC_PROGRESS_SECONDS`` to change)."""


def on_terminal(stream: TextIO | None = None) -> bool:
    """Whether ``stream`` (default stderr, where progress goes) is a terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # closed, or no isatty
        return False


def say(text: str, stream: TextIO | None = None) -> None:
    """One stage line on stderr (``eabc: making hopper-medium ...``), on a terminal or not."""
    print(f"eabc: {text}", file=sys.stderr if stream is None else stream, flush=True)


def bar(
    total: int,
    desc: str,
    unit: str = "step",
    initial: int = 0,
    enabled: bool = True,
    estimate: str | None = None,
    iterable: Iterable | None = None,
    **tqdm_options: Any,
):
    """A progress bar for ``total`` ``unit``s (over ``iterable`` when given, as tqdm's):
    tqdm's on a terminal, else a :class:`LineProgress` (silent when not ``enabled``).
    ``estimate`` (``about 5 minutes at ...``) is said when the work starts."""
    if not enabled:
        return LineProgress(total, desc, unit, initial, quiet=True, iterable=iterable)
    if on_terminal():
        if estimate:
            say(f"{desc}: {total - initial:,} {unit}s to go, {estimate}")
        return tqdm(iterable, total=total, initial=initial, desc=desc, unit=unit, **tqdm_options)
    return LineProgress(total, desc, unit, initial, estimate=estimate, iterable=iterable)


def write(text: str) -> None:
    """A message that does not break a bar on the terminal (tqdm.write); plain elsewhere."""
    tqdm.write(text, file=sys.stderr)


class LineProgress:
    """tqdm's interface (``update``, ``set_postfix``, ``close``, a context manager) as lines."""

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str = "step",
        initial: int = 0,
        estimate: str | None = None,
        quiet: bool = False,
        every: float | None = None,
        stream: TextIO | None = None,
        iterable: Iterable | None = None,
    ):
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.iterable = iterable
        self.quiet, self.every, self.stream = quiet, every or LOG_SECONDS, stream
        self.postfix = ""
        self._start_n, self._start = initial, time.perf_counter()
        self._last = self._start
        if not quiet:
            done = f", {initial:,} done" if initial else ""
            about = f", {estimate}" if estimate else ""
            self._say(f"{desc}: {total:,} {unit}s{done}{about}")

    def _say(self, text: str) -> None:
        say(text, self.stream)

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if not self.quiet and now - self._last >= self.every and self.n < self.total:
            self._last = now
            rate = (self.n - self._start_n) / max(now - self._start, 1e-9)
            left = (self.total - self.n) / rate if rate > 0 else float("inf")
            postfix = f" ({self.postfix})" if self.postfix else ""
            self._say(
                f"{self.desc}: {self.n:,}/{self.total:,} {self.unit}s ({self.n / self.total:.0%})"
                f", {rate:,.1f} {self.unit}s/s, about {duration(left)} left{postfix}"
            )

    def __iter__(self) -> Iterator:
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def set_postfix(self, values: dict | None = None, refresh: bool = True, **more) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in {**(values or {}), **more}.items())

    def set_description(self, desc: str, refresh: bool = True) -> None:
        self.desc = desc

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if self.quiet:
            return
        self.quiet = True  # once
        took = duration(time.perf_counter() - self._start)
        postfix = f" ({self.postfix})" if self.postfix else ""
        self._say(f"{self.desc}: {self.n:,}/{self.total:,} {self.unit}s in {took}{postfix}")

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
