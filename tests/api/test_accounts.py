"""Accounts and tokens: every route but health and configuration needs a token, users see only their own
flights and jobs, tokens are hashed at rest and revocable, signed URLs open one job's reads for a while,
foreign Host headers and other origins are refused, and flights and jobs can be deleted with their files."""

from __future__ import annotations

import io
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image as PILImage
from sqlalchemy import select, text

from core import accounts
from core.db import ApiToken, Database, Job
from core.settings import Settings
from tests.conftest import REPO, user_headers
from workers.workspace import flight_folder, job_workspace

OPEN_ROUTES = {("get", "/api/health"), ("get", "/api/config")}


def _jpeg(seed: int) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    out = io.BytesIO()
    PILImage.fromarray(pixels).save(out, "JPEG")
    return out.getvalue()


def _flight_with_job(client: TestClient, headers: dict[str, str] | None = None) -> tuple[int, int]:
    headers = headers or {}
    flight = client.post("/api/flights", json={"name": "park"}, headers=headers).json()["id"]
    photos = [("files", (f"p{k}.jpg", _jpeg(k))) for k in range(2)]
    assert client.post(f"/api/flights/{flight}/images", files=photos, headers=headers).status_code == 201
    job = client.post("/api/jobs", json={"flight_id": flight}, headers=headers)
    assert job.status_code == 202, job.text
    return flight, job.json()["id"]


def _concrete(path: str) -> str:
    for name, value in (("{job_id}", "1"), ("{flight_id}", "1"), ("{token_id}", "1"), ("{name}", "admin")):
        path = path.replace(name, value)
    return path.replace("{step}", "0").replace("{z}", "0").replace("{x}", "0").replace("{y}", "0")


def test_every_route_but_health_and_config_needs_a_token(client: TestClient) -> None:
    _flight_with_job(client)
    schema = client.app.openapi()  # type: ignore[attr-defined]
    anonymous = {"Authorization": ""}
    checked = 0
    for path, operations in schema["paths"].items():
        for method in operations:
            response = client.request(method, _concrete(path), headers=anonymous)
            if (method, path) in OPEN_ROUTES:
                assert response.status_code == 200, (method, path)
                continue
            assert response.status_code == 401, (method, path, response.status_code, response.text)
            assert response.headers["www-authenticate"].startswith("Bearer")
            if method != "head":  # an answer to HEAD has no body (tus asks the offset of an upload by HEAD)
                assert "token" in response.json()["detail"]
            checked += 1
    assert checked >= 25
    bad = client.get("/api/flights", headers={"Authorization": "Bearer fsk_not-a-token"})
    assert bad.status_code == 401 and "unknown or revoked" in bad.json()["detail"]


def test_an_anonymous_upload_is_refused_before_its_body_is_read(client: TestClient) -> None:
    flight, _ = _flight_with_job(client)

    def body() -> object:
        yield b"--x\r\n"
        raise AssertionError("the server read the body of an anonymous write")

    for authorization in ("", "Bearer fsk_made-up", "Basic YTpi"):
        response = client.post(
            f"/api/flights/{flight}/images",
            content=body(),
            headers={"Authorization": authorization, "Content-Type": "multipart/form-data; boundary=x"},
        )
        assert response.status_code == 401, authorization


def test_users_see_only_their_own_flights_and_jobs(client: TestClient) -> None:
    alice, bob = user_headers(client, "alice"), user_headers(client, "bob")
    flight, job = _flight_with_job(client, alice)
    assert [f["id"] for f in client.get("/api/flights", headers=alice).json()] == [flight]
    assert client.get("/api/flights", headers=bob).json() == []
    assert client.get("/api/jobs", headers=bob).json() == []
    for method, path in [
        ("get", f"/api/flights/{flight}"),
        ("post", f"/api/flights/{flight}/images"),
        ("put", f"/api/flights/{flight}/gcps"),
        ("delete", f"/api/flights/{flight}"),
        ("get", f"/api/jobs/{job}"),
        ("get", f"/api/jobs/{job}/outputs"),
        ("post", f"/api/jobs/{job}/cancel"),
        ("post", f"/api/jobs/{job}/retry"),
        ("delete", f"/api/jobs/{job}"),
        ("get", f"/tiles/{job}/tilejson.json"),
        ("get", f"/tiles/{job}/0/0/0.png"),
    ]:
        response = client.request(method, path, headers=bob)
        assert response.status_code == 404, (method, path, response.text)
        assert "not found" in response.json()["detail"]
    refused = client.post("/api/jobs", json={"flight_id": flight}, headers=bob)
    assert refused.status_code == 404 and f"flight {flight} not found" in refused.json()["detail"]
    # nothing of alice's changed, and the admin (the client's own token) sees everyone's
    assert client.get(f"/api/jobs/{job}", headers=alice).json()["status"] == "queued"
    assert len(client.get(f"/api/flights/{flight}", headers=alice).json()["images"]) == 2
    assert [j["id"] for j in client.get("/api/jobs").json()] == [job]
    assert client.get("/api/users", headers=alice).status_code == 403


