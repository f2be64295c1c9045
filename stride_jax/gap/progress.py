"""Progress bars for the stages of a diagnosis (tqdm, on stderr).

A diagnosis of a dozen Go1 logs takes minutes: each stage (the screen, its one-step check, the single
fits, the pairs, how far) shows a bar with its count and rate. ``show=False`` (``--no-progress``, the
benchmark's workers) turns them off.
"""

from __future__ import annotations

import contextlib
import sys
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm

T = TypeVar("T")


@contextlib.contextmanager
def bar(total: int, stage: str, show: bool = True) -> Iterator[tqdm]:
    """A bar of ``total`` steps labelled ``stage`` (a no-op bar when ``show`` is False)."""
    b = tqdm(total=total, desc=stage, file=sys.stderr, disable=not show, leave=True, dynamic_ncols=True,
             mininterval=0.5)
    try:
        yield b
    finally:
        b.close()


def track(items: Iterable[T], stage: str, show: bool = True, total: int | None = None) -> Iterator[T]:
    """``items`` with a bar labelled ``stage``."""
    items = list(items) if total is None else items
    with bar(len(items) if total is None else total, stage, show) as b:
        for x in items:
            yield x
            b.update(1)
