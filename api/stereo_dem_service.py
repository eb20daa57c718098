"""Stereo DEM jobs: two photos of the same ground and how their geometry is known, checked whole before the
job is recorded (one photo a side, the rig of a finished stereo-rig job, RPCs in both GeoTIFFs for an RPC
pair, sizes that fit the geometry), then matched, and triangulated when the pair has a camera model.

``geometry: auto`` is decided here, from what was uploaded: the job's ``config.json`` holds the geometry it
runs with, so its stages never guess.
"""

from __future__ import annotations

from typing import Any

from fastapi import UploadFile

from api.errors import InvalidInputError
from api.job_service import validated_config
from api.models import JobOut, JobResultOut
from api.photo_jobs import job_of_kind, record_photo_job
from api.queue import JobQueue
from core.accounts import Principal
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.algorithms.calibration import StereoRig
from workers.config import MAX_ID, MAX_STEREO_PIXELS, StereoDemConfig
from workers.workspace import job_workspace


async def create_stereo_dem(
    db: Database,
    settings: Settings,
    queue: JobQueue,
    left: list[UploadFile],
    right: list[UploadFile],
    options: dict[str, Any],
    *,
    owner: Principal | None = None,
) -> JobOut:
    """Record and queue a ``stereo_dem`` job over one ``left`` and one ``right`` photo, owned by ``owner``."""
    for side, files in (("left", left), ("right", right)):
        if len(files) != 1:
            raise InvalidInputError(f"{side}: a stereo DEM takes exactly one {side} photo, got {len(files)}")
    config = validated_config(JobKind.stereo_dem, with_rig(db, settings, options, owner))
    rig = _rig(config)

    def check(frames: list[dict[str, Any]]) -> None:
        by_side = {f["side"]: f for f in frames}
        config["geometry"] = _geometry(config, by_side, rig)  # written with the job once every check passed

    return await record_photo_job(
        db,
        settings,
        queue,
        JobKind.stereo_dem,
        options,
        config,
        {"left": left, "right": right},
        check,
        owner_id=owner.user_id if owner else None,
    )


def with_rig(db: Database, settings: Settings, options: dict[str, Any], owner: Principal | None) -> dict[str, Any]:
    """``options`` with ``rig`` taken from the finished stereo-rig job ``options.rig_job`` names (one ``owner``
    may see)."""
    job_id = options.get("rig_job")
    if job_id is None:
        return options
    if options.get("rig") is not None:
        raise InvalidInputError("options: give rig or rig_job, not both")
    if not isinstance(job_id, int) or isinstance(job_id, bool) or not 1 <= job_id <= MAX_ID:
        raise InvalidInputError(f"options.rig_job: the id (an integer from 1 to {MAX_ID}) of a stereo-rig job")
    with db.session() as s:
        job = s.get(Job, job_id)
        if (
            job is None
            or job.kind != JobKind.stereo_calibration
            or (owner is not None and not owner.may_see(job.owner_id))
        ):
            raise InvalidInputError(f"options.rig_job: there is no stereo-rig job {job_id}")
        if job.status != JobStatus.succeeded:
            raise InvalidInputError(
                f"options.rig_job: stereo-rig job {job_id} is {job.status}; use one that has succeeded"
            )
    ws = job_workspace(settings.data_dir, job_id)
    if not ws.has_calibration():
        raise InvalidInputError(f"options.rig_job: stereo-rig job {job_id} has no rig")
    return {**options, "rig": ws.load_calibration().get("rig")}


def _rig(config: dict[str, Any]) -> StereoRig | None:
    if config["rig"] is None:
        return None
    try:
        return StereoRig.from_json(config["rig"])
    except ValueError as exc:
        raise InvalidInputError(f"options.rig: {exc}") from None


def _geometry(config: dict[str, Any], frames: dict[str, dict[str, Any]], rig: StereoRig | None) -> str:
    """The geometry the job runs with (``auto`` decided); ``InvalidInputError`` when the photos do not fit it."""
    left, right = frames["left"], frames["right"]
    for frame in (left, right):
        if frame["width"] * frame["height"] > MAX_STEREO_PIXELS:
            raise InvalidInputError(
                f"{frame['name']} is {frame['width']}x{frame['height']} px, over the {MAX_STEREO_PIXELS} px a stereo "
                "photo may have; cut both photos to the area of interest"
            )
    geometry = StereoDemConfig.model_validate(config).resolved_geometry(bool(left.get("rpc") and right.get("rpc")))
    if geometry == "rpc":
        for frame in (left, right):
            if not frame.get("rpc"):
                raise InvalidInputError(
                    f"{frame['name']} has no usable RPC metadata; geometry 'rpc' needs two GeoTIFFs with RPCs"
                )
    if geometry == "rectified" and _size(left) != _size(right):
        raise InvalidInputError(
            f"a rectified pair has one size: {left['name']} is {_size(left)} px, {right['name']} {_size(right)} px"
        )
    if geometry == "rig" and rig is not None:
        for frame, camera in ((left, rig.left), (right, rig.right)):
            if _size(frame) != f"{camera.width}x{camera.height}":
                raise InvalidInputError(
                    f"{frame['name']} is {_size(frame)} px but the rig's {frame['side']} camera is "
                    f"{camera.width}x{camera.height}; use the rig's photos at full size"
                )
    return str(geometry)


def _size(frame: dict[str, Any]) -> str:
    return f"{frame['width']}x{frame['height']}"


def get_stereo_dem(db: Database, settings: Settings, job_id: int) -> JobResultOut:
    """The job and, once written, its ``report.json``."""
    job = job_of_kind(db, job_id, (JobKind.stereo_dem,), "stereo DEM")
    ws = job_workspace(settings.data_dir, job_id)
    return JobResultOut(job=job, result=ws.load_report() if ws.has_report() else None)
