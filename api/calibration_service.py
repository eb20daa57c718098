"""Calibration and stereo-rig jobs: what a request must hold (counts, sizes, marks), results, new marks.

Their photos live in the job's own folder (``api/photo_jobs.py``), not in a flight.
"""

from __future__ import annotations

from typing import Any

from fastapi import UploadFile

from api.errors import ConflictError, InvalidInputError
from api.job_service import enqueue, job_or_404, validated_config
from api.models import JobOut, JobResultOut, MarksUpdate
from api.photo_jobs import job_of_kind, record_photo_job
from api.queue import JobQueue
from core.accounts import Principal
from core.db import Database
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.algorithms.calibration import MIN_VIEWS
from workers.workspace import job_workspace

MIN_MARKS = 6  # marked points per image: a pose has six unknowns
# the stages that solve again over new marks (the corners found stay)
SOLVE_STAGES = {
    JobKind.calibration: ("calibrate_camera", "fit_plumb_line"),
    JobKind.stereo_calibration: ("calibrate_stereo",),
}


async def create_calibration(
    db: Database,
    settings: Settings,
    queue: JobQueue,
    kind: JobKind,
    groups: dict[str, list[UploadFile]],
    options: dict[str, Any],
    *,
    owner: Principal | None = None,
) -> JobOut:
    """Record and queue a ``calibration`` or ``stereo_calibration`` job over the uploaded photos, owned by
    ``owner``.

    ``groups`` maps a side ("" for one camera, "left"/"right" for a rig) to its photos, in order.
    """
    config = validated_config(kind, options)
    _check_counts(kind, config, groups)

    def check(frames: list[dict[str, Any]]) -> None:
        _check_sizes(kind, frames)
        _check_marks(config.get("markers", []), {f["name"] for f in frames})

    owner_id = owner.user_id if owner else None
    return await record_photo_job(db, settings, queue, kind, options, config, groups, check, owner_id=owner_id)


def _check_counts(kind: JobKind, config: dict[str, Any], groups: dict[str, list[UploadFile]]) -> None:
    if kind == JobKind.stereo_calibration:
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
        raise InvalidInputError(
            f"a calibration needs at least {MIN_VIEWS} photos of the board, got {len(groups.get('', []))}"
        )


def _check_sizes(kind: JobKind, frames: list[dict[str, Any]]) -> None:
    """Every photo of one camera has the camera's size."""
    for side in {f["side"] for f in frames}:
        mine = [f for f in frames if f["side"] == side]
        first = mine[0]
        for f in mine[1:]:
            if (f["width"], f["height"]) != (first["width"], first["height"]):
                camera = f"the {side} camera" if side else "one camera"
                raise InvalidInputError(
                    f"{f['name']} is {f['width']}x{f['height']} px but {first['name']} is "
                    f"{first['width']}x{first['height']}; photos of {camera} share one size"
                )


def _check_marks(marks: list[dict[str, Any]], names: set[str]) -> None:
    for mark in marks:
        if mark["image"] not in names:
            raise InvalidInputError(f"markers: no photo named {mark['image']!r} in this calibration")
        if mark["remove"]:
            continue
        if len(mark["image_points"]) != len(mark["board_points"]):
            raise InvalidInputError(
                f"markers of {mark['image']}: {len(mark['image_points'])} image points but "
                f"{len(mark['board_points'])} board points"
            )
        if len(mark["image_points"]) < MIN_MARKS:
            raise InvalidInputError(
                f"markers of {mark['image']}: at least {MIN_MARKS} points are needed, got {len(mark['image_points'])}"
            )


def get_calibration(db: Database, settings: Settings, job_id: int, kind: JobKind) -> JobResultOut:
    noun = "stereo rig" if kind == JobKind.stereo_calibration else "calibration"
    job = job_of_kind(db, job_id, (kind,), noun)
    ws = job_workspace(settings.data_dir, job_id)
    return JobResultOut(job=job, result=ws.load_calibration() if ws.has_calibration() else None)


def calibration_photos(db: Database, settings: Settings, job_id: int, kind: JobKind) -> dict[str, Any]:
    """The job's photos in upload order (``index`` names the preview: ``GET /api/jobs/{id}/photos/{index}/preview``),
    each with its size, side, the board corners found in it (``detect_corners``; null before, or where none) or
    why none, and what the user's marks did with it: ``marked`` (its marks replace the corners), ``removed``, or
    null."""
    noun = "stereo rig" if kind == JobKind.stereo_calibration else "calibration"
    job_of_kind(db, job_id, (kind,), noun)
    ws = job_workspace(settings.data_dir, job_id)
    try:
        found: dict[str, Any] = ws.load_corners()
    except (FileNotFoundError, ValueError):
        found = {}
    config = ws.load_config()
    marks = {m["image"]: m for m in config.get("markers", [])}
    photos = []
    for index, frame in enumerate(ws.load_inputs()):
        corners = (found.get("images") or {}).get(frame["name"]) or {}
        mark = marks.get(frame["name"])
        photos.append(
            {
                "index": index,
                "name": frame["name"],
                "side": frame.get("side", ""),
                "pair": frame.get("pair", 0),
                "width": frame["width"],
                "height": frame["height"],
                "corners": corners.get("points"),
                "reason": corners.get("reason", "" if found else "the corners are not found yet"),
                "marks": None
                if mark is None
                else "removed"
                if mark["remove"]
                else "marked"
                if mark["image_points"]
                else None,
            }
        )
    return {"pattern": found.get("pattern", config.get("pattern")), "photos": photos}


def replace_markers(
    db: Database,
    settings: Settings,
    queue: JobQueue,
    job_id: int,
    body: MarksUpdate,
    kind: JobKind = JobKind.calibration,
) -> JobOut:
    """Replace (or remove) the marks of some photos of a calibration or stereo rig and solve again; the corner
    detection is kept."""
    noun = "stereo rig" if kind == JobKind.stereo_calibration else "calibration"
    job = job_of_kind(db, job_id, (kind,), noun)
    if not JobStatus(job.status).finished:
        raise ConflictError(f"{noun} {job_id} is {job.status}; change its marks once it has finished")
    ws = job_workspace(settings.data_dir, job_id)
    config = ws.load_config()
    marks = [m.model_dump() for m in body.markers]
    _check_marks(marks, {f["name"] for f in ws.load_inputs()})
    merged = {m["image"]: m for m in config.get("markers", [])} | {m["image"]: m for m in marks}
    config = validated_config(kind, {**config, "markers": list(merged.values())})
    ws.save_config(config)
    for stage in SOLVE_STAGES[kind]:
        ws.forget_stage_report(stage)
    with db.session() as s:
        record = job_or_404(s, job_id)
        record.status, record.error, record.progress_detail = JobStatus.queued, "", "marks changed"
    return enqueue(db, queue, job_id)
