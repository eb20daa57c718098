"""The NodeODM-compatible routes, against NodeODM's own API description (its docs/swagger.json, API 2.2.1):
the fields and types each answer must carry, requests shaped as PyODM (WebODM's client) sends them
(multipart ``task/new/init``, one photo per ``task/new/upload/{uuid}``, form-encoded ``task/cancel``), the
token in ``?token=``, and the owner checks every route of ours keeps.

What NodeODM's description requires (read from it, not copied):
- ``/info``: version, taskQueueCount, maxImages, engineVersion, engine (+ totalMemory, availableMemory,
  cpuCores, maxParallelTasks, integers);
- ``/options``: a list of {name, type in int/float/string/bool (and enum, as NodeODM's own list has), value
  (a string), domain, help};
- ``task/{uuid}/info`` (TaskInfo): uuid, name, dateCreated (ms), processingTime (ms, -1 before it runs),
  status.code in 10/20/30/40/50, options [{name, value}], imagesCount, progress (0-100), output when asked;
- ``task/new/init`` and ``task/new/commit/{uuid}``: {uuid}; ``upload``, ``cancel``, ``remove``: {success};
- errors: {error}.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from core.db import Database, Job
from core.kinds import JobStatus
from tests.conftest import RecordingQueue, user_headers
from workers.workspace import job_workspace

STATUS = {"QUEUED": 10, "RUNNING": 20, "FAILED": 30, "COMPLETED": 40, "CANCELED": 50}
TASK_INFO = {"uuid", "name", "dateCreated", "processingTime", "status", "options", "imagesCount", "progress"}
NODE_INFO = {"version", "taskQueueCount", "maxImages", "engineVersion", "engine"}


@pytest.fixture
def node(client: TestClient) -> tuple[TestClient, str]:
    """The app without its default header, and a user's token, as PyODM would use it."""
    token = user_headers(client, "webodm")["Authorization"].removeprefix("Bearer ")
    client.headers.pop("Authorization")
    return client, token


def new_task(client: TestClient, token: str, options: list[dict] | None = None, name: str = "park") -> str:
    fields = {"name": name, "options": json.dumps(options or [])}
    response = client.post(f"/task/new/init?token={token}", files={k: (None, v) for k, v in fields.items()})
    assert response.status_code == 200, response.text
    return str(response.json()["uuid"])


def upload_each(client: TestClient, token: str, uuid: str, paths: list[Path]) -> None:
    for path in paths:  # PyODM sends one file per request
        files = [("images", (path.name, path.read_bytes(), "image/jpeg"))]
        response = client.post(f"/task/new/upload/{uuid}?token={token}", files=files)
        assert response.status_code == 200 and response.json() == {"success": True}, response.text


def test_info_and_options_follow_nodeodms_description(node: tuple[TestClient, str]) -> None:
    client, token = node
    info = client.get(f"/info?token={token}").json()
    assert set(info) >= NODE_INFO and info["engine"] == "fotoskhema"
    assert tuple(int(p) for p in info["version"].split(".")) >= (1, 4, 0)  # PyODM's chunked uploads need 1.4.0
    for key in ("taskQueueCount", "totalMemory", "availableMemory", "cpuCores", "maxParallelTasks"):
        assert isinstance(info[key], int)
    options = client.get(f"/options?token={token}").json()
    assert options and all({"name", "type", "value", "domain", "help"} <= set(o) for o in options)
    assert all(o["type"] in ("int", "float", "string", "bool", "enum") and isinstance(o["value"], str) for o in options)
    by_name = {o["name"]: o for o in options}
    assert by_name["mode"]["type"] == "enum" and by_name["mode"]["domain"] == ["planar", "ortho", "strip"]
    assert by_name["working-max-px"] == {
        **by_name["working-max-px"],
        "type": "int",
        "value": "2048",
        "domain": "integer: 256 <= x <= 20000",
    }
    assert by_name["gain-compensation"]["value"] == "true"


