"""Browser fixtures: one headless Chromium per module, a fresh watched page per test, and that page signed in
as the live service's admin."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.browser.support import LAUNCH_ARGS, PageWatch, chromium_path, sign_in_by_link


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    executable = chromium_path()
    if executable is None:
        pytest.skip("Chromium not found at /usr/bin/chromium nor on PATH: browser tests need it")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=executable, args=LAUNCH_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def watched_page(browser: Any) -> Iterator[tuple[Any, PageWatch]]:
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    page.set_default_timeout(20_000)
    watch = PageWatch()
    watch.attach(page)
    yield page, watch
    context.close()


@pytest.fixture
def signed_in_page(watched_page: tuple[Any, PageWatch], live_service: Any) -> tuple[Any, PageWatch]:
    """The watched page, signed in as the live service's admin by a ``#token=`` link (the token then stays in
    the tab's sessionStorage across the test's navigations)."""
    page, _ = watched_page
    sign_in_by_link(page, live_service.url, live_service.token)
    return watched_page
