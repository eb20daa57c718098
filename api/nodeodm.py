"""A NodeODM-compatible face of the service, so that WebODM (through PyODM) can use it as a processing node.

NodeODM's API (its ``docs/swagger.json``, version 2.2.1) in the subset WebODM calls: a task is initialised
(``task/new/init``: name and options), photos are uploaded to it in any number of requests, possibly in parallel
(``task/new/upload/{uuid}``, field ``images``; ``geo.txt`` and ``gcp_list.txt`` among them become the flight's
GPS side file and GCPs), and it is committed (``task/new/commit/{uuid}``), which starts it. Here a task is a
flight of the token's user, and on commit a mosaic job of that flight (``core.db.NodeOdmTask`` links them).
``task/{uuid}/info`` and ``output`` follow it, ``download/all.zip`` streams its outputs in ODM's folder layout
(``odm_orthophoto/odm_orthophoto.tif``, ``odm_report/``...), ``task/cancel`` and ``task/remove`` act on it.

Options are NodeODM's ``[{name, value}]``; ``/options`` lists the mosaic options a task may set (their NodeODM
names, types and domains, as NodeODM derives them from ODM's); as NodeODM does, a name it does not list is
dropped (and said so in the task's output), a value outside its domain is refused.
"""

from __future__ import annotations

import os
import time
import uuid as uuidlib
from importlib.metadata import version as package_version
from pathlib import Path
from typing import Any, get_args

from annotated_types import Ge, Gt, Le, Lt
from pydantic.fields import FieldInfo

from api import job_service
from api.errors import ConflictError, InvalidInputError, NotFoundError
from api.limits import parse_json
from api.models import JobCreate
from api.queue import JobQueue
from core.accounts import Principal
from core.db import Database, Flight, Job, NodeOdmTask
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.config import MosaicConfig
from workers.pipeline import PIPELINES, pipeline_key
from workers.workspace import job_workspace

API_VERSION = "2.2.1"  # the NodeODM API this follows (PyODM uploads in chunks from 1.4.0 on)
ENGINE = "fotoskhema"
STATUS_CODES = {  # NodeODM's status codes
    JobStatus.queued: 10,
    JobStatus.running: 20,
    JobStatus.failed: 30,
    JobStatus.succeeded: 40,
    JobStatus.cancelled: 50,
}
# NodeODM option name -> the mosaic option it sets, and its help text
OPTIONS: dict[str, tuple[str, str]] = {
    "mode": (
        "mode",
        "planar: frames chained onto one plane (flat ground); ortho: photo-triangulation and "
        "orthorectification; strip: planar, for aerial strip frames",
    ),
    "feature-type": ("feature_type", "sift for drone photos; harris_ncc for strips whose frames keep orientation"),
    "working-max-px": ("working_max_px", "longest side of the working copies, px (the mosaic's resolution)"),
    "output-resolution": ("output_resolution", "working: the working copies' pixels; native: the photos' own"),
    "blend": ("blend", "feather: overlaps cross-faded; multiband: seams cut where frames agree, then blended"),
    "gain-compensation": ("gain_compensation", "equalise brightness between overlapping photos"),
    "max-features": ("max_features", "SIFT keypoints kept per photo"),
    "min-inliers": ("min_inliers", "a pair of photos with fewer matches is not an overlap"),
    "gps-sigma-m": ("gps_sigma_m", "accuracy of the photos' GPS positions, m"),
    "gcp-sigma-m": ("gcp_sigma_m", "accuracy of the ground control points, m (ortho mode)"),
}
SIDE_FILES = {"geo.txt": "gps", "gcp_list.txt": "gcps"}  # uploaded beside the photos, as NodeODM takes them
# other files NodeODM takes beside the photos, for ODM steps this node does not have: accepted, not used
UNUSED_SIDE_FILES = frozenset({"image_groups.txt", "align.laz", "align.las", "align.tif"})
# our outputs in ODM's folder layout (WebODM looks for these), anything else under fotoskhema/
ODM_LAYOUT = {
    "mosaic.tif": "odm_orthophoto/odm_orthophoto.tif",
    "dsm.tif": "odm_dem/dsm.tif",
    "cutlines.geojson": "odm_orthophoto/cutlines.geojson",
}


