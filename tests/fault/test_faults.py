"""Faults on a live stack (real Redis, real Celery workers, real uvicorn): each job still ends, succeeded or
failed with a message, within a bounded time, and nothing is lost.

Thresholds are those of ``conftest.LIVENESS_ENV``: a heartbeat every 0.5 s, a stage silent for 3 s is dead.
"""

from __future__ import annotations

import time

import pytest

from tests.fault.conftest import MAX_DELIVERIES, STALE_S, FaultStack, pid_alive, wait_for

pytestmark = pytest.mark.e2e  # real processes, as the end-to-end tests

STAGE = "detect_features"  # the second mosaic stage: one stage done before it, five after


def test_worker_killed_mid_stage_is_replaced_and_the_job_succeeds(stack: FaultStack) -> None:
    (stack.faults / f"hold-{STAGE}").touch()
    job_id = stack.new_job()
    wait_for(stack.held(job_id, STAGE).exists, 60, f"{STAGE} of job {job_id} running")
    orphans = stack.kill_worker()
    wait_for(lambda: not any(pid_alive(p) for p in orphans), 10, "the pool process ended with its parent")
    (stack.faults / f"hold-{STAGE}").unlink()
    killed = time.monotonic()
    stack.start_worker()
    job = stack.wait_for_end(job_id, 60)
    assert job["status"] == "succeeded", job["error"]
    assert time.monotonic() - killed < 60
    assert f"reaper: job {job_id} sent again from {STAGE} (worker died)" in stack.api_log()
    assert stack.starts(job_id, "load_images") == 1, "a finished stage is not run again"
    assert stack.starts(job_id, STAGE) == 2


def test_a_stage_that_kills_its_process_every_time_fails_the_job_after_n_starts(stack: FaultStack) -> None:
    (stack.faults / f"crash-{STAGE}").touch()
    started = time.monotonic()
    job = stack.wait_for_end(stack.new_job(), 60 + MAX_DELIVERIES * 2 * STALE_S)
    assert job["status"] == "failed"
    assert job["error"].startswith(f"{STAGE}: the worker process running this stage stopped {MAX_DELIVERIES} times")
    assert stack.starts(job["id"], STAGE) == MAX_DELIVERIES  # then no more: neither Celery nor the reaper
    assert stack.worker is not None and stack.worker.poll() is None  # the worker lives on: only its pool died
    print(f"failed after {time.monotonic() - started:.1f} s")


def test_a_stage_message_queued_survives_a_redis_restart(stack: FaultStack) -> None:
    stack.stop_worker()  # nobody takes the message: it waits in Redis
    job_id = stack.new_job()
    token = wait_for(lambda: stack.record(job_id).celery_id, 10, "the chain recorded")
    assert token in stack.queued_chains()
    stack.kill_redis()
    stack.start_redis()
    assert token in stack.queued_chains(), "Redis lost a message it had accepted"
    stack.start_worker()
    job = stack.wait_for_end(job_id, 60)
    assert job["status"] == "succeeded", job["error"]
    assert f"reaper: job {job_id} " not in stack.api_log()  # it ran from the message Redis kept
    assert all(stack.starts(job_id, stage) == 1 for stage in job["stages"])


def test_redis_down_across_a_stage_boundary_and_the_job_still_ends(stack: FaultStack) -> None:
    whole = "align_frames"  # a stage done whole in one task: the next stage is sent as it ends
    (stack.faults / f"hold-{whole}").touch()
    job_id = stack.new_job()
    wait_for(stack.held(job_id, whole).exists, 60, f"{whole} of job {job_id} running")
    stack.kill_redis()
    (stack.faults / f"hold-{whole}").unlink()  # the stage ends while Redis is down: its next cannot be sent
    wait_for(lambda: whole in stack.job(job_id)["timings"], 30, f"{whole} finished")
    wait_for(lambda: stack.waiting_for(job_id) > STALE_S, 30, "the job waiting for its next stage for a while")
    stack.start_redis()
    job = stack.wait_for_end(job_id, 60)
    assert job["status"] == "succeeded", job["error"]
    assert stack.starts(job_id, "georeference") == 1


def test_redis_down_between_a_plan_and_its_parts_and_the_job_still_ends(stack: FaultStack) -> None:
    """The plan of a stage in parts ends while Redis is down: its parts cannot be sent; the reaper sends the job
    again from that stage once Redis is back, and the plan runs again."""
    (stack.faults / f"hold-{STAGE}").touch()
    job_id = stack.new_job()
    wait_for(stack.held(job_id, STAGE).exists, 60, f"{STAGE} of job {job_id} planning")
    stack.kill_redis()
    (stack.faults / f"hold-{STAGE}").unlink()
    wait_for(lambda: stack.waiting_for(job_id) > STALE_S, 30, "the job waiting for its parts for a while")
    stack.start_redis()
    job = stack.wait_for_end(job_id, 60)
    assert job["status"] == "succeeded", job["error"]
    assert stack.starts(job_id, STAGE) == 2 and stack.starts(job_id, "load_images") == 1


def test_health_says_503_while_the_worker_or_redis_is_down(stack: FaultStack) -> None:
    def health() -> tuple[int, dict]:
        with stack.client() as http:
            started = time.monotonic()
            response = http.get("/api/health", headers={"Authorization": ""})
            assert time.monotonic() - started < 1.0, "the health check answers within a second"
            return response.status_code, response.json()

    assert health() == (200, {"status": "ok", "database": "ok", "broker": "ok", "worker": "ok"})
    stack.kill_worker()
    code, body = wait_for(lambda: (h := health())[0] == 503 and h, 10, "503 once the worker died")
    assert body == {"status": "unavailable", "database": "ok", "broker": "ok", "worker": "down"}
    stack.start_worker()
    assert health()[0] == 200
    stack.kill_redis()
    code, body = health()
    assert code == 503 and body["broker"] == "down" and body["status"] == "unavailable"
    stack.start_redis()
    wait_for(lambda: health()[0] == 200, 10, "200 once Redis is back")
