"""``fotoskhema up`` keeps its Redis and its worker running: each is started again when it dies."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.conftest import _spawn, free_port, stack_env
from tests.fault.conftest import LIVENESS_ENV, pid_alive, wait_for

pytestmark = pytest.mark.e2e


def children(pid: int, name: str) -> list[int]:
    """Live processes whose parent is ``pid`` and whose command line names ``name``."""
    out = subprocess.run(["ps", "-o", "pid=,args=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines() if name in line and pid_alive(int(line.split()[0]))]


def test_up_starts_redis_and_the_worker_again_when_they_die(tmp_path: Path) -> None:
    port = free_port()
    env = stack_env(tmp_path / "data", f"redis://127.0.0.1:{free_port()}/0", **LIVENESS_ENV)
    up = _spawn([sys.executable, "-m", "api.cli", "up", "--port", str(port)], env, tmp_path / "up.log")

    def healthy() -> bool:
        try:
            return httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_for(healthy, 90, f"the stack up (log {tmp_path / 'up.log'})", every=0.25)
        for name in ("celery", "redis-server"):
            [old] = children(up.pid, name)
            os.kill(old, signal.SIGKILL)
            wait_for(lambda n=name, o=old: [p for p in children(up.pid, n) if p != o], 60, f"{name} started again")
            wait_for(healthy, 60, f"healthy again after {name} died", every=0.25)
        assert (tmp_path / "data" / "redis" / "appendonlydir").is_dir(), "Redis keeps an append-only file"
    finally:
        up.terminate()
        up.wait(timeout=60)
    assert not children(up.pid, "celery") and not children(up.pid, "redis-server")
