"""Time left of a job (core.eta) on planted timelines: stages that run at a known rate, with and without the
history of earlier jobs, a job slower than its history, and the parsing of progress counts."""

from __future__ import annotations

import pytest

from core.eta import UnitCount, estimate, parse_count, seconds_per_unit, working_megapixels

STAGES = [("load", 10.0), ("match", 30.0), ("compose", 60.0)]


def timeline(seconds: dict[str, float]) -> list[tuple[float, str, float, dict[str, float]]]:
    """(elapsed in the job, running stage, its fraction, finished stages) every second of a job whose stages
    take ``seconds`` and go at a constant rate."""
    out, t0, finished = [], 0.0, {}
    for name, _ in STAGES:
        for k in range(int(seconds[name])):
            out.append((t0 + k, name, k / seconds[name], dict(finished)))
        t0 += seconds[name]
        finished[name] = seconds[name]
    return out


def worst_error(seconds: dict[str, float], frames: float, history: dict[str, float] | None, after: float) -> float:
    """The largest |predicted - true| time left over the job's true duration, from ``after`` of it on."""
    total = sum(seconds.values())
    worst = 0.0
    for t, stage, fraction, finished in timeline(seconds):
        if t < after * total:
            continue
        elapsed = t - sum(finished.values())
        eta = estimate(STAGES, {"frames": frames}, finished, stage, fraction, elapsed, history)
        assert eta is not None
        worst = max(worst, abs(eta.seconds_left - (total - t)) / total)
    return worst


def test_without_history_the_weights_give_the_plan_once_something_is_measured() -> None:
    seconds = {"load": 10.0, "match": 30.0, "compose": 60.0}  # exactly the weights' shares
    assert estimate(STAGES, {"frames": 10}, {}, "load", 0.0, 0.0) is None  # nothing measured, nothing known
    assert worst_error(seconds, 10, None, after=0.05) < 0.02


def test_history_predicts_before_anything_is_measured_and_scales_with_the_work() -> None:
    stages = [("load_images", 10.0), ("match_features", 30.0), ("compose_mosaic", 60.0)]
    size = {"frames": 10, "megapixels": 3.0, "photo_megapixels": 12.0}
    earlier = (size, {"load_images": 6.0, "match_features": 20.0, "compose_mosaic": 30.0})
    history = seconds_per_unit([earlier])
    # reading goes per megapixel of the photos, composing per working megapixel, matching per photo
    assert history == {"load_images": 0.5, "match_features": 2.0, "compose_mosaic": 10.0}
    bigger = {"frames": 20, "megapixels": 30.0, "photo_megapixels": 120.0}
    eta = estimate(stages, bigger, {}, None, 0.0, 0.0, history)  # queued
    assert eta is not None and eta.seconds_left == pytest.approx(0.5 * 120 + 2 * 20 + 10 * 30)
    assert {s.basis for s in eta.stages.values()} == {"history"}
    assert working_megapixels([(4000, 3000), (1000, 500)], 2000) == pytest.approx(3.0 + 0.5)


def test_a_job_slower_than_its_history_is_caught_by_its_pace() -> None:
    history = {"load": 0.5, "match": 2.0, "compose": 4.0}  # 65 s for 10 frames
    seconds = {"load": 10.0, "match": 40.0, "compose": 80.0}  # this machine is twice as slow
    assert worst_error(seconds, 10, history, after=0.25) < 0.2  # the goal once a quarter is done
    eta = estimate(STAGES, {"frames": 10}, {"load": 10.0, "match": 40.0}, "compose", 0.5, 40.0, history)
    assert eta is not None and eta.seconds_left == pytest.approx(40.0, rel=0.1)  # near its own rate by then
    assert eta.stages["compose"].basis == "measured" and eta.stages["load"].basis == "done"


def test_a_stage_that_runs_unevenly_is_blended_with_its_plan() -> None:
    history = {"load": 1.0, "match": 1.0, "compose": 1.0}
    early = estimate(STAGES, {"frames": 10}, {"load": 10.0}, "match", 0.01, 5.0, history)  # a slow first 1 %
    assert early is not None and early.stage_seconds_left < 0.2 * 5.0 * 99  # not 495 s from 1 % alone
    count = UnitCount("pair", 4, 40)
    timed = estimate(STAGES, {"frames": 10}, {"load": 10.0}, "match", 0.1, 2.0, history, count)
    assert timed is not None and timed.stages["match"].units_per_second == pytest.approx(2.0)
    assert timed.stages["match"].unit == "pair"
    assert timed.to_json()["stages"]["match"]["units_per_second"] == 2.0


def test_progress_counts_are_read_from_the_details() -> None:
    assert parse_count("frame 4/12") == UnitCount("frame", 4, 12)
    assert parse_count("load step 2/5") == UnitCount("load step", 2, 5)
    assert parse_count("block 7 / 30") == UnitCount("block", 7, 30)
    assert parse_count("gain compensation") is None and parse_count("frame 1/0") is None
