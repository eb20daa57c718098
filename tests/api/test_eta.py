"""A job's time left through the API: the worker records what each stage counted and how long it took, and
``GET /api/jobs/{id}`` and its event stream answer an estimate from this job's rates and the service's
earlier jobs of the same pipeline."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.eta_service import forget_history, history, job_size
from core.db import Database, Job
from core.eta import DEFAULT_RATES, UnitCount, estimate, seconds_per_unit, similar_jobs
from core.kinds import JobStatus
from tests.api.test_jobs import flight_with
from tests.scenes import make_flight
from workers.pipeline import PIPELINES
from workers.tasks import execute_stage


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=3, frame_size=(320, 240), seed=6).paths


@pytest.fixture(autouse=True)
def fresh_history() -> None:
    forget_history()


def record(api_settings, job_id: int) -> Job:
    with Database(api_settings.resolved_database_url()).session() as s:
        job = s.get(Job, job_id)
        s.expunge(job)
        return job


def test_the_worker_records_the_work_and_the_api_estimates_from_it(
    client: TestClient, api_settings, frames: list[Path]
) -> None:
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames), "options": {"working_max_px": 320}})
    job = job.json()
    assert job["eta"] is None and record(api_settings, job["id"]).work == {
        "frames": 3,
        "megapixels": 0.23,
        "photo_megapixels": 0.23,
    }
    queued = client.get(f"/api/jobs/{job['id']}").json()["eta"]  # no history yet: the reference machine's rates
    assert queued is not None and {s["basis"] for s in queued["stages"].values()} == {"defaults"}
    db = Database(api_settings.resolved_database_url())
    execute_stage(job["id"], "load_images", db=db, data_dir=api_settings.data_dir)
    work = record(api_settings, job["id"]).work
    assert work["stages"]["load_images"]["unit"] == "frame" and work["stages"]["load_images"]["count"] == 3
    assert "current" not in work
    eta = client.get(f"/api/jobs/{job['id']}").json()["eta"]
    assert eta is not None and eta["seconds_left"] > 0
    assert eta["stages"]["load_images"]["basis"] == "done" and eta["stages"]["compose_mosaic"]["basis"] == "defaults"
    for stage in job["stages"][1:]:
        execute_stage(job["id"], stage, db=db, data_dir=api_settings.data_dir)
    done = client.get(f"/api/jobs/{job['id']}").json()
    assert done["status"] == "succeeded" and done["eta"] is None
    assert record(api_settings, job["id"]).work["stages"]["match_features"]["unit"] == "pair"

    # the next job of the pipeline starts from the rates this one measured, per input frame or megapixel (with
    # one job to go by, halfway to the reference machine's)
    forget_history()
    second = client.post(
        "/api/jobs", json={"flight_id": flight_with(client, frames), "options": {"working_max_px": 320}}
    )
    eta = client.get(f"/api/jobs/{second.json()['id']}").json()["eta"]
    size = job_size(record(api_settings, second.json()["id"]).work)
    first = job_size(record(api_settings, job["id"]).work)
    assert first["pairs"] == record(api_settings, job["id"]).work["stages"]["match_features"]["count"]
    assert "pairs" not in size  # not matched yet: its pairs are guessed from its photos
    rates = seconds_per_unit([(first, done["timings"])], DEFAULT_RATES["mosaic"])
    defaults = DEFAULT_RATES["mosaic"]
    assert rates["compose_mosaic"] == pytest.approx(
        (done["timings"]["compose_mosaic"] / size["megapixels"] + defaults["compose_mosaic"]) / 2
    )
    expected = estimate([(s.name, s.weight) for s in PIPELINES["mosaic"]], size, {}, None, 0.0, 0.0, rates)
    assert expected is not None and eta["seconds_left"] == pytest.approx(expected.seconds_left, abs=0.1)
    assert {s["basis"] for s in eta["stages"].values()} == {"history"}


def test_a_running_stage_goes_at_its_measured_rate(client: TestClient, api_settings, frames: list[Path]) -> None:
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)}).json()
    with Database(api_settings.resolved_database_url()).session() as s:
        row = s.get(Job, job["id"])
        row.status, row.stage, row.timings = (
            JobStatus.running,
            "match_features",
            {"load_images": 4.0, "detect_features": 8.0},
        )
        started = time.time() - 10.0
        row.work = {
            "frames": 3,
            "current": {
                "stage": "match_features",
                "started_at": started,
                "fraction": 0.5,
                "unit": "pair",
                "done": 5,
                "total": 10,
            },
        }
    asked = time.time()
    eta = client.get(f"/api/jobs/{job['id']}").json()["eta"]
    answered = time.time()
    match = eta["stages"]["match_features"]

    # the API's wiring of core.eta (whose arithmetic tests/unit/test_eta.py checks): this job's record, the
    # pipeline's default rates and the service's history of similar jobs (the earlier tests' finished job), the
    # stage's seconds as the API read its clock
    db = Database(api_settings.resolved_database_url())
    size = job_size(record(api_settings, job["id"]).work)

    def expected(at: float) -> Any:
        similar = similar_jobs(history(db, "mosaic", "mosaic", at), size)
        eta = estimate(
            [(spec.name, spec.weight) for spec in PIPELINES["mosaic"]],
            size,
            {"load_images": 4.0, "detect_features": 8.0},
            "match_features",
            0.5,
            at - started,
            seconds_per_unit(similar, DEFAULT_RATES["mosaic"]),
            UnitCount("pair", 5, 10),
            DEFAULT_RATES["mosaic"],
        )
        assert eta is not None
        return eta

    early, late = expected(asked), expected(answered)
    assert 5.0 < early.stages["match_features"].seconds_left < 10.0
    assert match["basis"] == "measured"
    for got, bounds in (
        (match["seconds_left"], [e.stages["match_features"].seconds_left for e in (early, late)]),
        (eta["seconds_left"], [e.seconds_left for e in (early, late)]),
    ):
        assert min(bounds) - 0.1 <= got <= max(bounds) + 0.1, (got, bounds)  # 0.1: the API rounds to 0.1 s
    assert match["unit"] == "pair" and match["units_per_second"] == pytest.approx(0.5, rel=0.05)
    assert eta["stage_seconds_left"] == match["seconds_left"] and eta["seconds_left"] > match["seconds_left"]

    with client.stream("GET", f"/api/jobs/{job['id']}/events") as stream:  # the same in the event stream
        data = next(line for line in stream.iter_lines() if line.startswith("data: "))
    assert json.loads(data.removeprefix("data: "))["eta"]["stages"]["match_features"]["unit"] == "pair"