def test_a_task_runs_as_a_mosaic_job_of_a_flight(
    node: tuple[TestClient, str],
    recording_queue: RecordingQueue,
    api_settings,
    processed: dict,
) -> None:
    client, token = node
    options = [{"name": "working-max-px", "value": "320"}, {"name": "dsm", "value": True}]
    uuid = new_task(client, token, options)
    upload_each(client, token, uuid, processed["frames"])
    upload_each(client, token, uuid, processed["frames"][:1])  # a retried upload: already there, still success
    before = client.get(f"/task/{uuid}/info?token={token}").json()
    assert set(before) >= TASK_INFO and before["status"]["code"] == STATUS["QUEUED"] and before["imagesCount"] == 3
    assert before["processingTime"] == -1 and before["options"] == [{"name": "working-max-px", "value": 320}]
    assert client.post(f"/task/new/commit/{uuid}?token={token}").json() == {"uuid": uuid}
    [(job_id, pipeline)] = recording_queue.sent
    job = client.get(f"/api/jobs/{job_id}", headers={"Authorization": f"Bearer {token}"}).json()
    assert pipeline == "mosaic" and job["options"] == {"working_max_px": 320}
    output = client.get(f"/task/{uuid}/output?token={token}").json()
    assert all(isinstance(line, str) for line in output) and any("dsm" in line for line in output)

    ws = job_workspace(api_settings.data_dir, job_id)  # the worker's part, from the pipeline's real outputs
    shutil.copytree(processed["job"], ws.root, dirs_exist_ok=True, ignore=shutil.ignore_patterns("config.json"))
    with Database(api_settings.resolved_database_url()).session() as s:
        record = s.get(Job, job_id)
        record.status, record.progress = JobStatus.succeeded, 100.0
        record.timings = {"load_images": 1.5, "compose_mosaic": 2.0}
    done = client.get(f"/task/{uuid}/info?token={token}&with_output=2").json()
    assert done["status"]["code"] == STATUS["COMPLETED"] and done["progress"] == 100
    assert (
        done["processingTime"] == 3500
        and done["output"] == client.get(f"/task/{uuid}/output?token={token}&line=2").json()
    )
    archive = client.get(f"/task/{uuid}/download/all.zip?token={token}")
    assert archive.status_code == 200 and archive.headers["content-type"] == "application/zip"
    names = zipfile.ZipFile(io.BytesIO(archive.content)).namelist()
    assert {"odm_orthophoto/odm_orthophoto.tif", "odm_report/report.json", "task_output.txt"} <= set(names)
    assert zipfile.ZipFile(io.BytesIO(archive.content)).read("odm_orthophoto/odm_orthophoto.tif") == (
        ws.mosaic_path().read_bytes()
    )
    assert client.get(f"/task/{uuid}/download/orthophoto.tif?token={token}").json()["error"] == "Invalid asset"
    assert client.post(f"/task/remove?token={token}", data={"uuid": uuid}).json() == {"success": True}
    gone = client.get(f"/task/{uuid}/info?token={token}")
    assert gone.status_code == 404 and "not found" in gone.json()["error"] and not ws.root.exists()


def test_cancel_stops_the_job(node: tuple[TestClient, str], processed: dict) -> None:
    client, token = node
    uuid = new_task(client, token)
    upload_each(client, token, uuid, processed["frames"][:2])
    refused = client.post(f"/task/cancel?token={token}", data={"uuid": uuid})  # nothing runs yet
    assert refused.status_code == 409 and "error" in refused.json()
    client.post(f"/task/new/commit/{uuid}?token={token}")
    assert client.post(f"/task/cancel?token={token}", json={"uuid": uuid}).json() == {"success": True}
    assert client.get(f"/task/{uuid}/info?token={token}").json()["status"]["code"] == STATUS["CANCELED"]
    late = client.post(f"/task/new/upload/{uuid}?token={token}", files=[("images", ("x.jpg", b"x", "image/jpeg"))])
    assert late.status_code == 409 and "committed" in late.json()["error"]
    missing = client.post(f"/task/cancel?token={token}", data={})
    assert missing.status_code == 422 and missing.json()["error"] == "uuid param missing."


