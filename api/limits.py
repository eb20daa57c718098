"""Bounds on every JSON the API parses (request bodies, the multipart ``options`` field, GCP files), checked
before the JSON is parsed (its size, its nesting depth); then values no response or database can hold (NaN,
Infinity, 1e400, lone surrogates), refused with their path, so that no such value is stored.

Python's ``json`` recurses once per level, so a body of ten thousand ``[`` would otherwise end in a
``RecursionError``; the depth is counted first by a scan that does not recurse.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.errors import ApiError, InvalidInputError, TooLargeError

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
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS") or not _json_request(scope):
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
