"""Before processing, in headless Chromium against the real service: the flight page shows where the photos were
taken, a preview of each and what the upload check found (a blurred photo, a dark one), a bad photo is deleted
before starting, and the options form starts a job with the options chosen."""

from __future__ import annotations

from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from PIL import Image

from tests.browser.support import ARTIFACTS
from tests.scenes import make_flight

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Five sound frames, a blurred one and an under-exposed one, all with their EXIF GPS."""
    flight = make_flight(tmp_path_factory.mktemp("check"), n_frames=7, frame_size=(480, 360), seed=11)
    for path, spoil in ((flight.paths[5], "blur"), (flight.paths[6], "dark")):
        exif = Image.open(path).info["exif"]
        rgb = np.asarray(Image.open(path).convert("RGB"))
        spoiled = cv2.GaussianBlur(rgb, (0, 0), 3.5) if spoil == "blur" else (rgb * 0.1).astype(np.uint8)
        Image.fromarray(spoiled).save(path, quality=92, exif=exif)
    return flight.paths


def test_the_check_flags_a_blurred_and_a_dark_photo_and_one_is_deleted(signed_in_page, live_service, photos) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    created = httpx.post(
        f"{live_service.url}/api/flights", json={"name": "Checked"}, headers=live_service.headers
    ).json()
    page.goto(f"{live_service.url}/#/flights/{created['id']}")
    page.get_by_test_id("file-input").set_input_files([str(p) for p in photos])
    rows = page.get_by_test_id("image-row")
    expect(rows).to_have_count(7, timeout=30_000)
    blurred = page.locator(f'[data-testid="image-row"]:has(td.filename:text-is("{photos[5].name}"))')
    dark = page.locator(f'[data-testid="image-row"]:has(td.filename:text-is("{photos[6].name}"))')
    expect(blurred.get_by_test_id("photo-check")).to_contain_text("Blurred")
    expect(blurred.get_by_test_id("photo-check")).to_contain_text("variance of the Laplacian")
    expect(dark.get_by_test_id("photo-check")).to_contain_text("Too dark")
    expect(dark.get_by_test_id("photo-check")).to_contain_text("nearly black")
    expect(page.locator("tr.flagged")).to_have_count(2)
    expect(page.get_by_test_id("check-summary")).to_contain_text("flags 2 photos of 7")
    # every photo on the map, the flagged ones in red; a preview of each
    markers = page.locator('[data-testid="photo-map"] path.leaflet-interactive')
    expect(markers).to_have_count(7)
    assert sorted(markers.evaluate_all("(ms) => ms.map((m) => m.getAttribute('fill'))")).count("#dc2626") == 2
    page.wait_for_function(
        "() => [...document.querySelectorAll('[data-testid=\"photo-thumb\"]')]"
        ".every((img) => img.complete && img.naturalWidth > 0)"
    )
    assert page.get_by_test_id("photo-thumb").count() == 7
    page.get_by_test_id("only-flagged").check()
    expect(rows).to_have_count(2)
    ARTIFACTS.mkdir(exist_ok=True)
    page.get_by_test_id("only-flagged").uncheck()
    page.screenshot(path=str(ARTIFACTS / "flight_check.png"), full_page=True)

    page.once("dialog", lambda dialog: dialog.accept())
    blurred.get_by_test_id("delete-photo").click()
    expect(rows).to_have_count(6)
    expect(markers).to_have_count(6)
    expect(page.locator("tr.flagged")).to_have_count(1)
    names = [
        i["filename"]
        for i in httpx.get(f"{live_service.url}/api/flights/{created['id']}", headers=live_service.headers).json()[
            "images"
        ]
    ]
    assert photos[5].name not in names and len(names) == 6
    watch.assert_clean(live_service.url)


def test_the_options_form_starts_a_job_with_what_was_chosen(signed_in_page, live_service, photos) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    url, headers = live_service.url, live_service.headers
    created = httpx.post(f"{url}/api/flights", json={"name": "Options"}, headers=headers).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in photos[:3]]
    assert httpx.post(f"{url}/api/flights/{created['id']}/images", files=files, headers=headers, timeout=60).is_success
    page.goto(f"{url}/#/flights/{created['id']}")
    expect(page.get_by_test_id("option-feature_type-default")).to_have_text("default: ORB features")
    expect(page.get_by_test_id("option-working_max_px")).to_have_value("2048")
    page.get_by_test_id("mode-ortho").check()
    expect(page.get_by_test_id("option-feature_type")).to_have_value("sift")  # ortho's default
    expect(page.get_by_test_id("option-output_resolution")).to_be_disabled()
    page.get_by_test_id("mode-planar").check()
    expect(page.get_by_test_id("option-feature_type")).to_have_value("orb")
    page.get_by_test_id("option-working_max_px").fill("1024")
    page.get_by_test_id("option-working_max_px").dispatch_event("change")
    page.get_by_test_id("option-blend").select_option("multiband")
    page.screenshot(path=str(ARTIFACTS / "flight_options.png"), full_page=False)
    page.get_by_test_id("start-job").click()
    page.wait_for_url("**/#/jobs/*")
    job_id = int(page.url.rsplit("/", 1)[1])
    job = httpx.get(f"{url}/api/jobs/{job_id}", headers=headers).json()
    assert job["options"] == {"working_max_px": 1024, "blend": "multiband"}  # only what differs from the defaults
    httpx.post(f"{url}/api/jobs/{job_id}/cancel", headers=headers)
    watch.assert_clean(url)