def test_options_are_checked_as_nodeodm_checks_them(node: tuple[TestClient, str]) -> None:
    client, token = node
    for bad, word in (
        ([{"name": "working-max-px", "value": "huge"}], "working-max-px"),
        ([{"name": "working-max-px", "value": "10"}], "working_max_px"),
        ([{"name": "mode", "value": "lidar"}], "mode"),
        ([{"name": "mode", "value": "ortho"}, {"name": "output-resolution", "value": "native"}], "native"),
    ):
        fields = {"options": (None, json.dumps(bad))}
        response = client.post(f"/task/new/init?token={token}", files=fields)
        assert response.status_code == 422 and word in response.json()["error"], response.text
    not_json = client.post(f"/task/new/init?token={token}", files={"options": (None, "[{")})
    assert not_json.status_code == 422 and "options" in not_json.json()["error"]
    uuid = "0f6b5e3c-8f0a-4bf1-9c7e-2a3b4c5d6e7f"
    made = client.post(f"/task/new/init?token={token}", files={"name": (None, "x")}, headers={"set-uuid": uuid})
    assert made.json() == {"uuid": uuid}
    again = client.post(f"/task/new/init?token={token}", files={"name": (None, "x")}, headers={"set-uuid": uuid})
    assert again.status_code == 409 and "already exists" in again.json()["error"]


def test_tokens_in_the_query_and_owners(node: tuple[TestClient, str], processed: dict) -> None:
    client, token = node
    for method, path in (("GET", "/info"), ("GET", "/options"), ("POST", "/task/new/init"), ("GET", "/task/list")):
        refused = client.request(method, path)
        assert refused.status_code == 401 and "token" in refused.json()["error"]
        assert client.request(method, f"{path}?token=wrong").status_code == 401
    uuid = new_task(client, token)
    upload = client.post(
        f"/task/new/upload/{uuid}", files=[("images", ("a.jpg", processed["frames"][0].read_bytes(), "image/jpeg"))]
    )
    assert upload.status_code == 401  # refused before the body is read (BearerForWrites)
    bearer = client.get(f"/task/{uuid}/info", headers={"Authorization": f"Bearer {token}"})
    assert bearer.status_code == 200  # a header works too
    other = user_headers(client, "mallory")["Authorization"].removeprefix("Bearer ")
    assert client.get(f"/task/{uuid}/info?token={other}").status_code == 404
    assert client.post(f"/task/remove?token={other}", data={"uuid": uuid}).status_code == 404
    assert client.get(f"/task/list?token={other}").json() == []
    assert client.get(f"/task/list?token={token}").json() == [{"uuid": uuid}]
    # the query token opens the NodeODM routes only
    assert client.get(f"/api/flights?token={token}").status_code == 401


def test_side_files_become_the_flights_gps_and_gcps(
    node: tuple[TestClient, str], api_settings, processed: dict
) -> None:
    client, token = node
    uuid = new_task(client, token)
    names = [p.name for p in processed["frames"]]
    geo = "EPSG:4326\n" + "".join(f"{n} -95.37 29.76 60\n" for n in names)
    gcps = "WGS84 UTM 15N\n" + "".join(f"271000 3294500 10 100 120 {n} gcp1\n" for n in names[:2])
    files = [
        ("images", ("geo.txt", geo.encode(), "text/plain")),
        ("images", ("gcp_list.txt", gcps.encode(), "text/plain")),
    ]
    assert client.post(f"/task/new/upload/{uuid}?token={token}", files=files).json() == {"success": True}
    flight_dir = next((api_settings.data_dir / "flights").iterdir())
    assert (flight_dir / "geo.txt").read_text() == geo and (flight_dir / "gcp_list.txt").read_text() == gcps
    groups = [("images", ("image_groups.txt", b"frame_000.jpg A\n", "text/plain"))]  # an ODM step we lack
    assert client.post(f"/task/new/upload/{uuid}?token={token}", files=groups).json() == {"success": True}
    bad = client.post(
        f"/task/new/upload/{uuid}?token={token}", files=[("images", ("geo.txt", b"EPSG:4326\nx y\n", "t"))]
    )
    assert bad.status_code == 422 and "geo.txt" in bad.json()["error"]
