"""Job lifecycle through the API with a recording queue, and the worker's record keeping in-process."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.job_service import form_options
from core.db import Database, Job
from core.kinds import JobStatus
from tests.conftest import RecordingQueue
from tests.scenes import make_flight
from workers.pipeline import stage_names
from workers.tasks import execute_stage
from workers.workspace import REPORT_FIGURES, job_workspace


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=3, frame_size=(400, 300), seed=6).paths


def flight_with(client: TestClient, paths: list[Path]) -> int:
    flight_id = int(client.post("/api/flights", json={"name": "f"}).json()["id"])
    if paths:
        files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]
        assert client.post(f"/api/flights/{flight_id}/images", files=files).status_code == 201
    return flight_id


def test_job_is_recorded_written_and_enqueued(
    client: TestClient, api_settings, recording_queue: RecordingQueue, frames: list[Path]
) -> None:
    flight_id = flight_with(client, frames)
    response = client.post(
        "/api/jobs", json={"flight_id": flight_id, "kind": "mosaic", "options": {"working_max_px": 512}}
    )
    assert response.status_code == 202
    job = response.json()
    assert job["status"] == "queued" and job["stages"] == stage_names("mosaic")
    assert recording_queue.sent == [(job["id"], "mosaic")]
    workspace = api_settings.data_dir / "jobs" / str(job["id"])
    assert (workspace / "config.json").exists() and (workspace / "inputs.json").exists()
    assert client.get(f"/api/jobs/{job['id']}").json()["options"] == {"working_max_px": 512}
    assert [j["id"] for j in client.get(f"/api/jobs?flight_id={flight_id}").json()] == [job["id"]]
    assert client.get(f"/api/jobs/{job['id']}/outputs").json() == {"outputs": [], "all_zip_url": None}
    assert client.get(f"/tiles/{job['id']}/tilejson.json").status_code == 409


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"ratio_test": "high"}, "options.ratio_test"),
        ({"working_max_px": 10}, "options.working_max_px"),
        ({"no_such_option": 1}, "options.no_such_option"),
    ],
)
def test_invalid_options_are_422_and_nothing_is_queued(
    client: TestClient, recording_queue: RecordingQueue, frames: list[Path], options: dict, fragment: str
) -> None:
    response = client.post("/api/jobs", json={"flight_id": flight_with(client, frames), "options": options})
    assert response.status_code == 422 and fragment in response.json()["detail"]
    assert recording_queue.sent == []


def test_job_needs_a_known_flight_with_two_images(client: TestClient, frames: list[Path]) -> None:
    assert client.post("/api/jobs", json={"flight_id": 404}).status_code == 404
    response = client.post("/api/jobs", json={"flight_id": flight_with(client, frames[:1])})
    assert response.status_code == 422 and "at least 2" in response.json()["detail"]
    assert client.post("/api/jobs", json={"flight_id": 1, "kind": "panorama"}).status_code == 422
    assert client.post("/api/jobs", json={"flight_id": "one"}).status_code == 422


def test_unknown_job_ids_are_404(client: TestClient) -> None:
    for path in (
        "/api/jobs/77",
        "/api/jobs/77/outputs",
        "/api/jobs/77/events",
        "/tiles/77/tilejson.json",
        "/tiles/77/1/0/0.png",
        "/api/jobs/77/outputs/mosaic.tif",
    ):
        response = client.get(path)
        assert response.status_code == 404, path
        assert "job 77 not found" in response.json()["detail"]
    assert client.post("/api/jobs/77/cancel").status_code == 404


def test_queue_down_is_503_and_the_job_is_marked_failed(
    client: TestClient, recording_queue: RecordingQueue, frames: list[Path]
) -> None:
    recording_queue.fail = True
    response = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)})
    assert response.status_code == 503
    job = client.get("/api/jobs").json()[0]
    assert job["status"] == "failed" and "job queue" in job["error"]


def test_cancel_then_cancel_again(client: TestClient, frames: list[Path]) -> None:
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)}).json()
    cancelled = client.post(f"/api/jobs/{job['id']}/cancel")
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    assert client.post(f"/api/jobs/{job['id']}/cancel").status_code == 409


def test_retry_resumes_from_the_stage_that_stopped(
    client: TestClient, api_settings, frames: list[Path], recording_queue: RecordingQueue
) -> None:
    job = client.post(
        "/api/jobs", json={"flight_id": flight_with(client, frames), "options": {"working_max_px": 400}}
    ).json()
    assert client.post(f"/api/jobs/{job['id']}/retry").status_code == 409  # still queued
    db = Database(api_settings.resolved_database_url())
    execute_stage(job["id"], "load_images", db=db, data_dir=api_settings.data_dir)
    client.post(f"/api/jobs/{job['id']}/cancel")
    frames_json = api_settings.data_dir / "jobs" / str(job["id"]) / "frames.json"
    written = frames_json.stat().st_mtime_ns
    retried = client.post(f"/api/jobs/{job['id']}/retry")
    assert retried.status_code == 202 and retried.json()["status"] == "queued"
    assert recording_queue.sent == [(job["id"], "mosaic"), (job["id"], "mosaic")]
    for stage in job["stages"]:
        status = execute_stage(job["id"], stage, db=db, data_dir=api_settings.data_dir)
    assert status == "succeeded" and frames_json.stat().st_mtime_ns == written  # load_images was not redone
    assert client.post(f"/api/jobs/{job['id']}/retry").status_code == 409  # succeeded jobs stay as they are
    assert client.post("/api/jobs/999/retry").status_code == 404


def test_worker_runs_every_stage_and_keeps_the_record(client: TestClient, api_settings, frames: list[Path]) -> None:
    """The Celery tasks' body, in-process: the record advances stage by stage and ends succeeded."""
    job = client.post(
        "/api/jobs", json={"flight_id": flight_with(client, frames), "options": {"working_max_px": 400}}
    ).json()
    db = Database(api_settings.resolved_database_url())
    progress = []
    for stage in job["stages"]:
        status = execute_stage(job["id"], stage, db=db, data_dir=api_settings.data_dir)
        record = client.get(f"/api/jobs/{job['id']}").json()
        progress.append(record["progress"])
        assert record["stage"] == stage and stage in record["timings"]
    assert status == "succeeded" and progress == sorted(progress) and progress[-1] == 100
    names = {o["name"] for o in client.get(f"/api/jobs/{job['id']}/outputs").json()["outputs"]}
    assert names == {
        "mosaic.tif",
        "frame_index.tif",
        "report.json",
        "footprints.geojson",
        "report.html",
        *REPORT_FIGURES,
    }
    cog = client.get(f"/api/jobs/{job['id']}/outputs/mosaic.tif")
    assert cog.status_code == 200 and cog.content[:4] in (b"II*\x00", b"II+\x00")
    assert client.get(f"/api/jobs/{job['id']}/outputs/config.json").status_code == 404  # only named outputs
    tilejson = client.get(f"/tiles/{job['id']}/tilejson.json").json()
    template, _, signature = tilejson["tiles"][0].partition("?")
    assert tilejson["georeferenced"] and template.endswith(f"/tiles/{job['id']}/{{z}}/{{x}}/{{y}}.png")
    assert "sig=" in signature


