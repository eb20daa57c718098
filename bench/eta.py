"""How far off a job's time left is, on real runs of the pipeline: ours (``core.eta``, as the API answers it)
against the reference a progress bar gives (elapsed x (100 - progress) / progress, from the weighted progress
the job record carries), on the same timelines.

Run by hand from the repository root::

    .venv/bin/python bench/eta.py [--json OUT] [--save-traces runs.json | --traces runs.json]

``--save-traces`` keeps the recorded runs; ``--traces`` replays such a file without running the pipeline (to
compare estimators on the same timelines).

Three runs, one after the other in this process, each recording every progress report a worker would write
(stage, share done, detail, time): a synthetic 12-frame GPS flight at 640 px, a 24-frame one at 800 px, and
the real Brighton strip (6 DJI frames) at 2048 px when ``../shared/data`` has it. Then each timeline is
replayed every 0.2 s as the API computes at a read: the running stage's start and last reported share and
count, the finished stages' seconds, and the history of the runs before it of a similar size (seconds of each
stage per input frame or working megapixel, as ``api.eta_service`` reads it from earlier jobs); the first run
has none, and the Brighton strip none of the synthetic flights (4-5x their working megapixels per photo).
Printed per run: the error of the predicted time left against the true one, as a share of the whole job, at
25, 50 and 75 % of the run and its worst from 25 % on (the goal: within 20 %), for ours and for the
progress-bar reference.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STEP_SECONDS = 0.2


def record_run(src: Path, out: Path, options: dict[str, Any]) -> dict[str, Any]:
    """Run the pipeline in-process; every progress report with its time, and each stage's start and end."""
    from core.eta import parse_count
    from workers.pipeline import pipeline_key, process_directory, stage_function, stage_names

    pipeline = pipeline_key("mosaic", options)
    for stage in stage_names(pipeline):
        stage_function(stage)  # imported before the clock, as a worker has them
    events: list[tuple[float, str, float, Any]] = []
    started = time.perf_counter()

    def progress(stage: str, fraction: float, detail: str) -> None:
        events.append((time.perf_counter() - started, stage, float(fraction), parse_count(detail)))

    report = process_directory(src, out, options, progress)
    total = time.perf_counter() - started
    from core.eta import working_megapixels

    sizes = [tuple(f["size"]) for f in report["frames_used"]] + [(1, 1)] * len(report["frames_rejected"])
    size = {
        "frames": float(len(sizes)),
        "megapixels": working_megapixels(sizes, options.get("working_max_px", 2048)),
        "photo_megapixels": working_megapixels(sizes, None),
    }
    return {
        "pipeline": pipeline,
        "events": events,
        "total": total,
        "size": size,
        "stage_seconds": report["stage_seconds"],
    }


