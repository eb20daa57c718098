"""The viewer in headless Chromium against the real service (Redis, Celery worker, uvicorn).

A user creates a flight, uploads synthetic frames through the file input, starts a mosaic job, follows
it to the end and sees the mosaic's tiles on the map. Every test fails on any console error, uncaught
page error or HTTP error answer, and on any request that leaves the service (the machines are offline:
no CDN, no basemap unless configured).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.browser.support import ARTIFACTS, JOB_TIMEOUT_MS, MOSAIC_TILES_SETTLED_JS, TERMINAL_STATUS_JS, wait_for
from tests.conftest import shared_data
from tests.scenes import make_flight

pytestmark = pytest.mark.browser


@pytest.fixture(params=["synthetic", "brighton"])
def photos(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, list[Path], str]:
    """(name, photo files, their size as the page prints it): 5 synthetic frames, or the 6 real
    Brighton drone frames of ../shared/data (the issue's 'done when')."""
    if request.param == "brighton":
        return "brighton", sorted(shared_data("drone_brighton_strip1").glob("*.JPG")), "4000 × 2250"
    flight = make_flight(tmp_path / "frames", n_frames=5, frame_size=(480, 360), gps=True, seed=7)
    return "synthetic", flight.paths, "480 × 360"


def test_mosaic_job_from_upload_to_map(signed_in_page, live_service, photos) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    name, paths, size_text = photos

    page.goto(f"{live_service.url}/")
    page.get_by_test_id("flight-name-input").fill("Browser test flight")
    page.get_by_test_id("create-flight").click()
    page.wait_for_url(re.compile(r"#/flights/\d+$"))
    expect(page.get_by_test_id("start-job")).to_be_disabled()

    page.get_by_test_id("file-input").set_input_files([str(p) for p in paths])
    rows = page.get_by_test_id("image-row")
    expect(rows).to_have_count(len(paths), timeout=60_000)
    expect(page.get_by_test_id("upload-progress")).to_have_attribute("aria-valuenow", "100")
    expect(rows.filter(has_text="no GPS")).to_have_count(0)  # every frame carries EXIF GPS
    expect(rows.first).to_contain_text(size_text)

    start = page.get_by_test_id("start-job")
    expect(start).to_be_enabled()
    start.click()
    page.wait_for_url(re.compile(r"#/jobs/\d+$"))
    expect(page.get_by_test_id("job-progress")).to_be_visible()
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the job did not finish")
    status = page.get_by_test_id("job-status").inner_text().strip()
    if status != "succeeded":
        error = page.get_by_test_id("job-error")
        detail = error.inner_text() if error.is_visible() else "(no error message shown)"
        pytest.fail(f"job ended {status}: {detail} (service logs: {getattr(live_service, 'logs', '?')})")
    expect(page.get_by_test_id("job-progress")).to_have_attribute("aria-valuenow", "100")
    expect(page.locator("li.stage")).not_to_have_count(0)
    expect(page.locator("li.stage:not(.stage-done)")).to_have_count(0)  # every stage done, with its time
    # EventSource cannot send the token: the stream is opened with the job's signature.
    followed = any(re.search(r"/events\?exp=\d+&sig=[^&]+$", url) for url in watch.request_urls)
    assert followed, "the job page did not follow the job by Server-Sent Events (with the job's signature)"

    expect(page.get_by_test_id("map")).to_be_visible()
    expect(page.locator('[data-testid="map"] img.leaflet-tile-loaded[src*="/tiles/"]').first).to_be_visible(
        timeout=30_000
    )
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic tiles did not settle")
    footprints_url = page.get_by_test_id("download-footprints").get_attribute("href")
    n_footprints = len(page.request.get(footprints_url).json()["features"])
    assert n_footprints >= 2, "a mosaic of overlapping frames has at least two footprints"
    expect(page.locator('[data-testid="map"] .leaflet-overlay-pane path')).to_have_count(n_footprints)

    page.get_by_test_id("opacity").fill("50")
    mosaic_layer = page.locator('[data-testid="map"] .leaflet-mosaic-pane .leaflet-layer').last
    expect(mosaic_layer).to_have_css("opacity", "0.5")
    page.get_by_test_id("opacity").fill("100")
    expect(page.get_by_test_id("quality")).to_be_visible()  # the report's Quality card, below the map
    expect(page.get_by_test_id("frames-used")).to_contain_text(re.compile(rf"^\d+ of {len(paths)}$"))
    ARTIFACTS.mkdir(exist_ok=True)  # before the checks below, so a failing run leaves its picture too
    page.screenshot(path=str(ARTIFACTS / f"viewer_{name}.png"), full_page=True)

    tiles = watch.tile_responses
    assert tiles, "no tile was requested"
    bad = [t for t in tiles if t[1] != 200 or not t[2].startswith("image/png")]
    assert not bad, f"tiles not answered 200 image/png: {bad}"

    cog = page.request.get(page.get_by_test_id("download-cog").get_attribute("href"))
    assert cog.ok, f"COG download answered {cog.status}"
    assert cog.body()[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"), "mosaic.tif is not a TIFF"
    report = page.request.get(page.get_by_test_id("download-report").get_attribute("href"))
    assert report.ok, f"report download answered {report.status}"
    assert isinstance(report.json(), dict)

    watch.assert_clean(live_service.url)


def test_flight_list_and_offline_api_docs(signed_in_page, live_service) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    page.goto(f"{live_service.url}/")
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    expect(page.get_by_test_id("flight-name-input")).to_be_visible()
    expect(page.locator(".card-body").first).not_to_contain_text("Loading flights")
    page.wait_for_load_state("networkidle")

    page.goto(f"{live_service.url}/docs")
    expect(page.locator(".swagger-ui").first).to_be_visible()
    expect(page.locator(".swagger-ui .opblock").first).to_be_visible()  # the spec loaded and rendered
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)


def test_a_long_unspaced_flight_name_wraps_instead_of_widening_the_page(signed_in_page, live_service) -> None:
    """A 200-character name and a 300-character description without spaces had made the flight page 3300 px wide
    (the breadcrumb kept the name on one line)."""
    import httpx
    from playwright.sync_api import expect

    page, watch = signed_in_page
    body = {"name": "Q" * 200, "description": "d" * 300}
    flight = httpx.post(f"{live_service.url}/api/flights", json=body, timeout=10, headers=live_service.headers).json()
    page.goto(f"{live_service.url}/#/flights/{flight['id']}")
    expect(page.locator("main h1")).to_contain_text("Q" * 20)
    page.wait_for_load_state("networkidle")
    assert page.evaluate("document.documentElement.scrollWidth") <= page.evaluate("window.innerWidth")
    watch.assert_clean(live_service.url)
