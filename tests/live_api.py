"""One uvicorn of the app alone (no Redis, no worker), over its own data dir, started and killed at will: for
tests of what the API does by itself across restarts and over a real socket (resumable uploads)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from tests.conftest import REPO, free_port, make_token

TUS = {"Tus-Resumable": "1.0.0"}


@dataclass
class ApiProcess:
    """One uvicorn of the app over ``data_dir`` (SQLite), started and killed at will."""

    data_dir: Path
    env: dict[str, str] = field(default_factory=dict)
    port: int = 0
    token: str = ""
    process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        from api.embedded_stack import wait_for_port

        self.port = free_port()
        log = (self.data_dir.parent / f"api-{self.port}.log").open("wb")
        cmd = [sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--port", str(self.port)]
        self.process = subprocess.Popen(cmd, env=self.env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        wait_for_port("127.0.0.1", self.port, 60, self.process)

    def kill(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.token}", **TUS}, timeout=30)

    def raw_patch(self, path: str, offset: int, length: int, sent: bytes, checksum: str = "") -> socket.socket:
        """A PATCH announcing ``length`` bytes of which only ``sent`` go; the open socket (close it to cut it)."""
        head = [
            f"PATCH {path} HTTP/1.1",
            f"Host: 127.0.0.1:{self.port}",
            f"Authorization: Bearer {self.token}",
            "Tus-Resumable: 1.0.0",
            "Content-Type: application/offset+octet-stream",
            f"Upload-Offset: {offset}",
            f"Content-Length: {length}",
        ] + ([f"Upload-Checksum: {checksum}"] if checksum else [])
        sock = socket.create_connection(("127.0.0.1", self.port))
        sock.sendall(("\r\n".join(head) + "\r\n\r\n").encode() + sent)
        return sock


def api_process(data_dir: Path, **settings: str) -> ApiProcess:
    """An ``ApiProcess`` (not started) over SQLite in ``data_dir``, with an admin's token, the reaper off (no
    Redis here) and ``settings`` as ``FOTOSKHEMA_<NAME>`` variables."""
    env = {
        **os.environ,
        "FOTOSKHEMA_DATA_DIR": str(data_dir),
        "FOTOSKHEMA_DATABASE_URL": "",
        "FOTOSKHEMA_REDIS_URL": "redis://127.0.0.1:1/0",  # nothing is queued here
        "FOTOSKHEMA_REAPER_SECONDS": "0",
        "FOTOSKHEMA_BASEMAP_URL": "none",  # offline: no page of these tests asks OpenStreetMap
        "PYTHONUNBUFFERED": "1",
        **{f"FOTOSKHEMA_{name.upper()}": value for name, value in settings.items()},
    }
    env.pop("DATABASE_URL", None)
    return ApiProcess(data_dir, env, token=make_token(env, "admin", admin=True))