# -- Options ---------------------------------------------------------------------------------------


def node_options() -> list[dict[str, Any]]:
    """``/options``: each option's name, type, default (as a string), domain and help, as NodeODM lists them."""
    out = []
    for name, (field, help_text) in OPTIONS.items():
        info = MosaicConfig.model_fields[field]
        kind, domain = _type_and_domain(info)
        value = info.default
        out.append(
            {
                "name": name,
                "type": kind,
                "value": str(value).lower() if kind == "bool" else str(value),
                "domain": domain,
                "help": help_text,
            }
        )
    return out


def _type_and_domain(info: FieldInfo) -> tuple[str, Any]:
    choices = get_args(info.annotation)
    if choices and all(isinstance(c, str) for c in choices):
        return "enum", list(choices)
    if info.annotation is bool:
        return "bool", ""
    kind = "int" if info.annotation is int else "float"
    low = next((m.ge if isinstance(m, Ge) else m.gt for m in info.metadata if isinstance(m, Ge | Gt)), None)
    high = next((m.le if isinstance(m, Le) else m.lt for m in info.metadata if isinstance(m, Le | Lt)), None)
    word = "integer" if kind == "int" else "float"
    return kind, f"{word}: {low} <= x <= {high}" if low is not None and high is not None else word


def map_options(raw: str) -> tuple[list[dict[str, Any]], dict[str, Any], list[str]]:
    """NodeODM's options JSON -> (the known options as given, converted; the mosaic options; names dropped)."""
    given = parse_json(raw or "[]", "options")
    if not isinstance(given, list) or not all(isinstance(o, dict) and isinstance(o.get("name"), str) for o in given):
        raise InvalidInputError("options: expected a JSON array of {name, value}")
    kept, options, dropped = [], {}, []
    for entry in given[:1000]:
        name = entry["name"][:100]
        if name not in OPTIONS:
            dropped.append(name)
            continue
        field = OPTIONS[name][0]
        value = _convert(name, entry.get("value"), *_type_and_domain(MosaicConfig.model_fields[field]))
        kept.append({"name": name, "value": value})
        options[field] = value
    try:
        job_service.validated_config(JobKind.mosaic, options)
    except InvalidInputError as exc:  # a value outside its range, or two that do not go together
        raise InvalidInputError(f"invalid options: {exc.detail}") from None
    return kept, options, dropped


def _convert(name: str, value: Any, kind: str, domain: Any) -> Any:
    text = str(value).strip().lower() if value is not None else ""
    try:
        if kind == "bool":
            if isinstance(value, bool):
                return value
            if text in ("true", "1", "false", "0"):
                return text in ("true", "1")
            raise ValueError
        if kind == "enum":
            if value not in domain:
                raise ValueError
            return value
        return int(text) if kind == "int" else float(text)
    except (TypeError, ValueError):
        shown = str(value)[:40]
        expected = domain or "true/false"
        raise InvalidInputError(f"option {name}: {shown!r} is not a valid value ({kind}, {expected})") from None


# -- Tasks -----------------------------------------------------------------------------------------


def init_task(db: Database, owner: Principal, name: str, options: str, set_uuid: str | None) -> str:
    """A new task (a flight of ``owner``), its options checked; answers its uuid."""
    kept, job_options, dropped = map_options(options)
    task_id = _uuid(set_uuid) if set_uuid else str(uuidlib.uuid4())
    with db.session() as s:
        if s.get(NodeOdmTask, task_id) is not None:
            raise ConflictError(f"task {task_id} already exists")
        title = (name or "").strip()[:200] or f"NodeODM task {task_id[:8]}"
        flight = Flight(name=title, description="made over the NodeODM API", owner_id=owner.user_id)
        s.add(flight)
        s.flush()
        options_record = {"given": kept, "job": job_options, "ignored": dropped}
        s.add(
            NodeOdmTask(uuid=task_id, owner_id=owner.user_id, flight_id=flight.id, name=title, options=options_record)
        )
    return task_id


