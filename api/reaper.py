"""The reaper: a thread of each API process that sends again the jobs nothing is running any more.

Every ``Settings.reaper_seconds`` (and once at start, which re-publishes what a restart lost) it looks at the
jobs ``queued`` or ``running``:

- **a stage whose heartbeat is stale** (older than ``stale_seconds``): its process died (kill -9, out of
  memory, the machine went away). The job is sent again from that stage, under a new chain token; the
  stages before it are skipped for their outputs. After ``max_deliveries`` starts that died, it fails.
- **a job waiting for its next stage** (no heartbeat) for longer than ``stale_seconds`` whose chain has no
  message in the queue: the message was lost (Redis restarted without it, Redis was down when the last
  stage ended and tried to send the next, or the worker holding it died). It is sent again from its stage.

Each change is a compare-and-set on what the pass read, so several API processes reaping at once send a job
once; a Redis lock also keeps all but one of them from doing the pass at all. A pass needs Redis (it cannot
send anything without it) and does nothing while Redis is down.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import timedelta
from typing import Any

import redis
from fastapi import FastAPI
from sqlalchemy import select, update
from sqlalchemy.exc import SQLAlchemyError

from api.queue import CeleryQueue
from api.resumable import UploadSweeper
from core.db import Database, Job, utcnow
from core.kinds import JobStatus
from core.settings import Settings
from workers.liveness import gave_up_message, new_token
from workers.pipeline import pipeline_key

log = logging.getLogger(__name__)

LOCK_KEY = "fotoskhema:reaper"


class Reaper:
    def __init__(self, db: Database, queue: CeleryQueue, settings: Settings) -> None:
        self.db, self.queue, self.settings = db, queue, settings
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="reaper", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        away = ""  # what kept the last pass from running, said once per outage
        while True:
            try:
                self.run_once()
                if away:
                    log.warning("reaper: passes run again")
                away = ""
            except (redis.RedisError, SQLAlchemyError, OSError) as exc:  # away for now: the next pass tries again
                if not away:
                    log.warning("reaper: passes skipped while Redis or the database is unreachable (%s)", exc)
                away = type(exc).__name__
            except Exception:
                log.exception("reaper: pass failed")
            if self._stop.wait(self.settings.reaper_seconds):
                return

    def run_once(self) -> list[tuple[int, str]]:
        """One pass; returns ``(job id, what was done)`` for each job it sent again or failed."""
        ttl_ms = max(100, int(900 * self.settings.reaper_seconds))
        if not self.queue.redis().set(LOCK_KEY, "1", nx=True, px=ttl_ms):
            return []  # another API process is doing this pass
        cutoff = utcnow() - timedelta(seconds=self.settings.stale_seconds)
        with self.db.session() as s:
            jobs = list(s.scalars(select(Job).where(Job.status.in_([JobStatus.queued, JobStatus.running]))))
        dead = [j for j in jobs if j.heartbeat_at is not None and j.heartbeat_at < cutoff]
        waiting = [j for j in jobs if j.heartbeat_at is None and j.updated_at < cutoff]
        pending = self.queue.pending_tokens() if waiting else set()
        done = []
        for job in dead:
            done.append((job.id, self._revive(job, cutoff, dead=True)))
        for job in waiting:
            if job.celery_id not in pending:
                done.append((job.id, self._revive(job, cutoff, dead=False)))
        for job_id, action in done:
            if action:
                log.warning("reaper: job %s %s", job_id, action)
        return [(job_id, action) for job_id, action in done if action]

    def _revive(self, seen: Job, cutoff: Any, *, dead: bool) -> str:
        """Send ``seen`` again from its stage, or fail it when that stage has died too often; '' when the job
        changed since it was read (another process got there first, or it came back to life)."""
        unchanged = [Job.id == seen.id, Job.celery_id == seen.celery_id, Job.deliveries == seen.deliveries]
        unchanged += [Job.status.in_([JobStatus.queued, JobStatus.running])]
        unchanged += [Job.heartbeat_at < cutoff] if dead else [Job.heartbeat_at.is_(None), Job.updated_at < cutoff]
        idle = {"heartbeat_at": None, "heartbeat_by": ""}
        if dead and seen.deliveries >= self.settings.max_deliveries:
            failed = {**idle, "deliveries": 0, "status": JobStatus.failed}
            failed["error"] = gave_up_message(seen.stage, seen.deliveries)
            return "failed: its stage died too often" if self._change(unchanged, failed) else ""
        token = new_token(after=seen.celery_id)
        detail = "sent again: its worker stopped" if dead else "sent again: its next stage was lost"
        if not self._change(unchanged, {**idle, "celery_id": token, "progress_detail": detail}):
            return ""
        # Sent after the record names the new chain: a task of it always finds itself current. If sending
        # fails (Redis went away), the job waits with no message, and a later pass sends it.
        self.queue.send(seen.id, pipeline_key(seen.kind, seen.options), token, from_stage=seen.stage)
        return f"sent again from {seen.stage or 'the start'} ({'worker died' if dead else 'message lost'})"

    def _change(self, where: list[Any], values: dict[str, Any]) -> bool:
        with self.db.session() as s:
            result = s.execute(update(Job).where(*where).values(**values).execution_options(synchronize_session=False))
            return bool(result.rowcount == 1)  # type: ignore[attr-defined]


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """The API process's background work: the reaper, when jobs go to a real queue and it is not turned off, and
    the upload sweeper; at the end, folder imports stop and the tiler's open COGs are closed."""
    settings: Settings = app.state.settings
    reaper = None
    if isinstance(app.state.queue, CeleryQueue) and settings.reaper_seconds > 0:
        reaper = Reaper(app.state.db, app.state.queue, settings)
        reaper.start()
    sweeper = UploadSweeper(app.state.db, settings)  # unfinished resumable uploads that expired, and their bytes
    sweeper.start()
    try:
        yield
    finally:
        sweeper.stop()
        app.state.imports.stop()  # running folder imports stop after their current photo
        if reaper is not None:
            reaper.stop()
        app.state.tiler.close()  # the COGs it holds open
