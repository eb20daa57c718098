"""Bounds on every request body and on every JSON the API parses.

``RequestLimits`` counts a body while it streams, before anything is spooled: the whole body, each file of a
multipart body, the number of its parts. Every JSON (request bodies, the multipart ``options`` field, GCP
files) is checked before it is parsed (its size, its nesting depth); then values no response or database can
hold (NaN, Infinity, 1e400, lone surrogates) are refused with their path, so that no such value is stored.

Python's ``json`` recurses once per level, so a body of ten thousand ``[`` would otherwise end in a
``RecursionError``; the depth is counted first by a scan that does not recurse.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from python_multipart.multipart import parse_options_header
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.errors import ApiError, InvalidInputError, TooLargeError
from api.uploads import display_name
from core.settings import Settings

MAX_JSON_BYTES = 1024 * 1024  # a JSON body or options field; Starlette's own limit on a multipart field too
MAX_JSON_DEPTH = 32  # nested objects and arrays; the deepest valid request (crack-survey options) has 7
MAX_INT_DIGITS = 100  # longer integers are refused while parsing, not converted

# Escapes first, then strings: two linear passes (one regex for strings with escapes backtracks quadratically
# over a run of escaped quotes that is never closed)
_ESCAPE = re.compile(rb"\\.", re.DOTALL)
_STRING = re.compile(rb'"[^"]*"')
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")
_OPENING = np.frombuffer(b"[{", dtype=np.uint8)


def nesting_depth(data: str | bytes) -> int:
    """How deeply the objects and arrays of a JSON text nest (``{}``: 1); strings are skipped, nothing recurses."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    brackets = _STRING.sub(b"", _ESCAPE.sub(b"", raw)).translate(None, _NOT_BRACKETS)
    if not brackets:
        return 0
    codes = np.frombuffer(brackets, dtype=np.uint8)
    steps = np.where(np.isin(codes, _OPENING), 1, -1)
    return int(np.cumsum(steps).max(initial=0))


def parse_json(data: str | bytes, what: str, max_bytes: int = MAX_JSON_BYTES) -> Any:
    """``data`` parsed, or ``TooLargeError`` / ``InvalidInputError`` naming ``what`` (the path of a value that
    is not a finite number starts with it: ``options.stages[0].load``) and the limit it breaks."""
    check_json(data, what, max_bytes)
    try:
        value = json.loads(data, parse_int=_short_int)
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"{what}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    except UnicodeDecodeError:
        raise InvalidInputError(f"{what}: not UTF-8 text") from None
    except ValueError as exc:  # an integer refused by _short_int
        raise InvalidInputError(f"{what}: {exc}") from None
    if (problem := _unstorable(value, what)) is not None:
        raise InvalidInputError(problem)
    return value


def check_json(data: str | bytes, what: str, max_bytes: int = MAX_JSON_BYTES) -> None:
    """Size and nesting depth of a JSON text that is about to be parsed."""
    if len(data) > max_bytes or (isinstance(data, str) and len(data.encode("utf-8", "surrogatepass")) > max_bytes):
        raise TooLargeError(f"{what}: larger than {max_bytes} bytes")
    depth = nesting_depth(data)
    if depth > MAX_JSON_DEPTH:
        raise InvalidInputError(f"{what}: JSON nested {depth} levels deep; at most {MAX_JSON_DEPTH} are accepted")


_JSON_NAMES = {"nan": "NaN", "inf": "Infinity (or a number beyond 1.8e308)", "-inf": "-Infinity"}


def _short_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise ValueError(f"an integer of {digits} digits is out of range; at most {MAX_INT_DIGITS} digits are read")
    return int(text)


