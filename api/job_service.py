"""Creating, reading and cancelling jobs. A job is born as a workspace (config + inputs) and a
``queued`` record before its chain is sent, so a worker always finds what it needs."""

from __future__ import annotations

import logging
import shutil
from datetime import timedelta
from typing import Any, get_args

from annotated_types import Ge, Le
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from api.errors import ConflictError, InvalidInputError, NotFoundError, UnavailableError
from api.eta_service import job_eta
from api.gcp_service import gcp_file
from api.gps_service import side_file_fixes
from api.models import JobCreate, JobOut
from api.queue import JobQueue
from core.accounts import Principal
from core.db import Database, Flight, Job, utcnow
from core.eta import working_megapixels
from core.kinds import JobStatus
from core.settings import Settings
from workers.algorithms.geometry import Camera
from workers.config import MosaicConfig, build_config
from workers.gps_file import with_side_file_gps
from workers.pipeline import pipeline_key, stage_names
from workers.workspace import flight_folder, job_workspace

log = logging.getLogger(__name__)


def job_out(job: Job) -> JobOut:
    return JobOut(
        id=job.id,
        flight_id=job.flight_id,
        kind=job.kind,
        status=job.status,
        stage=job.stage,
        stages=stage_names(pipeline_key(job.kind, job.options)),
        progress=job.progress,
        progress_detail=job.progress_detail,
        timings=job.timings or {},
        error=job.error,
        options=job.options or {},
        created_at=job.created_at,
        updated_at=job.updated_at,
    )


CAMERA_OPTIONS = ("camera", "left_camera", "right_camera")  # free-form camera JSON, checked by Camera.from_json


def validated_config(kind: str, options: dict[str, Any]) -> dict[str, Any]:
    """The config of a ``kind`` job with ``options`` merged over its defaults, every camera in it parsed;
    422 naming the option otherwise."""
    try:
        config = build_config(kind, options).model_dump()
    except ValidationError as exc:
        problems = "; ".join(f"{_option(e['loc'])}: {e['msg']}" for e in exc.errors()[:10])
        raise InvalidInputError(problems) from None
    for name in CAMERA_OPTIONS:
        if config.get(name) is not None:
            try:
                Camera.from_json(config[name])
            except ValueError as exc:
                raise InvalidInputError(f"options.{name}: {exc}") from None
    return config


# The mosaic options the viewer's form offers (the rest keep their defaults; the API takes them all)
FORM_OPTIONS = ("output_resolution", "working_max_px", "feature_type", "blend")
FORM_MODES = ("planar", "ortho")


def form_options() -> list[dict[str, Any]]:
    """Each of ``FORM_OPTIONS``: its choices (or its range), and its default in each of ``FORM_MODES`` (some
    defaults depend on the mode: planar mode registers with ORB, ortho mode with SIFT), from ``MosaicConfig``."""
    defaults = {mode: MosaicConfig.model_validate({"mode": mode}).model_dump() for mode in FORM_MODES}
    out = []
    for name in FORM_OPTIONS:
        info = MosaicConfig.model_fields[name]
        entry: dict[str, Any] = {"name": name, "default": {mode: d[name] for mode, d in defaults.items()}}
        if choices := get_args(info.annotation):
            entry["choices"] = list(choices)
        else:
            entry["minimum"] = next(m.ge for m in info.metadata if isinstance(m, Ge))
            entry["maximum"] = next(m.le for m in info.metadata if isinstance(m, Le))
        out.append(entry)
    return out


def _option(loc: tuple[int | str, ...]) -> str:
    return ".".join(["options", *map(str, loc)])


