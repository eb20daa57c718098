"""Celery tasks: one thin task per stage, named ``fotoskhema.<stage>``, each taking a job id and the token of
the chain that sent it (``workers.liveness``).

The job record in the database is the truth about a job; a task keeps it current (stage, progress,
timings, error, heartbeat) and stops early when the job was cancelled or sent again.
"""

from __future__ import annotations

import logging
import re
import shutil
import time
import uuid
from functools import lru_cache
from pathlib import Path
from typing import Any

from celery.exceptions import Ignore, SoftTimeLimitExceeded
from celery.signals import worker_ready, worker_shutdown

from core.db import Database, Job
from core.eta import parse_count
from core.kinds import JobStatus
from core.settings import get_settings
from workers import liveness
from workers.celery_app import app
from workers.pipeline import PIPELINES, PipelineError, overall_progress, pipeline_key, run_stage, task_name
from workers.workspace import job_workspace

log = logging.getLogger(__name__)


class JobCancelledError(Exception):
    """The job was cancelled while a stage ran."""


class JobDeletedError(JobCancelledError):
    """The job was deleted while a stage ran: what the stage wrote since goes too."""


class JobSupersededError(Exception):
    """The job's record was taken over (sent again by the reaper) while a stage ran."""


@lru_cache(maxsize=1)
def _database() -> Database:
    return Database(get_settings().resolved_database_url())


class JobRecorder:
    """Writes a running stage's state into the job record, at most every ``interval`` seconds."""

    def __init__(
        self,
        db: Database,
        job_id: int,
        pipeline: str,
        stage: str,
        interval: float = 0.5,
        beat: liveness.Heartbeat | None = None,
    ) -> None:
        self.db, self.job_id, self.pipeline, self.stage, self.interval = db, job_id, pipeline, stage, interval
        self.beat = beat
        self._last = 0.0

    def update(self, current: dict[str, Any] | None = None, **fields: Any) -> str:
        """Apply ``fields`` to the record (and ``current`` to what ``work`` says of the running stage); return
        its status."""
        with self.db.session() as s:
            job = s.get(Job, self.job_id)
            if job is None:
                raise JobDeletedError(f"job {self.job_id} no longer exists")
            if job.status == JobStatus.cancelled:
                return job.status
            for key, value in fields.items():
                setattr(job, key, value)
            if current is not None:
                work = dict(job.work or {})
                work["current"] = {**(work.get("current") or {}), **current, "stage": self.stage}
                job.work = work  # a new dict: the JSON column sees the change
            return job.status

    def start(self) -> None:
        """Record when this stage started (the time-left estimate measures its rate from then)."""
        self.update(current={"started_at": time.time(), "fraction": 0.0, "unit": None, "done": 0, "total": 0})

    def progress(self, fraction: float, detail: str) -> None:
        if self.beat is not None and self.beat.lost:  # the record is no longer this run's: cancelled, or sent again
            if self.update() == JobStatus.cancelled:
                raise JobCancelledError(f"job {self.job_id} was cancelled")
            raise JobSupersededError(f"job {self.job_id} was taken over")
        now = time.monotonic()
        if now - self._last < self.interval and fraction < 1.0:
            return
        self._last = now
        current: dict[str, Any] = {"fraction": min(max(float(fraction), 0.0), 1.0)}
        if (count := parse_count(detail)) is not None:
            current.update(unit=count.unit, done=count.done, total=count.total)
        status = self.update(
            current, progress=overall_progress(self.pipeline, self.stage, fraction), progress_detail=detail
        )
        if status == JobStatus.cancelled:
            raise JobCancelledError(f"job {self.job_id} was cancelled")


