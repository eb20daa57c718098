"""Crack surveys of a specimen (a plate or a mesh): photos per load stage, rectified, cracks measured and compared."""

from __future__ import annotations

from fastapi import APIRouter, File, Form, UploadFile

from api import crack_survey_service as service
from api.auth import UserDep
from api.deps import DbDep, JobId, QueueDep, SettingsDep
from api.models import JobOut, JobResultOut
from api.photo_jobs import parse_options

router = APIRouter(prefix="/api", tags=["crack survey"])

OPTIONS_HELP = (
    "JSON object (see CrackSurveyConfig): camera (camera JSON) or calibration_job (id), specimen "
    "{width_mm, height_mm} for a plate or {mesh: file name, plane: null or 3 points} for a mesh, "
    "stages [{label, load, photos: [{image, control_points: [{pixel: [x, y], model: [X, Y, Z]}]}]}], "
    "mm_per_px"
)
MODEL_HELP = "the specimen's triangle mesh in mm (OBJ, PLY or STL) when options.specimen.mesh names it"


@router.post("/crack-surveys", status_code=202, response_model=JobOut)
async def create_crack_survey(
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    queue: QueueDep,
    files: list[UploadFile] = File(default=[], description="the photos the stages name"),
    options: str = Form("", description=OPTIONS_HELP),
    model: UploadFile | None = File(default=None, description=MODEL_HELP),
) -> JobOut:
    """Measure the cracks of a specimen at each load stage and compare consecutive stages."""
    return await service.create_crack_survey(db, settings, queue, files, parse_options(options), model, owner=principal)


@router.get("/crack-surveys/{job_id}", response_model=JobResultOut)
def get_crack_survey(job_id: JobId, db: DbDep, settings: SettingsDep) -> JobResultOut:
    """The job and, once finished, ``report.json``: control point residuals, cracks per stage, comparisons."""
    return service.get_crack_survey(db, settings, job_id)
