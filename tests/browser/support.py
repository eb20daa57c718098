"""What the browser tests share: where Chromium is, and a watch over everything a page says and asks for."""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"
JOB_TIMEOUT_MS = 180_000
TILE_URL = re.compile(r"/tiles/\d+/(?:load-steps/\d+/)?\d+/\d+/\d+\.png")  # a mosaic's or a load stage's
TERMINAL_STATUS_JS = """() => {
  const badge = document.querySelector('[data-testid="job-status"]');
  return badge !== null && ['succeeded', 'failed', 'cancelled'].includes(badge.textContent.trim());
}"""
MOSAIC_TILES_SETTLED_JS = """() => {
  const tiles = [...document.querySelectorAll('[data-testid="map"] img.leaflet-tile')]
    .filter((img) => img.src.includes('/tiles/'));
  // complete: loaded or failed (a failed tile is reported by the response and console checks); one
  // zoom level left and every tile faded in: Leaflet has finished swapping levels.
  const zooms = new Set(tiles.map((img) => img.src.split('/').slice(-3)[0]));  // .../{z}/{x}/{y}.png
  return tiles.length > 0 && zooms.size === 1
    && tiles.every((img) => img.complete && getComputedStyle(img).opacity === '1');
}"""


def chromium_path() -> str | None:
    if CHROMIUM.exists():
        return str(CHROMIUM)
    return shutil.which("chromium")


@dataclass
class PageWatch:
    """Everything a page said or asked for that a test may want to assert on."""

    console_errors: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)
    request_urls: list[str] = field(default_factory=list)
    failed_requests: list[str] = field(default_factory=list)
    error_responses: list[str] = field(default_factory=list)
    tile_responses: list[tuple[str, int, str]] = field(default_factory=list)

    def attach(self, page: Any) -> None:
        page.on("console", self._on_console)
        page.on("pageerror", lambda exc: self.page_errors.append(str(exc)))
        page.on("request", lambda request: self.request_urls.append(request.url))
        page.on("requestfailed", self._on_request_failed)
        page.on("response", self._on_response)

    def _on_console(self, message: Any) -> None:
        if message.type == "error":
            self.console_errors.append(f"{message.text} ({message.location.get('url', '')})")

    def _on_request_failed(self, request: Any) -> None:
        # ERR_ABORTED is the page cancelling its own request: Leaflet drops the tiles of a zoom level
        # it left before they arrived. Anything else (refused, reset, DNS) is a real failure.
        if "ERR_ABORTED" not in (request.failure or ""):
            self.failed_requests.append(f"{request.url}: {request.failure}")

    def _on_response(self, response: Any) -> None:
        if response.status >= 400:
            self.error_responses.append(f"{response.status} {response.url}")
        if TILE_URL.search(response.url):
            content_type = response.headers.get("content-type", "")
            self.tile_responses.append((response.url, response.status, content_type))

    def forget(self, fragment: str) -> None:
        """Drop the error answers (and the browser's console line about them) a test provoked on purpose."""
        self.error_responses[:] = [r for r in self.error_responses if fragment not in r]
        self.console_errors[:] = [c for c in self.console_errors if "status of 4" not in c]

    def summary(self) -> str:
        problems = self.page_errors + self.console_errors + self.error_responses + self.failed_requests
        return "; ".join(problems) or "no errors recorded"

    def assert_clean(self, service_url: str) -> None:
        assert not self.page_errors, f"uncaught page errors: {self.page_errors}"
        assert not self.console_errors, f"console errors: {self.console_errors}"
        assert not self.error_responses, f"HTTP error answers: {self.error_responses}"
        assert not self.failed_requests, f"failed requests: {self.failed_requests}"
        # data: and blob: URLs are the page's own inline resources, never network traffic.
        foreign = [
            url
            for url in self.request_urls
            if not url.startswith(service_url.rstrip("/") + "/") and not url.startswith(("data:", "blob:"))
        ]
        assert not foreign, f"requests that left the service: {foreign}"


def sign_in_by_link(page: Any, service_url: str, token: str, route: str = "/") -> None:
    """Open ``route`` (e.g. ``/`` or ``/jobs/3``) with a sign-in link (``#<route>?token=...``; ``#token=...`` for
    ``/``) and wait until the top bar says who is signed in."""
    from playwright.sync_api import expect

    page.goto(f"{service_url}/#token={token}" if route == "/" else f"{service_url}/#{route}?token={token}")
    expect(page.get_by_test_id("signed-in-as")).to_be_visible()


def wait_for(page: Any, script: str, timeout_ms: int, watch: PageWatch, what: str) -> None:
    """Wait for ``script`` to return true; on timeout, fail saying what the page reported meanwhile."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeoutError

    try:
        page.wait_for_function(script, timeout=timeout_ms)
    except PlaywrightTimeoutError:
        pytest.fail(f"{what} within {timeout_ms / 1000:.0f} s; the page reported: {watch.summary()}")
