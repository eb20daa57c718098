"""Celery tasks: one thin task per stage, named ``fotoskhema.<stage>``, each taking a job id and the token of
the chain that sent it (``workers.liveness``).

The job record in the database is the truth about a job; a task keeps it current (stage, progress,
timings, error, heartbeat) and stops early when the job was cancelled or sent again.
"""

from __future__ import annotations

import contextlib
import logging
import re
import shutil
import time
import uuid
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import redis
from celery import Task, chord, group
from celery.canvas import Signature
from celery.exceptions import Ignore, SoftTimeLimitExceeded
from celery.signals import worker_ready, worker_shutdown

from core.db import Database, Job
from core.eta import parse_count
from core.kinds import JobStatus
from core.settings import get_settings
from workers import liveness
from workers import pipeline as stages
from workers.celery_app import app
from workers.config import build_config
from workers.pipeline import (
    PARTED_STAGES,
    PIPELINES,
    PipelineError,
    finish_stage,
    forget_parts_if_stale,
    job_kind,
    overall_progress,
    part_unit,
    parts_summary,
    pipeline_key,
    plan_stage,
    progress_shares,
    run_parts,
    run_stage,
    stage_done,
    task_name,
)
from workers.workspace import JobWorkspace, job_workspace, noop_progress

log = logging.getLogger(__name__)
T = TypeVar("T")
PART_TASK, FINISH_TASK = "fotoskhema.part", "fotoskhema.finish"


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
        beat: liveness.Heartbeat | liveness.PartBeat | None = None,
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
        count = parse_count(detail)
        last_unit = count is not None and count.done == count.total  # the count a stage ends with is kept
        if now - self._last < self.interval and fraction < 1.0 and not last_unit:
            return
        self._last = now
        current: dict[str, Any] = {"fraction": min(max(float(fraction), 0.0), 1.0)}
        if count is not None:
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
    claim, pipeline = _claim(db, job_id, stage, token)
    if claim != JobStatus.running:
        return claim
    ws = job_workspace(data_dir or settings.data_dir, job_id)
    with liveness.Heartbeat(db, job_id, settings.heartbeat_seconds) as beat:
        rec = JobRecorder(db, job_id, pipeline, stage, beat=beat)
        rec.start()
        outcome, report = _guarded(rec, ws, lambda: run_stage(ws, pipeline, stage, progress=rec.progress))
    return outcome if report is None else _recorded(rec, ws, stage, report, token)


class Plan(NamedTuple):
    """What ``execute_plan`` found: the job's status, and whether the stage's parts are to be sent (``todo``,
    which may be empty: then its finish runs at once)."""

    status: str
    todo: list[str]
    planned: bool


def execute_plan(
    job_id: int, stage: str, db: Database | None = None, data_dir: Path | None = None, token: str | None = None
) -> Plan:
    """Claim parted ``stage`` and run its plan (``workers.pipeline.plan_stage``); the parts not yet done are
    returned for the workers. A stage already done is recorded as in ``execute_stage``."""
    db, settings = db or _database(), get_settings()
    claim, pipeline = _claim(db, job_id, stage, token)
    if claim != JobStatus.running:
        return Plan(claim, [], False)
    ws = job_workspace(data_dir or settings.data_dir, job_id)
    if (done := stage_done(ws, stage)) is not None:
        return Plan(_record_done(JobRecorder(db, job_id, pipeline, stage), stage, done, token), [], False)
    forget_parts_if_stale(ws, stage)
    # the plan's heartbeat keeps the stage's start count on leaving: parts that keep dying still end the job
    with liveness.Heartbeat(db, job_id, settings.heartbeat_seconds, hold=True) as beat:
        rec = JobRecorder(db, job_id, pipeline, stage, beat=beat)
        cfg = build_config(job_kind(pipeline), ws.load_config())
        rec.start()
        rec.progress(0.0, "planning")
        outcome, todo = _guarded(rec, ws, lambda: plan_stage(stages.stage_module(stage), stage, ws, cfg))
    return Plan(outcome, [], False) if todo is None else Plan(JobStatus.running, todo, True)


