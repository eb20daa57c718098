"""Server-side imports of a folder into a flight, from the directories ops allow (``api.folder_import``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Request
from starlette.concurrency import run_in_threadpool

from api import folder_import
from api.auth import UserDep
from api.deps import DbDep, FlightId, SettingsDep
from api.models import ImportCreate, ImportOut
from core.db import FolderImport
from workers.config import MAX_ID

router = APIRouter(prefix="/api/flights/{flight_id}/imports", tags=["imports"])
ImportId = Annotated[int, Path(ge=1, le=MAX_ID, description="the import's id")]


def import_out(record: FolderImport) -> ImportOut:
    return ImportOut(
        id=record.id,
        flight_id=record.flight_id,
        root=record.root,
        path=record.path,
        status=record.status,
        total=record.total,
        done=record.done,
        imported=record.imported,
        skipped=record.skipped,
        refused=record.refused,
        errors=record.errors or {},
        bytes_copied=record.bytes_copied,
        gps=record.gps or {},
        error=record.error,
        created_at=record.created_at,
        updated_at=record.updated_at,
    )


@router.post("", status_code=202, response_model=ImportOut)
async def start_import(
    flight_id: FlightId, body: ImportCreate, request: Request, principal: UserDep, db: DbDep, settings: SettingsDep
) -> ImportOut:
    """Import the photos of a folder under one of the server's import directories (``FOTOSKHEMA_IMPORT_DIRS``;
    403 when there are none), named relative to it: ``{"root": 0, "path": "route_17/frames"}``. The folder is
    listed, its GPS side file (geo.txt or gps.csv) stored as PUT /gps would, and the import runs in the
    background: follow it with GET. 404/422 for a folder that is not there or outside the directory."""
    runner = request.app.state.imports
    record = await run_in_threadpool(
        folder_import.start_import, db, settings, runner, flight_id, principal.user_id, body
    )
    return import_out(record)


@router.get("", response_model=list[ImportOut])
def list_imports(flight_id: FlightId, db: DbDep, settings: SettingsDep) -> list[ImportOut]:
    """The flight's imports, newest first."""
    return [import_out(r) for r in folder_import.list_imports(db, settings, flight_id)]


@router.get("/{import_id}", response_model=ImportOut)
def get_import(flight_id: FlightId, import_id: ImportId, db: DbDep, settings: SettingsDep) -> ImportOut:
    """How far the import is: photos found, looked at, imported, skipped, refused (with why)."""
    return import_out(folder_import.get_import(db, settings, flight_id, import_id))


@router.post("/{import_id}/cancel", response_model=ImportOut)
def cancel_import(
    flight_id: FlightId, import_id: ImportId, principal: UserDep, db: DbDep, settings: SettingsDep
) -> ImportOut:
    """Stop a running import after its current photo; what it imported stays. 409 once it has ended."""
    return import_out(folder_import.cancel_import(db, settings, flight_id, import_id))
