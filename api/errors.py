"""One table from exception to HTTP status; every error is answered as ``{"detail": ...}``."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse


class ApiError(Exception):
    """An error the client can act on; subclasses fix the status code."""

    status_code = 400

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class NotFoundError(ApiError):
    status_code = 404


class ConflictError(ApiError):
    """The resource exists but is not in a state that allows the request (e.g. job not finished)."""

    status_code = 409


class TooLargeError(ApiError):
    status_code = 413


class InvalidInputError(ApiError):
    status_code = 422


class UnavailableError(ApiError):
    """A backing service (the queue) is down; retrying later may succeed."""

    status_code = 503


def install_error_handlers(app: FastAPI) -> None:
    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ApiError)
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code)

    app.add_exception_handler(ApiError, handle)
