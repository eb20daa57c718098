"""The ordered thread map: order kept, progress counted, and an interruption stops the rest."""

from __future__ import annotations

import threading
import time

import pytest

from workers.parallel import ordered_map, thread_count


def test_results_keep_their_order_and_progress_counts_up() -> None:
    seen: list[tuple[float, str]] = []
    out = ordered_map(
        lambda x: (time.sleep(0.01 * (5 - x)), x * x)[1], list(range(5)), 2, lambda f, d: seen.append((f, d)), "frame"
    )
    assert out == [0, 1, 4, 9, 16]
    assert [d for _, d in seen] == [f"frame {k}/5" for k in range(1, 6)] and seen[-1][0] == 1.0
    assert thread_count(3) == 3 and thread_count(0) >= 1


def test_an_exception_in_progress_stops_work_not_yet_started() -> None:
    started: list[int] = []
    lock = threading.Lock()

    def work(x: int) -> int:
        with lock:
            started.append(x)
        time.sleep(0.05)
        return x

    def cancel(_fraction: float, _detail: str) -> None:
        raise RuntimeError("cancelled")

    with pytest.raises(RuntimeError):
        ordered_map(work, list(range(50)), 2, cancel, "pair")
    assert len(started) < 10  # the queued items were dropped, not run
