"""A multiband mosaic's cut lines on the job page's map, in headless Chromium against the real service."""

from __future__ import annotations

from typing import Any

import httpx
import pytest

from tests.browser.support import ARTIFACTS, MOSAIC_TILES_SETTLED_JS, wait_for
from tests.scenes import make_flight

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def multiband_job(live_service: Any, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A finished multiband mosaic of 5 synthetic GPS frames, made through the HTTP API."""
    folder = tmp_path_factory.mktemp("cutlines") / "frames"
    flight = make_flight(folder, n_frames=5, frame_size=(480, 360), gps=True, seed=7)
    url, headers = live_service.url, live_service.headers
    created = httpx.post(f"{url}/api/flights", json={"name": "Seams"}, timeout=10, headers=headers).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in flight.paths]
    uploaded = httpx.post(f"{url}/api/flights/{created['id']}/images", files=files, timeout=60, headers=headers)
    assert uploaded.status_code < 300, uploaded.text
    body = {"flight_id": created["id"], "kind": "mosaic", "options": {"blend": "multiband"}}
    response = httpx.post(f"{url}/api/jobs", json=body, timeout=10, headers=headers)
    assert response.status_code == 202, response.text
    job = live_service.wait_for_job(response.json()["id"], timeout=180)
    assert job["status"] == "succeeded", f"mosaic job ended {job['status']}: {job['error']}"
    return job


def test_cut_lines_are_drawn_over_the_mosaic(signed_in_page, live_service, multiband_job) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    page.goto(f"{live_service.url}/#/jobs/{multiband_job['id']}")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic tiles did not settle")
    paths = page.locator('[data-testid="map"] .leaflet-overlay-pane path')
    footprints = page.request.get(page.get_by_test_id("download-footprints").get_attribute("href")).json()
    cutlines = page.request.get(page.get_by_test_id("download-cutlines").get_attribute("href")).json()
    n_footprints = len(footprints["features"])
    assert len(cutlines["features"]) == n_footprints == 5
    toggle = page.get_by_test_id("cutlines-toggle")
    expect(toggle).not_to_be_checked()  # off at first: the footprints are what a user looks at first
    expect(paths).to_have_count(n_footprints)
    toggle.check()
    expect(paths).to_have_count(2 * n_footprints)  # Leaflet draws each frame's MultiPolygon as one path
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "viewer_cutlines.png"), full_page=True)
    toggle.uncheck()
    expect(paths).to_have_count(n_footprints)
    watch.assert_clean(live_service.url)