def test_worker_skips_a_cancelled_job(client: TestClient, api_settings, frames: list[Path]) -> None:
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)}).json()
    db = Database(api_settings.resolved_database_url())
    assert execute_stage(job["id"], "load_images", db=db, data_dir=api_settings.data_dir) == "running"
    client.post(f"/api/jobs/{job['id']}/cancel")
    assert execute_stage(job["id"], "detect_features", db=db, data_dir=api_settings.data_dir) == "cancelled"
    record = client.get(f"/api/jobs/{job['id']}").json()
    assert record["status"] == "cancelled" and "detect_features" not in record["timings"]
    assert not (api_settings.data_dir / "jobs" / str(job["id"]) / "features").exists()


def test_worker_records_a_pipeline_error(client: TestClient, api_settings, frames: list[Path], tmp_path: Path) -> None:
    """Two frames that do not overlap: the job fails with a message a user can act on."""
    far_apart = make_flight(tmp_path, n_frames=2, frame_size=(400, 300), overlap=0.0, seed=8).paths
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, far_apart)}).json()
    db = Database(api_settings.resolved_database_url())
    with pytest.raises(Exception, match="no two frames overlap"):
        for stage in job["stages"]:
            execute_stage(job["id"], stage, db=db, data_dir=api_settings.data_dir)
    record = client.get(f"/api/jobs/{job['id']}").json()
    assert record["status"] == "failed" and record["error"].startswith("align_frames: no two frames overlap")


def test_docs_render_offline(client: TestClient) -> None:
    html = client.get("/docs").text
    assert "/vendor/swagger-ui/swagger-ui-bundle.js" in html and "cdn" not in html.lower()
    assert client.get("/vendor/swagger-ui/swagger-ui-bundle.js").status_code == 200
    assert client.get("/vendor/leaflet/leaflet.js").status_code == 200
    schema = client.get("/openapi.json").json()
    assert schema["info"]["title"] == "Fotoskhema"
    # every kind's options are in the schema, though a route takes them as a free object
    options = schema["components"]["schemas"]
    assert {
        "MosaicConfig",
        "CalibrationConfig",
        "StereoCalibrationConfig",
        "CrackSurveyConfig",
        "StereoDemConfig",
    } <= set(options)
    working = options["MosaicConfig"]["properties"]["working_max_px"]
    assert (working["default"], working["minimum"], working["maximum"]) == (2048, 256, 20000)
    assert "square_mm" in options["CalibrationConfig"]["properties"]
    assert "MosaicConfig" in options["JobCreate"]["properties"]["options"]["description"]
    assert client.get("/api/health").json()["status"] == "ok"
    settings = client.app.state.settings  # type: ignore[attr-defined]
    config = client.get("/api/config").json()
    assert config.pop("mosaic_options") == form_options()
    assert config == {
        "basemap_url": "https://tile.openstreetmap.org/{z}/{x}/{y}.png",  # OpenStreetMap unless ops set none
        "basemap_name": "OpenStreetMap",
        "public_read": False,
        "max_upload_bytes": settings.max_upload_bytes,  # the viewer splits uploads by these
        "max_request_bytes": settings.max_request_bytes,
        "max_files_per_request": settings.max_files_per_request,
        "resumable_upload_bytes": settings.resumable_upload_bytes,  # and sends larger files by tus
        "resumable_chunk_bytes": settings.resumable_chunk_bytes,
        "import_dirs": 0,
    }
    assert client.get("/vendor/tus/tus.min.js").status_code == 200  # the viewer's tus client, vendored
    assert client.get("/vendor/geodesic/geographiclib-geodesic.min.js").status_code == 200  # the map's tools
    assert client.get("/vendor/proj4/proj4.js").status_code == 200