def create_job(db: Database, settings: Settings, queue: JobQueue, body: JobCreate, owner: Principal) -> JobOut:
    """Record a job on one of ``owner``'s flights (any flight for an admin) and queue it."""
    config = validated_config(body.kind, body.options)
    with db.session() as s:
        flight = s.get(Flight, body.flight_id)
        if flight is None or not owner.may_see(flight.owner_id):
            raise NotFoundError(f"flight {body.flight_id} not found")
        if len(flight.images) < 2:
            raise InvalidInputError(f"flight {flight.id} has {len(flight.images)} image(s); a mosaic needs at least 2")
        gps_source, fixes = side_file_fixes(settings.data_dir, flight.id)  # positions that override EXIF's
        frames = [with_side_file_gps(_frame_input(settings, flight.id, i), gps_source, fixes) for i in flight.images]
        job = Job(
            flight_id=flight.id,
            kind=body.kind,
            options=body.options,
            status=JobStatus.queued,
            owner_id=owner.user_id,
            work=_size(frames, config),  # what its time left is estimated per (core.eta)
        )
        s.add(job)
        s.flush()
        ws = job_workspace(settings.data_dir, job.id)
        try:
            ws.save_config(config)
            ws.save_inputs(frames)
            if (gcps := gcp_file(settings.data_dir, flight.id)) is not None:  # the job keeps its own copy
                ws.gcp_dir().mkdir(parents=True, exist_ok=True)
                shutil.copyfile(gcps, ws.gcp_dir() / gcps.name)
        except OSError:
            shutil.rmtree(ws.root, ignore_errors=True)
            raise
        job_id = job.id
    return enqueue(db, queue, job_id)


def _size(frames: list[dict[str, Any]], config: dict[str, Any]) -> dict[str, Any]:
    """A job's size: its photos, their megapixels, and the megapixels the stages handle (at the working size, or
    whole for a mosaic at the photos' own resolution: strips, ``output_resolution: native``)."""
    sizes = [(int(f.get("width") or 0), int(f.get("height") or 0)) for f in frames]
    native = config.get("mode") == "strip" or config.get("output_resolution") == "native"
    working = working_megapixels(sizes, None if native else config.get("working_max_px"))
    return {
        "frames": len(frames),
        "megapixels": round(working, 3),
        "photo_megapixels": round(working_megapixels(sizes, None), 3),
    }


def _frame_input(settings: Settings, flight_id: int, image: Any) -> dict[str, Any]:
    path = (flight_folder(settings.data_dir, flight_id) / image.stored_name).resolve()
    meta = {k: v for k, v in (image.meta or {}).items() if k != "sha256"}
    return {**meta, "name": image.filename, "path": str(path), "image_id": image.id}


def enqueue(db: Database, queue: JobQueue, job_id: int) -> JobOut:
    """Send a recorded job's pipeline; a queue that is down fails the job and answers 503."""
    with db.session() as s:
        job = job_or_404(s, job_id)
        pipeline, previous = pipeline_key(job.kind, job.options), job.celery_id
    try:
        chain_id = queue.enqueue(job_id, pipeline, after=previous)  # a retry's chain sorts after the last
    except Exception as exc:  # the broker is down: say so, and don't leave a job that never runs
        with db.session() as s:
            failed = job_or_404(s, job_id)
            failed.status, failed.error = JobStatus.failed, "could not reach the job queue; retry the job"
        log.warning("job %s: could not reach the job queue: %s", job_id, exc)
        raise UnavailableError("the job queue is unavailable; try again shortly") from None
    with db.session() as s:
        sent = job_or_404(s, job_id)
        sent.celery_id = chain_id
        return job_out(sent)


