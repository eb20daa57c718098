"""bench/mosaic_vs_opencv.py's summaries: the median run of a repeat, and each side's memory and CPU split."""

from __future__ import annotations

import time
from typing import Any

from bench.mosaic_vs_opencv import cpu_seconds, cpu_split, median_run, memory_split


def _run(seconds: float, cpu_s: float, peak: float, start: float = 80.0) -> dict[str, Any]:
    return {"ok": True, "seconds": seconds, "cpu_s": cpu_s, "peak_mib": peak, "start_mib": start}


def test_the_median_run_keeps_its_own_seconds_and_the_medians_of_the_rest() -> None:
    runs = [_run(1.5, 2.9, 300.0), _run(1.2, 2.0, 250.0, 90.0), _run(1.3, 2.5, 200.0)]
    middle = median_run(runs)
    assert middle["seconds"] == 1.3  # the run of median seconds, not an average
    assert (middle["peak_mib"], middle["cpu_s"], middle["start_mib"]) == (250.0, 2.5, 80.0)


def test_a_failed_run_is_the_result() -> None:
    failed = {"ok": False, "status": "child died", "seconds": float("nan"), "peak_mib": float("nan")}
    assert median_run([_run(1.0, 2.0, 100.0), failed]) is failed


def test_cpu_split_gives_both_sides_and_the_cores_kept_busy() -> None:
    line = cpu_split(_run(1.5, 2.4, 300.0), _run(1.0, 1.2, 300.0))
    assert line == "CPU s ours 2.40, OpenCV 1.20 (2.00x); cores busy on average ours 1.60, OpenCV 1.20"
    assert cpu_split(_run(1.5, 2.4, 300.0), {"ok": False}) is None


def test_memory_split_separates_the_imports_from_the_run() -> None:
    line = memory_split(_run(1.0, 1.0, 190.0, 87.0), _run(1.0, 1.0, 136.0, 44.0))
    assert line == "MiB at the start (imports) ours 87, OpenCV 44; added by the run ours 103, OpenCV 92 (1.12x)"


def test_cpu_seconds_counts_this_process_working() -> None:
    before, started = cpu_seconds(), time.perf_counter()
    while time.perf_counter() - started < 0.2:  # 0.2 s of work in this thread
        sum(i * i for i in range(1000))
    assert cpu_seconds() > before  # (the machine may lend this thread less than all of it)
