"""Per-frame and per-pair work on a thread per core: OpenCV and NumPy release the GIL in their heavy
calls, so threads give real parallelism without copying images between processes."""

from __future__ import annotations

import ctypes
import os
import threading
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from functools import cache
from typing import Generic, TypeVar

from workers.workspace import ProgressFn

T = TypeVar("T")
R = TypeVar("R")


def thread_count(requested: int) -> int:
    """``requested`` threads, or one per CPU core this process may run on for 0 (a worker pinned to some cores
    with ``taskset`` or a container's cpuset uses those)."""
    return requested if requested > 0 else usable_cores()


def usable_cores() -> int:
    affinity = getattr(os, "sched_getaffinity", None)
    return max(1, len(affinity(0)) if affinity is not None else (os.cpu_count() or 1))


# glibc gives arrays over 128 KiB (its starting threshold) pages of their own and returns them when freed, so a
# stage that makes and drops a window's float copies again and again faults every page in anew: composing one band
# of a 75000 px strip took 600k page faults and 1.5 s of system time in 3.0 s (and threads fault under one lock
# per process). Kept in the process up to 32 MiB an array and 64 MiB free at a heap's top: 6k faults, 0.6 s.
# Set by the stages that make and drop large arrays window after window (compose_mosaic, match_strips): on the
# Brighton strip's 14 MP mosaic compose took 0.73 s instead of 0.82 s (medians of four), the 30-frame synthetic
# flight's 1.18 s instead of 1.32 s, for up to 40 MiB more at the job's peak (that flight: 342 -> 382 MiB).
MALLOC_MMAP_THRESHOLD = 32 << 20
MALLOC_TRIM_THRESHOLD = 64 << 20


@cache
def keep_freed_memory() -> bool:
    """Set glibc's thresholds (``mallopt``) for the rest of this process, unless the environment sets them;
    False where libc is not glibc or the environment decides."""
    if any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl, macOS, Windows
        return False
    return bool(mallopt(-3, MALLOC_MMAP_THRESHOLD) and mallopt(-1, MALLOC_TRIM_THRESHOLD))  # M_MMAP_, M_TRIM_


def release_freed_memory() -> bool:
    """Give the memory freed in this process back to the system (glibc's ``malloc_trim``: the free pages inside its
    heaps too, not only at their top); False where libc is not glibc."""
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


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


def ordered_imap(fn: Callable[[T], R], items: Sequence[T], threads: int) -> Iterator[R]:
    """``fn(x) for x in items``, in order, on ``threads`` threads with at most two results per thread computed
    ahead of the one consumed: a caller that writes each result as it comes holds a few, never all of them."""
    if threads <= 1 or len(items) <= 1:
        yield from (fn(item) for item in items)
        return
    pool = ThreadPoolExecutor(max_workers=threads)
    pending: deque[Future[R]] = deque()
    try:
        for item in items:
            if len(pending) >= 2 * threads:
                yield pending.popleft().result()
            pending.append(pool.submit(fn, item))
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # a caller that stopped early: the rest is dropped


V = TypeVar("V")


class RecentCache(Generic[V]):
    """The values built for the ``size`` most recently used keys, each built once however many threads ask
    for it at the same time (the others wait for it). A process matching a job's pairs keeps the features and
    search index of the frames its pairs share, whichever worker it is and whichever pairs it was given."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._values: OrderedDict[Hashable, V] = OrderedDict()
        self._building: dict[Hashable, threading.Lock] = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, build: Callable[[], V]) -> V:
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
            building = self._building.setdefault(key, threading.Lock())
        with building:
            with self._lock:
                if key in self._values:
                    return self._values[key]
            value = build()
            with self._lock:
                self._values[key] = value
                self._building.pop(key, None)
                while len(self._values) > self.size:
                    self._values.popitem(last=False)
            return value
