"""Server-side import of a folder of photos into a flight, from the directories ops allow
(``Settings.import_dirs``, ``FOTOSKHEMA_IMPORT_DIRS``; none by default: import is off).

A request names a folder relative to one of those directories. Nothing outside them can be named: the path
must be relative, without ``..``, and the folder it leads to, once every symbolic link is resolved, must lie
inside the directory; so must every photo in it (a link to a file elsewhere is refused, a special file too).

What happens at once (``start_import``, answered 4xx with a message when it fails): the folder is listed (at
most ``max_import_files`` photos: ``.jpg .jpeg .tif .tiff .png``), its GPS side file (``geo.txt`` or
``gps.csv``, if there is one) is checked and stored as ``PUT /api/flights/{id}/gps`` would, and the disk is
checked when the files must be copied. Then a thread of the API process (``ImportRunner``, two imports at a
time) takes the photos one by one, as an upload takes a file: each is hard-linked into the flight's folder
under a temporary name (no disk used; a copy when the folder is on another file system or the link is not
allowed), checked (``api.uploads.check_photo``), refused if the flight has its bytes already, and moved into
place with its database row (``commit_staged``). A photo that fails is named in the import's ``errors`` and the
rest go on. Progress is the ``core.db.FolderImport`` row; a running import stamps it every few seconds, so one
whose API process stopped reads as ``interrupted``: POST the folder again and the photos already imported from
it (same file, size and time) are skipped without being read.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import stat
import threading
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from api.errors import (
    ApiError,
    ConflictError,
    ForbiddenError,
    InsufficientStorageError,
    InvalidInputError,
    NotFoundError,
    TooLargeError,
)
from api.gps_service import store_gps
from api.limits import MAX_GPS_BYTES
from api.models import ImportCreate
from api.uploads import StagedFile, check_photo, commit_staged, display_name, file_sha256, refuse_duplicates
from core.db import Database, Flight, FolderImport, Image, utcnow
from core.settings import Settings
from workers.gps_file import GPS_FILE_NAMES
from workers.workspace import flight_folder

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = frozenset({".jpg", ".jpeg", ".tif", ".tiff", ".png"})
MAX_ERRORS = 200  # refused files named in an import's record; the count goes on
COPY_BYTES = 4 * 1024 * 1024
HEARTBEAT_SECONDS = 5.0  # how often a running import stamps its record
RUNNING = "running"
INTERRUPTED = "the API process running it stopped; POST the folder again to import the rest"


@dataclass(frozen=True)
class Candidate:
    """A photo file of the folder: its name relative to the folder, its resolved path and identity."""

    name: str  # relative to the imported folder, with /
    path: Path  # resolved, inside the import directory
    source: str  # relative to the import directory: what a later import of it is recognised by
    size: int
    mtime_ns: int


@dataclass(frozen=True)
class ImportPlan:
    flight_id: int
    root: int
    base: Path  # the import directory, resolved
    folder: Path  # the folder, resolved
    photos: list[Candidate]
    refused: dict[str, str]  # names found but refused while listing (links outside, special files)
    copy: bool  # False when a hard link is expected to work (same file system)


# -- What a request may name --------------------------------------------------------------------------------


def resolve_folder(settings: Settings, root: int, path: str) -> tuple[Path, Path]:
    """(import directory, folder) both resolved, or the 4xx that says why ``path`` cannot be imported. Neither
    the import directory's own path nor where a link points is ever said back."""
    if not settings.import_dirs:
        raise ForbiddenError(
            "server-side import is off: the server's operators list the directories it may import from in "
            "FOTOSKHEMA_IMPORT_DIRS"
        )
    if root >= len(settings.import_dirs):
        raise InvalidInputError(
            f"root: this server has {len(settings.import_dirs)} import directories, 0 to "
            f"{len(settings.import_dirs) - 1}"
        )
    text = path.strip()
    if text.startswith(("/", "\\", "~")) or re.match(r"^[A-Za-z]:", text):
        raise InvalidInputError(f"path: {text!r} is absolute; name the folder relative to import directory {root}")
    parts = [p for p in re.split(r"[\\/]+", text) if p not in ("", ".")]
    if ".." in parts:
        raise InvalidInputError(f"path: {text!r} goes up with '..'; name the folder inside import directory {root}")
    try:
        base = Path(settings.import_dirs[root]).resolve(strict=True)
    except OSError:
        raise NotFoundError(f"import directory {root} is not there on the server; tell its operators") from None
    try:  # links resolved as far as the path exists: whether it leads out is said before whether it exists
        folder = base.joinpath(*parts).resolve()
        if not folder.is_relative_to(base):
            raise InvalidInputError(f"path: {text!r} leads outside import directory {root} (a symbolic link)")
        folder = folder.resolve(strict=True)
    except FileNotFoundError:
        raise NotFoundError(f"path: no folder {text!r} in import directory {root}") from None
    except (OSError, RuntimeError):  # a loop of links, a name too long, no permission
        raise InvalidInputError(f"path: {text!r} cannot be opened in import directory {root}") from None
    if not folder.is_dir():
        raise InvalidInputError(f"path: {text!r} is not a folder")
    return base, folder


