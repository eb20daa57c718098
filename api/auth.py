"""Who a request acts for, and whether it may touch what its path names.

Every route but health, viewer configuration and static files is behind ``authorize``, a router dependency:
it reads ``Authorization: Bearer <token>`` (401 without a valid one), or, for the reads that image tags and
``EventSource`` make (tiles, downloads, the event stream of a job), a signed ``?exp=&sig=`` for that job.
A job or flight named in the path that the user may not see answers 404, as if it did not exist. With
``FOTOSKHEMA_PUBLIC_READ`` on, GET requests need no token (writes still do).
"""

from __future__ import annotations

import asyncio
from datetime import datetime
from typing import Annotated
from urllib.parse import parse_qs, urlencode

from fastapi import Depends, Request
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import TypeAdapter, ValidationError
from sqlalchemy import select
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from api.deps import DbDep, SettingsDep
from api.errors import ForbiddenError, NotFoundError, UnauthorizedError
from core import accounts
from core.accounts import Principal
from core.db import Database, Flight, Job
from core.settings import Settings

READ_METHODS = frozenset({"GET", "HEAD"})
# The reads a signed URL opens: what image tags, links and EventSource fetch. Not the job's JSON, its outputs
# listing or its TileJSON, which hand out fresh signatures: those need the token, so a signed link cannot
# renew itself past its expiry or its owner's revoked token.
SIGNED_ROUTES = frozenset(
    {"tile", "load_step_tile", "stage_tile", "stereo_tile", "download_output", "job_events", "tms_tile", "tms_tile_png"}
    | {"download_all", "wmts_capabilities", "stac_item", "job_photo_preview"}
)
# The reads a flight's signature opens (``GET /api/flights/{id}`` answers it): its photos' previews, for <img>.
SIGNED_FLIGHT_ROUTES = frozenset({"image_preview"})
# Of those, the answers that carry links (a WMTS layer's tile template, a STAC item's assets): opened by a signed
# URL they hand on that same signature (``link_signature``), never a fresh one, so a link still cannot renew itself.
RELINKING_ROUTES = frozenset({"wmts_capabilities", "stac_item"})
_AS_INT = TypeAdapter(int)


# Declares the scheme in the OpenAPI schema (the docs page's "Authorize" button); a missing header is ours to answer.
bearer = HTTPBearer(auto_error=False, description="an API token: `fotoskhema users create NAME` prints one")


def token_cache(request: Request) -> accounts.TokenCache:
    return request.app.state.tokens  # type: ignore[no-any-return]


