"""Independent work in runs of neighbouring items, in a process pool when one is worth it."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from typing import TypeVar

import numpy as np

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")


def map_in_runs(
    fn: Callable[[S, Sequence[T]], R],
    shared: S,
    items: Sequence[T],
    pool: Executor | None,
    jobs: int,
    min_items: int = 64,
) -> list[R]:
    """``fn(shared, run)`` over runs of neighbouring ``items``, in order.

    One run in this process without a pool or with fewer than ``min_items`` items (shipping them
    would cost more than the work); otherwise two runs per worker, so that uneven runs even out
    on a loaded machine. Neighbours stay together: work they share is done once per run.
    """
    if pool is None or jobs <= 1 or len(items) < min_items:
        return [fn(shared, items)]
    bounds = np.linspace(0, len(items), 2 * jobs + 1).astype(int)
    runs = [items[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]
    return list(pool.map(fn, [shared] * len(runs), runs))