def list_photos(base: Path, folder: Path, recursive: bool, limit: int) -> tuple[list[Candidate], dict[str, str]]:
    """The photo files of ``folder`` (and its sub-folders), sorted by name; refused: name -> why. Hidden
    files and other kinds of file (XML, logs) are not listed; more than ``limit`` photos answer 413."""
    photos: list[Candidate] = []
    refused: dict[str, str] = {}
    for name, entry in _walk(base, folder, recursive, refused):
        if Path(name).suffix.lower() not in PHOTO_SUFFIXES:
            continue
        try:
            real = Path(entry).resolve(strict=True)
            info = real.stat()
        except (OSError, RuntimeError):
            refused[name] = "cannot be opened (a broken link, or no permission)"
            continue
        if not real.is_relative_to(base):
            refused[name] = "a symbolic link to a file outside the import directory"
        elif not stat.S_ISREG(info.st_mode):
            refused[name] = "not a regular file"
        else:
            source = real.relative_to(base).as_posix()
            photos.append(Candidate(name, real, source, info.st_size, info.st_mtime_ns))
        if len(photos) > limit:
            raise TooLargeError(
                f"the folder holds more than {limit} photos; import its sub-folders one at a time "
                "(the server's FOTOSKHEMA_MAX_IMPORT_FILES)"
            )
    photos.sort(key=lambda c: c.name)
    return photos, refused


def _walk(base: Path, folder: Path, recursive: bool, refused: dict[str, str]) -> Iterator[tuple[str, str]]:
    """(name relative to ``folder``, path) of every non-hidden file; sub-folders (resolved, inside ``base``,
    each once) when ``recursive``."""
    pending, seen = [(folder, "")], {folder}
    while pending:
        directory, prefix = pending.pop()
        try:
            entries = sorted(os.scandir(directory), key=lambda e: e.name)
        except OSError:
            refused[prefix or "."] = "the folder cannot be read"
            continue
        for entry in entries:
            if entry.name.startswith("."):
                continue
            name = f"{prefix}{entry.name}"
            if entry.is_dir(follow_symlinks=True):
                real = Path(entry.path).resolve()
                if recursive and not real.is_relative_to(base):
                    refused[f"{name}/"] = "a symbolic link to a folder outside the import directory"
                elif recursive and real not in seen:
                    seen.add(real)
                    pending.append((real, f"{name}/"))
                continue
            yield name, entry.path


# -- Starting an import -------------------------------------------------------------------------------------