def execute_stage(
    job_id: int, stage: str, db: Database | None = None, data_dir: Path | None = None, token: str | None = None
) -> str:
    """Run ``stage`` of job ``job_id`` and record the outcome; returns the job's status after it, or why the
    stage did not run (``workers.liveness.SUPERSEDED``, ``BUSY``, ``MISSING``).

    ``db`` and ``data_dir`` default to the process settings (they are explicit for tests); ``token`` is the
    chain's (``None``: not sent as a chain).
    """
    db, settings = db or _database(), get_settings()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or JobStatus(job.status).finished:
            return job.status if job else liveness.MISSING
        pipeline = pipeline_key(job.kind, job.options)
    claim = liveness.claim_stage(
        db,
        job_id,
        stage,
        token,
        progress=overall_progress(pipeline, stage, 0.0),
        max_deliveries=settings.max_deliveries,
        stale_seconds=settings.stale_seconds,
    )
    if claim != JobStatus.running:
        if claim == JobStatus.failed:
            log.error("job %s stage %s: its process died %s times; job failed", job_id, stage, settings.max_deliveries)
        return claim
    ws = job_workspace(data_dir or get_settings().data_dir, job_id)
    with liveness.Heartbeat(db, job_id, settings.heartbeat_seconds) as beat:
        rec = JobRecorder(db, job_id, pipeline, stage, beat=beat)
        try:
            rec.start()
            report = run_stage(ws, pipeline, stage, progress=rec.progress)
        except JobDeletedError:
            shutil.rmtree(ws.root, ignore_errors=True)  # the API removed the folder; the stage may have written since
            return liveness.MISSING
        except JobCancelledError:
            return JobStatus.cancelled
        except JobSupersededError:
            log.warning("job %s stage %s: sent again while it ran; this run stops", job_id, stage)
            return liveness.SUPERSEDED
        except PipelineError as exc:
            rec.update(status=JobStatus.failed, error=f"{stage}: {public_message(str(exc))}")
            raise
        except Exception as exc:
            rec.update(status=JobStatus.failed, error=_failure_message(job_id, stage, exc))
            raise
    status = _record_done(rec, stage, report, token)
    if status == liveness.MISSING:
        shutil.rmtree(ws.root, ignore_errors=True)  # deleted as the stage ended
    return status


def _failure_message(job_id: int, stage: str, exc: Exception) -> str:
    """What the user reads about a stage that crashed: what they can do, never a path, host or library name.
    The details go to the worker's log under a reference the user can quote."""
    if isinstance(exc, SoftTimeLimitExceeded):
        hours = get_settings().stage_time_limit_seconds / 3600
        log.error("job %s stage %s: stopped at the time limit", job_id, stage)
        return f"{stage}: stopped after running longer than the limit of {hours:g} h; try with fewer or smaller images"
    if isinstance(exc, MemoryError):
        log.error("job %s stage %s: out of memory", job_id, stage)
        return f"{stage}: the worker ran out of memory; try with fewer or smaller images"
    ref = uuid.uuid4().hex[:8]
    log.exception("job %s stage %s crashed (reference %s)", job_id, stage, ref)
    return f"{stage}: internal error (reference {ref}); the operators find the details in the worker's log"


_ABSOLUTE_PATH = re.compile(r"(?<![\w.~-])(?:/[^\s/:'\"]+)+/([^\s/:'\"]+)")


def public_message(message: str) -> str:
    """``message`` with every absolute path cut to its last part (the file's name), which is the user's."""
    return _ABSOLUTE_PATH.sub(r"\1", message)


def _record_done(rec: JobRecorder, stage: str, report: dict[str, Any], token: str | None) -> str:
    with rec.db.session() as s:
        job = s.get(Job, rec.job_id)
        if job is None:
            return liveness.MISSING
        if not liveness.accepts(token, job.celery_id):  # sent again as it ended: the new chain records it
            return liveness.SUPERSEDED
        job.timings = {**job.timings, stage: report.get("wall_seconds", 0.0)}
        work = dict(job.work or {})
        last = work.pop("current", None) or {}
        unit = last.get("unit") if last.get("stage") == stage else None
        count = last.get("total") if unit else None
        work["stages"] = {
            **work.get("stages", {}),
            stage: {"seconds": report.get("wall_seconds", 0.0), "unit": unit, "count": count},
        }
        job.work = work
        job.progress = overall_progress(rec.pipeline, stage, 1.0)
        if stage == PIPELINES[rec.pipeline][-1].name and job.status == JobStatus.running:
            job.status, job.progress, job.progress_detail = JobStatus.succeeded, 100.0, "done"
        return job.status


def _register(stage: str) -> None:
    @app.task(name=task_name(stage), acks_late=True)
    def stage_task(job_id: int, token: str | None = None) -> str:
        status = execute_stage(job_id, stage, token=token)
        if status not in (JobStatus.running, JobStatus.succeeded):
            # Cancelled, failed, sent again or running elsewhere: drop the rest of this chain, so that it never
            # runs beside another chain of the job.
            raise Ignore()
        return status


for _stage in sorted({spec.name for specs in PIPELINES.values() for spec in specs}):
    _register(_stage)


_beacons: list[liveness.WorkerBeacon] = []


@worker_ready.connect
def _start_beacon(sender: Any, **_: Any) -> None:
    """In the worker's main process: tell /api/health, through Redis, that this worker is alive."""
    queues = list(sender.app.amqp.queues.consume_from)
    beacon = liveness.WorkerBeacon(
        str(sender.app.conf.broker_url), str(sender.hostname), queues, get_settings().worker_beacon_seconds
    )
    beacon.start()
    _beacons.append(beacon)


@worker_shutdown.connect
def _stop_beacon(**_: Any) -> None:
    while _beacons:
        _beacons.pop().stop()
