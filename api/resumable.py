"""Resumable uploads of photos into a flight: the tus 1.0.0 protocol (https://tus.io/protocols/resumable-upload)
with its creation, checksum, termination and expiration extensions, over part files in the flight's folder.

Each upload is a ``core.db.Upload`` row (length, offset stored for good, expiry) and a part file
(``workers.workspace.flight_upload_path``) beside the flight's photos, so a partial upload survives a restart of
the API and resumes from its offset. A ``PATCH`` streams its body to the end of the part file through a 1 MiB
buffer (bounded memory whatever the file's size), hashing it as it goes, then syncs the file and moves the row's
offset: the row never counts a byte the disk may not hold. A body cut short keeps what arrived, unless it came
with an ``Upload-Checksum`` (then nothing of it is kept); a checksum that does not match answers 460 and keeps
nothing of the chunk. When the last byte has arrived the file is checked exactly as a multipart photo is
(``api.uploads.check_photo``, then the duplicate check) and moved into the flight's photos with its database row
in one transaction; a file that fails is deleted with its upload (413/422/409 naming it).

One request writes to an upload at a time: a ``PATCH`` holds an exclusive ``flock`` on the part file (another
answers 423, which tus clients retry). Unfinished uploads idle for ``Settings.upload_expiry_seconds`` are deleted
with their part files by ``UploadSweeper`` (a thread of each API process), or when a client next asks for them
(410). Why our own code and not a library: of the Python tus servers, none that is maintained does the checksum
extension, and each keeps its own store and file layout apart from the flight's photos, owner checks and the
photo check that every upload must pass.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import fcntl
import hashlib
import logging
import os
import shutil
import threading
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta
from email.utils import format_datetime
from pathlib import Path
from typing import IO, Any

import anyio
from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from api.errors import (
    ApiError,
    ChecksumMismatchError,
    ConflictError,
    GoneError,
    InsufficientStorageError,
    InvalidInputError,
    LockedError,
    NotFoundError,
    TooLargeError,
    UnsupportedMediaError,
)
from api.uploads import StagedFile, check_photo, commit_staged, display_name, file_sha256, refuse_duplicates
from core.db import Database, Image, Upload, utcnow
from core.settings import Settings
from workers.workspace import flight_folder, flight_upload_path, flight_uploads_folder

log = logging.getLogger(__name__)

TUS_VERSION = "1.0.0"
TUS_EXTENSIONS = "creation,checksum,termination,expiration"
CHECKSUMS: dict[str, Callable[[], Any]] = {  # tus names -> hashlib; sha1 is the one tus requires
    "sha256": hashlib.sha256,
    "sha512": hashlib.sha512,
    "sha1": hashlib.sha1,
    "md5": hashlib.md5,
}
PATCH_CONTENT_TYPE = "application/offset+octet-stream"
MAX_METADATA_CHARS = 4096  # an Upload-Metadata header; the filename is all we use of it
WRITE_BYTES = 1024 * 1024  # a PATCH body is written (and hashed) in pieces of this size, off the event loop
IDLE_SECONDS = 60.0  # a PATCH whose body stops arriving this long is treated as cut off (tus: close on timeout)


@dataclass(frozen=True)
class UploadState:
    """What the routes answer about one upload."""

    id: str
    flight_id: int
    filename: str
    length: int
    offset: int
    expires_at: datetime
    metadata_header: str
    image_id: int | None

    @property
    def location(self) -> str:
        return upload_location(self.flight_id, self.id)

    @property
    def complete(self) -> bool:
        return self.image_id is not None

    def headers(self) -> dict[str, str]:
        """``Upload-Offset`` and, while it is unfinished, ``Upload-Expires`` (RFC 9110 date)."""
        out = {"Upload-Offset": str(self.offset)}
        if not self.complete:
            out["Upload-Expires"] = format_datetime(self.expires_at, usegmt=True)
        return out


def upload_location(flight_id: int, upload_id: str) -> str:
    return f"/api/flights/{flight_id}/uploads/{upload_id}"


def _state(row: Upload) -> UploadState:
    return UploadState(
        row.id, row.flight_id, row.filename, row.length, row.offset, row.expires_at, row.metadata_header, row.image_id
    )


# -- Headers -------------------------------------------------------------------------------------------------


def parse_metadata(header: str) -> dict[str, str]:
    """``Upload-Metadata``: comma-separated ``key base64value`` pairs (the value may be left out), keys unique.
    Values are decoded as UTF-8 text; a value that is not is refused (we only read ``filename``)."""
    if len(header) > MAX_METADATA_CHARS:
        raise InvalidInputError(f"Upload-Metadata: longer than {MAX_METADATA_CHARS} characters")
    pairs: dict[str, str] = {}
    for item in header.split(","):
        key, _, value = item.strip().partition(" ")
        if not key or not key.isascii() or not key.isprintable():
            raise InvalidInputError("Upload-Metadata: each pair is a key and a Base64 value separated by a space")
        if key in pairs:
            raise InvalidInputError(f"Upload-Metadata: the key {key!r} is given twice")
        try:
            pairs[key] = base64.b64decode(value.strip(), validate=True).decode("utf-8")
        except (binascii.Error, UnicodeDecodeError):
            raise InvalidInputError(f"Upload-Metadata: the value of {key!r} is not Base64 of UTF-8 text") from None
    return pairs


def parse_checksum(header: str) -> tuple[str, bytes]:
    """``Upload-Checksum: <algorithm> <base64 digest>`` -> (algorithm, digest); 400 for an unknown algorithm."""
    name, _, value = header.strip().partition(" ")
    if name not in CHECKSUMS:
        supported = ",".join(CHECKSUMS)
        raise ApiError(f"Upload-Checksum: algorithm {name[:20]!r} is not supported; use one of {supported}")
    try:
        digest = base64.b64decode(value.strip(), validate=True)
    except binascii.Error:
        raise ApiError("Upload-Checksum: the digest is not Base64") from None
    if len(digest) != CHECKSUMS[name]().digest_size:
        raise ApiError(f"Upload-Checksum: a {name} digest has {CHECKSUMS[name]().digest_size} bytes")
    return name, digest


def parse_offset(header: str | None, what: str) -> int:
    if header is None or not header.strip().isdigit() or len(header.strip()) > 20:
        raise ApiError(f"{what}: a non-negative integer is required")
    return int(header.strip())


# -- Creation, state, termination ----------------------------------------------------------------------------


def create_upload(
    db: Database,
    settings: Settings,
    flight_id: int,
    owner_id: int | None,
    length_header: str | None,
    metadata_header: str | None,
    defer_header: str | None = None,
) -> UploadState:
    """A new, empty upload of ``Upload-Length`` bytes named by ``Upload-Metadata``'s ``filename``."""
    if defer_header is not None:
        raise ApiError("Upload-Defer-Length is not supported: send Upload-Length")
    length = parse_offset(length_header, "Upload-Length")
    meta = parse_metadata(metadata_header or "") if metadata_header else {}
    if not meta.get("filename"):
        raise InvalidInputError("Upload-Metadata: a 'filename' is required")
    name = display_name(meta["filename"])
    if length > settings.max_upload_bytes:
        raise TooLargeError(f"{name}: file is larger than {settings.max_upload_bytes} bytes")
    if length == 0:
        raise InvalidInputError(f"{name}: empty file")
    folder = flight_uploads_folder(settings.data_dir, flight_id)
    folder.mkdir(parents=True, exist_ok=True)
    flight_folder(settings.data_dir, flight_id).mkdir(exist_ok=True)  # where the photo goes: gone = flight deleted
    _check_free_space(db, folder, length, name)
    upload_id = uuid.uuid4().hex
    part = flight_upload_path(settings.data_dir, flight_id, upload_id)
    part.touch(exist_ok=False)
    try:
        with db.session() as s:
            row = Upload(
                id=upload_id,
                flight_id=flight_id,
                owner_id=owner_id,
                filename=name,
                metadata_header=metadata_header or "",
                length=length,
                offset=0,
                expires_at=utcnow() + timedelta(seconds=settings.upload_expiry_seconds),
            )
            s.add(row)
            s.flush()
            return _state(row)
    except BaseException:
        part.unlink(missing_ok=True)
        raise


