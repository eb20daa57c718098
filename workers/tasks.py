"""Celery tasks: one thin task per stage, named ``fotoskhema.<stage>``, each taking a job id.

The job record in the database is the truth about a job; a task keeps it current (stage, progress,
timings, error) and stops early when the job was cancelled.
"""

from __future__ import annotations

import logging
import time
from functools import lru_cache
from pathlib import Path
from typing import Any

from celery.exceptions import Ignore

from core.db import Database, Job
from core.kinds import JobStatus
from core.settings import get_settings
from workers.celery_app import app
from workers.pipeline import PIPELINES, PipelineError, overall_progress, pipeline_key, run_stage, task_name
from workers.workspace import job_workspace

log = logging.getLogger(__name__)


class JobCancelledError(Exception):
    """The job was cancelled while a stage ran."""


@lru_cache(maxsize=1)
def _database() -> Database:
    return Database(get_settings().resolved_database_url())


class JobRecorder:
    """Writes a running stage's state into the job record, at most every ``interval`` seconds."""

    def __init__(self, db: Database, job_id: int, pipeline: str, stage: str, interval: float = 0.5) -> None:
        self.db, self.job_id, self.pipeline, self.stage, self.interval = db, job_id, pipeline, stage, interval
        self._last = 0.0

    def update(self, **fields: Any) -> str:
        """Apply ``fields`` to the record and return its status."""
        with self.db.session() as s:
            job = s.get(Job, self.job_id)
            if job is None:
                raise JobCancelledError(f"job {self.job_id} no longer exists")
            if job.status == JobStatus.cancelled:
                return job.status
            for key, value in fields.items():
                setattr(job, key, value)
            return job.status

    def progress(self, fraction: float, detail: str) -> None:
        now = time.monotonic()
        if now - self._last < self.interval and fraction < 1.0:
            return
        self._last = now
        status = self.update(progress=overall_progress(self.pipeline, self.stage, fraction), progress_detail=detail)
        if status == JobStatus.cancelled:
            raise JobCancelledError(f"job {self.job_id} was cancelled")


def execute_stage(job_id: int, stage: str, db: Database | None = None, data_dir: Path | None = None) -> str:
    """Run ``stage`` of job ``job_id`` and record the outcome; returns the job's status after it.

    ``db`` and ``data_dir`` default to the process settings (they are explicit for tests).
    """
    db = db or _database()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or JobStatus(job.status).finished:
            return job.status if job else "missing"
        pipeline = pipeline_key(job.kind, job.options)
    rec = JobRecorder(db, job_id, pipeline, stage)
    if (
        rec.update(
            status=JobStatus.running, stage=stage, progress=overall_progress(pipeline, stage, 0.0), progress_detail=""
        )
        == JobStatus.cancelled
    ):
        return JobStatus.cancelled
    ws = job_workspace(data_dir or get_settings().data_dir, job_id)
    try:
        report = run_stage(ws, pipeline, stage, progress=rec.progress)
    except JobCancelledError:
        return JobStatus.cancelled
    except PipelineError as exc:
        rec.update(status=JobStatus.failed, error=f"{stage}: {exc}")
        raise
    except Exception as exc:
        log.exception("job %s stage %s crashed", job_id, stage)
        rec.update(status=JobStatus.failed, error=f"{stage}: internal error: {type(exc).__name__}: {exc}")
        raise
    return _record_done(rec, stage, report)


def _record_done(rec: JobRecorder, stage: str, report: dict[str, Any]) -> str:
    with rec.db.session() as s:
        job = s.get(Job, rec.job_id)
        assert job is not None
        job.timings = {**job.timings, stage: report.get("wall_seconds", 0.0)}
        job.progress = overall_progress(rec.pipeline, stage, 1.0)
        if stage == PIPELINES[rec.pipeline][-1].name and job.status == JobStatus.running:
            job.status, job.progress, job.progress_detail = JobStatus.succeeded, 100.0, "done"
        return job.status


def _register(stage: str) -> None:
    @app.task(name=task_name(stage), acks_late=True)
    def stage_task(job_id: int) -> str:
        status = execute_stage(job_id, stage)
        if status not in (JobStatus.running, JobStatus.succeeded):
            # Cancelled, or ended elsewhere: drop the rest of this chain, so that it never runs beside
            # the chain of a retry.
            raise Ignore()
        return status


for _stage in sorted({spec.name for specs in PIPELINES.values() for spec in specs}):
    _register(_stage)