def execute_parts(
    job_id: int,
    stage: str,
    keys: list[str],
    db: Database | None = None,
    data_dir: Path | None = None,
    token: str | None = None,
) -> str:
    """Do parts ``keys`` of ``stage`` in this process (its threads), as long as the job is chain ``token``'s and
    running; returns ``running``, or why it stopped. A part's crash that is not the user's data propagates, so
    Celery tries the part again (``part_retries``); a ``PipelineError`` fails the job."""
    db, settings = db or _database(), get_settings()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None:
            return liveness.MISSING
        if job.status != JobStatus.running or not liveness.accepts(token, job.celery_id):
            return job.status if job.status != JobStatus.running else liveness.SUPERSEDED
        pipeline = pipeline_key(job.kind, job.options)
    ws = job_workspace(data_dir or settings.data_dir, job_id)
    cfg = build_config(job_kind(pipeline), ws.load_config())
    total = max(1, len(ws.load_plan(stage)))
    with liveness.PartBeat(db, job_id, token, settings.heartbeat_seconds) as beat:
        rec = JobRecorder(db, job_id, pipeline, stage, beat=beat)

        unit = part_unit(stages.stage_module(stage))
        plan, parts = progress_shares(stages.stage_module(stage))

        def progress(_fraction: float, _detail: str) -> None:
            done = len(ws.parts_done(stage))
            rec.progress(plan + parts * done / total, f"{unit} {done}/{total}")

        try:
            run_parts(stages.stage_module(stage), stage, ws, cfg, keys, progress)
        except JobDeletedError:
            shutil.rmtree(ws.root, ignore_errors=True)  # the API removed the folder; the part may have written since
            return liveness.MISSING
        except JobCancelledError:
            return JobStatus.cancelled
        except JobSupersededError:
            return liveness.SUPERSEDED
        except PipelineError as exc:
            rec.update(status=JobStatus.failed, error=f"{stage}: {public_message(str(exc))}")
            return JobStatus.failed
    return JobStatus.running


def fail_parts(
    job_id: int, stage: str, exc: BaseException | None, db: Database | None = None, message: str = ""
) -> None:
    """A part crashed on every try, or its process died every time: the job fails, with a message the user can
    act on (``message``, or one made from ``exc``)."""
    db = db or _database()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.status != JobStatus.running:
            return
        pipeline = pipeline_key(job.kind, job.options)
    rec = JobRecorder(db, job_id, pipeline, stage)
    if not message:
        message = _failure_message(job_id, stage, exc) if isinstance(exc, Exception) else f"{stage}: internal error"
    rec.update(status=JobStatus.failed, error=message, heartbeat_at=None, heartbeat_by="", deliveries=0)


def execute_finish(
    job_id: int, stage: str, db: Database | None = None, data_dir: Path | None = None, token: str | None = None
) -> str:
    """The finish of parted ``stage`` once its parts are done (any left are done here first); records the
    outcome as ``execute_stage`` does."""
    db, settings = db or _database(), get_settings()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or JobStatus(job.status).finished:
            return job.status if job else liveness.MISSING
        pipeline = pipeline_key(job.kind, job.options)
    ws = job_workspace(data_dir or settings.data_dir, job_id)
    if (done := stage_done(ws, stage)) is not None:  # a finish delivered twice
        return _record_done(JobRecorder(db, job_id, pipeline, stage), stage, done, token)
    if not liveness.take_over(db, job_id, token):
        return liveness.SUPERSEDED
    with liveness.Heartbeat(db, job_id, settings.heartbeat_seconds) as beat:
        rec = JobRecorder(db, job_id, pipeline, stage, beat=beat)
        cfg = build_config(job_kind(pipeline), ws.load_config())
        module = stages.stage_module(stage)

        def finish() -> dict[str, Any]:
            left = [k for k in ws.load_plan(stage) if k not in ws.parts_done(stage)]
            run_parts(module, stage, ws, cfg, left, noop_progress)  # parts lost with their chunk, if any
            plan, parts = progress_shares(module)
            report = finish_stage(
                module, stage, ws, cfg, lambda f, d: rec.progress(plan + parts + (1.0 - plan - parts) * f, d)
            )
            report["wall_seconds"] = round(time.time() - ws.plan_started(stage), 3)
            report["parts"] = parts_summary(ws, stage)
            ws.save_stage_report(stage, report)
            return report

        outcome, report = _guarded(rec, ws, finish)
    return outcome if report is None else _recorded(rec, ws, stage, report, token)


def _claim(db: Database, job_id: int, stage: str, token: str | None) -> tuple[str, str]:
    """Claim ``stage`` of the job for this delivery (``liveness.claim_stage``); its outcome and the pipeline."""
    settings = get_settings()
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or JobStatus(job.status).finished:
            return (job.status if job else liveness.MISSING), ""
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
    if claim == JobStatus.failed:
        log.error("job %s stage %s: its process died %s times; job failed", job_id, stage, settings.max_deliveries)
    return claim, pipeline


def _guarded(rec: JobRecorder, ws: JobWorkspace, work: Callable[[], T]) -> tuple[str, T | None]:
    """``work()``'s result, or (its result None) why the stage stopped: the job was deleted (what the stage
    wrote since goes too), cancelled or sent again. A ``PipelineError`` or a crash fails the job and is raised."""
    try:
        return JobStatus.running, work()
    except JobDeletedError:
        shutil.rmtree(ws.root, ignore_errors=True)  # the API removed the folder; the stage may have written since
        return liveness.MISSING, None
    except JobCancelledError:
        return JobStatus.cancelled, None
    except JobSupersededError:
        log.warning("job %s stage %s: sent again while it ran; this run stops", rec.job_id, rec.stage)
        return liveness.SUPERSEDED, None
    except PipelineError as exc:
        rec.update(status=JobStatus.failed, error=f"{rec.stage}: {public_message(str(exc))}")
        raise
    except Exception as exc:
        rec.update(status=JobStatus.failed, error=_failure_message(rec.job_id, rec.stage, exc))
        raise