@pytest.mark.parametrize(
    ("setting", "url", "name"),
    [
        ("none", "", ""),
        ("", "", ""),
        ("https://tiles.example.org/{z}/{x}/{y}.png", "https://tiles.example.org/{z}/{x}/{y}.png", "tiles.example.org"),
    ],
)
def test_ops_choose_the_basemap_or_none(client: TestClient, setting: str, url: str, name: str) -> None:
    client.app.state.settings.basemap_url = setting  # type: ignore[attr-defined]
    config = client.get("/api/config").json()
    assert (config["basemap_url"], config["basemap_name"]) == (url, name)


def test_the_form_options_are_the_config_models_defaults(client: TestClient) -> None:
    options = {o["name"]: o for o in client.get("/api/config").json()["mosaic_options"]}
    assert set(options) == {"output_resolution", "working_max_px", "feature_type", "blend"}
    assert options["feature_type"]["default"] == {"planar": "orb", "ortho": "sift"}  # by mode, as jobs get them
    assert options["working_max_px"] == {
        "name": "working_max_px",
        "default": {"planar": 2048, "ortho": 2048},
        "minimum": 256,
        "maximum": 20000,
    }
    assert options["blend"]["choices"] == ["feather", "multiband"]


def test_a_succeeded_job_carries_its_report_warnings(client: TestClient, api_settings, frames: list[Path]) -> None:
    """A client can refuse a result the report warns about without downloading the report."""
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames), "kind": "mosaic"}).json()
    ws = job_workspace(api_settings.data_dir, job["id"])
    warning = "1 of 3 frames could not be placed and are left out: b.jpg"
    ws.save_report({"kind": "mosaic", "warnings": [warning]})
    assert client.get(f"/api/jobs/{job['id']}").json()["warnings"] is None  # not finished: no verdict yet
    db = Database(api_settings.resolved_database_url())
    with db.session() as s:
        s.get(Job, job["id"]).status = JobStatus.succeeded
    assert client.get(f"/api/jobs/{job['id']}").json()["warnings"] == [warning]


def test_retry_waits_until_a_cancelled_stage_has_stopped(client: TestClient, api_settings, frames: list[Path]) -> None:
    from core.db import utcnow

    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)}).json()
    db = Database(api_settings.resolved_database_url())
    with db.session() as s:  # cancelled while its stage runs: the stage still beats until its next report
        record = s.get(Job, job["id"])
        record.status, record.stage, record.heartbeat_at, record.heartbeat_by = (
            "cancelled",
            "match_features",
            utcnow(),
            "w:1",
        )
    early = client.post(f"/api/jobs/{job['id']}/retry")
    assert early.status_code == 409 and "still stopping" in early.json()["detail"]
    with db.session() as s:  # the stage stopped: its heartbeat is cleared
        s.get(Job, job["id"]).heartbeat_at = None
    assert client.post(f"/api/jobs/{job['id']}/retry").status_code == 202


def test_the_event_stream_of_a_job_deleted_while_followed_ends_cleanly(client: TestClient, frames: list[Path]) -> None:
    """A job deleted while its events are followed (the viewer's delete button on a running job): the stream says
    ``deleted`` and ends, rather than breaking off (an error in the browser, and EventSource reconnects)."""
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames)}).json()  # queued: never ends
    with client.stream("GET", f"/api/jobs/{job['id']}/events") as stream:
        lines = stream.iter_lines()
        assert next(lines) == "event: progress"
        assert client.delete(f"/api/jobs/{job['id']}").status_code == 204
        rest = list(lines)  # to the stream's end, which comes
    events = [line for line in rest if line.startswith("event: ")]
    assert events[-1] == "event: deleted" and f'data: {{"id": {job["id"]}}}' in rest
    assert client.get(f"/api/jobs/{job['id']}/events").status_code == 404