def job_or_404(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise NotFoundError(f"job {job_id} not found")
    return job


def get_job(db: Database, job_id: int) -> JobOut:
    with db.session() as s:
        job = job_or_404(s, job_id)
        return job_out(job)


def flight_name(db: Database, flight_id: int | None) -> str | None:
    """The name of flight ``flight_id`` (None for none): shown in titles of what other tools read."""
    if flight_id is None:
        return None
    with db.session() as s:
        flight = s.get(Flight, flight_id)
        return flight.name if flight is not None else None


def get_job_live(db: Database, job_id: int) -> JobOut:
    """The job with its time left while it is queued or running (``api.eta_service``)."""
    with db.session() as s:
        job = job_or_404(s, job_id)
        return job_out(job).model_copy(update={"eta": job_eta(db, job)})


def job_with_warnings(db: Database, settings: Settings, job_id: int) -> JobOut:
    """The job with its time left, or with the warnings of its report once it has succeeded (a report that cannot
    be read has none)."""
    job = get_job_live(db, job_id)
    if job.status != JobStatus.succeeded:
        return job
    try:
        warnings = job_workspace(settings.data_dir, job_id).load_report().get("warnings", [])
    except (OSError, ValueError, AttributeError):  # no report (calibrations), or a damaged one
        warnings = []
    return job.model_copy(update={"warnings": [w for w in warnings if isinstance(w, str)]})


def list_jobs(db: Database, flight_id: int | None, owner_id: int | None) -> list[JobOut]:
    """Jobs, newest first: of one flight, and of one owner, where given."""
    with db.session() as s:
        query = select(Job).order_by(Job.id.desc())
        if flight_id is not None:
            query = query.where(Job.flight_id == flight_id)
        if owner_id is not None:
            query = query.where(Job.owner_id == owner_id)
        return [job_out(j) for j in s.scalars(query)]


def retry_job(db: Database, settings: Settings, queue: JobQueue, job_id: int) -> JobOut:
    """Queue a failed or cancelled job again; stages that finished are skipped, so it resumes where it stopped.
    Not while the stage of a cancelled job is still stopping: the retry would run it beside itself."""
    with db.session() as s:
        job = job_or_404(s, job_id)
        if job.status not in (JobStatus.failed, JobStatus.cancelled):
            raise ConflictError(f"job {job_id} is {job.status}; only a failed or cancelled job can be retried")
        beat = job.heartbeat_at
        if beat is not None and utcnow() - beat < timedelta(seconds=settings.stale_seconds):
            raise ConflictError(
                f"job {job_id}'s {job.stage} stage is still stopping (at its next progress report); retry shortly"
            )
        job.status, job.error, job.progress_detail = JobStatus.queued, "", "retrying"
    return enqueue(db, queue, job_id)


def cancel_job(db: Database, job_id: int) -> JobOut:
    """Mark the job cancelled; its running stage stops at its next progress report, the rest never start."""
    with db.session() as s:
        job = job_or_404(s, job_id)
        if JobStatus(job.status).finished:
            raise ConflictError(f"job {job_id} is already {job.status}")
        job.status, job.progress_detail = JobStatus.cancelled, "cancelled by user"
        return job_out(job)


def delete_job(db: Database, settings: Settings, job_id: int) -> None:
    """Delete a job's record and files. A running stage stops at its next progress report (it finds no
    record), and the rest of its chain never starts."""
    with db.session() as s:
        s.delete(job_or_404(s, job_id))
    shutil.rmtree(job_workspace(settings.data_dir, job_id).root, ignore_errors=True)


def delete_flight(db: Database, settings: Settings, flight_id: int) -> None:
    """Delete a flight with its photos, ground control and jobs (running ones stop as ``delete_job`` says)."""
    with db.session() as s:
        flight = s.get(Flight, flight_id)
        if flight is None:
            raise NotFoundError(f"flight {flight_id} not found")
        jobs = list(s.scalars(select(Job).where(Job.flight_id == flight_id)))
        job_ids = [job.id for job in jobs]
        for job in jobs:
            s.delete(job)
        s.delete(flight)
    for job_id in job_ids:
        shutil.rmtree(job_workspace(settings.data_dir, job_id).root, ignore_errors=True)
    shutil.rmtree(flight_folder(settings.data_dir, flight_id).parent, ignore_errors=True)  # photos and GCPs