def _uuid(text: str) -> str:
    try:
        return str(uuidlib.UUID(text.strip()))
    except ValueError:
        raise InvalidInputError(f"invalid set-uuid: {text[:40]!r}") from None


def task_or_404(db: Database, task_id: str, viewer: Principal) -> NodeOdmTask:
    """The task, if ``viewer`` may see it and its flight still exists; else 404 (as for one that does not exist)."""
    with db.session() as s:
        task = s.get(NodeOdmTask, task_id[:36])
        if task is None or not viewer.may_see(task.owner_id) or s.get(Flight, task.flight_id) is None:
            raise NotFoundError(f"{task_id[:36]} not found")
        s.expunge(task)
        return task


def task_ids(db: Database, viewer: Principal) -> list[str]:
    """The uuids of the tasks ``viewer`` may see, oldest first."""
    with db.session() as s:
        query = s.query(NodeOdmTask.uuid, NodeOdmTask.owner_id).order_by(NodeOdmTask.created_at)
        return [uuid for uuid, owner in query if viewer.may_see(owner)]


def side_file_kind(filename: str) -> str | None:
    """``gps``, ``gcps`` or ``unused`` for a side file uploaded beside the photos (by its name), else None: a
    photo."""
    name = filename.lower()
    return SIDE_FILES.get(name) or ("unused" if name in UNUSED_SIDE_FILES else None)


def commit_task(db: Database, settings: Settings, queue: JobQueue, task: NodeOdmTask, owner: Principal) -> None:
    """Start the task: a mosaic job of its flight with its options (once; a second commit changes nothing)."""
    if task.job_id is not None:
        return
    body = JobCreate(flight_id=task.flight_id, kind="mosaic", options=task.options.get("job", {}))
    job = job_service.create_job(db, settings, queue, body, owner)
    with db.session() as s:
        record = s.get(NodeOdmTask, task.uuid)
        if record is not None:
            record.job_id = job.id


def task_info(db: Database, task: NodeOdmTask, with_output: int | None) -> dict[str, Any]:
    """``task/{uuid}/info``: NodeODM's TaskInfo (status code, progress %, processing time in ms, ...)."""
    job = _job(db, task)
    with db.session() as s:
        images = len(s.get(Flight, task.flight_id).images)  # type: ignore[union-attr]
    status: dict[str, Any] = {"code": STATUS_CODES[JobStatus(job.status)] if job else STATUS_CODES[JobStatus.queued]}
    if job is not None and job.status == JobStatus.failed and job.error:
        status["errorMessage"] = job.error
    info: dict[str, Any] = {
        "uuid": task.uuid,
        "name": task.name,
        "dateCreated": int(task.created_at.timestamp() * 1000),
        "processingTime": _processing_ms(job),
        "status": status,
        "options": task.options.get("given", []),
        "imagesCount": images,
        "progress": 100.0 if job is not None and job.status == JobStatus.succeeded else (job.progress if job else 0.0),
    }
    if with_output is not None:
        info["output"] = _slice(output_lines(db, task), with_output)
    return info


def _job(db: Database, task: NodeOdmTask) -> Job | None:
    if task.job_id is None:
        return None
    with db.session() as s:
        job = s.get(Job, task.job_id)
        if job is not None:
            s.expunge(job)
        return job


def _processing_ms(job: Job | None) -> int:
    """Milliseconds spent processing: its finished stages, and the running one so far; -1 before it starts."""
    if job is None or not job.timings and job.status == JobStatus.queued:
        return -1
    seconds = sum(v for v in (job.timings or {}).values() if isinstance(v, int | float))
    current = (job.work or {}).get("current") or {}
    if job.status == JobStatus.running and current.get("started_at"):
        seconds += max(0.0, time.time() - float(current["started_at"]))
    return int(seconds * 1000)


