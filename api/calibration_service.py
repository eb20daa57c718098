"""Calibration and stereo-rig jobs: their photos live in the job's own folder, not in a flight.

A request is checked whole (options, counts, image sizes, marks) before anything is recorded; the
photos are validated into a staging folder and moved into the job folder only once the job exists.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi import UploadFile

from api.db import Database, Job, JobStatus
from api.errors import ConflictError, InvalidInputError, NotFoundError
from api.job_service import enqueue, job_or_404, job_out, validated_config
from api.models import CalibrationOut, JobOut, MarksUpdate
from api.queue import JobQueue
from api.settings import Settings
from api.uploads import StagedFile, stage_images, stored_name
from workers.workspace import JobWorkspace, job_workspace, read_json

MIN_VIEWS = 3  # a camera (or a rig) needs boards seen from at least three directions
MIN_MARKS = 6  # marked points per image: a pose has six unknowns


def parse_options(raw: str | None) -> dict[str, Any]:
    """The multipart ``options`` field: a JSON object, or empty."""
    if not raw:
        return {}
    try:
        options = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"options: not valid JSON ({exc.msg} at character {exc.pos})") from None
    if not isinstance(options, dict):
        raise InvalidInputError("options: must be a JSON object")
    return options


async def create_calibration(db: Database, settings: Settings, queue: JobQueue, kind: str,
                             groups: dict[str, list[UploadFile]], options: dict[str, Any]) -> JobOut:
    """Record and queue a ``calibration`` or ``stereo_calibration`` job over the uploaded photos.

    ``groups`` maps a side ("" for one camera, "left"/"right" for a rig) to its photos, in order.
    """
    config = validated_config(kind, options)
    _check_counts(kind, config, groups)

    def check(frames: list[dict[str, Any]]) -> None:
        _check_sizes(kind, frames)
        _check_marks(config.get("markers", []), {f["name"] for f in frames})

    return await record_photo_job(db, settings, queue, kind, options, config, groups, check)


async def record_photo_job(db: Database, settings: Settings, queue: JobQueue, kind: str, options: dict[str, Any],
                           config: dict[str, Any], groups: dict[str, list[UploadFile]],
                           check: Callable[[list[dict[str, Any]]], None]) -> JobOut:
    """Stage and validate the photos, ``check`` their frames (raise ``InvalidInputError``), then record the
    job with its photos in its own folder and queue it; a failed request leaves nothing behind.

    Frames are ``{"name", "side", "pair", "width", "height"}``, and ``"path"`` once stored.
    """
    staging = Path(settings.data_dir) / "incoming" / uuid.uuid4().hex
    try:
        staged = {side: await stage_images(files, staging, settings) for side, files in groups.items()}
        frames = _frames(staged)
        check(frames)
        with db.session() as s:
            job = Job(flight_id=None, kind=kind, options=options, status=JobStatus.queued.value)
            s.add(job)
            s.flush()
            _write_workspace(job_workspace(settings.data_dir, job.id), staged, frames, config)
            job_id = job.id
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return enqueue(db, queue, job_id)


def _check_counts(kind: str, config: dict[str, Any], groups: dict[str, list[UploadFile]]) -> None:
    if kind == "stereo_calibration":
        left, right = len(groups.get("left", [])), len(groups.get("right", []))
        if left != right:
            raise InvalidInputError(f"a stereo rig needs pairs: {left} left and {right} right photo(s)")
        if left < MIN_VIEWS:
            raise InvalidInputError(f"a stereo rig needs at least {MIN_VIEWS} photo pairs, got {left}")
    elif config["method"] == "plumb_line":
        if len(config["lines"]) < 2 or any(len(line) < 3 for line in config["lines"]):
            raise InvalidInputError("options.lines: plumb-line calibration needs at least 2 lines of 3+ points")
        if not groups.get("") and config["image_size"] is None:
            raise InvalidInputError("options.image_size: give [width, height] or upload the photo of the lines")
    elif len(groups.get("", [])) < MIN_VIEWS:
        raise InvalidInputError(f"a calibration needs at least {MIN_VIEWS} photos of the board, "
                                f"got {len(groups.get('', []))}")


def _frames(staged: dict[str, list[StagedFile]]) -> list[dict[str, Any]]:
    frames, names = [], set()
    for side, items in staged.items():
        for n, item in enumerate(items):
            if item.display_name in names:
                raise InvalidInputError(f"{item.display_name}: two photos of this request have the same name")
            names.add(item.display_name)
            frames.append({"name": item.display_name, "side": side, "pair": n,
                           "width": item.meta["width"], "height": item.meta["height"]})
    return frames


def _check_sizes(kind: str, frames: list[dict[str, Any]]) -> None:
    """Every photo of one camera has the camera's size."""
    for side in {f["side"] for f in frames}:
        mine = [f for f in frames if f["side"] == side]
        first = mine[0]
        for f in mine[1:]:
            if (f["width"], f["height"]) != (first["width"], first["height"]):
                camera = f"the {side} camera" if side else "one camera"
                raise InvalidInputError(f"{f['name']} is {f['width']}x{f['height']} px but {first['name']} is "
                                        f"{first['width']}x{first['height']}; photos of {camera} share one size")


