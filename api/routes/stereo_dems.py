"""Stereo DEMs: a disparity map of two photos of the same ground and, for a georeferenced (RPC) pair, a DSM."""

from __future__ import annotations

from fastapi import APIRouter, File, Form, UploadFile

from api import stereo_dem_service as service
from api.auth import UserDep
from api.deps import DbDep, JobId, QueueDep, SettingsDep
from api.models import JobOut, JobResultOut
from api.photo_jobs import parse_options

router = APIRouter(prefix="/api", tags=["stereo DEM"])

OPTIONS_HELP = (
    "JSON object (see StereoDemConfig): geometry (auto, rectified, rig, uncalibrated, rpc), rectified: true, "
    'rig_job (a stereo-rig job id), method (sgbm or local), num_disparities, min_disparity, e.g. {"method": "local"}'
)


@router.post("/stereo-dems", status_code=202, response_model=JobOut)
async def create_stereo_dem(
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    queue: QueueDep,
    left: list[UploadFile] = File(..., description="the left photo (JPEG, PNG or TIFF; a GeoTIFF with RPCs)"),
    right: list[UploadFile] = File(..., description="the right photo, of the same ground"),
    options: str = Form("", description=OPTIONS_HELP),
) -> JobOut:
    """Match a stereo pair: ``disparity.tif`` and ``confidence.tif`` in the left view, and for an RPC pair
    ``dsm.tif`` (metres above the ellipsoid, UTM) with ``dsm_mask.tif``; a rig pair gives ``depth.tif``."""
    return await service.create_stereo_dem(db, settings, queue, left, right, parse_options(options), owner=principal)


@router.get("/stereo-dems/{job_id}", response_model=JobResultOut)
def get_stereo_dem(job_id: JobId, db: DbDep, settings: SettingsDep) -> JobResultOut:
    """The job and, once finished, ``report.json``: geometry, disparity range and shares, DSM figures, legend."""
    return service.get_stereo_dem(db, settings, job_id)
