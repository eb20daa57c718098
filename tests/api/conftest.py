"""Fixtures of the API tests: the real pipeline's outputs of a small flight, for routes that serve a finished
job's files (STAC, WMTS, all.zip, NodeODM)."""

from __future__ import annotations

import shutil

import pytest
from fastapi.testclient import TestClient

from core.db import Database, Job
from core.kinds import JobStatus
from tests.scenes import make_flight
from workers.pipeline import process_directory
from workers.workspace import job_workspace


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Three synthetic frames with GPS through the whole pipeline, in-process: the photos and the job folder."""
    root = tmp_path_factory.mktemp("processed")
    flight = make_flight(root / "frames", n_frames=3, frame_size=(320, 240), seed=1)
    process_directory(root / "frames", root / "job", {"working_max_px": 320})
    return {"frames": flight.paths, "job": root / "job"}


def finished_job(client: TestClient, api_settings, processed: dict) -> int:
    """A succeeded mosaic job of the client's user whose folder holds the processed outputs."""
    from tests.api.test_jobs import flight_with

    job = client.post("/api/jobs", json={"flight_id": flight_with(client, processed["frames"])}).json()
    ws = job_workspace(api_settings.data_dir, job["id"])
    shutil.copytree(processed["job"], ws.root, dirs_exist_ok=True, ignore=shutil.ignore_patterns("config.json"))
    with Database(api_settings.resolved_database_url()).session() as s:
        s.get(Job, job["id"]).status = JobStatus.succeeded
    return int(job["id"])
