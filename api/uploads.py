"""Storing uploaded photos: stream each file to a temporary name inside the flight folder, validate
it, and only when every file of the request is good, move them all into place and record them.
A failed request leaves nothing behind."""

from __future__ import annotations

import hashlib
import os
import re
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import UploadFile
from sqlalchemy import func, select
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api.errors import ConflictError, InvalidInputError, NotFoundError, TooLargeError
from core.db import Database, Flight, Image
from core.settings import Settings
from workers.image_meta import ImageLimits, InvalidImageError, inspect_image
from workers.workspace import flight_folder

CHUNK = 1024 * 1024
EXTENSIONS = {"JPEG": "jpg", "MPO": "jpg", "PNG": "png", "TIFF": "tif"}


@dataclass
class StagedFile:
    display_name: str
    temp_path: Path
    size: int
    sha256: str
    meta: dict[str, Any]


MAX_DISPLAY_NAME = 200  # characters of a file's name kept for display


def display_name(raw: str | None) -> str:
    """The client's filename reduced to a harmless label: last path part, printable, at most
    ``MAX_DISPLAY_NAME`` characters, a longer one shortened before its extension (which says what it is).

    Used only for display; files are stored under server-chosen names.
    """
    base = re.split(r"[\\/]", raw or "")[-1]
    cleaned = "".join(ch for ch in base if ch.isprintable()).strip(" .")
    if len(cleaned) > MAX_DISPLAY_NAME:
        stem, dot, extension = cleaned.rpartition(".")
        keep = f"{dot}{extension}" if stem and 0 < len(extension) <= 10 else ""
        cleaned = cleaned[: MAX_DISPLAY_NAME - len(keep)].rstrip(" .") + keep
    return cleaned or "unnamed"


async def store_uploads(db: Database, settings: Settings, flight_id: int, files: list[UploadFile]) -> list[Image]:
    """Validate and store ``files`` as images of flight ``flight_id``, all or none."""
    with db.session() as s:
        if s.get(Flight, flight_id) is None:
            raise NotFoundError(f"flight {flight_id} not found")
    if not files:
        raise InvalidInputError("no files in the request (multipart field 'files')")
    folder = flight_folder(settings.data_dir, flight_id)
    staged: list[StagedFile] = []
    try:
        staged = await stage_images(files, folder, settings)
        refuse_duplicates(db, flight_id, staged)
        return commit_staged(db, flight_id, folder, staged)
    finally:
        for item in staged:
            item.temp_path.unlink(missing_ok=True)


async def stage_images(files: list[UploadFile], folder: Path, settings: Settings) -> list[StagedFile]:
    """Stream and validate ``files`` to temporary names in ``folder``; on any bad file, none stay."""
    folder.mkdir(parents=True, exist_ok=True)
    staged: list[StagedFile] = []
    try:
        for upload in files:
            staged.append(await _stage(upload, folder, settings))
    except BaseException:
        for item in staged:
            item.temp_path.unlink(missing_ok=True)
        raise
    return staged


def stored_name(seq: int, item: StagedFile) -> str:
    """The server's name for a staged photo: sequence number, random part, extension by format."""
    return f"{seq:05d}_{uuid.uuid4().hex[:8]}.{EXTENSIONS.get(item.meta['format'], 'img')}"


async def _stage(upload: UploadFile, folder: Path, settings: Settings) -> StagedFile:
    name = display_name(upload.filename)
    temp = folder / f".upload-{uuid.uuid4().hex}.part"
    digest, size = hashlib.sha256(), 0
    try:
        with temp.open("wb") as out:
            while chunk := await upload.read(CHUNK):
                size += len(chunk)
                if size > settings.max_upload_bytes:
                    raise TooLargeError(f"{name}: file is larger than {settings.max_upload_bytes} bytes")
                digest.update(chunk)
                out.write(chunk)
        meta = await run_in_threadpool(check_photo, temp, name, settings)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    return StagedFile(name, temp, size, digest.hexdigest(), meta)


def file_sha256(path: Path) -> str:
    """The SHA-256 of a stored file (a finished resumable upload, an imported photo), as ``_stage`` hashes a
    multipart photo while it streams: what duplicates are found by."""
    with path.open("rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def image_limits(settings: Settings) -> ImageLimits:
    return ImageLimits(
        settings.max_image_pixels,
        settings.max_image_side,
        settings.min_image_side,
        settings.image_decode_budget_bytes,
    )


def check_photo(path: Path, name: str, settings: Settings) -> dict[str, Any]:
    """``path``'s metadata once it checks out as a photo (``inspect_image``; blocking, run it off the event
    loop), else 413 (too large) or 422 naming the file by ``name``. The file is left where it is either way."""
    try:
        return inspect_image(path, image_limits(settings))
    except InvalidImageError as exc:
        raise (TooLargeError if exc.too_large else InvalidInputError)(f"{name}: {exc}") from None


def refuse_duplicates(db: Database, flight_id: int, staged: list[StagedFile]) -> None:
    """409 naming the first of ``staged`` whose bytes are already a photo of the flight (or twice in ``staged``)."""
    seen: dict[str, str] = {}
    with db.session() as s:
        for name, sha in s.execute(
            select(Image.filename, Image.meta["sha256"].as_string()).where(Image.flight_id == flight_id)
        ):
            seen[sha] = name
    for item in staged:
        if item.sha256 in seen:
            raise ConflictError(f"{item.display_name}: the same photo is already in this flight as {seen[item.sha256]}")
        seen[item.sha256] = item.display_name


def commit_staged(
    db: Database,
    flight_id: int,
    folder: Path,
    staged: list[StagedFile],
    also: Callable[[Session, list[Image]], None] | None = None,
) -> list[Image]:
    """Move ``staged`` into ``folder`` under server-chosen names and record them as photos of the flight, in one
    transaction (``also(session, images)`` runs in it too, after the photos have ids): all or none."""
    moved: list[Path] = []
    try:
        with db.session() as s:
            seq = (s.scalar(select(func.max(Image.seq)).where(Image.flight_id == flight_id)) or 0) + 1
            images = []
            for n, item in enumerate(staged):
                stored = stored_name(seq + n, item)
                os.replace(item.temp_path, folder / stored)
                moved.append(folder / stored)
                image = Image(
                    flight_id=flight_id,
                    seq=seq + n,
                    filename=item.display_name,
                    stored_name=stored,
                    size_bytes=item.size,
                    width=item.meta["width"],
                    height=item.meta["height"],
                    meta={**item.meta, "sha256": item.sha256},
                )
                s.add(image)
                images.append(image)
            s.flush()
            if also is not None:
                also(s, images)
            return images
    except BaseException:
        for path in moved:  # the records rolled back: take the files back out too
            path.unlink(missing_ok=True)
        raise