def _check_free_space(db: Database, folder: Path, length: int, name: str) -> None:
    """507 when the disk cannot hold ``length`` more bytes beside what the unfinished uploads still need."""
    with db.session() as s:
        pending = s.scalar(
            select(func.coalesce(func.sum(Upload.length - Upload.offset), 0)).where(Upload.image_id.is_(None))
        )
    free = shutil.disk_usage(folder).free - int(pending or 0)
    if length > free:
        raise InsufficientStorageError(
            f"{name}: the server has room for {max(free, 0)} more bytes of uploads, not {length}; "
            "ask its operators for disk space"
        )


def upload_state(db: Database, settings: Settings, flight_id: int, upload_id: str) -> UploadState:
    """The upload, 404 if unknown, 410 (and deleted now) if it expired unfinished."""
    with db.session() as s:
        row = s.get(Upload, upload_id)
        if row is None or row.flight_id != flight_id:
            raise NotFoundError(f"upload {upload_id} not found in flight {flight_id}")
        state = _state(row)
    if not state.complete and state.expires_at < utcnow():
        _delete_upload(db, settings, state, expired_at=utcnow())
        raise GoneError(f"{state.filename}: the upload expired unfinished; start it again")
    return state


def list_uploads(db: Database, flight_id: int) -> list[UploadState]:
    """The flight's unfinished uploads, oldest first."""
    with db.session() as s:
        rows = s.scalars(
            select(Upload).where(Upload.flight_id == flight_id, Upload.image_id.is_(None)).order_by(Upload.created_at)
        )
        return [_state(row) for row in rows]


