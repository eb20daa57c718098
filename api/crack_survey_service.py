"""Crack-survey jobs: photos of a specimen (a plate or a mesh) per load stage, with control points, kept in
the job's folder.

The request is checked whole before anything is recorded: options (control points: at least four per
photo on a plate, six on a mesh, on the specimen, not on one line), the camera (given, or a finished
calibration job's), the mesh (it parses; the control points lie on it), and that the uploaded photos are
exactly those the options name, each of the camera's size with its control points inside it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from fastapi import UploadFile
from starlette.concurrency import run_in_threadpool

from api.errors import InvalidInputError, TooLargeError
from api.job_service import validated_config
from api.models import JobOut, JobResultOut
from api.photo_jobs import job_of_kind, record_photo_job
from api.queue import JobQueue
from api.uploads import display_name
from core.accounts import Principal
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.algorithms.geometry import Camera
from workers.algorithms.specimen import Mesh, best_fit_plane, distance_to_surface, plane_through, read_mesh
from workers.config import MAX_ID, check_raster_size
from workers.workspace import job_workspace, specimen_model_path

ON_MESH_TOLERANCE = 0.005  # a mesh's control points must lie this close to its surface, times its diagonal
ON_MESH_MIN_MM = 1.0  # ... or this close, mm, whichever is larger


async def create_crack_survey(
    db: Database,
    settings: Settings,
    queue: JobQueue,
    files: list[UploadFile],
    options: dict[str, Any],
    model: UploadFile | None = None,
    *,
    owner: Principal | None = None,
) -> JobOut:
    """Record and queue a crack survey over ``files``, the photos its ``options.stages`` name, and ``model``,
    the specimen's mesh when ``options.specimen.mesh`` names one; it belongs to ``owner``."""
    config = validated_config(JobKind.crack_survey, with_calibration_camera(db, settings, options, owner))
    try:
        camera = Camera.from_json(config["camera"])
    except ValueError as exc:
        raise InvalidInputError(f"options.camera: {exc}") from None
    attachments = await _mesh_attachment(config, model, settings.max_mesh_bytes)
    photos = {p["image"]: p for stage in config["stages"] for p in stage["photos"]}

    def check(frames: list[dict[str, Any]]) -> None:
        _check_names(list(photos), [f["name"] for f in frames])
        for frame in frames:
            _check_photo(frame, photos[frame["name"]], camera)

    return await record_photo_job(
        db,
        settings,
        queue,
        JobKind.crack_survey,
        options,
        config,
        {"": files},
        check,
        attachments,
        owner_id=owner.user_id if owner else None,
    )


def with_calibration_camera(
    db: Database, settings: Settings, options: dict[str, Any], owner: Principal | None = None
) -> dict[str, Any]:
    """``options`` with ``camera`` taken from the finished calibration job ``options.calibration_job`` names
    (one ``owner`` may see)."""
    job_id = options.get("calibration_job")
    if job_id is None:
        return options
    if "camera" in options:
        raise InvalidInputError("options: give camera or calibration_job, not both")
    if not isinstance(job_id, int) or isinstance(job_id, bool) or not 1 <= job_id <= MAX_ID:
        raise InvalidInputError(f"options.calibration_job: the id (an integer from 1 to {MAX_ID}) of a calibration job")
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.kind != JobKind.calibration or (owner is not None and not owner.may_see(job.owner_id)):
            raise InvalidInputError(f"options.calibration_job: there is no calibration job {job_id}")
        if job.status != JobStatus.succeeded:
            raise InvalidInputError(
                f"options.calibration_job: calibration job {job_id} is {job.status}; use one that has succeeded"
            )
    result = job_workspace(settings.data_dir, job_id).load_calibration()
    return {**options, "camera": result["camera"]}


