"""Per-frame and per-pair work on a thread per core: OpenCV and NumPy release the GIL in their heavy
calls, so threads give real parallelism without copying images between processes."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import TypeVar

from workers.workspace import ProgressFn

T = TypeVar("T")
R = TypeVar("R")


def thread_count(requested: int) -> int:
    """``requested`` threads, or one per CPU core for 0."""
    return requested if requested > 0 else max(1, os.cpu_count() or 1)


def ordered_map(fn: Callable[[T], R], items: Sequence[T], threads: int, progress: ProgressFn, unit: str) -> list[R]:
    """``[fn(x) for x in items]`` on ``threads`` threads, reporting "unit k/n" as results arrive.

    Progress is reported from the calling thread only (it may write the job record).
    """
    n = len(items)
    if threads <= 1 or n <= 1:
        out = []
        for k, item in enumerate(items):
            progress(k / max(n, 1), f"{unit} {k + 1}/{n}")
            out.append(fn(item))
        return out
    results: list[R | None] = [None] * n
    pool = ThreadPoolExecutor(max_workers=threads)
    try:
        futures = {pool.submit(fn, item): k for k, item in enumerate(items)}
        for done, future in enumerate(as_completed(futures), start=1):
            results[futures[future]] = future.result()
            progress(done / n, f"{unit} {done}/{n}")  # may raise (job cancelled): then stop early
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # work not yet started is dropped
    return results  # type: ignore[return-value]
