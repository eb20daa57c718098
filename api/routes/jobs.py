"""Jobs: create, follow (JSON or Server-Sent Events), cancel, download outputs."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse

from api import job_service, photo_service
from api.auth import UserDep, Viewer, job_signature, link_signature, owner_filter
from api.deps import DbDep, FlightFilter, JobId, PhotoIndex, PreviewSize, QueueDep, SettingsDep
from api.errors import ConflictError, NotFoundError
from api.models import JobCreate, JobOut, OutputOut, OutputsOut
from api.stac import stac_item
from api.zipstream import zip_chunks
from core.kinds import JobStatus
from workers.workspace import job_workspace

router = APIRouter(prefix="/api/jobs", tags=["jobs"])

MEDIA_TYPES = {
    ".tif": "image/tiff; application=geotiff; profile=cloud-optimized",
    ".json": "application/json",
    ".geojson": "application/geo+json",
    ".csv": "text/csv",
    ".png": "image/png",
    ".html": "text/html; charset=utf-8",
    ".svg": "image/svg+xml",
}
# The report and its pictures open in the browser, as documents with no script, no request to anywhere and an
# origin of their own (sandbox): whatever a photo's name held, it cannot reach the viewer's token.
INLINE_SUFFIXES = frozenset({".html", ".svg"})
JPEG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/jpeg": {}}}}
DOCUMENT_POLICY = "default-src 'none'; style-src 'unsafe-inline'; img-src data:; sandbox"


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
    """Server-Sent Events: ``progress`` with the job JSON (its ``eta`` too) at every change, then ``end`` when it
    finishes, or ``deleted`` (``{"id": ...}``) when it is deleted meanwhile: the stream ends cleanly either way (a
    stream cut short is an error in the browser, and EventSource would reconnect)."""
    job_service.get_job(db, job_id)  # 404 before the stream starts

    async def stream() -> AsyncIterator[str]:
        last = ""
        while not await request.is_disconnected():
            try:
                job = await asyncio.to_thread(job_service.get_job_live, db, job_id)
            except NotFoundError:
                yield f'event: deleted\ndata: {{"id": {job_id}}}\n\n'
                return
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
        all_zip_url=f"{request.url_for('download_all', job_id=job_id)}?{signature}" if outputs else None,
        outputs=[
            OutputOut(
                name=name,
                size_bytes=path.stat().st_size,
                url=f"{request.url_for('download_output', job_id=job_id, name=name)}?{signature}",
            )
            for name, path in outputs.items()
        ],
    )


@router.get("/{job_id}/outputs/all.zip", name="download_all", responses={200: {"content": {"application/zip": {}}}})
def download_all(job_id: JobId, db: DbDep, settings: SettingsDep) -> StreamingResponse:
    """Every output of the job in one ZIP, under the names /outputs lists, written as it is sent."""
    job_service.get_job(db, job_id)
    outputs = job_workspace(settings.data_dir, job_id).outputs()
    if not outputs:
        raise ConflictError(f"job {job_id} has no outputs yet")
    headers = {"Content-Disposition": f'attachment; filename="job{job_id}_all.zip"'}
    return StreamingResponse(zip_chunks(outputs.items()), media_type="application/zip", headers=headers)


@router.get("/{job_id}/outputs/{name}", name="download_output")
def download_output(job_id: JobId, name: str, db: DbDep, settings: SettingsDep) -> FileResponse:
    """Download one output by its public name (never a path: only names listed by /outputs resolve). The HTML
    report and its SVG pictures open in the browser (sandboxed); the rest downloads."""
    job_service.get_job(db, job_id)
    path = job_workspace(settings.data_dir, job_id).outputs().get(name)
    if path is None:
        raise NotFoundError(f"job {job_id} has no output named {name!r}")
    inline = path.suffix in INLINE_SUFFIXES
    return FileResponse(
        path,
        media_type=MEDIA_TYPES.get(path.suffix, "application/octet-stream"),
        filename=f"job{job_id}_{name}",
        content_disposition_type="inline" if inline else "attachment",
        headers={"Content-Security-Policy": DOCUMENT_POLICY, "X-Content-Type-Options": "nosniff"} if inline else None,
    )


@router.get("/{job_id}/photos/{index}/preview", name="job_photo_preview", responses=JPEG)
def job_photo_preview(job_id: JobId, index: PhotoIndex, settings: SettingsDep, size: PreviewSize = 1024) -> Response:
    """A reduced JPEG of the job's photo ``index`` (its input order, 0-based: a mosaic footprint's ``index``, a
    calibration's photos as uploaded), at most ``size`` px on its longer side; opened by the job's signature."""
    jpeg = photo_service.job_photo_preview(settings, job_id, index, size)
    return Response(jpeg, media_type="image/jpeg", headers={"Cache-Control": photo_service.PREVIEW_CACHE})


@router.get("/{job_id}/stac.json", name="stac_item", responses={200: {"content": {"application/geo+json": {}}}})
def get_stac_item(job_id: JobId, request: Request, viewer: Viewer, db: DbDep, settings: SettingsDep) -> JSONResponse:
    """The succeeded job as a STAC 1.1 item (projection extension): mosaic, DSM when present, report and
    footprints as assets with signed URLs; opened by a signed URL, it hands on that signature."""
    job = job_service.get_job(db, job_id)
    ws = job_workspace(settings.data_dir, job_id)
    outputs = ws.outputs()
    if job.status != JobStatus.succeeded or "mosaic.tif" not in outputs:
        raise ConflictError(f"job {job_id} has no finished mosaic (status: {job.status}); a STAC item needs one")
    signature = link_signature(request, viewer, settings, job_id, job.created_at)
    item = stac_item(
        job,
        outputs,
        ws.load_report(),
        _capture_times(ws),
        _item_links(request, job, signature, outputs),
        job_service.flight_name(db, job.flight_id),
    )
    return JSONResponse(item, media_type="application/geo+json")


def _item_links(request: Request, job: JobOut, signature: str, outputs: dict[str, Any]) -> dict[str, str]:
    links = {name: f"{request.url_for('download_output', job_id=job.id, name=name)}?{signature}" for name in outputs}
    links["self"] = str(request.url_for("stac_item", job_id=job.id))
    links["viewer"] = f"{str(request.base_url).rstrip('/')}/#/jobs/{job.id}"
    zero = str(request.url_for("tms_tile_png", job_id=job.id, tms_id="WebMercatorQuad", z=0, x=0, y=0))
    links["xyz"] = zero.removesuffix("/0/0/0.png") + "/{z}/{x}/{y}.png?" + signature
    links["wmts"] = f"{request.url_for('wmts_capabilities', job_id=job.id, tms_id='WebMercatorQuad')}?{signature}"
    return links


def _capture_times(ws: Any) -> list[str]:
    try:
        return [f["datetime"] for f in ws.load_inputs() if isinstance(f.get("datetime"), str)]
    except (OSError, ValueError, KeyError, TypeError):
        return []