async def _mesh_attachment(config: dict[str, Any], model: UploadFile | None, max_bytes: int) -> dict[str, bytes]:
    """The uploaded mesh, read, parsed and checked against the control points: {path in the job: bytes}."""
    name = config["specimen"]["mesh"]
    if name is None:
        if model is not None:
            raise InvalidInputError(
                "a model file was uploaded but options.specimen is a plate; "
                "name the file in options.specimen.mesh to use it"
            )
        return {}
    if model is None or display_name(model.filename) != name:
        raise InvalidInputError(f"options.specimen.mesh names {name!r}: upload that file as the 'model' field")
    data = await model.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise TooLargeError(f"{name}: file is larger than {max_bytes} bytes")
    await run_in_threadpool(_check_mesh, data, name, config)  # parsing is slow: not on the event loop
    return {str(specimen_model_path(name)): data}


def _check_mesh(data: bytes, name: str, config: dict[str, Any]) -> None:
    """The mesh in ``data`` parses; its plane, its raster's size and the control points on it are valid."""
    plane = config["specimen"]["plane"]
    try:
        mesh = read_mesh(data, name)
        frame = best_fit_plane(mesh) if plane is None else plane_through(mesh, np.array(plane))
    except ValueError as exc:
        raise InvalidInputError(f"options.specimen: {exc}") from None
    width_mm, height_mm = frame.to_plane(mesh.vertices).max(axis=0)[:2]  # as rectify_specimen sizes it
    try:
        if config["mm_per_px"] is not None:  # None: the photos' sampling, checked when they are oriented
            check_raster_size(float(width_mm), float(height_mm), config["mm_per_px"])
    except ValueError as exc:
        raise InvalidInputError(f"options.mm_per_px: {name}: {exc}") from None
    _check_on_mesh(mesh, config["stages"])


def _check_on_mesh(mesh: Mesh, stages: list[dict[str, Any]]) -> None:
    """Every control point within ``ON_MESH_TOLERANCE`` of the model's surface."""
    tolerance = max(ON_MESH_MIN_MM, ON_MESH_TOLERANCE * mesh.diagonal_mm)
    for s, stage in enumerate(stages):
        for photo in stage["photos"]:
            model = np.array([p["model"] for p in photo["control_points"]], dtype=np.float64)
            distances = distance_to_surface(mesh, model)
            worst = int(np.argmax(distances))
            if distances[worst] > tolerance:
                raise InvalidInputError(
                    f"options.stages[{s}] photo {photo['image']}: control point {worst} at model "
                    f"{model[worst].tolist()} is {distances[worst]:.2f} mm from the model's surface "
                    f"(at most {tolerance:.2f} mm)"
                )


def _check_names(named: list[str], uploaded: list[str]) -> None:
    if missing := [n for n in named if n not in uploaded]:
        raise InvalidInputError(f"options.stages name photo(s) that were not uploaded: {', '.join(missing)}")
    if extra := [n for n in uploaded if n not in named]:
        raise InvalidInputError(f"uploaded photo(s) that no stage of options.stages names: {', '.join(extra)}")


def _check_photo(frame: dict[str, Any], photo: dict[str, Any], camera: Camera) -> None:
    if (frame["width"], frame["height"]) != (camera.width, camera.height):
        raise InvalidInputError(
            f"{frame['name']} is {frame['width']}x{frame['height']} px but the camera is "
            f"{camera.width}x{camera.height}; every photo must come from the calibrated camera "
            "at full size"
        )
    for k, point in enumerate(photo["control_points"]):
        x, y = point["pixel"]
        if not (-0.5 <= x <= camera.width - 0.5 and -0.5 <= y <= camera.height - 0.5):
            raise InvalidInputError(f"{frame['name']}: control point {k} at pixel [{x}, {y}] is outside the photo")


def get_crack_survey(db: Database, settings: Settings, job_id: int) -> JobResultOut:
    job = job_of_kind(db, job_id, (JobKind.crack_survey,), "crack survey")
    ws = job_workspace(settings.data_dir, job_id)
    return JobResultOut(job=job, result=ws.load_report() if ws.has_report() else None)
