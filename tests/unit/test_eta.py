"""Time left of a job (core.eta) on planted timelines: stages that run at a known rate, with and without the
history of earlier jobs, a job slower than its history, and the parsing of progress counts; and on the recorded
progress of three real runs (``bench/eta.py --save-traces``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.eta import errors, replay, size_at, stage_seconds, trace_run
from core.eta import (
    DEFAULT_RATES,
    PAIRS_PER_PHOTO,
    UnitCount,
    estimate,
    parse_count,
    seconds_per_unit,
    similar_jobs,
    working_megapixels,
)

STAGES = [("load", 10.0), ("match", 30.0), ("compose", 60.0)]
# bench/eta.py --save-traces on the loaded 2-core reference machine (load average 6-7): a 12-frame synthetic
# grid at 640 px, a 24-frame one at 800 px and the Brighton strip at 2048 px, every progress report with its time;
# none of them among the runs DEFAULT_RATES were measured on
TRACES = Path(__file__).parent / "data" / "eta_traces.json"
QUIET_TRACES = Path(__file__).parent / "data" / "eta_traces_quiet.json"


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
    size = {"frames": 10, "megapixels": 3.0, "photo_megapixels": 12.0, "pairs": 40}
    earlier = (size, {"load_images": 6.0, "match_features": 20.0, "compose_mosaic": 30.0})
    history = seconds_per_unit([earlier])
    # reading goes per megapixel of the photos, composing per working megapixel, matching per pair of photos
    assert history == {"load_images": 0.5, "match_features": 0.5, "compose_mosaic": 10.0}
    bigger = {"frames": 20, "megapixels": 30.0, "photo_megapixels": 120.0}
    eta = estimate(stages, bigger, {}, None, 0.0, 0.0, history)  # queued: its pairs guessed from its photos
    assert eta is not None and eta.seconds_left == pytest.approx(0.5 * 120 + 0.5 * PAIRS_PER_PHOTO * 20 + 10 * 30)
    matched = estimate(stages, {**bigger, "pairs": 50}, {}, None, 0.0, 0.0, history)  # once matching counted them
    assert matched is not None and matched.seconds_left == pytest.approx(0.5 * 120 + 0.5 * 50 + 10 * 30)
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


def test_a_running_stage_counts_down_its_expected_time_and_does_not_end_before_it() -> None:
    history = {"load": 1.0, "match": 1.0, "compose": 1.0}  # 10 s a stage for 10 frames
    finished = {"load": 10.0, "match": 10.0}

    def left(fraction: float, elapsed: float) -> float:
        eta = estimate(STAGES, {"frames": 10}, finished, "compose", fraction, elapsed, history)
        assert eta is not None
        return eta.stage_seconds_left

    # planning, nothing reported done: time goes on (less 3 s, though the pace it sets for the job grows)
    assert left(0.0, 4.0) < left(0.0, 1.0) - 1.5
    # 95 % reported after 3 s (a plan's or a last step's share ahead of its time): not taken as nearly done (its
    # own rate says 0.16 s; the job's pace, taking the share at its word, makes the stage 7.8 s)
    assert left(0.95, 3.0) > 4.5
    assert left(0.5, 5.0) == pytest.approx(5.0, abs=0.5)  # on time: its own rate and its plan agree


def test_only_earlier_jobs_of_a_similar_size_and_the_reference_predict_a_job() -> None:
    strip = {"frames": 6, "megapixels": 14.2}  # 2.4 working MP per photo
    grid = ({"frames": 12, "megapixels": 3.7}, {"compose_mosaic": 2.0})  # 0.3 MP per photo
    near = ({"frames": 8, "megapixels": 12.0}, {"compose_mosaic": 6.0})  # 1.5 MP per photo
    assert similar_jobs([grid, near], strip) == [near]
    assert similar_jobs([grid, near], {"frames": 6}) == [grid, near]  # its pixels unknown: all of them
    one = seconds_per_unit([near], {"compose_mosaic": 0.3})  # one job is halfway to the reference
    assert one["compose_mosaic"] == pytest.approx((0.5 + 0.3) / 2)
    assert seconds_per_unit([], {"compose_mosaic": 0.3}) == {}  # no history: the caller's defaults


@pytest.mark.parametrize("traces", [TRACES, QUIET_TRACES], ids=["busy machine", "quiet machine"])
def test_on_three_recorded_runs_the_time_left_is_within_a_fifth_of_the_job_from_a_quarter_done(traces: Path) -> None:
    """The runs of bench/eta.py, on a machine busy with other work and on a quiet one (2-2.5x faster than the
    default rates, which came from a busy one): each within 20 % of the job once a quarter is done."""
    runs = [trace_run(t) for t in json.loads(traces.read_text())]
    assert [name.split(",")[0] for name, _ in runs] == ["synthetic 12 frames", "synthetic 24 frames", "Brighton strip"]
    done: list[dict] = []
    for name, run in runs:
        # as the API reads it: the earlier runs of a similar size (the strip has none: 4-8x the grids' pixels)
        similar = similar_jobs([(size_at(r), stage_seconds(r)) for r in done], run["size"])
        assert len(similar) == (0 if name.startswith("Brighton") else len(done))
        series = replay(run, seconds_per_unit(similar, DEFAULT_RATES["mosaic"]) or None)
        ours, bar = (errors(run, series, which)["worst_after_25%"] for which in (1, 2))
        assert ours < 0.2 and ours < 0.7 * bar, (name, ours, bar)  # a progress bar's extrapolation: 31-37 %
        done.append(run)
    # matching's pairs are read once it has counted them, and then replace the guess from the photos
    brighton = runs[2][1]
    assert "pairs" not in size_at(brighton, 0.5) and size_at(brighton)["pairs"] == 15