def output_lines(db: Database, task: NodeOdmTask) -> list[str]:
    """The task's console output, one line per event, only ever appended to (WebODM reads it from a line on)."""
    lines = [f"Fotoskhema {ENGINE} task {task.uuid}: {task.name}"]
    if task.options.get("ignored"):
        lines.append(f"Options this node does not use, ignored: {', '.join(task.options['ignored'])}")
    job = _job(db, task)
    if job is None:
        return [*lines, "Waiting for the photos to be committed"]
    lines.append(f"Mosaic job {job.id} created")
    finished = (job.work or {}).get("stages", {})
    for spec in PIPELINES[pipeline_key(job.kind, job.options)]:
        if spec.name in finished:
            entry = finished[spec.name]
            counted = f" ({entry['count']} {entry['unit']}s)" if entry.get("unit") and entry.get("count") else ""
            lines.append(f"{spec.name}: done in {float(entry.get('seconds') or 0):.1f} s{counted}")
        elif spec.name == job.stage and job.status == JobStatus.running:
            lines.append(f"{spec.name}: running")
            break
    if job.status == JobStatus.failed:
        lines.append(f"Failed: {job.error}")
    elif job.status == JobStatus.cancelled:
        lines.append("Cancelled")
    elif job.status == JobStatus.succeeded:
        lines.append("Done")
    return lines


def _slice(lines: list[str], start: int) -> list[str]:
    return lines[start:] if start >= 0 else lines[start:]


def cancel_task(db: Database, task: NodeOdmTask) -> None:
    job = _job(db, task)
    if job is None:
        raise ConflictError(f"task {task.uuid} has not been committed: nothing runs")
    if job.status != JobStatus.cancelled:
        job_service.cancel_job(db, job.id)


def remove_task(db: Database, settings: Settings, task: NodeOdmTask) -> None:
    """Delete the task's job, flight, photos and outputs."""
    job_service.delete_flight(db, settings, task.flight_id)  # its jobs too
    with db.session() as s:
        record = s.get(NodeOdmTask, task.uuid)
        if record is not None:
            s.delete(record)


def node_info(db: Database) -> dict[str, Any]:
    """``/info``: NodeODM's node description; memory and cores are the API host's."""
    with db.session() as s:
        waiting = s.query(Job).filter(Job.status.in_([JobStatus.queued, JobStatus.running])).count()
    pages = os.sysconf("SC_PHYS_PAGES") if hasattr(os, "sysconf") else 0
    free = os.sysconf("SC_AVPHYS_PAGES") if hasattr(os, "sysconf") else 0
    page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 0
    return {
        "version": API_VERSION,
        "taskQueueCount": waiting,
        "totalMemory": pages * page,
        "availableMemory": free * page,
        "cpuCores": os.cpu_count() or 1,
        "maxImages": None,
        "maxParallelTasks": 1,
        "engineVersion": package_version("fotoskhema"),
        "engine": ENGINE,
    }


def archive_entries(settings: Settings, db: Database, task: NodeOdmTask) -> list[tuple[str, Path | bytes]]:
    """What ``all.zip`` of a finished task holds: the outputs in ODM's layout, and the console output."""
    job = _job(db, task)
    if job is None or job.status != JobStatus.succeeded:
        raise ConflictError("Asset not ready")
    entries: list[tuple[str, Path | bytes]] = []
    for name, path in job_workspace(settings.data_dir, job.id).outputs().items():
        if name in ODM_LAYOUT:
            entries.append((ODM_LAYOUT[name], path))
        elif name.startswith("report"):
            entries.append((f"odm_report/{name}", path))
        else:
            entries.append((f"fotoskhema/{name}", path))
    entries.append(("task_output.txt", ("\n".join(output_lines(db, task)) + "\n").encode("utf-8")))
    return entries