def start_import(
    db: Database, settings: Settings, runner: ImportRunner, flight_id: int, owner_id: int | None, body: ImportCreate
) -> FolderImport:
    """Check the request (folder, photos, GPS side file, disk), record the import and start it; blocking (it
    lists the folder and parses the GPS file): run it off the event loop."""
    with db.session() as s:
        if s.get(Flight, flight_id) is None:
            raise NotFoundError(f"flight {flight_id} not found")
    base, folder = resolve_folder(settings, body.root, body.path)
    photos, refused = list_photos(base, folder, body.recursive, settings.max_import_files)
    if not photos:
        suffixes = " ".join(sorted(PHOTO_SUFFIXES))
        raise InvalidInputError(f"path: no photos ({suffixes}) in {body.path!r}")
    _refuse_second_import(db, settings, flight_id)
    images = flight_folder(settings.data_dir, flight_id)
    images.mkdir(parents=True, exist_ok=True)
    copy = os.stat(folder).st_dev != os.stat(images).st_dev
    if copy:
        _check_disk(images, sum(p.size for p in photos))
    gps = _store_side_file(db, settings, flight_id, folder, base)
    with db.session() as s:
        record = FolderImport(
            flight_id=flight_id,
            owner_id=owner_id,
            root=body.root,
            path=body.path.strip() or ".",
            status=RUNNING,
            total=len(photos),
            refused=len(refused),
            errors=dict(list(refused.items())[:MAX_ERRORS]),
            gps=gps,
        )
        s.add(record)
        s.flush()
    runner.submit(record.id, ImportPlan(flight_id, body.root, base, folder, photos, refused, copy))
    return record


def _refuse_second_import(db: Database, settings: Settings, flight_id: int) -> None:
    with db.session() as s:
        running = s.scalars(
            select(FolderImport).where(FolderImport.flight_id == flight_id, FolderImport.status == RUNNING)
        )
        for other in running:
            if not is_stale(settings, other):
                raise ConflictError(f"import {other.id} of this flight is still running; wait for it or cancel it")


def _check_disk(folder: Path, needed: int) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free:
        raise InsufficientStorageError(
            f"the folder's photos ({needed} bytes) must be copied (it is on another file system than the "
            f"server's data) and the server has {free} bytes free"
        )


def _store_side_file(db: Database, settings: Settings, flight_id: int, folder: Path, base: Path) -> dict[str, Any]:
    """The folder's ``geo.txt`` or ``gps.csv``, checked and stored as ``PUT /gps`` does; {} if it has none."""
    for name in GPS_FILE_NAMES:
        candidate = folder / name
        if not candidate.exists():
            continue
        real = candidate.resolve()
        if not real.is_relative_to(base) or not real.is_file():
            raise InvalidInputError(f"{name}: not a regular file inside the import directory")
        with real.open("rb") as handle:
            content = handle.read(MAX_GPS_BYTES + 1)
        return store_gps(db, settings.data_dir, flight_id, name, content)
    return {}


def is_stale(settings: Settings, record: FolderImport) -> bool:
    """A running import whose process stopped stamping it (the API restarted)."""
    quiet = timedelta(seconds=max(settings.stale_seconds, 6 * HEARTBEAT_SECONDS))
    return record.status == RUNNING and record.updated_at < utcnow() - quiet


# -- Running it ---------------------------------------------------------------------------------------------