def test_tokens_are_stored_hashed_and_revocation_takes_effect(client: TestClient) -> None:
    created = client.post("/api/users", json={"name": "carol", "label": "tablet"})
    assert created.status_code == 201
    token = created.json()["token"]
    carol = {"Authorization": f"Bearer {token}"}
    me = client.get("/api/me", headers=carol).json()
    assert me["name"] == "carol" and not me["is_admin"] and me["tokens"][0]["label"] == "tablet"
    assert token not in client.get("/api/users").text  # listings never show a secret
    db: Database = client.app.state.db  # type: ignore[attr-defined]
    with db.session() as s:
        stored = list(s.execute(text("SELECT token_hash, prefix FROM api_tokens")))
        assert all(token not in (h, p) and len(p) < 12 for h, p in stored)
        assert accounts.hash_token(token) in {h for h, _ in stored}
    second = client.post("/api/users/carol/tokens", params={"label": "laptop"}).json()["token"]
    assert client.delete(f"/api/tokens/{me['tokens'][0]['id']}", headers=carol).status_code == 200
    assert client.get("/api/me", headers=carol).status_code == 401
    assert client.get("/api/me", headers={"Authorization": f"Bearer {second}"}).json()["name"] == "carol"
    assert client.post("/api/users", json={"name": "carol"}).status_code == 409
    assert client.post("/api/users", json={"name": "<b>x</b>"}).status_code == 422
    assert client.post("/api/users/nobody/tokens").status_code == 404


def test_a_signed_url_opens_one_jobs_reads_until_it_expires(client: TestClient, api_settings: Settings) -> None:
    _, job = _flight_with_job(client)
    _, other = _flight_with_job(client)
    signature = client.get(f"/api/jobs/{job}").json()["signature"]
    anonymous = {"Authorization": ""}
    download = f"/api/jobs/{job}/outputs/mosaic.tif"  # a queued job has none: 404 once let in
    opened = client.get(f"{download}?{signature}", headers=anonymous)
    assert opened.status_code == 404 and "no output named" in opened.json()["detail"]
    assert client.get(download, headers=anonymous).status_code == 401
    assert client.get(f"/tiles/{job}/0/0/0.png?{signature}", headers=anonymous).status_code == 409  # no mosaic yet
    assert client.get(f"/api/jobs/{other}/outputs/mosaic.tif?{signature}", headers=anonymous).status_code == 401
    tampered = signature[:-1] + ("0" if signature[-1] != "0" else "1")
    assert client.get(f"{download}?{tampered}", headers=anonymous).status_code == 401
    assert client.post(f"/api/jobs/{job}/cancel?{signature}", headers=anonymous).status_code == 401  # reads only
    # what hands out signatures needs the token, so a signed link cannot renew itself
    for renewing in (f"/api/jobs/{job}", f"/api/jobs/{job}/outputs", f"/tiles/{job}/tilejson.json"):
        assert client.get(f"{renewing}?{signature}", headers=anonymous).status_code == 401, renewing
    key = accounts.signing_key("", api_settings.data_dir)
    with client.app.state.db.session() as s:  # type: ignore[attr-defined]
        created_at = s.get(Job, job).created_at
    scope = accounts.job_scope(job, created_at)
    expired = accounts.sign(key, scope, 60, now=0.0)
    response = client.get(download, params=expired, headers=anonymous)
    assert response.status_code == 401 and "expired" in response.json()["detail"]
    for odd in ({"exp": "\u00b2", "sig": "a"}, {"exp": "9999999999", "sig": "\u00e9" * 43}):
        assert client.get(download, params=odd, headers=anonymous).status_code == 401
    assert stat.S_IMODE(os.stat(api_settings.data_dir / "secret_key").st_mode) == 0o600


def test_no_spelling_of_an_id_escapes_the_owner_check(client: TestClient) -> None:
    alice, bob = user_headers(client, "alice"), user_headers(client, "bob")
    flight, job = _flight_with_job(client, alice)
    for spelling in (f"{flight}.0", f"+{flight}", f"%20{flight}", f"{flight}%20"):
        assert client.get(f"/api/flights/{spelling}", headers=bob).status_code in (404, 422), spelling
        assert client.delete(f"/api/flights/{spelling}", headers=bob).status_code in (404, 422), spelling
    for spelling in (f"{job}.0", f"+{job}"):
        assert client.get(f"/api/jobs/{spelling}", headers=bob).status_code in (404, 422), spelling
        assert client.get(f"/tiles/{spelling}/tilejson.json", headers=bob).status_code in (404, 422), spelling
    assert len(client.get(f"/api/flights/{flight}", headers=alice).json()["images"]) == 2
    assert client.get(f"/api/jobs/{job}", headers=alice).status_code == 200


def test_a_deleted_jobs_signature_does_not_open_the_job_that_reuses_its_id(client: TestClient) -> None:
    flight, job = _flight_with_job(client)
    signature = client.get(f"/api/jobs/{job}").json()["signature"]
    assert client.delete(f"/api/jobs/{job}").status_code == 204
    again = client.post("/api/jobs", json={"flight_id": flight}).json()["id"]  # SQLite reuses the largest id
    assert client.get(f"/api/jobs/{again}?{signature}", headers={"Authorization": ""}).status_code == 401


