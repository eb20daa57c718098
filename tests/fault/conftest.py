"""A stack whose parts the fault tests kill and start again: a real Redis server, real Celery worker
processes (with ``tests.fault.worker_faults`` loaded) and a real uvicorn, on free local ports, with liveness
thresholds of a few seconds instead of a minute."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import redis

from core.db import Database, Job, utcnow
from tests.conftest import _spawn, free_port, make_token, stack_env
from tests.scenes import make_flight

T = TypeVar("T")

HEARTBEAT_S, STALE_S, REAPER_S, BEACON_S, MAX_DELIVERIES = 0.5, 3.0, 0.5, 0.5, 3
LIVENESS_ENV = {
    "FOTOSKHEMA_HEARTBEAT_SECONDS": str(HEARTBEAT_S),
    "FOTOSKHEMA_STALE_SECONDS": str(STALE_S),
    "FOTOSKHEMA_REAPER_SECONDS": str(REAPER_S),
    "FOTOSKHEMA_WORKER_BEACON_SECONDS": str(BEACON_S),
    "FOTOSKHEMA_MAX_DELIVERIES": str(MAX_DELIVERIES),
}


def wait_for(condition: Callable[[], T], timeout: float, what: str, every: float = 0.1) -> T:
    """Poll ``condition`` until it returns something true; return that, or fail saying ``what`` never happened."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(every)
    raise AssertionError(f"{what}: not after {timeout} s")


@dataclass
class FaultStack:
    root: Path
    env: dict[str, str]
    redis_url: str
    url: str
    token: str
    faults: Path  # files that switch on tests.fault.worker_faults
    redis_server: subprocess.Popen[bytes] | None = None
    worker: subprocess.Popen[bytes] | None = None
    api: subprocess.Popen[bytes] | None = None
    flight_id: int = 0
    extra_workers: list[subprocess.Popen[bytes]] = field(default_factory=list)
    _workers_started: int = 0
    _dead: list[subprocess.Popen[bytes]] = field(default_factory=list)

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    @cached_property
    def db(self) -> Database:
        return Database(f"sqlite:///{self.root / 'data' / 'fotoskhema.db'}")

    # -- processes --

    def start_redis(self) -> None:
        from api.embedded_stack import start_redis

        assert self.redis_server is None or self.redis_server.poll() is not None, "Redis already runs"
        self.redis_server = start_redis(self.redis_url, self.root / "redis")
        assert self.redis_server is not None, "something else listens on the test's Redis port"

    def kill_redis(self) -> None:
        assert self.redis_server is not None
        self.redis_server.kill()
        self.redis_server.wait()

    def start_worker(self) -> None:
        """A new worker process (named ``faultN@host``), once it says in Redis that it is alive."""
        assert self.worker is None or self.worker.poll() is not None, "a worker already runs"
        self.worker = self._new_worker()

    def start_extra_worker(self, queues: str = "cpu,gpu") -> subprocess.Popen[bytes]:
        """One more worker beside the first (scale-out tests); stop it with ``stop_extra_workers``."""
        worker = self._new_worker(queues)
        self.extra_workers.append(worker)
        return worker

    def stop_extra_workers(self) -> None:
        while self.extra_workers:
            worker = self.extra_workers.pop()
            for pid in _children(worker.pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            worker.kill()
            worker.wait()

    def _new_worker(self, queues: str = "cpu,gpu") -> subprocess.Popen[bytes]:
        self._workers_started += 1
        name = f"fault{self._workers_started}"
        cmd = [sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker", "--include"]
        cmd += ["tests.fault.worker_faults", "-Q", queues, "--concurrency", "1", "-n", f"{name}@%h"]
        cmd += ["--loglevel", "INFO", "--without-gossip", "--without-mingle"]
        worker = _spawn(cmd, self.env, self.logs / f"worker-{name}.log")
        wait_for(lambda: self._beacon_of(name), 60, f"worker {name} ready (log {self.logs})")
        return worker

    def kill_worker(self) -> list[int]:
        """SIGKILL the worker's main process only, as the OOM killer or ``kill -9`` would; returns the pids
        of its pool processes, which then have no parent."""
        assert self.worker is not None
        children = _children(self.worker.pid)
        self.worker.kill()
        self.worker.wait()
        return children

    def stop_worker(self) -> None:
        """A warm shutdown (SIGTERM): the worker finishes what it runs, gives back what it holds and leaves."""
        assert self.worker is not None
        self.worker.terminate()
        self.worker.wait(timeout=30)

    def ensure_up(self) -> None:
        """Every part running, no fault switched on: what each test starts from."""
        for path in self.faults.glob("*"):
            if path.name.startswith(("hold-", "crash-", "fail-once-")):
                path.unlink()
        self.stop_extra_workers()
        if self.redis_server is None or self.redis_server.poll() is not None:
            self.start_redis()
        if self.worker is None or self.worker.poll() is not None:
            self.start_worker()

    def _beacon_of(self, name: str) -> bool:
        try:
            members = redis.Redis.from_url(self.redis_url, socket_timeout=1).zrange("fotoskhema:workers", 0, -1)
        except redis.RedisError:
            return False
        return any(f'"{name}@' in m.decode() for m in members)

    # -- the API --

    def client(self, timeout: float = 30.0) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.token}"}, timeout=timeout)

    def new_job(self, flight_id: int = 0, **options: Any) -> int:
        body = {"flight_id": flight_id or self.flight_id, "options": {"working_max_px": 480, **options}}
        with self.client() as http:
            response = http.post("/api/jobs", json=body)
        assert response.status_code == 202, response.text
        return int(response.json()["id"])

    def job_folder(self, job_id: int) -> Path:
        return self.root / "data" / "jobs" / str(job_id)

    def job(self, job_id: int) -> dict[str, Any]:
        with self.client() as http:
            return dict(http.get(f"/api/jobs/{job_id}").json())

    def wait_for_end(self, job_id: int, timeout: float) -> dict[str, Any]:
        def ended() -> dict[str, Any] | None:
            job = self.job(job_id)
            return job if job["status"] in ("succeeded", "failed", "cancelled") else None

        return wait_for(ended, timeout, f"job {job_id} ended (logs in {self.logs})", every=0.25)

    def record(self, job_id: int) -> Job:
        """The job's row, as the workers and the reaper see it (the API does not show liveness fields)."""
        with self.db.session() as s:
            job = s.get(Job, job_id)
            assert job is not None
            return job

    def waiting_for(self, job_id: int) -> float:
        """Seconds the job has been waiting for a stage to start (no heartbeat, nothing written); 0 if running."""
        job = self.record(job_id)
        return 0.0 if job.heartbeat_at is not None else (utcnow() - job.updated_at).total_seconds()

    def queued_chains(self) -> set[str]:
        """Tokens of the chains with a message waiting in the ``cpu`` list of Redis."""
        raw = redis.Redis.from_url(self.redis_url, socket_timeout=1).lrange("cpu", 0, -1)
        return {json.loads(m)["headers"]["id"].partition(".")[0] for m in raw}

    def api_log(self) -> str:
        return (self.logs / "api.log").read_text(errors="replace")

    def held(self, job_id: int, stage: str) -> Path:
        """The marker ``worker_faults`` writes once ``stage`` of ``job_id`` is held mid-run."""
        return self.faults / f"held-{job_id}-{stage}"

    def starts(self, job_id: int, stage: str) -> int:
        path = self.faults / f"started-{job_id}-{stage}"
        return len(path.read_text().splitlines()) if path.exists() else 0


def _children(pid: int) -> list[int]:
    found = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(p) for p in found.split()]


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return not Path(f"/proc/{pid}/stat").read_text().split(") ")[-1].startswith("Z")


