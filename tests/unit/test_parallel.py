"""The ordered thread maps: order kept, progress counted, an interruption stops the rest, and the streaming one
holds only a few results ahead of its consumer."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import pytest

from workers.parallel import keep_freed_memory, ordered_imap, ordered_map, thread_count


def test_results_keep_their_order_and_progress_counts_up() -> None:
    seen: list[tuple[float, str]] = []
    out = ordered_map(
        lambda x: (time.sleep(0.01 * (5 - x)), x * x)[1], list(range(5)), 2, lambda f, d: seen.append((f, d)), "frame"
    )
    assert out == [0, 1, 4, 9, 16]
    assert [d for _, d in seen] == [f"frame {k}/5" for k in range(1, 6)] and seen[-1][0] == 1.0
    assert thread_count(3) == 3 and thread_count(0) >= 1


def recording(seconds: float) -> tuple[list[int], Callable[[int], int]]:
    """The items started so far, and work that records its item, sleeps ``seconds`` and returns it."""
    started: list[int] = []
    lock = threading.Lock()

    def work(x: int) -> int:
        with lock:
            started.append(x)
        time.sleep(seconds)
        return x

    return started, work


def test_an_exception_in_progress_stops_work_not_yet_started() -> None:
    started, work = recording(0.05)

    def cancel(_fraction: float, _detail: str) -> None:
        raise RuntimeError("cancelled")

    with pytest.raises(RuntimeError):
        ordered_map(work, list(range(50)), 2, cancel, "pair")
    assert len(started) < 10  # the queued items were dropped, not run


def test_the_streaming_map_keeps_order_and_computes_only_a_few_ahead() -> None:
    finished: list[int] = []
    lock = threading.Lock()

    def work(x: int) -> int:
        time.sleep(0.002 * (x % 3))
        with lock:
            finished.append(x)
        return x * x

    ahead = []
    out = []
    for k, value in enumerate(ordered_imap(work, list(range(40)), 3)):
        time.sleep(0.01)  # a slow consumer (the band's writer): the threads must wait for it
        with lock:
            ahead.append(len(finished) - (k + 1))
        out.append(value)
    assert out == [x * x for x in range(40)]
    assert max(ahead) <= 2 * 3  # results held, computed but not yet consumed: two per thread at most
    assert list(ordered_imap(work, [7], 4)) == [49] and list(ordered_imap(work, [1, 2], 1)) == [1, 4]


def test_a_consumer_that_stops_drops_the_work_not_yet_started() -> None:
    started, work = recording(0.01)
    stream = ordered_imap(work, list(range(100)), 2)
    assert [next(stream) for _ in range(3)] == [0, 1, 2]
    stream.close()  # the band's writer failed: the generator's pool is shut down
    assert len(started) <= 3 + 2 * 2 + 2


def test_the_stages_bound_gdals_block_cache_unless_the_environment_sets_it() -> None:
    """GDAL would take 5 % of the machine's memory per process (6.4 GB on a 128 GB host)."""
    code = "import workers, rasterio.env; print(rasterio.env.get_gdal_config('GDAL_CACHEMAX'))"  # GDAL's, in bytes
    env = {k: v for k, v in os.environ.items() if k != "GDAL_CACHEMAX"}
    run = [sys.executable, "-c", code]
    assert subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout.split() == [str(512 << 20)]
    env["GDAL_CACHEMAX"] = "64"
    assert subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout.split() == [str(64 << 20)]


FAULTS = """
import resource, sys
import numpy as np
from workers.parallel import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(50):  # a compose window's float copies, 3 MiB each, made together and dropped
    copies = [np.ones((512, 512, 3), np.float32) for _ in range(4)]
    del copies
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and Linux's page-fault count")
def test_kept_freed_memory_is_not_faulted_in_again() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "MALLOC_MMAP_THRESHOLD_")}
    faults = {
        mode: int(
            subprocess.run(
                [sys.executable, "-c", FAULTS, mode], env=env, capture_output=True, text=True, check=True
            ).stdout
        )  # fmt: skip
        for mode in ("default", "keep")
    }
    # by default glibc raises its threshold to an array's size once one is freed, and returns the heap's top once
    # it is twice that: each round's four copies (768 pages each) are faulted in again; kept, only the first's
    assert faults["keep"] < 4 * 768 * 2 and faults["default"] > 4 * 768 * 25, faults
    assert keep_freed_memory() in (True, False)
