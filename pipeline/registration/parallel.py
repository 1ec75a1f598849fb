"""One thread per core for the per-pair work of the whole-job correction (docs/end-of-job.md).

A pair's work (KD-tree queries, numpy on thousands of points, Open3D) releases the GIL, so the pairs of one
stage share the cores in threads of this process: no pickling of scans, no second copy of them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

#: ``pair_map(fn, items)``: ``[fn(x) for x in items]``, in order, the calls spread over the threads
PairMap = Callable[[Callable[[Any], Any], Iterable[Any]], list]


@contextmanager
def pair_threads(threads: int | None = None) -> Iterator[PairMap]:
    """A :data:`PairMap` over ``threads`` threads (default one per core), for the ``with`` block."""
    with ThreadPoolExecutor(threads or os.cpu_count() or 1, thread_name_prefix="pairs") as pool:
        yield lambda fn, items: list(pool.map(fn, items))