class ImportRunner:
    """The imports of one API process: two run at a time (each on one core: the photo checks), the rest wait;
    a thread stamps the records of all of them so that other processes see they are alive."""

    def __init__(self, db: Database, settings: Settings) -> None:
        self.db, self.settings = db, settings
        self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="import")
        self._active: set[int] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None

    def submit(self, import_id: int, plan: ImportPlan) -> None:
        with self._lock:
            self._active.add(import_id)
            if self._heartbeat is None:
                self._heartbeat = threading.Thread(target=self._stamp, name="import-heartbeat", daemon=True)
                self._heartbeat.start()
        self._pool.submit(self._run, import_id, plan)

    def stop(self) -> None:
        """At the API's shutdown: the running imports stop after their current photo (they read as interrupted)."""
        self._stop.set()
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._heartbeat is not None:
            self._heartbeat.join(timeout=10)

    def _stamp(self) -> None:
        while not self._stop.wait(HEARTBEAT_SECONDS):
            with self._lock:
                ids = list(self._active)
            if ids:
                try:
                    with self.db.session() as s:
                        s.execute(
                            update(FolderImport)
                            .where(FolderImport.id.in_(ids), FolderImport.status == RUNNING)
                            .values(updated_at=utcnow())
                            .execution_options(synchronize_session=False)
                        )
                except Exception:
                    log.exception("import heartbeat failed")

    def _run(self, import_id: int, plan: ImportPlan) -> None:
        try:
            status, error = run_import(self.db, self.settings, import_id, plan, self._stop)
        except Exception:
            log.exception("import %s failed", import_id)
            status, error = "failed", "the import stopped on an internal error; POST the folder again to go on"
        finally:
            with self._lock:
                self._active.discard(import_id)
        if status == RUNNING:  # the API is shutting down
            status, error = "interrupted", INTERRUPTED
        _set(self.db, import_id, {"status": status, "error": error}, where_running=True)


def run_import(
    db: Database, settings: Settings, import_id: int, plan: ImportPlan, stop: threading.Event
) -> tuple[str, str]:
    """Import ``plan``'s photos one by one; the final (status, error). ``running`` when the process stops it."""
    done_before = _imported_sources(db, plan.flight_id, plan.root)
    counts = {"done": 0, "imported": 0, "skipped": 0, "refused": len(plan.refused), "bytes_copied": 0}
    errors = dict(plan.refused)
    images = flight_folder(settings.data_dir, plan.flight_id)
    for photo in plan.photos:
        if stop.is_set():
            return RUNNING, ""
        if _status(db, import_id) != RUNNING:
            return "cancelled", ""  # cancelled by a request
        if (photo.source, photo.size, photo.mtime_ns) in done_before:
            counts["skipped"] += 1
        else:
            outcome = _import_one(db, settings, plan, photo, images, counts)
            if outcome is not None:
                counts["refused"] += 1
                errors[photo.name] = outcome
        counts["done"] += 1
        _set(db, import_id, {"errors": dict(list(errors.items())[:MAX_ERRORS]), **counts})
    if plan.photos and _status(db, import_id) == RUNNING:
        _refresh_gps(db, settings, import_id, plan)
    return "succeeded", ""


def _import_one(
    db: Database, settings: Settings, plan: ImportPlan, photo: Candidate, images: Path, counts: dict[str, int]
) -> str | None:
    """Stage, check and store one photo; None when it is in the flight now (or already was), else why not."""
    if photo.size > settings.max_upload_bytes:
        return f"file is larger than {settings.max_upload_bytes} bytes"
    temp = images / f".import-{uuid.uuid4().hex}.part"
    try:
        sha256, copied = _stage(photo, temp, plan.copy)
        counts["bytes_copied"] += copied
        meta = check_photo(temp, display_name(photo.name), settings)
        meta["import_source"] = {
            "root": plan.root,
            "path": photo.source,
            "size": photo.size,
            "mtime_ns": photo.mtime_ns,
        }
        staged = StagedFile(display_name(photo.name), temp, photo.size, sha256, meta)
        try:
            refuse_duplicates(db, plan.flight_id, [staged])
        except ConflictError:
            counts["skipped"] += 1
            return None
        commit_staged(db, plan.flight_id, images, [staged])
        counts["imported"] += 1
        return None
    except ApiError as exc:
        return exc.detail.removeprefix(f"{display_name(photo.name)}: ")
    except OSError as exc:  # never the path: the reason only
        return f"could not be read or stored ({exc.strerror or type(exc).__name__})"
    finally:
        temp.unlink(missing_ok=True)