def stage_spans(run: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(stage, start, end) in the run, from its first and last progress report (write_report's own end is the
    run's end: its report is written before its seconds are)."""
    spans: dict[str, list[float]] = {}
    for t, stage, _, _ in run["events"]:
        spans.setdefault(stage, [t, t])[1] = t
    names = list(spans)
    out = []
    for k, name in enumerate(names):
        end = spans[names[k + 1]][0] if k + 1 < len(names) else run["total"]
        out.append((name, spans[name][0], end))
    return out


def size_at(run: dict[str, Any], t: float = float("inf")) -> dict[str, float]:
    """The run's size as its job record tells it at ``t``: frames and megapixels, and the pairs matching counts
    once it has counted them (as ``api.eta_service.job_size`` reads them)."""
    counts = [c.total for when, stage, _, c in run["events"] if stage == "match_features" and c and when <= t]
    return {**run["size"], "pairs": float(counts[0])} if counts else dict(run["size"])


def stage_seconds(run: dict[str, Any]) -> dict[str, float]:
    """Each stage's seconds as a worker records them in the job's timings (write_report's too, which the
    pipeline's report cannot hold: it is written before its own seconds are)."""
    return {name: end - start for name, start, end in stage_spans(run)}


def replay(
    run: dict[str, Any], history: dict[str, float] | None, defaults: bool = True
) -> list[tuple[float, float | None, float | None]]:
    """(t, ours, progress-bar reference) predicted seconds left every STEP_SECONDS of the run."""
    from core.eta import DEFAULT_RATES, estimate
    from workers.pipeline import PIPELINES, overall_progress

    stages = [(s.name, s.weight) for s in PIPELINES[run["pipeline"]]]
    spans = stage_spans(run)
    out = []
    t = STEP_SECONDS
    while t < run["total"]:
        finished = {name: end - start for name, start, end in spans if end <= t}
        current = next(((n, s) for n, s, e in spans if s <= t < e), None)
        last = [e for e in run["events"] if e[0] <= t and current and e[1] == current[0]]
        fraction, count = (last[-1][2], last[-1][3]) if last else (0.0, None)
        name = current[0] if current else None
        rates = DEFAULT_RATES.get(run["pipeline"]) if defaults else None
        elapsed = t - current[1] if current else 0.0
        eta = estimate(stages, size_at(run, t), finished, name, fraction, elapsed, history, count, rates)
        progress = overall_progress(run["pipeline"], name, fraction) if name else 0.0
        bar = t * (100 - progress) / progress if progress > 0 else None
        out.append((t, None if eta is None else eta.seconds_left, bar))
        t += STEP_SECONDS
    return out


def errors(run: dict[str, Any], series: list[tuple[float, float | None, float | None]], which: int) -> dict[str, Any]:
    """|predicted - true time left| / job duration at 25, 50, 75 % and the worst from 25 % on; None: no estimate."""
    total = run["total"]

    def error(t: float, predicted: float | None) -> float | None:
        return None if predicted is None else abs(predicted - (total - t)) / total

    at = {}
    for share in (0.25, 0.5, 0.75):
        t, *values = min(series, key=lambda row: abs(row[0] - share * total))
        at[f"{round(share * 100)}%"] = error(t, values[which - 1])
    late = [error(row[0], row[which]) for row in series if row[0] >= 0.25 * total]
    worst = None if any(e is None for e in late) or not late else max(late)  # type: ignore[type-var]
    return {**at, "worst_after_25%": worst}


def trace_json(name: str, run: dict[str, Any]) -> dict[str, Any]:
    """A recorded run as JSON (a progress count as [unit, done, total]): what ``--traces`` reads back."""
    events = [
        [t, stage, fraction, None if c is None else [c.unit, c.done, c.total]]
        for t, stage, fraction, c in run["events"]
    ]
    return {"name": name, **run, "events": events}


def trace_run(trace: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """``trace_json``'s run again."""
    from core.eta import UnitCount

    events = [(t, stage, fraction, None if c is None else UnitCount(*c)) for t, stage, fraction, c in trace["events"]]
    run = {k: v for k, v in trace.items() if k != "name"}
    return trace["name"], {**run, "events": events}


def recorded_runs(tmp: Path, save: Path | None) -> list[tuple[str, dict[str, Any]]]:
    """The three runs, each recorded as it ran (written to ``save`` as JSON traces when given)."""
    from tests.scenes import make_flight

    runs: list[tuple[str, Path, dict[str, Any]]] = []
    make_flight(tmp / "s12", n_frames=12, frame_size=(640, 480), layout="grid", seed=11)
    runs.append(("synthetic 12 frames, 640 px", tmp / "s12", {"working_max_px": 640}))
    make_flight(tmp / "s24", n_frames=24, frame_size=(800, 600), layout="grid", seed=12)
    runs.append(("synthetic 24 frames, 800 px", tmp / "s24", {"working_max_px": 800}))
    brighton = ROOT.parent / "shared" / "data" / "drone_brighton_strip1"
    if brighton.is_dir():
        runs.append(("Brighton strip, 6 frames, 2048 px", brighton, {"working_max_px": 2048}))
    out = [(name, record_run(src, tmp / f"job{k}", options)) for k, (name, src, options) in enumerate(runs)]
    if save is not None:
        save.write_text(json.dumps([trace_json(name, run) for name, run in out]))
    return out


def main() -> None:
    from core.eta import DEFAULT_RATES, seconds_per_unit, similar_jobs

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", type=Path, help="write the figures here too")
    parser.add_argument("--save-traces", type=Path, help="write the recorded runs here (JSON)")
    parser.add_argument("--traces", type=Path, help="replay runs recorded by --save-traces instead of running")
    args = parser.parse_args()
    if args.traces:
        recorded = [trace_run(t) for t in json.loads(args.traces.read_text())]
    else:
        recorded = recorded_runs(Path(tempfile.mkdtemp(prefix="bench-eta-")), args.save_traces)
    done: list[dict[str, Any]] = []
    results = []
    for name, run in recorded:
        similar = similar_jobs([(size_at(r), stage_seconds(r)) for r in done], run["size"])  # as the API picks them
        history = seconds_per_unit(similar, DEFAULT_RATES.get(run["pipeline"])) or None
        series = replay(run, history)
        row = {
            "run": name,
            "seconds": round(run["total"], 2),
            "history_jobs": len(similar),
            "ours": errors(run, series, 1),
            "progress_bar": errors(run, series, 2),
        }
        if done:  # the same run as a first job on a service would see it
            row["ours_without_history"] = errors(run, replay(run, None), 1)
        row["ours_weights_only"] = errors(run, replay(run, None, defaults=False), 1)  # no rates at all
        results.append(row)
        done.append(run)
        print(_line(row))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


def _line(row: dict[str, Any]) -> str:
    def fmt(e: dict[str, Any]) -> str:
        return "  ".join(f"{k} {'-' if v is None else f'{v * 100:5.1f} %'}" for k, v in e.items())

    text = f"{row['run']} ({row['seconds']} s, history of {row['history_jobs']} run(s))\n"
    text += f"  ours:          {fmt(row['ours'])}\n"
    if "ours_without_history" in row:
        text += f"  ours, no hist: {fmt(row['ours_without_history'])}\n"
    text += f"  weights only:  {fmt(row['ours_weights_only'])}\n"
    text += f"  progress bar:  {fmt(row['progress_bar'])}"
    return text


if __name__ == "__main__":
    main()
