"""Deleting a flight and a job from their pages, in headless Chromium against the real service: the browser's
confirm() is asked first (dismissed: nothing is deleted), then DELETE, and the page goes back to the list."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.browser.support import ARTIFACTS, PageWatch
from tests.scenes import make_flight

pytestmark = pytest.mark.browser


@pytest.fixture
def admin_http(live_service: Any) -> Iterator[httpx.Client]:
    """An HTTP client of the live service with the admin's token."""
    with live_service.client() as http:
        yield http


def _answer_dialogs(page: Any, accept: list[bool]) -> list[str]:
    """Answer the page's next dialogs with ``accept`` (in turn); answers the messages they showed."""
    messages: list[str] = []

    def on_dialog(dialog: Any) -> None:
        messages.append(f"{dialog.type}: {dialog.message}")
        dialog.accept() if accept.pop(0) else dialog.dismiss()

    page.on("dialog", on_dialog)
    return messages


def test_delete_flight_asks_first(
    signed_in_page: tuple[Any, PageWatch], live_service: Any, admin_http: httpx.Client
) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    flight = admin_http.post("/api/flights", json={"name": "To be deleted"}).json()
    page.goto(f"{live_service.url}/#/flights/{flight['id']}")
    expect(page.locator("h1")).to_have_text("To be deleted")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "delete_flight.png"))
    messages = _answer_dialogs(page, [False, True])

    page.get_by_test_id("delete-flight").click()
    assert len(messages) == 1 and messages[0].startswith("confirm: Delete the flight “To be deleted”")
    expect(page).to_have_url(re.compile(rf"#/flights/{flight['id']}$"))
    assert admin_http.get(f"/api/flights/{flight['id']}").status_code == 200, "a dismissed confirm deleted the flight"

    page.get_by_test_id("delete-flight").click()
    page.wait_for_url(re.compile(r"#/$"))
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    expect(page.locator(f'a[href="#/flights/{flight["id"]}"]')).to_have_count(0)
    assert len(messages) == 2
    assert admin_http.get(f"/api/flights/{flight['id']}").status_code == 404
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)


def test_delete_job_goes_back_to_its_flight(
    signed_in_page: tuple[Any, PageWatch], live_service: Any, admin_http: httpx.Client, tmp_path: Path
) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    frames = make_flight(tmp_path / "frames", n_frames=2, frame_size=(320, 240), seed=11)
    flight = admin_http.post("/api/flights", json={"name": "Job to delete"}).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in frames.paths]
    assert admin_http.post(f"/api/flights/{flight['id']}/images", files=files).status_code == 201
    job = admin_http.post("/api/jobs", json={"flight_id": flight["id"], "kind": "mosaic"}).json()
    page.goto(f"{live_service.url}/#/jobs/{job['id']}")
    expect(page.get_by_test_id("job-status")).to_be_visible()
    messages = _answer_dialogs(page, [True])

    page.get_by_test_id("delete-job").click()
    page.wait_for_url(re.compile(rf"#/flights/{flight['id']}$"))
    assert len(messages) == 1 and messages[0].startswith(f"confirm: Delete job #{job['id']}"), messages
    expect(page.locator("h1")).to_have_text("Job to delete")
    expect(page.get_by_test_id("job-item")).to_have_count(0)
    assert admin_http.get(f"/api/jobs/{job['id']}").status_code == 404
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)
