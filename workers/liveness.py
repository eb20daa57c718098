"""How a job shows it is alive, shared by the workers and the API's reaper and health check.

- A **chain token** names one sending of a job's stages. The record holds the newest (``Job.celery_id``);
  a task of an older chain stops (``accepts``), so a chain sent again never runs beside the one it replaces.
- A stage **claims** its job when it starts (``claim_stage``): it counts the start in ``Job.deliveries`` (reset
  when the stage ends, so only starts whose process died add up) and fails the job once a stage has died
  ``max_deliveries`` times, whoever redelivered it (Celery after a lost pool process, or the reaper).
- While a stage runs, a ``Heartbeat`` thread stamps ``Job.heartbeat_at``; a stamp older than
  ``Settings.stale_seconds`` means its process is gone. ``heartbeat_at`` is NULL while the job waits for a stage.
- A worker's main process refreshes its entry in a Redis sorted set (``WorkerBeacon``), which ``/api/health``
  reads (``live_workers``).

No stage code or OpenCV here: the API imports this module.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import socket
import threading
import time
from datetime import timedelta
from typing import Any

import redis
from sqlalchemy import update
from sqlalchemy.exc import SQLAlchemyError

from core.db import Database, Job, utcnow
from core.kinds import JobStatus

log = logging.getLogger(__name__)

SUPERSEDED = "superseded"  # claim_stage: a newer chain of the job was sent; this task's chain stops
BUSY = "busy"  # claim_stage: another live process runs this stage now (a duplicate delivery)
MISSING = "missing"  # claim_stage: no such job
WORKERS_KEY = "fotoskhema:workers"  # sorted set: worker -> Redis time of its last beacon


def new_token(after: str = "") -> str:
    """A chain token that sorts after ``after``: ``g``, 16 hex digits of nanoseconds, 8 random hex digits.

    Tokens of one job compare as strings in the order they were made (also across hosts whose clocks lag,
    thanks to ``after``). ``g`` sorts after every hex digit, so a token is newer than the Celery ids that
    versions without tokens stored in ``celery_id``.
    """
    ns = time.time_ns()
    if is_token(after):
        ns = max(ns, int(after[1:17], 16) + 1)
    return f"g{ns:016x}{secrets.token_hex(4)}"


def is_token(value: str) -> bool:
    return len(value) == 25 and value[0] == "g" and all(c in "0123456789abcdef" for c in value[1:])


def accepts(token: str | None, current: str) -> bool:
    """Whether a task of chain ``token`` may run for a job whose record names chain ``current``.

    ``None`` is a call outside any chain (tests, messages sent before tokens existed): it runs unless a chain
    with a token was sent since. A newer token than the record's may run: the API records the token it sent
    only once the message is out, so the first task can start before that.
    """
    if token is None:
        return not is_token(current)
    return token >= current or not is_token(current)


def this_process() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def holder_is_gone(holder: str) -> bool:
    """Whether the process ``host:pid`` is known to be dead: only a process of this host can be looked at."""
    host, _, pid = holder.rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, someone else's
        return False
    return False


def gave_up_message(stage: str, starts: int) -> str:
    return (
        f"{stage}: the worker process running this stage stopped {starts} times before it finished "
        "(killed, or out of memory); it is not started again. Retry the job once the workers have more "
        "memory, or with smaller images."
    )


def claim_stage(
    db: Database,
    job_id: int,
    stage: str,
    token: str | None,
    *,
    progress: float,
    max_deliveries: int,
    stale_seconds: float,
) -> str:
    """Mark job ``job_id`` running ``stage`` for this delivery; returns ``running``, or why not: the job's
    finished status (``failed`` when this start is one too many), ``MISSING``, ``SUPERSEDED`` or ``BUSY``.

    A compare-and-set on the fields it read, so two deliveries (or a delivery and the reaper) racing on one
    job never both win, on SQLite as on PostgreSQL.
    """
    me = this_process()
    for _ in range(20):
        now = utcnow()
        with db.session() as s:
            job = s.get(Job, job_id)
            if job is None:
                return MISSING
            if JobStatus(job.status).finished:
                return job.status
            if not accepts(token, job.celery_id):
                return SUPERSEDED
            same = job.stage == stage
            if same and _held_elsewhere(job, now, stale_seconds, me):
                return BUSY
            deliveries = job.deliveries + 1 if same else 1
            values: dict[str, Any] = {
                "status": JobStatus.running,
                "stage": stage,
                "deliveries": deliveries,
                "heartbeat_at": now,
                "heartbeat_by": me,
                "progress": progress,
                "progress_detail": "",
            }
            if token is not None:
                values["celery_id"] = token
            if deliveries > max_deliveries:
                values = {**_idle(), "status": JobStatus.failed, "error": gave_up_message(stage, deliveries - 1)}
            claimed = s.execute(
                update(Job)
                .where(
                    Job.id == job_id,
                    Job.celery_id == job.celery_id,
                    Job.status == job.status,
                    Job.stage == job.stage,
                    Job.deliveries == job.deliveries,
                )
                .values(**values)
                .execution_options(synchronize_session=False)
            )
            if claimed.rowcount == 1:  # type: ignore[attr-defined]
                return str(values["status"])
    return BUSY  # changed under us twenty times: someone else is busy with it


def _held_elsewhere(job: Job, now: Any, stale_seconds: float, me: str) -> bool:
    """A fresh heartbeat of another process that may be alive: a duplicate delivery (a Redis visibility
    timeout that ran out) must not run the stage a second time beside it."""
    if job.heartbeat_at is None or job.heartbeat_by in ("", me):
        return False
    return now - job.heartbeat_at < timedelta(seconds=stale_seconds) and not holder_is_gone(job.heartbeat_by)


def _idle() -> dict[str, Any]:
    """The liveness fields of a job no process runs a stage of."""
    return {"heartbeat_at": None, "heartbeat_by": "", "deliveries": 0}


class _Beat:
    """A daemon thread that calls ``_alive()`` every ``interval`` s while the ``with`` block runs; ``lost`` turns
    true once ``_alive`` says the record is no longer this run's (cancelled, failed or sent again)."""

    def __init__(self, db: Database, job_id: int, interval: float) -> None:
        self.db, self.job_id, self.interval = db, job_id, interval
        self._stop, self._lost = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"{type(self).__name__}-{job_id}", daemon=True)

    @property
    def lost(self) -> bool:
        return self._lost.is_set()

    def _alive(self) -> bool:
        raise NotImplementedError

    def _start(self) -> None:
        self._thread.start()

    def _end(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                if not self._alive():
                    self._lost.set()
                    return
            except SQLAlchemyError:  # the database is away for a moment: the stale threshold allows for it
                log.warning("job %s: heartbeat not written", self.job_id, exc_info=True)

    def _update(self, where: list[Any], values: dict[str, Any]) -> bool:
        with self.db.session() as s:
            done = s.execute(
                update(Job)
                .where(Job.id == self.job_id, *where)
                .values(**values)
                .execution_options(synchronize_session=False)
            )
            return bool(done.rowcount == 1)  # type: ignore[attr-defined]


class Heartbeat(_Beat):
    """While a stage runs (``with Heartbeat(...)``), stamps its job's ``heartbeat_at`` every ``interval`` s
    from a daemon thread. ``lost`` turns true once the record is no longer this process's (cancelled, failed
    or sent again by the reaper); on leaving, the job is marked idle and its start count reset."""

    def __init__(self, db: Database, job_id: int, interval: float, *, hold: bool = False) -> None:
        super().__init__(db, job_id, interval)
        self.hold = hold  # on leaving, keep the start count: a stage's plan, whose parts are still to run
        self.me = this_process()

    def __enter__(self) -> Heartbeat:
        self._start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._end()
        self._update([Job.heartbeat_by == self.me], {**_idle(), "deliveries": Job.deliveries} if self.hold else _idle())

    def _alive(self) -> bool:
        return self._update([Job.heartbeat_by == self.me, Job.status == JobStatus.running], {"heartbeat_at": utcnow()})


class PartBeat(_Beat):
    """While one worker does parts of a stage spread over several (``with PartBeat(...)``), stamps the job's
    ``heartbeat_at`` every ``interval`` s, as long as the record is still chain ``token``'s and running. Many
    processes stamp one job at once, so nothing is held: ``heartbeat_by`` stays empty. ``lost`` turns true once
    the record is no longer the chain's or no longer running (cancelled, failed, sent again). On leaving, the
    heartbeat is cleared: the job then waits for its next message (another part, or the stage's finish), which
    the reaper finds in the queue; the other parts still running stamp it again within ``interval``."""

    def __init__(self, db: Database, job_id: int, token: str | None, interval: float) -> None:
        super().__init__(db, job_id, interval)
        self.where = [Job.status == JobStatus.running, Job.heartbeat_by == ""]
        if token is not None:
            self.where.append(Job.celery_id == token)

    def __enter__(self) -> PartBeat:
        if not self._alive():
            self._lost.set()
        self._start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._end()
        with contextlib.suppress(SQLAlchemyError):
            self._update(self.where, {"heartbeat_at": None})

    def _alive(self) -> bool:
        return self._update(self.where, {"heartbeat_at": utcnow()})


def take_over(db: Database, job_id: int, token: str | None) -> bool:
    """Hold job ``job_id`` for this process (its stage's finish) if it is still chain ``token``'s and running."""
    where = [Job.id == job_id, Job.status == JobStatus.running]
    if token is not None:
        where.append(Job.celery_id == token)
    with db.session() as s:
        done = s.execute(
            update(Job)
            .where(*where)
            .values(heartbeat_at=utcnow(), heartbeat_by=this_process())
            .execution_options(synchronize_session=False)
        )
        return bool(done.rowcount == 1)  # type: ignore[attr-defined]


def redis_client(url: str, timeout: float) -> redis.Redis:
    return redis.Redis.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout)