def test_public_read_opens_reads_but_not_writes(api_settings: Settings, recording_queue) -> None:
    from api.main import create_app

    app = create_app(api_settings.model_copy(update={"public_read": True}), queue=recording_queue)
    with TestClient(app) as anonymous:
        assert anonymous.get("/api/flights").status_code == 200
        assert anonymous.post("/api/flights", json={"name": "x"}).status_code == 401


def test_foreign_host_headers_and_other_origins_are_refused(client: TestClient) -> None:
    rebound = client.get("/api/flights", headers={"Host": "attacker.example"})
    assert rebound.status_code == 400 and "host" in rebound.json()["detail"]
    assert client.get("/api/health", headers={"Host": "localhost:8000"}).status_code == 200
    preflight = client.options(
        "/api/jobs/1/cancel",
        headers={"Origin": "https://attacker.example", "Access-Control-Request-Method": "POST"},
    )
    assert "access-control-allow-origin" not in preflight.headers
    cross = client.get("/api/health", headers={"Origin": "https://attacker.example"})
    assert "access-control-allow-origin" not in cross.headers


def test_cors_opens_only_to_the_origins_ops_name(api_settings: Settings, recording_queue) -> None:
    from api.main import create_app

    settings = api_settings.model_copy(update={"cors_origins": ["https://survey.example"]})
    with TestClient(create_app(settings, queue=recording_queue)) as c:
        ok = c.get("/api/health", headers={"Origin": "https://survey.example"})
        assert ok.headers["access-control-allow-origin"] == "https://survey.example"
        other = c.get("/api/health", headers={"Origin": "https://attacker.example"})
        assert "access-control-allow-origin" not in other.headers


def test_deleting_a_flight_takes_its_photos_jobs_and_files(client: TestClient, api_settings: Settings) -> None:
    flight, job = _flight_with_job(client)
    keep_flight, keep_job = _flight_with_job(client)
    data = api_settings.data_dir
    assert flight_folder(data, flight).is_dir() and job_workspace(data, job).root.is_dir()
    assert client.delete(f"/api/flights/{flight}").status_code == 204
    assert client.get(f"/api/flights/{flight}").status_code == 404
    assert client.get(f"/api/jobs/{job}").status_code == 404
    assert not flight_folder(data, flight).parent.exists() and not job_workspace(data, job).root.exists()
    assert client.delete(f"/api/flights/{flight}").status_code == 404
    # the other flight and its job are untouched
    assert len(client.get(f"/api/flights/{keep_flight}").json()["images"]) == 2
    assert client.get(f"/api/jobs/{keep_job}").json()["status"] == "queued"
    assert job_workspace(data, keep_job).root.is_dir()


def test_deleting_a_running_job_stops_it(client: TestClient, api_settings: Settings) -> None:
    from workers.pipeline import pipeline_key
    from workers.tasks import JobCancelledError, JobRecorder

    _, job = _flight_with_job(client)
    db: Database = client.app.state.db  # type: ignore[attr-defined]
    recorder = JobRecorder(db, job, pipeline_key("mosaic", {}), "load_images")
    recorder.update(status="running")
    assert client.delete(f"/api/jobs/{job}").status_code == 204
    assert not job_workspace(api_settings.data_dir, job).root.exists()
    with pytest.raises(JobCancelledError):
        recorder.progress(1.0, "the stage's next report")


def test_users_command_makes_lists_and_revokes_tokens(tmp_path: Path) -> None:
    env = {**os.environ, "FOTOSKHEMA_DATA_DIR": str(tmp_path), "FOTOSKHEMA_DATABASE_URL": ""}
    env.pop("DATABASE_URL", None)

    def users(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "api.cli", "users", *args]
        return subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=60)

    token = users("create", "dora", "--label", "office").stdout.strip()
    assert token.startswith("fsk_") and len(token) > 40
    assert users("create", "dora").returncode == 1
    listing = users("list").stdout
    assert "dora" in listing and "office" in listing and token not in listing
    db = Database(f"sqlite:///{tmp_path / 'fotoskhema.db'}")
    assert accounts.authenticate(db, token) is not None
    with db.session() as s:
        token_id = s.scalar(select(ApiToken.id))
    assert users("revoke", str(token_id)).returncode == 0
    assert accounts.authenticate(db, token) is None


def test_up_makes_an_admin_token_once_and_keeps_it_private(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from api.accounts_cli import ADMIN_TOKEN_FILE, announce_admin_token

    settings = Settings(data_dir=tmp_path)
    announce_admin_token(settings)
    printed = capsys.readouterr().out
    path = tmp_path / ADMIN_TOKEN_FILE
    token = path.read_text().strip()
    assert token in printed and stat.S_IMODE(path.stat().st_mode) == 0o600
    principal = accounts.authenticate(Database(settings.resolved_database_url()), token)
    assert principal is not None and principal.is_admin
    announce_admin_token(settings)  # a second start says where the token is, and does not show it again
    again = capsys.readouterr().out
    assert token not in again and str(path.resolve()) in again
