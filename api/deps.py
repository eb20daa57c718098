"""Typed dependencies: everything a handler needs comes from the app's state, built once."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Query, Request

from api.queue import JobQueue
from core.db import Database
from core.settings import Settings
from workers.config import MAX_ID


def get_settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


def get_db(request: Request) -> Database:
    return request.app.state.db  # type: ignore[no-any-return]


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings)]
DbDep = Annotated[Database, Depends(get_db)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]

# Ids and indices in a path or query are bounded to what the database holds (signed 64-bit), so a larger
# number is answered 422 instead of overflowing the driver.
JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="the job's id")]
FlightId = Annotated[int, Path(ge=1, le=MAX_ID, description="the flight's id")]
FlightFilter = Annotated[int | None, Query(ge=1, le=MAX_ID, description="only the jobs of this flight")]
ImageId = Annotated[int, Path(ge=1, le=MAX_ID, description="the photo's id")]
PhotoIndex = Annotated[int, Path(ge=0, le=MAX_ID, description="the photo's place in the job's inputs, from 0")]
PreviewSize = Annotated[int, Query(ge=32, le=2048, description="longer side of the preview, px")]
TokenId = Annotated[int, Path(ge=1, le=MAX_ID, description="the token's id")]
UserName = Annotated[str, Path(max_length=64, description="the user's name")]
TileIndex = Annotated[int, Path(ge=-MAX_ID - 1, le=MAX_ID)]  # a zoom, column, row or load step