@pytest.fixture(scope="session")
def fault_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FaultStack]:
    from api.embedded_stack import find_redis_server, stop, wait_for_port

    try:
        find_redis_server()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    root = tmp_path_factory.mktemp("fault")
    (root / "logs").mkdir()
    (root / "faults").mkdir()
    (root / "data").mkdir()
    redis_url = f"redis://127.0.0.1:{free_port()}/0"
    env = stack_env(
        root / "data",
        redis_url,
        **LIVENESS_ENV,
        FOTOSKHEMA_CELERY_QUEUE="cpu",
        FOTOSKHEMA_FAULT_DIR=str(root / "faults"),
    )
    port = free_port()
    stack = FaultStack(
        root, env, redis_url, f"http://127.0.0.1:{port}", make_token(env, "admin", admin=True), root / "faults"
    )
    try:
        stack.start_redis()
        # Two API processes, as `fotoskhema serve` runs on a machine with the cores: two reapers at once.
        cmd = [sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--host", "127.0.0.1"]
        stack.api = _spawn([*cmd, "--port", str(port), "--workers", "2"], env, stack.logs / "api.log")
        stack.start_worker()
        wait_for_port("127.0.0.1", port, 60, stack.api)
        stack.flight_id = _upload_flight(stack, root / "flight")
        yield stack
    finally:
        for path in stack.faults.glob("hold-*"):
            path.unlink()
        stack.stop_extra_workers()
        stop([stack.worker, stack.api, stack.redis_server])


@pytest.fixture
def stack(fault_stack: FaultStack) -> FaultStack:
    fault_stack.ensure_up()
    return fault_stack


def _upload_flight(stack: FaultStack, folder: Path) -> int:
    flight = make_flight(folder, n_frames=4, frame_size=(480, 360), seed=5)
    with stack.client(timeout=120) as http:
        flight_id = int(http.post("/api/flights", json={"name": "faults"}).json()["id"])
        files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in flight.paths]
        response = http.post(f"/api/flights/{flight_id}/images", files=files)
    assert response.status_code == 201, response.text
    return flight_id
