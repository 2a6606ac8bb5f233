"""Progress of a long loop, on a terminal and in a log file alike.

On a terminal a rich progress bar is drawn (on stderr by default). Anywhere else (a SLURM log,
``nohup``, CI) a bar would print nothing until the end, so instead a line is logged through
:mod:`logging` at most every ``every_s`` seconds, and once at the end::

    predict: 120/500 images, 2.1/s, ETA 3 min
    predict: 500/500 images in 4 min, 2.1/s

Advance it by hand::

    with Progress(len(images), "predict", unit="images") as progress:
        for batch in batches:
            ...
            progress.advance(len(batch))

or wrap an iterable (an item counts once the loop body has finished with it)::

    for frame_id in track(frame_ids, "preparing kitti train", unit="frames"):
        ...

``terminal`` chooses between the two (None: whether ``stream`` is a terminal); ``clock`` (default
:func:`time.monotonic`) can be replaced, so a test needs no sleeping.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sized
from types import TracebackType
from typing import Any, TextIO, TypeVar

T = TypeVar("T")

DEFAULT_EVERY_S = 60.0

_log = logging.getLogger(__name__)


class Progress:
    """Counts the items of a loop and shows how far it got: a rich bar on a terminal, periodic
    log lines elsewhere (see the module docstring). Use it as a context manager.

    Args:
        total: how many items the loop has; None when unknown (no ETA, no bar length).
        description: what the loop does, first on every line (e.g. ``"predict"``).
        unit: what an item is called in the lines (``"images"``, ``"frames"``).
        every_s: the shortest time in seconds between two periodic lines.
        terminal: True draws the bar, False logs lines; None (default): the bar when ``stream``
            is a terminal.
        transient: remove the bar from the terminal when done.
        logger: where the lines go (default: this module's logger).
        stream: where the bar is drawn (default: ``sys.stderr``, keeping stdout for results).
        clock: seconds, monotonic (default: :func:`time.monotonic`).

    Raises:
        ValueError: ``total`` is negative or not an integer, or ``every_s`` is not > 0.
    """

    def __init__(
        self,
        total: int | None,
        description: str,
        *,
        unit: str = "items",
        every_s: float = DEFAULT_EVERY_S,
        terminal: bool | None = None,
        transient: bool = False,
        logger: logging.Logger | None = None,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if total is not None and (isinstance(total, bool) or not isinstance(total, int)):
            raise ValueError(f"progress total={total!r}: expected an integer >= 0 or None")
        if total is not None and total < 0:
            raise ValueError(f"progress total={total}: expected an integer >= 0 or None")
        if not every_s > 0:
            raise ValueError(f"progress every_s={every_s}: expected seconds > 0")
        self.total = total
        self.description = description
        self.unit = unit
        self.every_s = float(every_s)
        self.stream = sys.stderr if stream is None else stream
        self.terminal = _isatty(self.stream) if terminal is None else bool(terminal)
        self.transient = transient
        self.logger = _log if logger is None else logger
        self.clock = clock
        self.done = 0
        self._start = 0.0
        self._last_line = 0.0
        self._bar: Any = None
        self._task: Any = None

    def __enter__(self) -> Progress:
        self._start = self._last_line = self.clock()
        if self.terminal:
            from rich import progress as rich
            from rich.console import Console

            self._bar = rich.Progress(
                rich.TextColumn("{task.description}"),
                rich.BarColumn(),
                rich.MofNCompleteColumn(),
                rich.TimeRemainingColumn(),
                console=Console(file=self.stream),
                transient=self.transient,
            )
            self._task = self._bar.add_task(self.description, total=self.total)
            self._bar.__enter__()
        return self

    def advance(self, n: int = 1) -> None:
        """Counts ``n`` more items done; off a terminal, logs a line if ``every_s`` has passed
        since the last one (or since the start) and items are left (the end has its own)."""
        self.done += n
        if self._bar is not None:
            self._bar.advance(self._task, n)
            return
        if self.terminal or (self.total is not None and self.done >= self.total):
            return  # the final line follows
        now = self.clock()
        if now - self._last_line >= self.every_s:
            self._last_line = now
            self.logger.info("%s", self.line(now))

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if self._bar is not None:
            self._bar.__exit__(exc_type, exc, traceback)
            self._bar = None
        elif not self.terminal:
            # Also when the loop failed: the line says how far it got.
            self.logger.info("%s", self.line(self.clock(), final=True))

    def line(self, now: float, final: bool = False) -> str:
        """The log line at time ``now`` (of ``clock``): done/total, rate and ETA, or for the
        final line the time taken instead of the ETA."""
        elapsed = max(now - self._start, 0.0)
        count = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        parts = [f"{self.description}: {count} {self.unit}"]
        if final:
            parts[0] += f" in {format_duration(elapsed)}"
        rate = self.done / elapsed if elapsed > 0 else None
        if rate is not None and self.done:
            parts.append(f"{_format_rate(rate)}/s")
        if not final and rate and self.total is not None and self.done < self.total:
            parts.append(f"ETA {format_duration((self.total - self.done) / rate)}")
        return ", ".join(parts)


def track(
    iterable: Iterable[T],
    description: str,
    *,
    total: int | None = None,
    **options: Any,
) -> Iterator[T]:
    """Yields the items of ``iterable`` under a :class:`Progress`, advancing it by one after each.

    ``total`` defaults to ``len(iterable)`` when it has one; ``options`` are Progress's keyword
    arguments (``unit``, ``every_s``, ``terminal``, ``transient``, ``logger``, ``stream``,
    ``clock``). Leaving the loop early (``break``, an error) still ends the bar or logs the last
    line.
    """
    if total is None and isinstance(iterable, Sized):
        total = len(iterable)
    with Progress(total, description, **options) as progress:
        for item in iterable:
            yield item
            progress.advance()


def format_duration(seconds: float) -> str:
    """``42 s``, ``3 min``, ``2 h 5 min``: precise enough for an ETA, short enough for a line."""
    if not math.isfinite(seconds):
        return "?"
    seconds = max(seconds, 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes} min"


def _format_rate(rate: float) -> str:
    return f"{rate:.2g}" if rate < 10 else f"{rate:.0f}"


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