def current_principal(
    tokens: Annotated[accounts.TokenCache, Depends(token_cache)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> Principal | None:
    """The user of the request's token; None when it has none (a 401 comes from ``authorize`` if needed)."""
    if credentials is None or not credentials.credentials.strip():
        return None
    principal = tokens.authenticate(credentials.credentials.strip())
    if principal is None:
        raise UnauthorizedError("the API token is unknown or revoked; sign in again with a valid token")
    return principal


def authorize(
    request: Request,
    db: DbDep,
    settings: SettingsDep,
    principal: Annotated[Principal | None, Depends(current_principal)],
) -> None:
    """The router dependency: a valid token, a valid signature for the job in the path, or public read;
    and the job or flight the path names must be one this user may see."""
    read = request.method in READ_METHODS
    job_id = _path_id(request, "job_id")
    if principal is None:
        signable = read and job_id is not None and _route_name(request) in SIGNED_ROUTES
        if signable and job_id is not None and _signed_for(request, db, settings, job_id):
            return
        flight_id = _path_id(request, "flight_id")
        flight_signed = read and flight_id is not None and _route_name(request) in SIGNED_FLIGHT_ROUTES
        if flight_signed and flight_id is not None and _signed_for_flight(request, db, settings, flight_id):
            return
        if read and settings.public_read:
            return
        raise UnauthorizedError("this needs an API token: send 'Authorization: Bearer <token>'")
    if principal.is_admin:
        return
    if job_id is not None:
        _check_owner(db, Job, job_id, principal, "job")
    if (flight_id := _path_id(request, "flight_id")) is not None:
        _check_owner(db, Flight, flight_id, principal, "flight")


def require_admin(principal: Annotated[Principal | None, Depends(current_principal)]) -> Principal:
    if principal is None:
        raise UnauthorizedError("this needs an admin's API token")
    if not principal.is_admin:
        raise ForbiddenError("only an admin may manage users and their tokens")
    return principal


def require_user(principal: Annotated[Principal | None, Depends(current_principal)]) -> Principal:
    if principal is None:
        raise UnauthorizedError("this needs an API token: send 'Authorization: Bearer <token>'")
    return principal


Viewer = Annotated[Principal | None, Depends(current_principal)]  # None: anonymous public read or a signed URL
UserDep = Annotated[Principal, Depends(require_user)]
AdminDep = Annotated[Principal, Depends(require_admin)]


def owner_filter(viewer: Principal | None) -> int | None:
    """The owner id a listing is limited to, or None for all (an admin, or anonymous public read)."""
    return None if viewer is None or viewer.is_admin else viewer.user_id


def job_signature(settings: Settings, job_id: int, created_at: datetime) -> str:
    """The query string (``exp=...&sig=...``) that opens a job's tiles, downloads and events for a while."""
    key = accounts.signing_key(settings.secret_key, settings.data_dir)
    return urlencode(accounts.sign(key, accounts.job_scope(job_id, created_at), settings.signed_url_seconds))


def link_signature(
    request: Request, viewer: Principal | None, settings: Settings, job_id: int, created: datetime
) -> str:
    """The query string that signs the links of an answer about job ``job_id``: the request's own ``exp`` and
    ``sig`` when a signed URL opened it (``authorize`` has checked them), else a fresh signature."""
    exp, sig = request.query_params.get("exp"), request.query_params.get("sig")
    if viewer is None and exp is not None and sig is not None and _route_name(request) in RELINKING_ROUTES:
        return urlencode({"exp": exp, "sig": sig})
    return job_signature(settings, job_id, created)


def _signed_for(request: Request, db: Database, settings: Settings, job_id: int) -> bool:
    exp, sig = request.query_params.get("exp"), request.query_params.get("sig")
    if exp is None or sig is None:
        return False
    key = accounts.signing_key(settings.secret_key, settings.data_dir)
    with db.session() as s:
        job = s.get(Job, job_id) if 1 <= job_id < 2**63 else None
        scope = accounts.job_scope(job_id, job.created_at) if job is not None else None
    if scope is None or not accounts.signature_valid(key, scope, exp, sig):
        raise UnauthorizedError("the link has expired or is not valid; open the job again to get a new one")
    return True


def _signed_for_flight(request: Request, db: Database, settings: Settings, flight_id: int) -> bool:
    exp, sig = request.query_params.get("exp"), request.query_params.get("sig")
    if exp is None or sig is None:
        return False
    key = accounts.signing_key(settings.secret_key, settings.data_dir)
    with db.session() as s:
        flight = s.get(Flight, flight_id) if 1 <= flight_id < 2**63 else None
        scope = accounts.flight_scope(flight_id, flight.created_at) if flight is not None else None
    if scope is None or not accounts.signature_valid(key, scope, exp, sig):
        raise UnauthorizedError("the link has expired or is not valid; open the flight again to get a new one")
    return True


def _path_id(request: Request, name: str) -> int | None:
    """The path parameter ``name`` read as the route reads it (pydantic's lax int: "5.0", " 5", "+5" are 5),
    so that no spelling of an id the route accepts escapes the owner check."""
    raw = request.path_params.get(name)
    if raw is None:
        return None
    try:
        return _AS_INT.validate_python(raw)
    except ValidationError:
        return None  # the route's own validation answers 422


def _route_name(request: Request) -> str:
    route = request.scope.get("route")
    return str(getattr(route, "name", ""))


def _check_owner(
    db: Database, model: type[Job] | type[Flight], record_id: int, principal: Principal, what: str
) -> None:
    if not 1 <= record_id < 2**63:
        return  # the route's own validation answers 422
    with db.session() as s:
        row = s.execute(select(model.owner_id).where(model.id == record_id)).first()
        if row is not None and not principal.may_see(row.owner_id):
            raise NotFoundError(f"{what} {record_id} not found")


class TrustedHosts:
    """Answer 400 to a request whose ``Host`` header is not one of ``allowed`` ("*" allows any): a page on an
    attacker's domain that resolves to this machine (DNS rebinding) is refused. JSON like every error."""

    def __init__(self, app: ASGIApp, allowed: list[str]) -> None:
        self.app = app
        self.any = "*" in allowed
        self.allowed = {h.lower() for h in allowed}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or self.any:
            await self.app(scope, receive, send)
            return
        host = Headers(scope=scope).get("host", "").lower()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host  # "[::1]:8000" -> "[::1]"
        if name in self.allowed or name.strip("[]") in self.allowed:
            await self.app(scope, receive, send)
            return
        detail = "this server does not answer for that host name (set FOTOSKHEMA_ALLOWED_HOSTS)"
        await JSONResponse({"detail": detail}, status_code=400)(scope, receive, send)


# NodeODM's routes (api/routes/nodeodm.py) take the token as ?token=, as NodeODM clients send it; no other does
QUERY_TOKEN_PATHS = ("/task/",)


class BearerForWrites:
    """Answer 401 at once to a write (POST, PUT, DELETE, ...) under /api or /tiles without a valid bearer
    token, before its body is read: a client without one cannot make the server spool an upload (FastAPI
    reads a form before it runs the route's dependencies). The owner checks are ``authorize``'s. NodeODM's
    writes (under /task/) are held to the same, their token read from ``?token=`` too (NodeODM's ``error``
    field in the answer)."""

    def __init__(self, app: ASGIApp, tokens: accounts.TokenCache) -> None:
        self.app, self.tokens = app, tokens

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        node = path.startswith(QUERY_TOKEN_PATHS)
        if (
            scope["type"] == "http"
            and scope["method"] not in READ_METHODS | {"OPTIONS"}
            and (path.startswith(("/api/", "/tiles/")) or node)
        ):
            scheme, _, token = Headers(scope=scope).get("authorization", "").partition(" ")
            token = token.strip() if scheme.lower() == "bearer" else ""
            if node and not token:
                token = _query_token(scope)
            if not token:
                detail = "this needs an API token: send 'Authorization: Bearer <token>'"
            elif await asyncio.to_thread(self.tokens.authenticate, token) is None:
                detail = "the API token is unknown or revoked; sign in again with a valid token"
            else:
                await self.app(scope, receive, send)
                return
            body = {"detail": detail, "error": detail} if node else {"detail": detail}
            response = JSONResponse(body, status_code=401, headers=UnauthorizedError.headers)
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)


def _query_token(scope: Scope) -> str:
    values = parse_qs(bytes(scope.get("query_string", b"")).decode("latin-1")).get("token", [])
    return values[0].strip()[:512] if values else ""