def _check_marks(marks: list[dict[str, Any]], names: set[str]) -> None:
    for mark in marks:
        if mark["image"] not in names:
            raise InvalidInputError(f"markers: no photo named {mark['image']!r} in this calibration")
        if mark["remove"]:
            continue
        if len(mark["image_points"]) != len(mark["board_points"]):
            raise InvalidInputError(f"markers of {mark['image']}: {len(mark['image_points'])} image points but "
                                    f"{len(mark['board_points'])} board points")
        if len(mark["image_points"]) < MIN_MARKS:
            raise InvalidInputError(f"markers of {mark['image']}: at least {MIN_MARKS} points are needed, "
                                    f"got {len(mark['image_points'])}")


def _write_workspace(ws: JobWorkspace, staged: dict[str, list[StagedFile]], frames: list[dict[str, Any]],
                     config: dict[str, Any]) -> None:
    folder = ws.root / "images"
    folder.mkdir(parents=True, exist_ok=True)
    items = [item for side in staged.values() for item in side]
    for n, (item, frame) in enumerate(zip(items, frames, strict=True)):
        path = folder / stored_name(n + 1, item)
        os.replace(item.temp_path, path)
        frame["path"] = str(path.resolve())
    ws.save_config(config)
    ws.save_inputs(frames)


def job_of_kind(db: Database, job_id: int, kinds: tuple[str, ...], noun: str) -> JobOut:
    """The job ``job_id`` if it is of one of ``kinds``, else 404 naming it a ``noun``."""
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.kind not in kinds:
            raise NotFoundError(f"{noun} {job_id} not found")
        return job_out(job)


def get_calibration(db: Database, settings: Settings, job_id: int, kind: str) -> CalibrationOut:
    noun = "stereo rig" if kind == "stereo_calibration" else "calibration"
    job = job_of_kind(db, job_id, (kind,), noun)
    result = job_workspace(settings.data_dir, job_id).calibration_file()
    return CalibrationOut(job=job, result=read_json(result) if result.exists() else None)


def replace_markers(db: Database, settings: Settings, queue: JobQueue, job_id: int, body: MarksUpdate) -> JobOut:
    """Replace (or remove) the marks of some photos and solve again; the corner detection is kept."""
    job = job_of_kind(db, job_id, ("calibration",), "calibration")
    if not JobStatus(job.status).finished:
        raise ConflictError(f"calibration {job_id} is {job.status}; change its marks once it has finished")
    ws = job_workspace(settings.data_dir, job_id)
    config = ws.load_config()
    marks = [m.model_dump() for m in body.markers]
    _check_marks(marks, {f["name"] for f in ws.load_inputs()})
    merged = {m["image"]: m for m in config["markers"]} | {m["image"]: m for m in marks}
    config = validated_config("calibration", {**config, "markers": list(merged.values())})
    ws.save_config(config)
    for stage in ("calibrate_camera", "fit_plumb_line"):
        ws.stage_report_file(stage).unlink(missing_ok=True)
    with db.session() as s:
        record = job_or_404(s, job_id)
        record.status, record.error, record.progress_detail = JobStatus.queued.value, "", "marks changed"
    return enqueue(db, queue, job_id)
