"""One large mosaic job on 1 and on N Celery worker processes, each held to one core, as stand-ins for hosts.

Run by hand from the repository root::

    .venv/bin/python bench/scale_out.py [--frames 120] [--workers 1 2] [--size 640x480] [--json OUT]

A real stack for each run: a Redis server, the API (uvicorn, one process, on no core of its own) and the
workers, each pinned to its own core with ``taskset`` (so one thread: the stages size their pools by the cores
a process may use) and with one BLAS and OpenCV thread. The same synthetic GPS flight (``tests/scenes.py``,
two-way serpentine lines) is uploaded and mosaicked; the script prints the wall time from the job's creation to
its end, each stage's seconds, the speed-up against the first run for the whole job and for the stages in parts
(those spread over the workers), which of them each worker did, and whether the COG's pixels are identical
across runs. Where a GPU worker is running on the ``gpu`` queue it takes the GPU stages' parts; this script
starts CPU workers only.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

import httpx  # noqa: E402
import numpy as np  # noqa: E402
import rasterio  # noqa: E402

from api.embedded_stack import start_redis, stop, wait_for_port  # noqa: E402
from tests.conftest import free_port, make_token, stack_env  # noqa: E402
from tests.scenes import make_flight  # noqa: E402
from workers.pipeline import PIPELINES  # noqa: E402

PARTED = [spec.name for spec in PIPELINES["mosaic"] if spec.parted]
ONE_THREAD = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}


def run(frames_dir: Path, workers: int, scratch: Path) -> dict[str, Any]:
    """The job on a fresh stack with ``workers`` worker processes; its timings and where its COG is."""
    cores = os.sched_getaffinity(0)
    if workers > len(cores):
        raise SystemExit(f"{workers} workers need {workers} cores; this machine lets us use {len(cores)}")
    root = scratch / f"{workers}-workers"
    (root / "logs").mkdir(parents=True)
    redis_url = f"redis://127.0.0.1:{free_port()}/0"
    env = stack_env(root / "data", redis_url, FOTOSKHEMA_CELERY_QUEUE="cpu", FOTOSKHEMA_WORKER_BEACON_SECONDS="0.5")
    procs: list[subprocess.Popen[bytes]] = []
    try:
        redis_server = start_redis(redis_url, root / "redis")
        procs += [redis_server] if redis_server else []
        token = make_token(env, "bench", admin=True)
        port = free_port()
        api = [sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--port", str(port)]
        procs.append(_spawn(api, env, root / "logs" / "api.log"))
        for n, core in enumerate(sorted(cores)[:workers]):
            cmd = ["taskset", "-c", str(core), sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker"]
            cmd += ["-Q", "cpu", "--concurrency", "1", "-n", f"bench{n}@%h", "--without-gossip", "--without-mingle"]
            procs.append(_spawn(cmd, {**env, **ONE_THREAD}, root / "logs" / f"worker{n}.log"))
        wait_for_port("127.0.0.1", port, 60, procs[-1])
        url = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=300) as http:
            _wait_for_workers(http, workers)
            flight = http.post("/api/flights", json={"name": "scale out"}).json()["id"]
            paths = sorted(frames_dir.glob("*.jpg"))
            for start in range(0, len(paths), 50):
                files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in paths[start : start + 50]]
                assert http.post(f"/api/flights/{flight}/images", files=files).status_code == 201
            started = time.perf_counter()
            job = http.post("/api/jobs", json={"flight_id": flight, "options": {"working_max_px": 2048}}).json()
            while job["status"] not in ("succeeded", "failed", "cancelled"):
                time.sleep(0.2)
                job = http.get(f"/api/jobs/{job['id']}").json()
            seconds = time.perf_counter() - started
        if job["status"] != "succeeded":
            raise SystemExit(f"{workers} workers: the job {job['status']}: {job.get('error')} (logs: {root / 'logs'})")
        folder = root / "data" / "jobs" / str(job["id"])
        by = {
            s: json.loads((folder / "reports" / f"{s}.json").read_text()).get("parts", {}).get("by", {}) for s in PARTED
        }
        return {
            "workers": workers,
            "seconds": seconds,
            "stages": job["timings"],
            "cog": str(folder / "mosaic.tif"),
            "by": by,
        }
    finally:
        stop(procs)


def _wait_for_workers(http: httpx.Client, workers: int) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if http.get("/api/health").status_code == 200:
            time.sleep(1.5 * workers)  # every worker's beacon, not only the first one's
            return
        time.sleep(0.2)
    raise SystemExit("the workers did not start (see the logs)")


def _spawn(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=log.open("wb"), stderr=subprocess.STDOUT)


def same_pixels(a: str, b: str) -> bool:
    with rasterio.open(a) as ra, rasterio.open(b) as rb:
        return bool(
            ra.shape == rb.shape
            and np.array_equal(ra.read(), rb.read())
            and np.array_equal(ra.dataset_mask(), rb.dataset_mask())
        )


def print_table(results: list[dict[str, Any]]) -> None:
    base = results[0]
    stages = list(base["stages"])
    print(f"{'workers':>8}{'job s':>9}{'speed-up':>10}{'parted s':>10}{'speed-up':>10}{'same COG':>10}")
    for r in results:
        parted = sum(r["stages"].get(s, 0.0) for s in PARTED)
        base_parted = sum(base["stages"].get(s, 0.0) for s in PARTED)
        same = "yes" if same_pixels(base["cog"], r["cog"]) else "NO"
        print(
            f"{r['workers']:>8}{r['seconds']:>9.1f}{base['seconds'] / r['seconds']:>10.2f}"
            f"{parted:>10.1f}{base_parted / max(parted, 1e-9):>10.2f}{same:>10}"
        )
    print("per stage, s (stages in parts marked *):")
    print(f"{'stage':>18}" + "".join(f"{r['workers']:>10}" for r in results))
    for stage in stages:
        mark = "*" if stage in PARTED else " "
        print(f"{stage + mark:>18}" + "".join(f"{r['stages'].get(stage, 0.0):>10.2f}" for r in results))
    for r in results:
        shares = {
            w: sum(by.get(w, {}).get("parts", 0) for by in r["by"].values()) for by in r["by"].values() for w in by
        }
        print(f"{r['workers']} workers: parts done per worker process: {shares}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--size", default="640x480", help="frame width x height, px")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not shutil.which("taskset"):
        raise SystemExit("taskset (util-linux) is needed to hold each worker to one core")
    width, height = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory(prefix="fotoskhema-scale-") as tmp:
        scratch = Path(tmp)
        frames = scratch / "frames"
        make_flight(frames, n_frames=args.frames, frame_size=(width, height), layout="grid", gps=True, seed=3)
        print(
            f"{args.frames} frames of {width}x{height}; workers {args.workers}, one core and one thread each",
            flush=True,
        )
        results = []
        for n in args.workers:
            results.append(run(frames, n, scratch))
            print(f"  {n} worker(s): {results[-1]['seconds']:.1f} s", flush=True)
        print_table(results)
        if args.json:
            args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
