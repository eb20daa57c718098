"""Flights and their photos."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, File, Response, UploadFile
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool

from api import job_service, photo_service
from api.auth import UserDep, Viewer, owner_filter
from api.deps import DbDep, FlightId, ImageId, PreviewSize, SettingsDep
from api.gcp_service import MAX_GCP_BYTES, store_gcps
from api.gps_service import store_gps
from api.limits import MAX_GPS_BYTES
from api.models import FlightCreate, FlightDetail, FlightOut, UploadResult
from api.uploads import display_name, store_uploads
from core.db import Flight, Image

JPEG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/jpeg": {}}}}  # OpenAPI: previews are JPEG

router = APIRouter(prefix="/api/flights", tags=["flights"])


def flight_out(flight: Flight, image_count: int) -> FlightOut:
    return FlightOut(
        id=flight.id,
        name=flight.name,
        description=flight.description,
        created_at=flight.created_at,
        image_count=image_count,
    )


@router.post("", status_code=201, response_model=FlightOut)
def create_flight(body: FlightCreate, principal: UserDep, db: DbDep) -> FlightOut:
    with db.session() as s:
        flight = Flight(name=body.name, description=body.description, owner_id=principal.user_id)
        s.add(flight)
        s.flush()
        return flight_out(flight, 0)


@router.get("", response_model=list[FlightOut])
def list_flights(viewer: Viewer, db: DbDep) -> list[FlightOut]:
    """Your flights (every flight for an admin), newest first."""
    with db.session() as s:
        counts = select(Image.flight_id, func.count().label("n")).group_by(Image.flight_id).subquery()
        query = (
            select(Flight, func.coalesce(counts.c.n, 0))
            .outerjoin(counts, counts.c.flight_id == Flight.id)
            .order_by(Flight.id.desc())
        )
        if (owner_id := owner_filter(viewer)) is not None:
            query = query.where(Flight.owner_id == owner_id)
        rows = s.execute(query)
        return [flight_out(f, n) for f, n in rows]


@router.get("/{flight_id}", response_model=FlightDetail)
def get_flight(flight_id: FlightId, db: DbDep, settings: SettingsDep) -> FlightDetail:
    """The flight and its photos: each with its position's source, what the upload-time check measured and
    finds against the flight's other photos (``issues``), and a signed ``preview_url``."""
    return photo_service.flight_detail(db, settings, flight_id)


@router.delete("/{flight_id}", status_code=204)
def delete_flight(flight_id: FlightId, db: DbDep, settings: SettingsDep) -> Response:
    """Delete the flight with its photos, ground control points and jobs (running ones stop)."""
    job_service.delete_flight(db, settings, flight_id)
    return Response(status_code=204)


@router.post("/{flight_id}/images", status_code=201, response_model=UploadResult)
async def upload_images(
    flight_id: FlightId,
    db: DbDep,
    settings: SettingsDep,
    files: list[UploadFile] = File(..., description="one or more photos"),
) -> UploadResult:
    """Validate and store photos; answers every file's metadata and what the photo check finds (against the
    flight's other photos too), or a 4xx naming the bad file."""
    stored = {i.id for i in await store_uploads(db, settings, flight_id, files)}
    detail = await run_in_threadpool(photo_service.flight_detail, db, settings, flight_id)
    return UploadResult(images=[i for i in detail.images if i.id in stored])


@router.delete("/{flight_id}/images/{image_id}", status_code=204)
def delete_image(flight_id: FlightId, image_id: ImageId, db: DbDep, settings: SettingsDep) -> Response:
    """Delete one photo of the flight (a blurred or dark one, say) before processing; 409 while a job of the
    flight is waiting or running."""
    photo_service.delete_image(db, settings, flight_id, image_id)
    return Response(status_code=204)


@router.get("/{flight_id}/images/{image_id}/preview", name="image_preview", responses=JPEG)
def image_preview(
    flight_id: FlightId, image_id: ImageId, db: DbDep, settings: SettingsDep, size: PreviewSize = 256
) -> Response:
    """A reduced JPEG of the photo, at most ``size`` px on its longer side; opened by the token or by the
    flight's ``signature`` (``GET /api/flights/{id}``), as an ``<img>`` must."""
    jpeg = photo_service.image_preview(db, settings, flight_id, image_id, size)
    return Response(jpeg, media_type="image/jpeg", headers={"Cache-Control": photo_service.PREVIEW_CACHE})


@router.put("/{flight_id}/gcps")
async def upload_gcps(
    flight_id: FlightId,
    db: DbDep,
    settings: SettingsDep,
    file: UploadFile = File(..., description="gcp_list.txt (ODM) or ground_control_points.json (OpenSfM)"),
) -> dict:
    """Set the flight's ground control points, used by ``mode: "ortho"`` jobs; replaces earlier ones."""
    content = await file.read(MAX_GCP_BYTES + 1)
    return store_gcps(db, settings.data_dir, flight_id, display_name(file.filename), content)


@router.put("/{flight_id}/gps")
async def upload_gps(
    flight_id: FlightId,
    db: DbDep,
    settings: SettingsDep,
    file: UploadFile = File(..., description="geo.txt (ODM) or a CSV name,lat,lon,alt[,accuracy]"),
) -> dict:
    """Set the flight's GPS side file: the photos it names take their position from it, not from EXIF, in
    jobs created from now on; replaces the earlier file. Answers what it holds and each photo's GPS source."""
    content = await file.read(MAX_GPS_BYTES + 1)
    name = display_name(file.filename)
    return await run_in_threadpool(store_gps, db, settings.data_dir, flight_id, name, content)  # pyproj: off the loop
