"""One place that decides how progress bars look; they stay quiet when stderr is not a terminal."""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterable[T]:
    """Wrap an iterable in a progress bar (hidden on non-TTY output such as CI logs)."""
    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False, disable=None, dynamic_ncols=True)


class Laps:
    """Wall-clock time of each named part of a piece of work, from the previous lap (or the start) to the call;
    `per_second` sets the unit (1: seconds, 1e3: milliseconds)."""

    def __init__(self, per_second: float = 1.0) -> None:
        self.times: dict[str, float] = {}
        self._per_second = per_second
        self._clock = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.times[name] = (now - self._clock) * self._per_second
        self._clock = now