def terminate_upload(db: Database, settings: Settings, flight_id: int, upload_id: str) -> None:
    """tus termination: the upload and its part file are deleted (a finished one's photo stays in the flight)."""
    state = upload_state(db, settings, flight_id, upload_id)
    path = flight_upload_path(settings.data_dir, flight_id, upload_id)
    with _locked(path, state.filename, missing_ok=True):
        _delete_upload(db, settings, state)


def _delete_upload(db: Database, settings: Settings, state: UploadState, *, expired_at: datetime | None = None) -> bool:
    """Delete the row (only if it is still unfinished and expired at ``expired_at``, when given) and then the part
    file; whether it was."""
    where = [Upload.id == state.id]
    if expired_at is not None:
        where += [Upload.expires_at < expired_at, Upload.image_id.is_(None)]
    with db.session() as s:
        gone = s.execute(delete(Upload).where(*where).execution_options(synchronize_session=False))
    if gone.rowcount == 1:  # type: ignore[attr-defined]
        flight_upload_path(settings.data_dir, state.flight_id, state.id).unlink(missing_ok=True)
        return True
    return False


@contextmanager
def _locked(path: Path, name: str, *, missing_ok: bool = False) -> Iterator[IO[bytes] | None]:
    """The part file opened for writing under an exclusive ``flock``; 423 if another request holds it."""
    try:
        handle = path.open("r+b")
    except FileNotFoundError:
        if missing_ok:
            yield None
            return
        raise GoneError(f"{name}: the upload's data is gone; start it again") from None
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise LockedError(f"{name}: another request is writing to this upload; retry in a moment") from None
        yield handle


# -- Appending -----------------------------------------------------------------------------------------------


@dataclass
class _Chunk:
    """A PATCH body as it is written: bytes received and their hash under the client's algorithm, if any."""

    handle: IO[bytes]
    start: int
    algorithm: str | None
    received: int = 0
    cut_off: bool = False
    hash: Any = field(init=False)

    def __post_init__(self) -> None:
        self.hash = CHECKSUMS[self.algorithm]() if self.algorithm else None

    def write(self, data: bytes) -> None:  # in a worker thread: hashlib and the write release the GIL
        if self.hash is not None:
            self.hash.update(data)
        self.handle.write(data)

    def sync(self) -> None:
        self.handle.flush()
        os.fdatasync(self.handle.fileno())  # the bytes and the file's size: what the offset counts on

    def discard(self) -> None:
        self.handle.truncate(self.start)


