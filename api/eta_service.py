"""A running job's time left (``core.eta``) from its record and the service's recent jobs of the same pipeline.

The history (each stage's seconds and the job's size on the last ``HISTORY_JOBS`` succeeded jobs of the
pipeline; those of a similar size give the median seconds per input frame or megapixel) is read at most once a
minute per pipeline and process: a job page's event stream asks every second.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from sqlalchemy import select

from core.db import Database, Job
from core.eta import DEFAULT_RATES, UnitCount, estimate, seconds_per_unit, similar_jobs
from core.kinds import JobStatus
from workers.pipeline import PIPELINES, pipeline_key

HISTORY_JOBS = 20  # recent succeeded jobs of a pipeline whose stage rates predict the next one's
HISTORY_SCAN = 200  # succeeded jobs of the kind looked at to find them
HISTORY_SECONDS = 60.0  # how long a process keeps a pipeline's history before reading it again

Samples = list[tuple[dict[str, float], dict[str, float]]]  # earlier jobs' (size, stage seconds)
_cache: dict[tuple[str, str], tuple[float, Samples]] = {}
_lock = threading.Lock()


def job_eta(db: Database, job: Job, now: float | None = None) -> dict[str, Any] | None:
    """``core.eta.Eta.to_json()`` of a queued or running job; None for a finished one or when there is nothing
    to go by yet (no history, nothing measured)."""
    if JobStatus(job.status).finished:
        return None
    now = time.time() if now is None else now
    pipeline = pipeline_key(job.kind, job.options)
    work = job.work or {}
    names = {spec.name for spec in PIPELINES[pipeline]}
    finished = {k: float(v) for k, v in (job.timings or {}).items() if k in names and isinstance(v, int | float)}
    current = work.get("current") or {}
    running = job.status == JobStatus.running and current.get("stage") == job.stage and job.stage in names
    count = None
    if running and current.get("unit") and int(current.get("total") or 0) > 0:
        count = UnitCount(str(current["unit"]), int(current.get("done") or 0), int(current["total"]))
    eta = estimate(
        [(spec.name, spec.weight) for spec in PIPELINES[pipeline]],
        job_size(work),
        finished,
        job.stage if running else None,
        float(current.get("fraction") or 0.0) if running else 0.0,
        max(0.0, now - float(current.get("started_at") or now)) if running else 0.0,
        seconds_per_unit(
            similar_jobs(history(db, job.kind, pipeline, now), job_size(work)), DEFAULT_RATES.get(pipeline)
        ),
        count,
        DEFAULT_RATES.get(pipeline),
    )
    return None if eta is None else eta.to_json()


def history(db: Database, kind: str, pipeline: str, now: float) -> Samples:
    """The size and stage seconds of the service's recent succeeded jobs of ``pipeline`` (``core.eta`` takes
    the similar ones' seconds per unit of work)."""
    key = (str(db.engine.url), pipeline)
    with _lock:
        cached = _cache.get(key)
    if cached is not None and now - cached[0] < HISTORY_SECONDS:
        return cached[1]
    query = (
        select(Job.options, Job.timings, Job.work)
        .where(Job.kind == kind, Job.status == JobStatus.succeeded)
        .order_by(Job.id.desc())
        .limit(HISTORY_SCAN)
    )
    samples: Samples = []
    with db.session() as s:
        for options, timings, work in s.execute(query):
            if (work or {}).get("frames") and timings and pipeline_key(kind, options) == pipeline:
                samples.append((job_size(work), timings))
            if len(samples) >= HISTORY_JOBS:
                break
    with _lock:
        _cache[key] = (now, samples)
    return samples


def job_size(work: dict[str, Any]) -> dict[str, float]:
    """What a job's record says of its size: input frames and, when known, working megapixels and the pairs of
    photos matching counts (from its start)."""
    size = {"frames": float(work.get("frames") or 1)}
    for key in ("megapixels", "photo_megapixels"):
        if isinstance(work.get(key), int | float):
            size[key] = float(work[key])
    matching = (work.get("stages") or {}).get("match_features") or {}
    current = work.get("current") or {}
    if current.get("stage") == "match_features" and not matching:
        matching = {"unit": current.get("unit"), "count": current.get("total")}
    if matching.get("unit") == "pair" and isinstance(matching.get("count"), int) and matching["count"] > 0:
        size["pairs"] = float(matching["count"])
    return size


def forget_history() -> None:
    """Drop the cached histories (tests that change the jobs a history is read from)."""
    with _lock:
        _cache.clear()
