"""The rules the fault tests rely on, in-process on a SQLite file: chain tokens, the claim a stage makes when
it starts, the reaper's compare-and-set, and what a user reads about a crash."""

from __future__ import annotations

import socket
import subprocess
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from celery.exceptions import SoftTimeLimitExceeded

from api.reaper import Reaper
from core.db import Database, Job, utcnow
from core.kinds import JobStatus
from core.settings import Settings
from workers import liveness
from workers.tasks import _failure_message, public_message

CLAIM = {"progress": 0.0, "max_deliveries": 3, "stale_seconds": 60.0}


@pytest.fixture
def db(tmp_path: Path) -> Database:
    return Database(f"sqlite:///{tmp_path / 'jobs.db'}")


def add_job(db: Database, **fields: Any) -> int:
    with db.session() as s:
        job = Job(kind="mosaic", **fields)
        s.add(job)
        s.flush()
        return job.id


def record(db: Database, job_id: int) -> Job:
    with db.session() as s:
        job = s.get(Job, job_id)
        assert job is not None
        return job


def test_tokens_sort_in_the_order_they_are_made_even_after_a_clock_from_the_future() -> None:
    future = f"g{(2**63):016x}00000000"
    assert liveness.new_token(after=future) > future
    first = liveness.new_token()
    assert liveness.is_token(first) and liveness.new_token(after=first) > first
    assert first > "ffffffff-celery-id-of-an-earlier-version"
    assert liveness.accepts(first, "") and liveness.accepts(first, first)
    assert not liveness.accepts(first, liveness.new_token(after=first))  # an older chain stops
    assert liveness.accepts(None, "recorded-1") and not liveness.accepts(None, first)


def test_a_stage_counts_its_starts_and_the_one_too_many_fails_the_job(db: Database) -> None:
    token = liveness.new_token()
    job_id = add_job(db, celery_id=token)
    for start in (1, 2, 3):  # each start's process died: nothing reset the count
        assert liveness.claim_stage(db, job_id, "detect_features", token, **CLAIM) == JobStatus.running
        assert record(db, job_id).deliveries == start
    assert liveness.claim_stage(db, job_id, "detect_features", token, **CLAIM) == JobStatus.failed
    job = record(db, job_id)
    assert job.error == liveness.gave_up_message("detect_features", 3) and job.deliveries == 0
    assert liveness.claim_stage(db, job_id, "detect_features", token, **CLAIM) == JobStatus.failed


def test_a_stage_that_ends_resets_the_count(db: Database) -> None:
    job_id = add_job(db)
    assert liveness.claim_stage(db, job_id, "load_images", None, **CLAIM) == JobStatus.running
    with liveness.Heartbeat(db, job_id, interval=0.05):
        pass
    job = record(db, job_id)
    assert (job.deliveries, job.heartbeat_at, job.heartbeat_by) == (0, None, "")


def test_an_older_chain_is_refused_and_a_newer_one_takes_over(db: Database) -> None:
    old = liveness.new_token()
    new = liveness.new_token(after=old)
    job_id = add_job(db, celery_id=new)
    assert liveness.claim_stage(db, job_id, "load_images", old, **CLAIM) == liveness.SUPERSEDED
    newest = liveness.new_token(after=new)  # sent, but not yet recorded by the API
    assert liveness.claim_stage(db, job_id, "load_images", newest, **CLAIM) == JobStatus.running
    assert record(db, job_id).celery_id == newest


def test_a_duplicate_delivery_never_runs_beside_a_live_holder(db: Database) -> None:
    token = liveness.new_token()
    fresh = {"celery_id": token, "status": JobStatus.running, "stage": "match_features", "deliveries": 1}
    elsewhere = add_job(db, **fresh, heartbeat_at=utcnow(), heartbeat_by="another-host:4242")
    assert liveness.claim_stage(db, elsewhere, "match_features", token, **CLAIM) == liveness.BUSY
    gone = subprocess.run(["sh", "-c", "echo $$"], capture_output=True, text=True, check=True).stdout.strip()
    died_here = add_job(db, **fresh, heartbeat_at=utcnow(), heartbeat_by=f"{socket.gethostname()}:{gone}")
    assert liveness.claim_stage(db, died_here, "match_features", token, **CLAIM) == JobStatus.running
    assert record(db, died_here).deliveries == 2  # Celery's redelivery after a lost pool process counts


class RecordingSender:
    def __init__(self) -> None:
        self.sent: list[tuple[int, str, str, str]] = []

    def send(self, job_id: int, pipeline: str, token: str, from_stage: str = "") -> None:
        self.sent.append((job_id, pipeline, token, from_stage))


def test_two_reapers_racing_send_a_dead_job_once(db: Database, tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, stale_seconds=5, max_deliveries=3)
    stale = utcnow() - timedelta(seconds=30)
    token = liveness.new_token()
    job_id = add_job(
        db, celery_id=token, status=JobStatus.running, stage="match_features", deliveries=1, heartbeat_at=stale
    )
    seen = record(db, job_id)
    sender = RecordingSender()
    reapers = [Reaper(db, sender, settings) for _ in range(2)]  # type: ignore[arg-type]
    cutoff = utcnow() - timedelta(seconds=5)
    actions = [r._revive(seen, cutoff, dead=True) for r in reapers]
    assert actions[0].startswith("sent again from match_features") and actions[1] == ""
    assert len(sender.sent) == 1 and sender.sent[0][3] == "match_features"
    job = record(db, job_id)
    assert job.celery_id == sender.sent[0][2] > token and job.heartbeat_at is None


def test_the_reaper_fails_a_stage_that_died_too_often(db: Database, tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, stale_seconds=5, max_deliveries=3)
    stale = utcnow() - timedelta(seconds=30)
    job_id = add_job(db, status=JobStatus.running, stage="compose_mosaic", deliveries=3, heartbeat_at=stale)
    sender = RecordingSender()
    action = Reaper(db, sender, settings)._revive(record(db, job_id), utcnow(), dead=True)  # type: ignore[arg-type]
    assert action.startswith("failed") and sender.sent == []
    assert record(db, job_id).error == liveness.gave_up_message("compose_mosaic", 3)


def test_errors_keep_file_names_but_never_server_paths() -> None:
    message = "/srv/fotoskhema/data/jobs/7/photos/IMG_0042.JPG: the photo could not be decoded"
    assert public_message(message) == "IMG_0042.JPG: the photo could not be decoded"
    assert public_message("frame 4/12 and ratio 0.8/1") == "frame 4/12 and ratio 0.8/1"


@pytest.mark.parametrize(
    ("exc", "says"),
    [
        (OSError(2, "No such file or directory", "/srv/data/jobs/7/features/a.npz"), "internal error (reference "),
        (MemoryError(), "ran out of memory"),
        (SoftTimeLimitExceeded(), "longer than the limit of 24 h"),
    ],
)
def test_a_crash_is_told_without_paths_hosts_or_library_names(exc: Exception, says: str) -> None:
    message = _failure_message(7, "match_features", exc)
    assert message.startswith("match_features: ") and says in message
    for leak in ("/srv", "OSError", "Errno", "celery", "Soft", socket.gethostname()):
        assert leak not in message
