"""Shared fixtures: an API app over a temporary data dir with a recording queue, and a live stack
(real Redis server, real Celery worker process, real uvicorn server) for end-to-end tests."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data(name: str) -> Path:
    """A folder of ../shared/data, or skip the test saying why."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data {path} is absent (see shared/data/MANIFEST.md)")
    return path


@dataclass
class RecordingQueue:
    """Stands in for Celery in API tests: records what would be sent, in order."""

    sent: list[tuple[int, str]] = field(default_factory=list)
    fail: bool = False

    def enqueue(self, job_id: int, kind: str, after: str = "") -> str:
        if self.fail:
            raise ConnectionError("broker unreachable")
        self.sent.append((job_id, kind))
        return f"recorded-{job_id}"


@pytest.fixture(params=["sqlite", "postgresql"])
def api_settings(request: pytest.FixtureRequest, tmp_path: Path):
    """Settings over a temporary data dir; every API test runs on SQLite and on a real PostgreSQL."""
    from core.settings import Settings

    url = fresh_database(request.getfixturevalue("postgres_base_url")) if request.param == "postgresql" else ""
    return Settings(
        data_dir=tmp_path / "data",
        database_url=url,
        redis_url="redis://127.0.0.1:1/0",
        allowed_hosts=["testserver", "127.0.0.1", "localhost"],  # TestClient sends Host: testserver
    )


