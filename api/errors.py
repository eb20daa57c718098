"""One table from exception to HTTP status; every error is answered as ``{"detail": ...}``."""

from __future__ import annotations

import json
import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

MAX_ECHO_CHARS = 200  # a 422 shows at most this much of the value it refuses


class ApiError(Exception):
    """An error the client can act on; subclasses fix the status code."""

    status_code = 400
    headers: dict[str, str] | None = None

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class UnauthorizedError(ApiError):
    """No token, or one that is unknown or revoked."""

    status_code = 401
    headers = {"WWW-Authenticate": 'Bearer realm="fotoskhema"'}


class ForbiddenError(ApiError):
    """A valid token that may not do this (an admin route)."""

    status_code = 403


class NotFoundError(ApiError):
    status_code = 404


class ConflictError(ApiError):
    """The resource exists but is not in a state that allows the request (e.g. job not finished)."""

    status_code = 409


class TooLargeError(ApiError):
    status_code = 413


class InvalidInputError(ApiError):
    status_code = 422


class GoneError(ApiError):
    """It existed and was removed (an expired resumable upload): start again."""

    status_code = 410


class PreconditionFailedError(ApiError):
    """A tus request of a protocol version this server does not speak."""

    status_code = 412
    headers = {"Tus-Version": "1.0.0"}


class UnsupportedMediaError(ApiError):
    status_code = 415


class LockedError(ApiError):
    """Another request is writing to this resource now; retry shortly (tus clients do)."""

    status_code = 423


class ChecksumMismatchError(ApiError):
    """tus checksum extension: the chunk's bytes are not those the client hashed; nothing of it was kept."""

    status_code = 460


class InsufficientStorageError(ApiError):
    """The server's disk cannot hold what the request would store."""

    status_code = 507


class UnavailableError(ApiError):
    """A backing service (the queue) is down; retrying later may succeed."""

    status_code = 503


def install_error_handlers(app: FastAPI) -> None:
    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ApiError)
        return JSONResponse({"detail": _encodable(exc.detail)}, status_code=exc.status_code, headers=exc.headers)

    async def handle_invalid_request(_request: Request, exc: Exception) -> JSONResponse:
        """FastAPI's 422 (one entry per problem: loc, msg, type), with the refused ``input`` cut short."""
        assert isinstance(exc, RequestValidationError)
        problems = [{**e, "input": shown(e.get("input"))} for e in exc.errors()]
        return JSONResponse({"detail": jsonable_encoder(problems)}, status_code=422)

    app.add_exception_handler(ApiError, handle)
    app.add_exception_handler(RequestValidationError, handle_invalid_request)


def shown(value: Any) -> Any:
    """A refused value as a 422 may show it: small numbers and short strings as they are, anything else as
    JSON text, cut to ``MAX_ECHO_CHARS``: a response never echoes a huge input back."""
    if value is None or isinstance(value, bool) or (isinstance(value, int) and value.bit_length() <= 600):
        return value
    if isinstance(value, float) and math.isfinite(value):
        return value
    if not isinstance(value, str):
        try:
            value = json.dumps(jsonable_encoder(value), ensure_ascii=False)
        except (ValueError, TypeError, RecursionError):  # NaN, an integer too long to print
            value = f"<{type(value).__name__}>"
    return _encodable(value if len(value) <= MAX_ECHO_CHARS else value[:MAX_ECHO_CHARS] + "...")


def _encodable(text: str) -> str:
    """``text`` with anything UTF-8 cannot encode (a lone surrogate) replaced by ``?``."""
    return text.encode("utf-8", "replace").decode("utf-8")
