"""One job spread over several Celery worker processes (real Redis, real workers, real uvicorn): the stages in
parts go out as chords over every worker of the queue, and the mosaic is the same bytes whether one worker or
three did it, whatever order the parts ended in, and when a worker dies in the middle."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio

from tests.fault.conftest import STALE_S, FaultStack, _children, wait_for
from tests.scenes import make_flight
from workers.pipeline import PIPELINES

pytestmark = pytest.mark.e2e  # real processes, as the end-to-end tests

# small windows and bands, so that every stage in parts has a few parts for each worker
OPTIONS: dict[str, Any] = {"block_px": 256}
PARTED = ("load_images", "detect_features", "match_features", "measure_ties", "compose_mosaic")


@pytest.fixture(scope="module")
def flight(fault_stack: FaultStack) -> int:
    folder = fault_stack.root / "scale-flight"
    made = make_flight(folder, n_frames=8, frame_size=(480, 360), layout="grid", seed=12)
    with fault_stack.client(timeout=120) as http:
        flight_id = int(http.post("/api/flights", json={"name": "scale out"}).json()["id"])
        files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in made.paths]
        assert http.post(f"/api/flights/{flight_id}/images", files=files).status_code == 201
    return flight_id


@pytest.fixture(scope="module")
def one_worker(fault_stack: FaultStack, flight: int) -> dict[str, Any]:
    """The reference: the job done by the stack's single worker."""
    fault_stack.ensure_up()
    job = fault_stack.wait_for_end(fault_stack.new_job(flight, **OPTIONS), 180)
    assert job["status"] == "succeeded", job["error"]
    return _outputs(fault_stack, job["id"])


def test_three_workers_make_the_same_mosaic_as_one(stack: FaultStack, flight: int, one_worker: dict) -> None:
    for _ in range(2):
        stack.start_extra_worker()
    job = stack.wait_for_end(stack.new_job(flight, **OPTIONS), 180)
    assert job["status"] == "succeeded", job["error"]
    three = _outputs(stack, job["id"])
    _assert_same(three, one_worker)
    # the parts were spread: some stage had its parts done by more than one worker process
    assert max(len(three["parts"][stage]["by"]) for stage in PARTED) >= 2, three["parts"]
    assert len({who for stage in PARTED for who in three["parts"][stage]["by"]}) >= 2


def test_a_worker_killed_mid_fan_out_loses_only_its_parts(stack: FaultStack, flight: int, one_worker: dict) -> None:
    for _ in range(2):
        stack.start_extra_worker()
    stage = "compose_mosaic"
    (stack.faults / f"hold-part-{stage}").touch()
    job_id = stack.new_job(flight, **OPTIONS)
    held = wait_for(lambda: sorted(stack.faults.glob(f"held-part-{job_id}-{stage}-*")), 120, "parts held")
    victim_pid = int(held[0].read_text())
    owner = next(w for w in [stack.worker, *stack.extra_workers] if w and victim_pid in _children(w.pid))
    os.kill(victim_pid, signal.SIGKILL)
    owner.kill()  # the whole worker goes, as a host that leaves
    owner.wait()
    (stack.faults / f"hold-part-{stage}").unlink()
    job = stack.wait_for_end(job_id, 60 + 4 * STALE_S)
    assert job["status"] == "succeeded", job["error"]
    _assert_same(_outputs(stack, job_id), one_worker)
    assert stack.starts(job_id, "load_images") == 1  # stages before it were not redone
    # every part but the dead worker's ran once: the composed bands on disk were not made again
    starts = _part_starts(stack, job_id, stage)
    plan = json.loads((stack.job_folder(job_id) / "parts" / stage / "plan.json").read_text())["keys"]
    assert len(plan) <= starts < 2 * len(plan), (starts, len(plan))