@pytest.fixture(scope="session")
def postgres_base_url() -> Iterator[str]:
    """A throw-away PostgreSQL cluster (Debian's server binaries) on a free port, trust auth."""
    from api.embedded_stack import stop, wait_for_port

    initdb = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
    if not initdb:
        pytest.skip(
            "PostgreSQL server binaries are absent (Debian package postgresql; "
            "scripts/setup.sh --test installs it when run as root)"
        )
    bindir = initdb[-1].parent
    root = Path(tempfile.mkdtemp(prefix="fotoskhema-pg-"))
    as_user: list[str] = []
    if os.geteuid() == 0:  # initdb refuses to run as root: run the cluster as the package's user
        shutil.chown(root, "postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    data, port = root / "data", free_port()
    subprocess.run(
        [*as_user, str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust", "-E", "UTF8"],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    server = subprocess.Popen(
        [
            *as_user,
            str(bindir / "postgres"),
            "-D",
            str(data),
            "-p",
            str(port),
            "-k",
            str(root),
            "-c",
            "listen_addresses=127.0.0.1",
            "-c",
            "fsync=off",
        ],
        stdout=subprocess.DEVNULL,
        stderr=(root / "server.log").open("wb"),
    )
    try:
        wait_for_port("127.0.0.1", port, 30, server)
        yield f"postgresql+psycopg2://postgres@127.0.0.1:{port}/"
    finally:
        stop([server])
        shutil.rmtree(root, ignore_errors=True)


def fresh_database(base_url: str) -> str:
    """Create an empty database on the cluster at ``base_url``; return its URL."""
    import sqlalchemy

    name = f"t_{uuid.uuid4().hex[:12]}"
    engine = sqlalchemy.create_engine(base_url + "postgres", isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(sqlalchemy.text(f'CREATE DATABASE "{name}"'))
    engine.dispose()
    return base_url + name


@pytest.fixture
def recording_queue() -> RecordingQueue:
    return RecordingQueue()


@pytest.fixture
def client(api_settings, recording_queue):
    """A TestClient of the app that sends an admin's token (``client.headers``); see ``user_headers``."""
    with admin_client(api_settings, recording_queue) as test_client:
        yield test_client


@contextmanager
def admin_client(settings, queue) -> Iterator[Any]:
    """A TestClient of ``create_app(settings, queue)`` (Host ``testserver`` allowed) with a new admin's token."""
    from fastapi.testclient import TestClient

    from api.main import create_app
    from core import accounts

    if "testserver" not in settings.allowed_hosts:  # in place: tests change their settings object later
        settings.allowed_hosts = [*settings.allowed_hosts, "testserver"]
    app = create_app(settings, queue=queue)
    token = accounts.create_user(app.state.db, "admin", admin=True)
    with TestClient(app, headers={"Authorization": f"Bearer {token}"}) as test_client:
        yield test_client


def user_headers(client, name: str, *, admin: bool = False) -> dict[str, str]:
    """Headers with the token of a new user ``name`` of ``client``'s app."""
    from core import accounts

    return {"Authorization": f"Bearer {accounts.create_user(client.app.state.db, name, admin=admin)}"}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def stack_env(data_dir: Path, redis_url: str, **extra: str) -> dict[str, str]:
    """The environment of a service's processes started by a test or a bench: this one's, with its own data
    folder, Redis and an SQLite database there (the generic DATABASE_URL/REDIS_URL dropped), plus ``extra``."""
    env = {
        **os.environ,
        "FOTOSKHEMA_DATA_DIR": str(data_dir),
        "FOTOSKHEMA_REDIS_URL": redis_url,
        "FOTOSKHEMA_DATABASE_URL": "",
        "PYTHONUNBUFFERED": "1",
        **extra,
    }
    env.pop("DATABASE_URL", None)
    env.pop("REDIS_URL", None)
    return env


@dataclass
class LiveService:
    url: str
    data_dir: Path
    redis_url: str
    logs: Path
    token: str  # an admin's

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def client(self, timeout: float = 60.0) -> httpx.Client:
        """An HTTP client of the service that sends the admin's token."""
        return httpx.Client(base_url=self.url, headers=self.headers, timeout=timeout)

    def submit(self, path: str, files: list[Any], options: dict[str, Any]) -> int:
        """POST a job of photos and JSON ``options`` (calibrations, rigs, crack surveys); its id once accepted."""
        response = httpx.post(
            f"{self.url}{path}",
            files=files,
            data={"options": json.dumps(options)},
            timeout=60,
            headers=self.headers,
        )
        assert response.status_code == 202, response.text
        return int(response.json()["id"])

    def wait_for_job(self, job_id: int, timeout: float = 240.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = httpx.get(f"{self.url}/api/jobs/{job_id}", headers=self.headers, timeout=10).json()
            if job["status"] in ("succeeded", "failed", "cancelled"):
                return job
            time.sleep(0.5)
        raise AssertionError(f"job {job_id} still {job['status']} after {timeout} s; logs in {self.logs}")


@pytest.fixture(scope="session")
def live_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveService]:
    """Redis + Celery worker + uvicorn, as separate processes, on free local ports."""
    from api.embedded_stack import find_redis_server, start_redis, stop, wait_for_port

    try:
        find_redis_server()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    root = tmp_path_factory.mktemp("live")
    data_dir, logs = root / "data", root / "logs"
    logs.mkdir()
    redis_url = f"redis://127.0.0.1:{free_port()}/0"
    env = stack_env(
        data_dir,
        redis_url,
        FOTOSKHEMA_CELERY_QUEUE="cpu",
        FOTOSKHEMA_BASEMAP_URL="none",  # the tests run offline: a page that asked OpenStreetMap would fail
        # the event stream samples the job record: at the default 0.5 s a small job's stages can all pass between
        # two looks (CI saw 2 of 7 once)
        FOTOSKHEMA_SSE_POLL_SECONDS="0.1",
    )
    port = free_port()
    token = make_token(env, "admin", admin=True)
    procs: list[subprocess.Popen[bytes] | None] = [start_redis(redis_url, root / "redis")]
    try:
        procs.append(
            _spawn(
                [
                    sys.executable,
                    "-m",
                    "celery",
                    "-A",
                    "workers.celery_app",
                    "worker",
                    "-Q",
                    "cpu,gpu",
                    "--concurrency",
                    "1",
                    "--loglevel",
                    "INFO",
                    "--without-gossip",
                    "--without-mingle",
                ],
                env,
                logs / "worker.log",
            )
        )
        server = _spawn(
            [
                sys.executable,
                "-m",
                "uvicorn",
                "api.main:create_app",
                "--factory",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
            ],
            env,
            logs / "api.log",
        )
        procs.append(server)
        wait_for_port("127.0.0.1", port, 60, server)
        yield LiveService(f"http://127.0.0.1:{port}", data_dir, redis_url, logs, token)
    finally:
        stop(list(reversed(procs)))


def make_token(env: dict[str, str], name: str, *, admin: bool = False) -> str:
    """A new user's token from ``fotoskhema users create``, on the database of ``env``."""
    cmd = [sys.executable, "-m", "api.cli", "users", "create", name, *(["--admin"] if admin else [])]
    done = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, check=True)
    return done.stdout.strip()


def _spawn(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(cmd, env=env, cwd=REPO, stdout=log.open("wb"), stderr=subprocess.STDOUT)
