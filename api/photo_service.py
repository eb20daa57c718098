"""A flight's photos as the viewer shows them before processing: each with where a job will place it, what the
upload-time check measured and finds against the flight's other photos (``workers.photo_check.judge``), and a
signed preview; deleting a photo; previews of a job's photos (a mosaic's frames, a calibration's boards)."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import quote

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api.errors import ConflictError, InvalidInputError, NotFoundError
from api.gps_service import side_file_fixes
from api.models import FlightDetail, ImageOut
from core import accounts
from core.db import Database, Flight, Image, Job
from core.kinds import JobStatus
from core.settings import Settings
from workers.image_meta import decode_budget
from workers.photo_check import PhotoFacts, PreviewError, judge, preview_jpeg
from workers.workspace import flight_folder, job_workspace

PREVIEW_SIZES = (32, 2048)  # the smallest and largest preview a route makes, px on the longer side
PREVIEW_CACHE = "private, max-age=86400"  # a photo never changes under its URL (which names its stored file)


def flight_signature(settings: Settings, flight_id: int, created_at: Any) -> str:
    """``exp=...&sig=...`` that opens the previews of a flight's photos for a while (an <img> sends no token)."""
    key = accounts.signing_key(settings.secret_key, settings.data_dir)
    scope = accounts.flight_scope(flight_id, created_at)
    return "&".join(f"{k}={v}" for k, v in accounts.sign(key, scope, settings.signed_url_seconds).items())


def flight_detail(db: Database, settings: Settings, flight_id: int) -> FlightDetail:
    """The flight with its photos, judged against each other, and the signature of their previews."""
    with db.session() as s:
        flight = s.get(Flight, flight_id)
        if flight is None:
            raise NotFoundError(f"flight {flight_id} not found")
        signature = flight_signature(settings, flight_id, flight.created_at)
        images = judged_images(s, settings, flight, signature)
        return FlightDetail(
            id=flight.id,
            name=flight.name,
            description=flight.description,
            created_at=flight.created_at,
            image_count=len(images),
            images=images,
            signature=signature,
        )


def judged_image(db: Database, settings: Settings, flight_id: int, image_id: int) -> ImageOut | None:
    """One photo as ``flight_detail`` answers it (judged against its flight, its preview signed)."""
    return next((i for i in flight_detail(db, settings, flight_id).images if i.id == image_id), None)


def judged_images(s: Session, settings: Settings, flight: Flight, signature: str) -> list[ImageOut]:
    """Every photo of ``flight`` as ``ImageOut``, with its position's source and the check's issues."""
    try:
        _, fixes = side_file_fixes(settings.data_dir, flight.id)
    except InvalidInputError:  # a side file edited by hand since: jobs refuse it, and say so then
        fixes = {}
    images = sorted(flight.images, key=lambda i: i.seq)
    sources = {i.id: _gps_source(i, fixes) for i in images}
    facts = [
        PhotoFacts(i.id, i.filename, i.width, i.height, sources[i.id] is not None, (i.meta or {}).get("quality"))
        for i in images
    ]
    issues = judge(facts)
    return [image_out(i, sources[i.id], fixes, issues[i.id], signature) for i in images]


def _gps_source(image: Image, fixes: dict[str, Any]) -> str | None:
    if image.filename in fixes:
        return "side_file"
    return "exif" if (image.meta or {}).get("gps") else None


def image_out(
    image: Image,
    source: str | None = None,
    fixes: dict[str, Any] | None = None,
    issues: list[dict[str, str]] | None = None,
    signature: str = "",
) -> ImageOut:
    meta = image.meta or {}
    fix = (fixes or {}).get(image.filename) if source == "side_file" else None
    position = {"lat": fix.lat, "lon": fix.lon, "alt": fix.alt} if fix is not None else meta.get("gps")
    version = quote(image.stored_name[:14])  # a new photo that takes a deleted one's id gets another URL
    preview = f"/api/flights/{image.flight_id}/images/{image.id}/preview?v={version}"
    return ImageOut.model_validate(
        {
            "id": image.id,
            "seq": image.seq,
            "filename": image.filename,
            "stored_name": image.stored_name,
            "size_bytes": image.size_bytes,
            "width": image.width,
            "height": image.height,
            "gps": meta.get("gps"),
            **{k: meta.get(k) for k in ("focal_length_mm", "focal_length_35mm", "yaw", "pitch", "roll")},
            "gps_source": source if source is not None else ("exif" if meta.get("gps") else None),
            "position": position,
            "quality": meta.get("quality"),
            "issues": issues or [],
            "preview_url": f"{preview}&{signature}" if signature else preview,
        }
    )


def delete_image(db: Database, settings: Settings, flight_id: int, image_id: int) -> None:
    """Delete one photo of a flight with its file; 409 while a job of the flight is waiting or running (its
    photos are being read). Jobs that have ended keep their outputs."""
    with db.session() as s:
        image = s.get(Image, image_id)
        if image is None or image.flight_id != flight_id:
            raise NotFoundError(f"photo {image_id} not found in flight {flight_id}")
        active = [JobStatus.queued.value, JobStatus.running.value]
        busy = s.scalar(select(func.min(Job.id)).where(Job.flight_id == flight_id, Job.status.in_(active)))
        if busy is not None:
            raise ConflictError(
                f"job {busy} of flight {flight_id} is using its photos: delete photos once it has ended (or cancel it)"
            )
        path = flight_folder(settings.data_dir, flight_id) / image.stored_name
        s.delete(image)
    path.unlink(missing_ok=True)


def image_preview(db: Database, settings: Settings, flight_id: int, image_id: int, size: int) -> bytes:
    """A JPEG of photo ``image_id`` of the flight, at most ``size`` px on its longer side."""
    with db.session() as s:
        image = s.get(Image, image_id)
        if image is None or image.flight_id != flight_id:
            raise NotFoundError(f"photo {image_id} not found in flight {flight_id}")
        path = flight_folder(settings.data_dir, flight_id) / image.stored_name
    return _preview(settings, path, size, f"photo {image_id}")


def job_photo_preview(settings: Settings, job_id: int, index: int, size: int) -> bytes:
    """A JPEG of photo ``index`` (0-based, the job's input order: a mosaic's frame index) of a job."""
    try:
        frames = job_workspace(settings.data_dir, job_id).load_inputs()
    except (FileNotFoundError, ValueError):  # a job recorded without inputs has no photos
        frames = []
    if not 0 <= index < len(frames):
        raise NotFoundError(f"job {job_id} has no photo {index} (it has {len(frames)})")
    path = Path(str(frames[index].get("path", "")))
    # a job's inputs are its own photos or its flight's, all under the data directory; nothing else is served
    if not path.resolve().is_relative_to(Path(settings.data_dir).resolve()):
        raise NotFoundError(f"job {job_id} has no photo {index}")
    return _preview(settings, path, size, f"photo {index} of job {job_id}")


def _preview(settings: Settings, path: Path, size: int, what: str) -> bytes:
    if not path.is_file():
        raise NotFoundError(f"{what} is no longer stored")
    budget = decode_budget(settings.image_decode_budget_bytes)
    try:
        return preview_jpeg(path, size, budget.hold)
    except PreviewError as exc:
        raise ConflictError(f"{what} has no preview: {exc}") from None