async def append(
    db: Database,
    settings: Settings,
    flight_id: int,
    upload_id: str,
    headers: dict[str, str | None],
    body: AsyncIterator[bytes],
) -> UploadState:
    """tus PATCH: append ``body`` at ``Upload-Offset``; when it completes the upload, the photo is checked and
    stored. ``headers``: ``content-type``, ``upload-offset``, ``upload-checksum`` (None when absent)."""
    if (headers.get("content-type") or "").split(";")[0].strip().lower() != PATCH_CONTENT_TYPE:
        raise UnsupportedMediaError(f"a PATCH sends its bytes as Content-Type: {PATCH_CONTENT_TYPE}")
    offset = parse_offset(headers.get("upload-offset"), "Upload-Offset")
    checksum_header = headers.get("upload-checksum")
    checksum = parse_checksum(checksum_header) if checksum_header else None
    state = _current(db, settings, flight_id, upload_id, offset)
    if state.complete:
        return state  # a client that missed the answer to its last PATCH sends it again: nothing more to do
    path = flight_upload_path(settings.data_dir, flight_id, upload_id)
    with _locked(path, state.filename) as handle:
        assert handle is not None
        state = _current(db, settings, flight_id, upload_id, offset)  # as it stands now that no one else writes
        if state.complete:
            return state
        chunk = _Chunk(handle, state.offset, checksum[0] if checksum else None)
        await run_in_threadpool(chunk.discard)  # a tail written before a crash was never counted
        handle.seek(state.offset)
        await _receive(chunk, body, state, state.length - state.offset)
        if checksum is not None and (chunk.cut_off or chunk.hash is None or chunk.hash.digest() != checksum[1]):
            await run_in_threadpool(chunk.discard)
            if chunk.cut_off:
                return state  # the client is gone; it will ask for the offset again
            raise _mismatch(state.filename, checksum[0])
        await run_in_threadpool(chunk.sync)
        state = _advance(db, settings, state, chunk.received)
        if state.offset == state.length:
            state = await _finish(db, settings, state, path)
    return state


def _current(db: Database, settings: Settings, flight_id: int, upload_id: str, offset: int) -> UploadState:
    """The upload, 409 unless ``offset`` is where it stands."""
    state = upload_state(db, settings, flight_id, upload_id)
    if offset != state.offset:
        raise ConflictError(f"{state.filename}: Upload-Offset is {offset} but the upload has {state.offset} bytes")
    return state


def _mismatch(name: str, algorithm: str) -> ApiError:
    return ChecksumMismatchError(f"{name}: the chunk's {algorithm} is not the one sent; nothing of it was kept")


async def _receive(chunk: _Chunk, body: AsyncIterator[bytes], state: UploadState, room: int) -> None:
    """Write ``body`` through ``chunk`` in pieces of about ``WRITE_BYTES``; a body that stops (the client went
    away, or sent nothing for ``IDLE_SECONDS``) sets ``cut_off`` and keeps what arrived; one past the upload's
    length is refused (413) and discarded."""
    pieces: list[bytes] = []
    held = 0
    iterator = body.__aiter__()
    while True:
        try:
            with anyio.fail_after(IDLE_SECONDS):
                piece = await iterator.__anext__()
        except StopAsyncIteration:
            break
        except (ClientDisconnect, TimeoutError, OSError) as exc:
            log.info("upload %s: body cut off after %d bytes (%s)", state.id, chunk.received + held, type(exc).__name__)
            chunk.cut_off = True
            break
        if chunk.received + held + len(piece) > room:
            await run_in_threadpool(chunk.discard)
            raise TooLargeError(f"{state.filename}: the chunk goes past Upload-Length ({state.length} bytes)")
        pieces.append(piece)
        held += len(piece)
        if held >= WRITE_BYTES:
            await _flush(chunk, pieces)
            held = 0
    await _flush(chunk, pieces)


async def _flush(chunk: _Chunk, pieces: list[bytes]) -> None:
    if pieces:
        data = b"".join(pieces)
        pieces.clear()
        await run_in_threadpool(chunk.write, data)
        chunk.received += len(data)


def _advance(db: Database, settings: Settings, state: UploadState, received: int) -> UploadState:
    """Count ``received`` more bytes (already synced to disk) and move the expiry on; 404 if the upload was
    deleted meanwhile (terminated, or its flight)."""
    expires = utcnow() + timedelta(seconds=settings.upload_expiry_seconds)
    with db.session() as s:
        moved = s.execute(
            update(Upload)
            .where(Upload.id == state.id, Upload.offset == state.offset)
            .values(offset=state.offset + received, expires_at=expires)
            .execution_options(synchronize_session=False)
        )
    if moved.rowcount != 1:  # type: ignore[attr-defined]
        raise NotFoundError(f"{state.filename}: the upload was deleted while it was written")
    return replace(state, offset=state.offset + received, expires_at=expires)


