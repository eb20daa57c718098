"""Jobs: create, follow (JSON or Server-Sent Events), cancel, download outputs."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

from fastapi import APIRouter, Request, Response
from fastapi.responses import FileResponse, StreamingResponse

from api import job_service
from api.auth import UserDep, Viewer, job_signature, owner_filter
from api.deps import DbDep, FlightFilter, JobId, QueueDep, SettingsDep
from api.errors import NotFoundError
from api.models import JobCreate, JobOut, OutputOut, OutputsOut
from core.kinds import JobStatus
from workers.workspace import job_workspace

router = APIRouter(prefix="/api/jobs", tags=["jobs"])

MEDIA_TYPES = {
    ".tif": "image/tiff; application=geotiff; profile=cloud-optimized",
    ".json": "application/json",
    ".geojson": "application/geo+json",
    ".csv": "text/csv",
    ".png": "image/png",
}


@router.post("", status_code=202, response_model=JobOut)
def create_job(body: JobCreate, principal: UserDep, db: DbDep, settings: SettingsDep, queue: QueueDep) -> JobOut:
    """Queue a job on a flight; ``options`` override the pipeline defaults (see the MosaicConfig schema)."""
    return job_service.create_job(db, settings, queue, body, principal)


@router.get("", response_model=list[JobOut])
def list_jobs(viewer: Viewer, db: DbDep, flight_id: FlightFilter = None) -> list[JobOut]:
    """Your jobs (every job for an admin), newest first."""
    return job_service.list_jobs(db, flight_id, owner_filter(viewer))


@router.get("/{job_id}", response_model=JobOut)
def get_job(job_id: JobId, db: DbDep, settings: SettingsDep) -> JobOut:
    """The job's status, progress, a ``signature`` for its tile, download and event URLs and, once it has
    succeeded, the warnings of its report."""
    job = job_service.job_with_warnings(db, settings, job_id)
    return job.model_copy(update={"signature": job_signature(settings, job_id, job.created_at)})


@router.delete("/{job_id}", status_code=204)
def delete_job(job_id: JobId, db: DbDep, settings: SettingsDep) -> Response:
    """Delete the job and its files; a running job stops at its next progress report."""
    job_service.delete_job(db, settings, job_id)
    return Response(status_code=204)


@router.post("/{job_id}/cancel", response_model=JobOut)
def cancel_job(job_id: JobId, db: DbDep) -> JobOut:
    return job_service.cancel_job(db, job_id)


@router.post("/{job_id}/retry", status_code=202, response_model=JobOut)
def retry_job(job_id: JobId, db: DbDep, settings: SettingsDep, queue: QueueDep) -> JobOut:
    """Run a failed or cancelled job again from the stage where it stopped."""
    return job_service.retry_job(db, settings, queue, job_id)


@router.get("/{job_id}/events")
async def job_events(job_id: JobId, request: Request, db: DbDep, settings: SettingsDep) -> StreamingResponse:
    """Server-Sent Events: ``progress`` with the job JSON at every change, then ``end`` when it finishes."""
    job_service.get_job(db, job_id)  # 404 before the stream starts

    async def stream() -> AsyncIterator[str]:
        last = ""
        while not await request.is_disconnected():
            job = await asyncio.to_thread(job_service.get_job, db, job_id)
            data = job.model_dump_json()
            if JobStatus(job.status).finished:
                yield f"event: end\ndata: {data}\n\n"
                return
            if data != last:
                yield f"event: progress\ndata: {data}\n\n"
                last = data
            else:
                yield ": keep-alive\n\n"
            await asyncio.sleep(settings.sse_poll_seconds)

    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(stream(), media_type="text/event-stream", headers=headers)


@router.get("/{job_id}/outputs", response_model=OutputsOut)
def list_outputs(job_id: JobId, request: Request, db: DbDep, settings: SettingsDep) -> OutputsOut:
    job = job_service.get_job(db, job_id)
    outputs = job_workspace(settings.data_dir, job_id).outputs()
    signature = job_signature(settings, job_id, job.created_at)  # a link opens without a token, for a while
    return OutputsOut(
        outputs=[
            OutputOut(
                name=name,
                size_bytes=path.stat().st_size,
                url=f"{request.url_for('download_output', job_id=job_id, name=name)}?{signature}",
            )
            for name, path in outputs.items()
        ]
    )


@router.get("/{job_id}/outputs/{name}", name="download_output")
def download_output(job_id: JobId, name: str, db: DbDep, settings: SettingsDep) -> FileResponse:
    """Download one output by its public name (never a path: only names listed by /outputs resolve)."""
    job_service.get_job(db, job_id)
    path = job_workspace(settings.data_dir, job_id).outputs().get(name)
    if path is None:
        raise NotFoundError(f"job {job_id} has no output named {name!r}")
    return FileResponse(
        path, media_type=MEDIA_TYPES.get(path.suffix, "application/octet-stream"), filename=f"job{job_id}_{name}"
    )