def redis_now(client: redis.Redis) -> float:
    """Redis's clock, which every process that writes or reads beacons agrees on."""
    seconds, micros = client.time()  # type: ignore[misc]
    return float(seconds) + float(micros) / 1e6


class WorkerBeacon:
    """Refreshes this worker's entry in ``WORKERS_KEY`` every ``interval`` s from a daemon thread of the worker's
    main process, which is what dies with the worker; ``stop`` removes the entry."""

    def __init__(self, redis_url: str, name: str, queues: list[str], interval: float) -> None:
        self.client = redis_client(redis_url, timeout=max(1.0, interval))
        self.member = json.dumps({"name": name, "queues": sorted(queues)})
        self.interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-beacon", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with contextlib.suppress(redis.RedisError):  # gone anyway once its beacon is too old
            self.client.zrem(WORKERS_KEY, self.member)

    def _run(self) -> None:
        while True:
            try:
                now = redis_now(self.client)
                self.client.zadd(WORKERS_KEY, {self.member: now})
                self.client.zremrangebyscore(WORKERS_KEY, 0, now - 100 * self.interval)  # long-gone workers
            except redis.RedisError:  # the broker is down: the worker reconnects, and so does the beacon
                pass
            if self._stop.wait(self.interval):
                return


def live_workers(client: redis.Redis, queue: str, max_age: float) -> int:
    """How many workers that consume ``queue`` sent a beacon in the last ``max_age`` seconds."""
    members: list[bytes] = client.zrangebyscore(WORKERS_KEY, redis_now(client) - max_age, "+inf")  # type: ignore[assignment]
    return sum(1 for m in members if queue in json.loads(m).get("queues", []))
