"""Resumable uploads of a flight's photos (tus 1.0.0: core, creation, checksum, termination, expiration); the
protocol and storage are ``api.resumable``'s. Every answer carries ``Tus-Resumable``, errors too."""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Request, Response
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from starlette.types import ASGIApp, Receive, Scope, Send

from api import photo_service, resumable
from api.auth import UserDep
from api.deps import DbDep, FlightId, SettingsDep
from api.errors import ApiError, NotFoundError, PreconditionFailedError
from api.models import ImageOut, UploadOut
from api.photo_service import image_out
from core.db import Database, Flight
from core.settings import Settings

TUS_HEADERS = {"Tus-Resumable": resumable.TUS_VERSION}
# what a browser on another origin (FOTOSKHEMA_CORS_ORIGINS) must be let send and read
TUS_REQUEST_HEADERS = ["Tus-Resumable", "Upload-Length", "Upload-Metadata", "Upload-Offset", "Upload-Checksum"]
TUS_REQUEST_HEADERS += ["X-HTTP-Method-Override"]
TUS_RESPONSE_HEADERS = ["Location", "Tus-Resumable", "Tus-Version", "Tus-Extension", "Tus-Max-Size"]
TUS_RESPONSE_HEADERS += [
    "Tus-Checksum-Algorithm",
    "Upload-Offset",
    "Upload-Length",
    "Upload-Metadata",
    "Upload-Expires",
]


class TusRoute(APIRoute):
    """A route whose answers, errors included, say ``Tus-Resumable: 1.0.0`` as the protocol asks."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def tus_handler(request: Request) -> Response:
            try:
                response = await handler(request)
            except ApiError as exc:
                response = JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)
            response.headers.update(TUS_HEADERS)
            return response

        return tus_handler


def tus_version(tus_resumable: str | None) -> None:
    """412 (naming the version we speak) for a request without ``Tus-Resumable: 1.0.0``; checked in the handler,
    after the path's ids (a dependency would answer before their 422)."""
    if tus_resumable != resumable.TUS_VERSION:
        raise PreconditionFailedError(f"Tus-Resumable: this server speaks tus {resumable.TUS_VERSION}")


router = APIRouter(prefix="/api/flights/{flight_id}/uploads", tags=["uploads"], route_class=TusRoute)
TusResumable = Annotated[str | None, Header(description="the protocol version: 1.0.0")]
UploadId = Annotated[str, Path(pattern="^[0-9a-f]{32}$", description="the upload's id, from its URL")]


def upload_out(db: Database, state: resumable.UploadState, settings: Settings | None = None) -> UploadOut:
    """The upload as JSON; once complete, with its photo as the flight answers it (judged by the photo check,
    its preview signed) when ``settings`` are given, else as stored."""
    image = resumable.image_of(db, state)
    if image is not None and settings is not None:
        judged = photo_service.judged_image(db, settings, image.flight_id, image.id)
        return _upload_out(state, judged)
    return _upload_out(state, image_out(image) if image is not None else None)


def _upload_out(state: resumable.UploadState, image: ImageOut | None) -> UploadOut:
    return UploadOut(
        id=state.id,
        url=state.location,
        filename=state.filename,
        length=state.length,
        offset=state.offset,
        complete=state.complete,
        expires_at=None if state.complete else state.expires_at,
        image=image,
    )


def _flight_exists(db: Database, flight_id: int) -> None:
    with db.session() as s:
        if s.get(Flight, flight_id) is None:
            raise NotFoundError(f"flight {flight_id} not found")


@router.options("", status_code=204)
def tus_options(flight_id: FlightId, settings: SettingsDep) -> Response:
    """What this tus server does: version, extensions, the largest file, checksum algorithms."""
    return Response(status_code=204, headers=server_headers(settings))


def server_headers(settings: Settings) -> dict[str, str]:
    return {
        "Tus-Version": resumable.TUS_VERSION,
        "Tus-Extension": resumable.TUS_EXTENSIONS,
        "Tus-Max-Size": str(settings.max_upload_bytes),
        "Tus-Checksum-Algorithm": ",".join(resumable.CHECKSUMS),
    }


