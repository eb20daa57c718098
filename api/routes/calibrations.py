"""Camera calibrations (chessboards, hand marks, plumb lines) and stereo rigs, and measuring with a rig."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, File, Form, UploadFile

from api import calibration_service as service
from api.auth import UserDep
from api.deps import DbDep, JobId, QueueDep, SettingsDep
from api.models import JobOut, JobResultOut, MarksUpdate, MeasureRequest
from api.photo_jobs import parse_options
from api.stereo_service import measure_with_rig
from core.kinds import JobKind

router = APIRouter(prefix="/api", tags=["calibration"])

OPTIONS_HELP = 'JSON object of options (see CalibrationConfig / StereoCalibrationConfig), e.g. {"pattern": [9, 6]}'


@router.post("/calibrations", status_code=202, response_model=JobOut)
async def create_calibration(
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    queue: QueueDep,
    files: list[UploadFile] = File(default=[], description="photos of the board"),
    options: str = Form("", description=OPTIONS_HELP),
) -> JobOut:
    """Calibrate one camera: chessboard photos (corners found automatically), hand marks, or plumb lines."""
    return await service.create_calibration(
        db, settings, queue, JobKind.calibration, {"": files}, parse_options(options), owner=principal
    )


@router.get("/calibrations/{job_id}", response_model=JobResultOut)
def get_calibration(job_id: JobId, db: DbDep, settings: SettingsDep) -> JobResultOut:
    """The job and, once solved, the camera JSON, RMS, per-point reprojection errors and parameter sigmas."""
    return service.get_calibration(db, settings, job_id, JobKind.calibration)


@router.get("/calibrations/{job_id}/photos")
def calibration_photos(job_id: JobId, db: DbDep, settings: SettingsDep) -> dict[str, Any]:
    """The photos of a calibration in upload order, each with its size, the board corners found in it (or why
    none) and what the marks did with it; ``index`` names its preview (``/api/jobs/{id}/photos/{index}/preview``)."""
    return service.calibration_photos(db, settings, job_id, JobKind.calibration)


@router.put("/calibrations/{job_id}/markers", status_code=202, response_model=JobOut)
def replace_markers(job_id: JobId, body: MarksUpdate, db: DbDep, settings: SettingsDep, queue: QueueDep) -> JobOut:
    """Replace or remove the marks of some photos, then solve again."""
    return service.replace_markers(db, settings, queue, job_id, body, JobKind.calibration)


@router.post("/stereo-rigs", status_code=202, response_model=JobOut)
async def create_stereo_rig(
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    queue: QueueDep,
    left: list[UploadFile] = File(..., description="left photos, in pair order"),
    right: list[UploadFile] = File(..., description="right photos, same order"),
    options: str = Form("", description=OPTIONS_HELP),
) -> JobOut:
    """Calibrate a two-camera rig from paired chessboard photos: rotation, baseline, RMS."""
    return await service.create_calibration(
        db,
        settings,
        queue,
        JobKind.stereo_calibration,
        {"left": left, "right": right},
        parse_options(options),
        owner=principal,
    )


@router.get("/stereo-rigs/{job_id}", response_model=JobResultOut)
def get_stereo_rig(job_id: JobId, db: DbDep, settings: SettingsDep) -> JobResultOut:
    return service.get_calibration(db, settings, job_id, JobKind.stereo_calibration)


@router.get("/stereo-rigs/{job_id}/photos")
def stereo_rig_photos(job_id: JobId, db: DbDep, settings: SettingsDep) -> dict[str, Any]:
    """The photos of a stereo rig (left ones, then right ones, ``pair`` their order), as for a calibration."""
    return service.calibration_photos(db, settings, job_id, JobKind.stereo_calibration)


@router.put("/stereo-rigs/{job_id}/markers", status_code=202, response_model=JobOut)
def replace_rig_markers(job_id: JobId, body: MarksUpdate, db: DbDep, settings: SettingsDep, queue: QueueDep) -> JobOut:
    """Replace or remove the marks of some of a rig's photos (left or right, by name), then solve again."""
    return service.replace_markers(db, settings, queue, job_id, body, JobKind.stereo_calibration)


@router.post("/stereo-rigs/{job_id}/measure")
def measure(job_id: JobId, body: MeasureRequest, db: DbDep, settings: SettingsDep) -> dict:
    """3D points (left camera frame, mm) of pixel pairs by the midpoint of the two rays, their distances
    and uncertainties."""
    return measure_with_rig(db, settings, job_id, body)