def _unstorable(value: Any, path: str) -> str | None:
    """What is wrong with the first value of parsed JSON that no response or database can hold: NaN or an
    infinity (``json`` reads NaN, Infinity and 1e400), or a string with a lone surrogate (``"\\ud800"``).
    The depth is already bounded, so recursing is safe."""
    if isinstance(value, float) and not math.isfinite(value):
        return f"{path}: {_JSON_NAMES[str(value)]} is not a finite number"
    if isinstance(value, str) and not _is_unicode(value):
        return f"{path}: not valid Unicode (a lone surrogate escape such as \\ud800)"
    if isinstance(value, dict):
        for key, item in value.items():
            where = f"{path}.{key}" if _is_unicode(key) else path
            if (problem := _unstorable(key, where) or _unstorable(item, where)) is not None:
                return problem
    if isinstance(value, list):
        for k, item in enumerate(value):
            if (problem := _unstorable(item, f"{path}[{k}]")) is not None:
                return problem
    return None


def _is_unicode(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


class JsonBodyLimits:
    """ASGI middleware: a request body FastAPI would parse as JSON is checked by ``parse_json`` first, and
    refused (413 too large; 422 too deep, not JSON, or a value no database holds) before any route sees it."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        tus_patch = scope.get("method") == "PATCH" and _TUS_UPLOAD.match(scope.get("path", ""))  # bytes, never JSON
        if (
            scope["type"] != "http"
            or scope["method"] in ("GET", "HEAD", "OPTIONS")
            or tus_patch
            or not _json_request(scope)
        ):
            await self.app(scope, receive, send)
            return
        body, error = await _read_body(scope, receive)
        if error is None and body:
            try:
                parse_json(body, "body")
            except ApiError as exc:
                error = exc
        if error is not None:
            await JSONResponse({"detail": error.detail}, status_code=error.status_code)(scope, receive, send)
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": body, "more_body": False}

        await self.app(scope, replay, send)


def _json_request(scope: Scope) -> bool:
    """Whether FastAPI would parse this body as JSON: no content type, ``application/json`` or ``+json``."""
    headers = dict(scope["headers"])
    content_type = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
    return not content_type or content_type == b"application/json" or content_type.endswith(b"+json")


async def _read_body(scope: Scope, receive: Receive) -> tuple[bytes, ApiError | None]:
    too_large = TooLargeError(f"body: larger than {MAX_JSON_BYTES} bytes")
    declared = dict(scope["headers"]).get(b"content-length", b"")
    if declared.isdigit() and int(declared) > MAX_JSON_BYTES:
        return b"", too_large
    chunks, size = [], 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            break
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > MAX_JSON_BYTES:
            return b"", too_large
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks), None


# -- Request bodies, bounded while they stream ---------------------------------------------------------------

MAX_GCP_BYTES = 5 * 1024 * 1024  # a GCP file (ODM gcp_list.txt or OpenSfM JSON)
MULTIPART_OVERHEAD = 64 * 1024  # what a small multipart request adds to its file: boundaries, part headers
# A GPS side file (geo.txt or CSV, ~60 bytes a frame: ~16000 frames). Its route keeps the default 1 MiB body
# cap (it is not one of _UPLOAD_ROUTES), so the file is bounded below that cap by the multipart overhead.
MAX_GPS_BYTES = MAX_JSON_BYTES - MULTIPART_OVERHEAD
MAX_PART_HEADER_BYTES = 16 * 1024  # the headers of one multipart part


@dataclass(frozen=True)
class BodyLimits:
    """The most one request may send: the whole body, and for multipart the number of parts and each one's size
    (a file part's ``file_bytes`` unless ``field_file_bytes`` names its field; a part without a file name,
    such as ``options``, ``MAX_JSON_BYTES``: Starlette's own limit on a form field)."""

    request_bytes: int
    parts: int = 16
    file_bytes: int = MAX_JSON_BYTES
    field_file_bytes: tuple[tuple[str, int], ...] = ()

    def part_bytes(self, field: str, filename: str | None) -> int:
        if filename is None:
            return MAX_JSON_BYTES
        return dict(self.field_file_bytes).get(field, self.file_bytes)


_UPLOAD_ROUTES = [  # (method, path, kind): the routes that take files
    ("POST", "/api/flights/{id}/images", "photos"),
    ("POST", "/api/calibrations", "photos"),
    ("POST", "/api/stereo-rigs", "photos"),
    ("POST", "/api/crack-surveys", "survey"),
    ("PUT", "/api/flights/{id}/gcps", "gcps"),
    ("POST", "/task/new/upload/{id}", "photos"),  # NodeODM's: photos, and geo.txt or gcp_list.txt beside them
]
_TUS_UPLOAD = re.compile(r"^/api/flights/[^/]+/uploads/[^/]+/?$")  # a resumable upload's URL (api.routes.uploads)
_ROUTE_PATTERNS = [
    (method, re.compile("^" + re.escape(path).replace(re.escape("{id}"), "[^/]+") + "/?$"), kind)
    for method, path, kind in _UPLOAD_ROUTES
]


def body_limits(settings: Settings, method: str, path: str, content_type: bytes) -> BodyLimits:
    """The limits of a request: those of its route when it sends files to one that takes them, else a body of
    at most ``MAX_JSON_BYTES`` (JSON, a form, anything else). A tus PATCH sends at most one file."""
    if method == "PATCH" and _TUS_UPLOAD.match(path):
        return BodyLimits(settings.max_upload_bytes)
    if content_type == b"multipart/form-data":
        for route_method, pattern, kind in _ROUTE_PATTERNS:
            if method == route_method and pattern.match(path):
                photos = BodyLimits(
                    settings.max_request_bytes, settings.max_files_per_request, settings.max_upload_bytes
                )
                if kind == "survey":
                    return replace(photos, field_file_bytes=(("model", settings.max_mesh_bytes),))
                if kind == "gcps":
                    return BodyLimits(MAX_GCP_BYTES + MULTIPART_OVERHEAD, 4, MAX_GCP_BYTES)
                return photos
    return BodyLimits(MAX_JSON_BYTES)


class _Refused(Exception):
    """Raised into the application by ``receive`` when the body breaks a limit; ``RequestLimits`` answers it."""


class RequestLimits:
    """ASGI middleware in front of everything: a body is bounded before any of it is spooled or parsed.

    A declared ``Content-Length`` over the route's limit is answered 413 without reading the body; otherwise
    the bytes are counted as they arrive (chunked bodies too) and, in a multipart body, each part's size and
    the number of parts. When a limit breaks, ``receive`` raises into the application, so Starlette's form
    parser closes (and so deletes) the spooled files it made, no route has run, and the answer is a 413
    ``{"detail": ...}`` naming the file or the limit, whatever the application was about to send.
    """

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limits = body_limits(self.settings, scope["method"], scope["path"], _content_type(scope))
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > limits.request_bytes:
            await _refuse(
                scope, send, f"request body: {int(declared)} bytes; at most {limits.request_bytes} are accepted"
            )
            return
        meter = _BodyMeter(limits, _boundary(scope))
        started = False

        async def counted() -> Message:
            message = await receive()
            if message["type"] == "http.request" and (problem := meter.feed(message.get("body", b""))):
                raise _Refused(problem)
            return message

        async def guarded(message: Message) -> None:
            nonlocal started
            if meter.problem is None:  # once refused, the application's own answer (a 400) is not sent
                started = started or message["type"] == "http.response.start"
                await send(message)

        try:
            await self.app(scope, counted, guarded)
        except _Refused:
            pass
        except Exception:
            if meter.problem is None:
                raise
        if meter.problem is not None:
            if started:  # a response under way cannot be replaced; the connection is cut instead
                raise _Refused(meter.problem)
            await _refuse(scope, send, meter.problem)


async def _refuse(scope: Scope, send: Send, detail: str) -> None:
    async def nothing() -> Message:
        return {"type": "http.disconnect"}

    # no "Connection: close": uvicorn then reads and drops the rest of the body for its keep-alive time, so the
    # client, still sending, reads this answer instead of a connection reset
    response = JSONResponse({"detail": detail}, status_code=413)
    await response(scope, nothing, send)


def _content_type(scope: Scope) -> bytes:
    return bytes(dict(scope["headers"]).get(b"content-type", b"")).split(b";")[0].strip().lower()


def _boundary(scope: Scope) -> bytes | None:
    if _content_type(scope) != b"multipart/form-data":
        return None
    _, params = parse_options_header(dict(scope["headers"]).get(b"content-type", b""))
    return params.get(b"boundary") or None


class _BodyMeter:
    """Counts a body as it streams: its size and, in a multipart body (``boundary`` given), the parts and the
    size of each. Just enough of RFC 7578 to find where each part's data starts and ends (the boundary may be
    split across chunks); Starlette parses the body itself. ``feed`` answers the first limit broken."""

    def __init__(self, limits: BodyLimits, boundary: bytes | None) -> None:
        self.limits = limits
        self.delimiter = b"\r\n--" + boundary if boundary else b""
        self.size = 0
        self.problem: str | None = None
        self.parts = 0
        self.state = "data"  # data (the preamble too) -> after delimiter -> headers -> data ...; "end"
        self.buffer = b"\r\n"  # the first delimiter has no line break before it
        self.part: tuple[str, str | None, int] | None = None  # (field, file name, limit) of the part read now
        self.part_size = 0

    def feed(self, chunk: bytes) -> str | None:
        if self.problem is None:
            self.size += len(chunk)
            if self.size > self.limits.request_bytes:
                self.problem = f"request body: larger than {self.limits.request_bytes} bytes"
            elif self.delimiter and self.state != "end":
                self.buffer += chunk
                self.problem = self._scan()
        return self.problem

    def _scan(self) -> str | None:
        while True:
            if self.state == "data":
                found = self.buffer.find(self.delimiter)
                keep = len(self.delimiter) - 1 if found < 0 else 0
                counted = found if found >= 0 else max(0, len(self.buffer) - keep)
                self.part_size += counted
                if self.part is not None and self.part_size > self.part[2]:
                    field, filename, limit = self.part
                    what = f"{display_name(filename)}: file" if filename is not None else f"{field}: field"
                    return f"{what} is larger than {limit} bytes"
                if found < 0:
                    self.buffer = self.buffer[counted:]
                    return None
                self.buffer, self.state, self.part = self.buffer[found + len(self.delimiter) :], "after", None
            elif self.state == "after":
                if len(self.buffer) < 2:
                    return None
                if self.buffer.startswith(b"--"):
                    self.state, self.buffer = "end", b""
                    return None
                self.parts += 1
                if self.parts > self.limits.parts:
                    return f"more than {self.limits.parts} parts (files and fields) in one request"
                self.state = "headers"
            else:  # headers, from the line break after the delimiter to the blank line
                end = self.buffer.find(b"\r\n\r\n")
                if end < 0:
                    if len(self.buffer) > MAX_PART_HEADER_BYTES:
                        return f"part {self.parts}: headers larger than {MAX_PART_HEADER_BYTES} bytes"
                    return None
                self.part = self._part(self.buffer[:end])
                self.buffer, self.state, self.part_size = self.buffer[end + 4 :], "data", 0

    def _part(self, headers: bytes) -> tuple[str, str | None, int]:
        disposition = b""
        for line in headers.split(b"\r\n"):
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-disposition":
                disposition = value.strip()
        _, options = parse_options_header(disposition)
        field = options.get(b"name", b"").decode("utf-8", "replace")
        raw = options.get(b"filename")
        filename = None if raw is None else raw.decode("utf-8", "replace")
        return field, filename, self.limits.part_bytes(field, filename)