@router.post("", status_code=201, response_model=UploadOut)
def create_upload(
    flight_id: FlightId,
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    tus_resumable: TusResumable = None,
    upload_length: Annotated[str | None, Header(description="the file's size in bytes")] = None,
    upload_metadata: Annotated[str | None, Header(description="'filename <base64>', other keys kept")] = None,
    upload_defer_length: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> JSONResponse:
    """tus creation: a new upload of ``Upload-Length`` bytes (at most the per-file limit; 413 above, 507 when
    the disk cannot hold it); its URL is in ``Location``. Send the bytes with PATCH."""
    tus_version(tus_resumable)
    _flight_exists(db, flight_id)
    state = resumable.create_upload(
        db, settings, flight_id, principal.user_id, upload_length, upload_metadata, upload_defer_length
    )
    body = upload_out(db, state).model_dump(mode="json")
    return JSONResponse(body, status_code=201, headers={"Location": state.location, **state.headers()})


@router.get("", response_model=list[UploadOut])
def list_uploads(flight_id: FlightId, principal: UserDep, db: DbDep) -> list[UploadOut]:
    """The flight's unfinished uploads and how far each is."""
    _flight_exists(db, flight_id)
    return [upload_out(db, state) for state in resumable.list_uploads(db, flight_id)]


@router.head("/{upload_id}")
def upload_offset(
    flight_id: FlightId,
    upload_id: UploadId,
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    tus_resumable: TusResumable = None,
) -> Response:
    """tus core: where to resume (``Upload-Offset``) and the whole length; 404 unknown, 410 expired."""
    tus_version(tus_resumable)
    state = resumable.upload_state(db, settings, flight_id, upload_id)
    headers = {**state.headers(), "Upload-Length": str(state.length), "Cache-Control": "no-store"}
    if state.metadata_header:
        headers["Upload-Metadata"] = state.metadata_header
    return Response(status_code=200, headers=headers)


@router.get("/{upload_id}", response_model=UploadOut)
def get_upload(
    flight_id: FlightId, upload_id: UploadId, principal: UserDep, db: DbDep, settings: SettingsDep
) -> UploadOut:
    """The upload as JSON: how far it is and, once complete, the photo it became."""
    return upload_out(db, resumable.upload_state(db, settings, flight_id, upload_id), settings)


@router.patch("/{upload_id}", status_code=204)
async def append_bytes(
    flight_id: FlightId,
    upload_id: UploadId,
    request: Request,
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    tus_resumable: TusResumable = None,
) -> Response:
    """tus core: append the body (``Content-Type: application/offset+octet-stream``) at ``Upload-Offset`` (409
    if that is not where the upload stands), optionally checked by ``Upload-Checksum`` (460 on a mismatch;
    nothing of the chunk is kept). The last byte makes it a photo of the flight, checked as a multipart photo is
    (413/422, 409 for a duplicate: the upload is deleted)."""
    tus_version(tus_resumable)
    names = ("content-type", "upload-offset", "upload-checksum")
    headers = {name: request.headers.get(name) for name in names}
    state = await resumable.append(db, settings, flight_id, upload_id, headers, request.stream())
    return Response(status_code=204, headers=state.headers())


@router.delete("/{upload_id}", status_code=204)
def terminate_upload(
    flight_id: FlightId,
    upload_id: UploadId,
    principal: UserDep,
    db: DbDep,
    settings: SettingsDep,
    tus_resumable: TusResumable = None,
) -> Response:
    """tus termination: the upload and its stored bytes are deleted (a complete upload's photo stays)."""
    tus_version(tus_resumable)
    resumable.terminate_upload(db, settings, flight_id, upload_id)
    return Response(status_code=204)


class TusMethodOverride:
    """tus core: a POST with ``X-HTTP-Method-Override: PATCH`` (or ``DELETE``) to an upload URL is that method,
    for clients that cannot send it. Only there, and only those two: nothing else changes its method."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "POST" and _is_upload_url(scope["path"]):
            override = dict(scope["headers"]).get(b"x-http-method-override", b"").strip().upper()
            if override in (b"PATCH", b"DELETE"):
                scope = {**scope, "method": override.decode()}
        await self.app(scope, receive, send)


def _is_upload_url(path: str) -> bool:
    parts = path.strip("/").split("/")
    return len(parts) == 5 and parts[:2] == ["api", "flights"] and parts[3] == "uploads"
