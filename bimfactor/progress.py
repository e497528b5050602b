"""One place that decides how progress bars look; they stay quiet when stderr is not a terminal."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterable[T]:
    """Wrap an iterable in a progress bar (hidden on non-TTY output such as CI logs)."""
    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False, disable=None, dynamic_ncols=True)