def _stage(photo: Candidate, temp: Path, copy: bool) -> tuple[str, int]:
    """``photo`` at ``temp``: a hard link (no disk used) unless ``copy`` or the link is refused, then a copy;
    (its SHA-256, bytes copied). The file must still be the regular file that was listed."""
    if not copy:
        try:
            os.link(photo.path, temp)
            linked = temp.stat()
            if not stat.S_ISREG(linked.st_mode) or linked.st_size != photo.size:
                raise ApiError("changed since the folder was listed")
            return file_sha256(temp), 0
        except OSError:  # another file system, or links not allowed (fs.protected_hardlinks): copy it
            temp.unlink(missing_ok=True)
    digest = hashlib.sha256()
    source = os.open(photo.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with open(source, "rb") as reader, temp.open("xb") as writer:
        if not stat.S_ISREG(os.fstat(reader.fileno()).st_mode):
            raise ApiError("not a regular file")
        while block := reader.read(COPY_BYTES):
            digest.update(block)
            writer.write(block)
    return digest.hexdigest(), temp.stat().st_size


def _imported_sources(db: Database, flight_id: int, root: int) -> set[tuple[str, int, int]]:
    """(path in the import directory, size, mtime_ns) of the flight's photos imported from ``root`` before."""
    with db.session() as s:
        metas = s.scalars(select(Image.meta).where(Image.flight_id == flight_id))
        sources = [m.get("import_source") for m in metas if isinstance(m, dict)]
    return {
        (src["path"], src["size"], src["mtime_ns"])
        for src in sources
        if isinstance(src, dict) and src.get("root") == root
    }


def _refresh_gps(db: Database, settings: Settings, import_id: int, plan: ImportPlan) -> None:
    """The side file's summary again, now that the photos it names are in the flight."""
    try:
        gps = _store_side_file(db, settings, plan.flight_id, plan.folder, plan.base)
    except ApiError as exc:  # changed since the import started
        gps = {"error": exc.detail}
    if gps:
        _set(db, import_id, {"gps": gps})


def _status(db: Database, import_id: int) -> str:
    with db.session() as s:
        return str(s.scalar(select(FolderImport.status).where(FolderImport.id == import_id)) or "")


def _set(db: Database, import_id: int, values: dict[str, Any], *, where_running: bool = False) -> None:
    where = [FolderImport.id == import_id] + ([FolderImport.status == RUNNING] if where_running else [])
    with db.session() as s:
        s.execute(
            update(FolderImport)
            .where(*where)
            .values(updated_at=utcnow(), **values)
            .execution_options(synchronize_session=False)
        )


# -- Reading and cancelling --------------------------------------------------------------------------------


def get_import(db: Database, settings: Settings, flight_id: int, import_id: int) -> FolderImport:
    with db.session() as s:
        record = s.get(FolderImport, import_id)
        if record is None or record.flight_id != flight_id:
            raise NotFoundError(f"import {import_id} not found in flight {flight_id}")
        if is_stale(settings, record):
            record.status = "interrupted"
            record.error = INTERRUPTED
        return record


def list_imports(db: Database, settings: Settings, flight_id: int) -> list[FolderImport]:
    with db.session() as s:
        ids = list(s.scalars(select(FolderImport.id).where(FolderImport.flight_id == flight_id)))
    return [get_import(db, settings, flight_id, i) for i in sorted(ids, reverse=True)]


def cancel_import(db: Database, settings: Settings, flight_id: int, import_id: int) -> FolderImport:
    """Stop a running import after its current photo; the photos imported so far stay. 409 once it ended."""
    record = get_import(db, settings, flight_id, import_id)
    if record.status != RUNNING:
        raise ConflictError(f"import {import_id} already ended ({record.status})")
    _set(db, import_id, {"status": "cancelled"}, where_running=True)
    return get_import(db, settings, flight_id, import_id)
