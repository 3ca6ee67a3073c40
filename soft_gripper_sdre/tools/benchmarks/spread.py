"""A benchmark figure as users meet it: the median of repeated runs with their min–max, and the load
the runs met.

Every timing row of BENCHMARKS.md is :data:`REPEATS` runs or more, written by :func:`figure` as
``median (min–max)``; no row is the best of its runs. :class:`LoadWatch` notes the 1-minute load
average before the first run and after the last.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from typing import Sequence

import numpy as np

#: the runs behind every timing row
REPEATS = 5


def median(samples: Sequence[float]) -> float:
    """The median of ``samples`` (NaN for none)."""
    return float(np.median(samples)) if len(samples) else float('nan')


def figure(samples: Sequence[float], unit: str = 'µs', scale: float = 1e6, digits: int = 0,
           sep: str = ' ') -> str:
    """``median unit (min–max)`` of ``samples`` times ``scale`` (default seconds → µs), with
    ``digits`` decimals; one sample gives its value alone."""
    values = np.asarray(samples, dtype=float) * scale
    if not len(values):
        return 'not measured'
    mid = f'{np.median(values):.{digits}f}{sep}{unit}'.rstrip()
    if len(values) == 1:
        return mid
    return f'{mid} ({values.min():.{digits}f}–{values.max():.{digits}f})'


def span(samples: Sequence[float], scale: float = 1.0, digits: int = 0) -> str:
    """``min–max`` of ``samples`` times ``scale``."""
    values = np.asarray(samples, dtype=float) * scale
    return f'{values.min():.{digits}f}–{values.max():.{digits}f}'


@dataclass
class LoadWatch:
    """The 1-minute load averages seen: :meth:`note` at any time, :meth:`text` for a row."""

    seen: list[float] = field(default_factory=list)

    def note(self) -> float:
        load = os.getloadavg()[0]
        self.seen.append(load)
        return load

    def text(self) -> str:
        """``load a → b`` (the first and last noted), or ``load a`` for one note."""
        if not self.seen:
            return 'load not noted'
        if len(self.seen) == 1:
            return f'load {self.seen[0]:.1f}'
        return f'load {self.seen[0]:.1f} → {self.seen[-1]:.1f}'


def watched(fn, repeats: int = REPEATS) -> tuple[list, LoadWatch]:
    """``fn()`` called ``repeats`` times: its results and the load before the first and after
    the last."""
    watch = LoadWatch()
    watch.note()
    out = [fn() for _ in range(repeats)]
    watch.note()
    return out, watch