def test_a_part_that_fails_is_retried_alone(stack: FaultStack, flight: int, one_worker: dict) -> None:
    stage = "detect_features"
    (stack.faults / f"fail-once-part-{stage}").touch()
    job = stack.wait_for_end(stack.new_job(flight, **OPTIONS), 180)
    assert job["status"] == "succeeded", job["error"]
    assert (stack.faults / f"failed-once-{job['id']}-{stage}").exists()
    assert stack.starts(job["id"], stage) == 1  # the stage was not planned again: the part was tried again
    _assert_same(_outputs(stack, job["id"]), one_worker)


def test_a_gpu_worker_takes_the_gpu_stages_parts(stack: FaultStack, flight: int, one_worker: dict) -> None:
    """A worker on the gpu queue alone (as `fotoskhema worker --gpu N` would be, less its cpu queue): while it is
    alive, the parts of the stages that run on a GPU go to it, and nothing else does; the mosaic is the same."""
    stack.stop_worker()  # the stack's worker takes both queues: a host with a GPU worker has cpu-only ones beside
    stack.start_extra_worker(queues="cpu")
    gpu = stack.start_extra_worker(queues="gpu")
    job = stack.wait_for_end(stack.new_job(flight, **OPTIONS), 180)
    assert job["status"] == "succeeded", job["error"]
    done = _outputs(stack, job["id"])
    _assert_same(done, one_worker)
    on_gpu = {f"{host}:{pid}" for host in {w.split(":")[0] for w in done["parts"]["load_images"]["by"]}
              for pid in _children(gpu.pid)}  # fmt: skip
    gpu_stages = {spec.name for spec in PIPELINES["mosaic"] if spec.gpu}
    assert gpu_stages == {"detect_features", "match_features"}
    for stage in PARTED:
        workers = set(done["parts"][stage]["by"])
        assert (workers <= on_gpu) if stage in gpu_stages else not (workers & on_gpu), (stage, workers, on_gpu)


def test_cancel_reaches_every_part(stack: FaultStack, flight: int) -> None:
    stack.start_extra_worker()
    stage = "measure_ties"
    (stack.faults / f"hold-part-{stage}").touch()
    job_id = stack.new_job(flight, **OPTIONS)
    wait_for(lambda: len(list(stack.faults.glob(f"held-part-{job_id}-{stage}-*"))) >= 2, 120, "parts held on both")
    with stack.client() as http:
        assert http.post(f"/api/jobs/{job_id}/cancel").status_code == 200
    (stack.faults / f"hold-part-{stage}").unlink()
    job = stack.wait_for_end(job_id, 30)
    assert job["status"] == "cancelled"
    folder = stack.job_folder(job_id)
    plan = json.loads((folder / "parts" / stage / "plan.json").read_text())["keys"]
    done = list((folder / "parts" / stage).glob("part_*.json"))
    assert len(done) < len(plan)  # the parts stopped after the one each held: not all of them ran
    assert not (folder / "reports" / f"{stage}.json").exists() and not (folder / "alignment.json").exists()


def _outputs(stack: FaultStack, job_id: int) -> dict[str, Any]:
    folder = stack.job_folder(job_id)
    with rasterio.open(folder / "mosaic.tif") as src:
        pixels = src.read()
        mask = src.dataset_mask()
        profile = {k: src.profile[k] for k in ("width", "height", "count", "dtype", "crs", "transform")}
    report = json.loads((folder / "report.json").read_text())
    parts = {s: json.loads((folder / "reports" / f"{s}.json").read_text())["parts"] for s in PARTED}
    return {"pixels": pixels, "mask": mask, "profile": profile, "report": report, "parts": parts}


def _assert_same(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a["profile"] == b["profile"]
    assert np.array_equal(a["mask"], b["mask"])
    assert np.array_equal(a["pixels"], b["pixels"]), "the mosaic's pixels differ"
    assert _comparable(a["report"]) == _comparable(b["report"])


def _comparable(report: dict[str, Any]) -> dict[str, Any]:
    """The report but its timings."""
    return {k: v for k, v in report.items() if k not in ("stage_seconds",)}


def _part_starts(stack: FaultStack, job_id: int, stage: str) -> int:
    path: Path = stack.faults / f"started-part-{job_id}-{stage}"
    return len(path.read_text().splitlines()) if path.exists() else 0
