"""Jobs whose photos belong to the job, not to a flight (calibrations, stereo rigs, crack surveys).

A request is checked whole before anything is recorded: the photos are validated into a staging
folder, the caller's check sees their names and sizes, and only then is the job recorded and its
photos moved into the job's folder; a failed request leaves nothing behind.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi import UploadFile

from api.errors import InvalidInputError, NotFoundError
from api.job_service import enqueue, job_out
from api.limits import parse_json
from api.models import JobOut
from api.queue import JobQueue
from api.uploads import StagedFile, stage_images, stored_name
from core.db import Database, Job
from core.eta import working_megapixels
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.workspace import JobWorkspace, atomic_path, job_workspace


def parse_options(raw: str | None) -> dict[str, Any]:
    """The multipart ``options`` field: a JSON object, or empty."""
    if not raw:
        return {}
    options = parse_json(raw, "options")  # bounded: size, depth, finite numbers
    if not isinstance(options, dict):
        raise InvalidInputError("options: must be a JSON object")
    return options


async def record_photo_job(
    db: Database,
    settings: Settings,
    queue: JobQueue,
    kind: JobKind,
    options: dict[str, Any],
    config: dict[str, Any],
    groups: dict[str, list[UploadFile]],
    check: Callable[[list[dict[str, Any]]], None],
    attachments: dict[str, bytes] | None = None,
    *,
    owner_id: int | None = None,
) -> JobOut:
    """Stage and validate the photos, ``check`` their frames (raise ``InvalidInputError``), then record the
    job with its photos in its own folder and queue it; a failed request leaves nothing behind.

    Frames are ``{"name", "side", "pair", "width", "height"}`` (and ``"rpc": true`` for a GeoTIFF with RPC
    metadata), and ``"path"`` once stored.
    ``attachments`` are other files of the job, already checked: path inside its folder -> content.
    ``owner_id`` is the user the job belongs to.
    """
    staging = Path(settings.data_dir) / "incoming" / uuid.uuid4().hex
    try:
        staged = {side: await stage_images(files, staging, settings) for side, files in groups.items()}
        frames = _frames(staged)
        check(frames)
        megapixels = round(working_megapixels([(f["width"], f["height"]) for f in frames], None), 3)
        with db.session() as s:
            job = Job(
                flight_id=None,
                kind=kind,
                options=options,
                status=JobStatus.queued,
                owner_id=owner_id,
                work={"frames": len(frames), "megapixels": megapixels, "photo_megapixels": megapixels},  # (core.eta)
            )
            s.add(job)
            s.flush()
            _write_workspace(job_workspace(settings.data_dir, job.id), staged, frames, config, attachments or {})
            job_id = job.id
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return enqueue(db, queue, job_id)


def _frames(staged: dict[str, list[StagedFile]]) -> list[dict[str, Any]]:
    frames, names = [], set()
    for side, items in staged.items():
        for n, item in enumerate(items):
            if item.display_name in names:
                raise InvalidInputError(f"{item.display_name}: two photos of this request have the same name")
            names.add(item.display_name)
            frames.append(
                {
                    "name": item.display_name,
                    "side": side,
                    "pair": n,
                    "width": item.meta["width"],
                    "height": item.meta["height"],
                    # a GeoTIFF with a rational polynomial camera model (stereo DEMs use it)
                    **({"rpc": True} if item.meta.get("rpc") else {}),
                }
            )
    return frames


def _write_workspace(
    ws: JobWorkspace,
    staged: dict[str, list[StagedFile]],
    frames: list[dict[str, Any]],
    config: dict[str, Any],
    attachments: dict[str, bytes],
) -> None:
    for relative, content in attachments.items():
        with atomic_path(ws.input_file(relative)) as tmp:
            tmp.write_bytes(content)
    folder = ws.images_dir()
    folder.mkdir(parents=True, exist_ok=True)
    items = [item for side in staged.values() for item in side]
    for n, (item, frame) in enumerate(zip(items, frames, strict=True)):
        path = folder / stored_name(n + 1, item)
        os.replace(item.temp_path, path)
        frame["path"] = str(path.resolve())
    ws.save_config(config)
    ws.save_inputs(frames)


def job_of_kind(db: Database, job_id: int, kinds: tuple[JobKind, ...], noun: str) -> JobOut:
    """The job ``job_id`` if it is of one of ``kinds``, else 404 naming it a ``noun``."""
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.kind not in kinds:
            raise NotFoundError(f"{noun} {job_id} not found")
        return job_out(job)
