"""Crack-survey jobs: photos of a planar specimen per load stage, with control points, kept in the job's folder.

The request is checked whole before anything is recorded: options (control points: at least four per
photo, on the specimen, not on one line), the camera, and that the uploaded photos are exactly those the
options name, each of the camera's size with its control points inside it.
"""

from __future__ import annotations

from typing import Any

from fastapi import UploadFile

from api.db import Database
from api.errors import InvalidInputError
from api.job_service import validated_config
from api.models import JobOut, JobResultOut
from api.photo_jobs import job_of_kind, record_photo_job
from api.queue import JobQueue
from api.settings import Settings
from workers.algorithms.camera import Camera
from workers.workspace import job_workspace, read_json

KIND = "crack_survey"


async def create_crack_survey(db: Database, settings: Settings, queue: JobQueue, files: list[UploadFile],
                              options: dict[str, Any]) -> JobOut:
    """Record and queue a crack survey over ``files``, the photos its ``options.stages`` name."""
    config = validated_config(KIND, options)
    try:
        camera = Camera.from_json(config["camera"])
    except ValueError as exc:
        raise InvalidInputError(f"options.camera: {exc}") from None
    photos = {p["image"]: p for stage in config["stages"] for p in stage["photos"]}

    def check(frames: list[dict[str, Any]]) -> None:
        _check_names(list(photos), [f["name"] for f in frames])
        for frame in frames:
            _check_photo(frame, photos[frame["name"]], camera)

    return await record_photo_job(db, settings, queue, KIND, options, config, {"": files}, check)


def _check_names(named: list[str], uploaded: list[str]) -> None:
    if missing := [n for n in named if n not in uploaded]:
        raise InvalidInputError(f"options.stages name photo(s) that were not uploaded: {', '.join(missing)}")
    if extra := [n for n in uploaded if n not in named]:
        raise InvalidInputError(f"uploaded photo(s) that no stage of options.stages names: {', '.join(extra)}")


def _check_photo(frame: dict[str, Any], photo: dict[str, Any], camera: Camera) -> None:
    if (frame["width"], frame["height"]) != (camera.width, camera.height):
        raise InvalidInputError(f"{frame['name']} is {frame['width']}x{frame['height']} px but the camera is "
                                f"{camera.width}x{camera.height}; every photo must come from the calibrated camera "
                                "at full size")
    for k, point in enumerate(photo["control_points"]):
        x, y = point["pixel"]
        if not (-0.5 <= x <= camera.width - 0.5 and -0.5 <= y <= camera.height - 0.5):
            raise InvalidInputError(f"{frame['name']}: control point {k} at pixel [{x}, {y}] is outside the photo")


def get_crack_survey(db: Database, settings: Settings, job_id: int) -> JobResultOut:
    job = job_of_kind(db, job_id, (KIND,), "crack survey")
    report = job_workspace(settings.data_dir, job_id).report_file()
    return JobResultOut(job=job, result=read_json(report) if report.exists() else None)