def _recorded(rec: JobRecorder, ws: JobWorkspace, stage: str, report: dict[str, Any], token: str | None) -> str:
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


def _register_parted(stage: str) -> None:
    @app.task(name=task_name(stage), bind=True, acks_late=True)
    def stage_task(self: Task, job_id: int, token: str | None = None) -> str:
        plan = execute_plan(job_id, stage, token=token)
        if plan.status not in (JobStatus.running, JobStatus.succeeded):
            raise Ignore()
        if not plan.planned:
            return plan.status  # done before: the chain goes on
        if not plan.todo:
            status = execute_finish(job_id, stage, token=token)
            if status not in (JobStatus.running, JobStatus.succeeded):
                raise Ignore()
            return status
        queue = (self.request.delivery_info or {}).get("routing_key") or get_settings().celery_queue
        # The parts of the stage, as a chord over every worker of the queue, then its finish; the rest of the
        # chain follows the finish (Celery's replace). Every task id starts with the chain's token (the reaper
        # finds a waiting job's messages by it).
        header = group(_part_signatures(job_id, stage, plan.todo, token, queue))
        body = app.signature(FINISH_TASK, args=(job_id, stage), kwargs={"token": token}, immutable=True, queue=queue)
        raise self.replace(chord(header, body))


def _part_signatures(job_id: int, stage: str, todo: list[str], token: str | None, queue: str) -> list[Signature]:
    """The parts ``todo`` in chunks, ``parts_per_worker`` for each live worker of the queue they go to: a GPU
    stage's to the GPU queue when a worker there is alive."""
    settings = get_settings()
    client = liveness.redis_client(str(app.conf.broker_url), 1.0)
    target = queue
    if _is_gpu_stage(stage):
        with contextlib.suppress(redis.RedisError):
            if liveness.live_workers(
                client, settings.gpu_queue, WORKER_MAX_AGE_FACTOR * settings.worker_beacon_seconds
            ):
                target = settings.gpu_queue
    try:
        workers = liveness.live_workers(client, target, WORKER_MAX_AGE_FACTOR * settings.worker_beacon_seconds)
    except redis.RedisError:
        workers = 1
    count = min(len(todo), settings.parts_per_worker * max(1, workers))
    chunks = [todo[k::count] for k in range(count)]  # interleaved: each chunk a spread of the frames or rows
    return [
        app.signature(
            PART_TASK,
            args=(job_id, stage, chunk),
            kwargs={"token": token},
            immutable=True,
            queue=target,
            task_id=f"{token}.{stage}.part{n}.{uuid.uuid4().hex[:8]}",
        )
        for n, chunk in enumerate(chunks)
    ]


def _is_gpu_stage(stage: str) -> bool:
    return any(spec.gpu for specs in PIPELINES.values() for spec in specs if spec.name == stage)


WORKER_MAX_AGE_FACTOR = 3  # a worker counts as alive for this many beacon intervals after its last one


@app.task(name=PART_TASK, bind=True, acks_late=True)
def part_task(self: Task, job_id: int, stage: str, keys: list[str], token: str | None = None) -> str:
    """Parts ``keys`` of ``stage``; a crash is tried again, alone, ``part_retries`` times, then fails the job.
    Never raises at the end: the chord's finish must always get its answer."""
    settings = get_settings()
    starts = _count_start(f"{self.request.id}")
    if starts > settings.max_deliveries:  # its process died every time (each death hands the message out again)
        log.error("job %s stage %s: a part's process died %s times; job failed", job_id, stage, starts - 1)
        fail_parts(job_id, stage, None, message=liveness.gave_up_message(stage, starts - 1))
        return JobStatus.failed
    try:
        return execute_parts(job_id, stage, keys, token=token)
    except Exception as exc:
        if self.request.retries < get_settings().part_retries:
            log.warning("job %s stage %s: part crashed (%s); tried again", job_id, stage, type(exc).__name__)
            raise self.retry(exc=exc, countdown=1) from None
        fail_parts(job_id, stage, exc)
        return JobStatus.failed


def _count_start(task_id: str) -> int:
    """How many times the part task ``task_id`` has started, this one included (Redis: shared by every worker);
    1 when Redis cannot say."""
    client = liveness.redis_client(str(app.conf.broker_url), 1.0)
    key = f"fotoskhema:part-starts:{task_id}"
    try:
        starts = int(client.incr(key))  # type: ignore[arg-type]
        client.expire(key, 7 * 24 * 3600)
        return starts
    except redis.RedisError:
        return 1


@app.task(name=FINISH_TASK, acks_late=True)
def finish_task(job_id: int, stage: str, token: str | None = None) -> str:
    status = execute_finish(job_id, stage, token=token)
    if status not in (JobStatus.running, JobStatus.succeeded):
        raise Ignore()  # the rest of the chain is dropped, as after a stage that did not end well
    return status


for _stage in sorted(PARTED_STAGES):
    _register_parted(_stage)
for _stage in sorted({spec.name for specs in PIPELINES.values() for spec in specs} - PARTED_STAGES):
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