async def _finish(db: Database, settings: Settings, state: UploadState, path: Path) -> UploadState:
    """All bytes are here: check the file as a multipart photo is checked, then make it a photo of the flight
    (the part file moves into the flight's photos, the row records the photo, in one transaction). A file that
    fails is deleted with its upload."""
    try:
        checked = await asyncio.gather(  # two cores: the photo check and the hash read the file at once
            run_in_threadpool(check_photo, path, state.filename, settings),
            run_in_threadpool(file_sha256, path),
            return_exceptions=True,  # both end before the file may be deleted; the check's refusal comes first
        )
        for outcome in checked:
            if isinstance(outcome, BaseException):
                raise outcome
        meta, sha256 = checked
        staged = StagedFile(state.filename, path, state.length, sha256, meta)
        refuse_duplicates(db, state.flight_id, [staged])
        image = await run_in_threadpool(_commit, db, settings, state, staged)
    except BaseException:
        _delete_upload(db, settings, state)
        raise
    return replace(state, image_id=image.id)


def _commit(db: Database, settings: Settings, state: UploadState, staged: StagedFile) -> Image:
    def mark_complete(s: Session, images: list[Image]) -> None:
        row = s.get(Upload, state.id)
        if row is None:  # terminated, or its flight deleted, while the file was checked
            raise NotFoundError(f"{state.filename}: the upload was deleted while it was checked")
        row.image_id = images[0].id

    folder = flight_folder(settings.data_dir, state.flight_id)
    if not folder.is_dir():
        raise NotFoundError(f"flight {state.flight_id} not found")
    return commit_staged(db, state.flight_id, folder, [staged], also=mark_complete)[0]


def image_of(db: Database, state: UploadState) -> Image | None:
    """The photo a finished upload became (None if it was deleted since)."""
    if state.image_id is None:
        return None
    with db.session() as s:
        return s.get(Image, state.image_id)


# -- Expiry --------------------------------------------------------------------------------------------------


def expire_uploads(db: Database, settings: Settings, now: datetime | None = None) -> int:
    """Delete the uploads whose expiry has passed (an unfinished one with its part file, unless a request is
    writing to it now), and part files that no upload names; how many uploads went."""
    now = now or utcnow()
    with db.session() as s:
        rows = [_state(r) for r in s.scalars(select(Upload).where(Upload.expires_at < now))]
    gone = 0
    for state in rows:
        path = flight_upload_path(settings.data_dir, state.flight_id, state.id)
        with suppress(LockedError), _locked(path, state.filename, missing_ok=True):
            gone += _delete_upload(db, settings, state, expired_at=None if state.complete else now)
    _remove_strays(db, settings, now)
    return gone


def _remove_strays(db: Database, settings: Settings, now: datetime) -> None:
    """Part files with no upload row (a process died between making one and recording it), once as old as an
    expiry."""
    cutoff = (now - timedelta(seconds=settings.upload_expiry_seconds)).timestamp()
    parts = list((settings.data_dir / "flights").glob("*/uploads/*.part"))
    if not parts:
        return
    with db.session() as s:
        known = set(s.scalars(select(Upload.id)))
    for part in parts:
        with suppress(OSError):
            if part.stem not in known and part.stat().st_mtime < cutoff:
                part.unlink()


class UploadSweeper:
    """A thread of the API process that runs ``expire_uploads`` every so often (a quarter of the expiry, at
    most every 5 minutes). Several API processes may sweep at once: each deletion is a compare-and-set."""

    def __init__(self, db: Database, settings: Settings) -> None:
        self.db, self.settings = db, settings
        self.interval = min(300.0, max(0.5, settings.upload_expiry_seconds / 4))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="upload-sweeper", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                if gone := expire_uploads(self.db, self.settings):
                    log.info("upload sweeper: %d expired uploads deleted", gone)
            except Exception:  # the database away for now: the next pass tries again
                log.exception("upload sweeper: pass failed")
