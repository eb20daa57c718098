"""The viewer's quality and calibration pages in headless Chromium against the real service.

Jobs are created through the HTTP API (the upload path is what test_viewer.py covers); the pages are then
opened and read as a user would. Every test fails on console errors, page errors, HTTP error answers it
did not provoke on purpose, and on requests that leave the service.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.browser.support import ARTIFACTS
from tests.conftest import shared_data
from tests.scenes import make_flight

pytestmark = pytest.mark.browser

NUMBER = re.compile(r"-?\d+(?:\.\d+)?")

# A report.json triangulation as the ortho pipeline writes it, with some fields missing on purpose.
TRIANGULATION = {
    "registered": 28,
    "total": 29,
    "not_registered": [{"name": "frame_028.jpg", "reason": "too few tie points with the registered cameras"}],
    "rms_px": 0.61,
    "rms_px_original": 1.22,
    "observations": 5120,
    "points": 1400,
    "outliers_dropped": 37,
    "datum": "gps_line_level_cameras",
    "self_calibration": {
        "focal_px_original": {"initial": 3000.0, "adjusted": 3012.4},
        "k1": {"initial": 0.0, "adjusted": -0.0123},
    },
    "images": [
        {
            "name": f"frame_{i:03d}.jpg",
            "rms_px": 0.5 + i / 100,
            "observations": 180 + i,
            "gps_residual_m": 0.8 if i else None,
            "status": "placed again" if i == 3 else "registered",
        }
        for i in range(28)
    ],
    "gps_residual_rms_m": 1.05,
    "gcps": [
        {
            "id": "gcp1",
            "role": "control",
            "observations": 4,
            "residual_px": 0.7,
            "error_m": [0.01, -0.02, 0.03],
            "error_3d_m": 0.037,
        },
        {"id": "chk1", "role": "checkpoint", "observations": 3, "residual_px": None, "error_m": None},  # no error_3d_m
    ],
}


def _numbers(text: str) -> list[float]:
    return [float(m) for m in NUMBER.findall(text)]


def _post_job(live_service: Any, path: str, files: list[tuple[str, tuple[str, bytes, str]]], options: dict) -> dict:
    job = live_service.wait_for_job(live_service.submit(path, files, options), timeout=120)
    assert job["status"] == "succeeded", f"{path} job ended {job['status']}: {job['error']}"
    return job


def _jpegs(paths: list[Path], field: str) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [(field, (p.name, p.read_bytes(), "image/jpeg")) for p in paths]


@pytest.fixture(scope="module")
def planar_job(live_service: Any, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A finished planar mosaic of 5 synthetic frames, made through the HTTP API."""
    folder = tmp_path_factory.mktemp("quality") / "frames"
    flight = make_flight(folder, n_frames=5, frame_size=(480, 360), gps=True, seed=7)
    url = live_service.url
    created = httpx.post(
        f"{url}/api/flights", json={"name": "Quality test flight"}, timeout=10, headers=live_service.headers
    ).json()
    uploaded = httpx.post(
        f"{url}/api/flights/{created['id']}/images",
        files=_jpegs(flight.paths, "files"),
        timeout=60,
        headers=live_service.headers,
    )
    assert uploaded.status_code < 300, uploaded.text
    body = {"flight_id": created["id"], "kind": "mosaic", "options": {}}
    response = httpx.post(f"{url}/api/jobs", json=body, timeout=10, headers=live_service.headers)
    assert response.status_code == 202, response.text
    job = live_service.wait_for_job(response.json()["id"], timeout=180)
    assert job["status"] == "succeeded", f"mosaic job ended {job['status']}: {job['error']}"
    return job


def _screenshot(page: Any, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


@pytest.mark.realdata
def test_calibration_job_page(signed_in_page, live_service) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    lefts = sorted(shared_data("calib_chessboard").glob("left*.jpg"))
    job = _post_job(live_service, "/api/calibrations", _jpegs(lefts, "files"), {"pattern": [9, 6], "square_mm": 25})

    page.goto(f"{live_service.url}/#/jobs/{job['id']}")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    expect(page.locator(".breadcrumb")).to_contain_text("Calibrations")
    expect(page.locator("main")).not_to_contain_text("null")
    expect(page.locator("main")).to_contain_text("Distorts the ideal projection (OpenCV's)")  # not distort_ideal
    rms = page.get_by_test_id("calibration-rms")
    expect(rms).to_contain_text("px")
    (rms_px,) = _numbers(rms.inner_text())
    assert 0 < rms_px < 0.5, f"RMS shown {rms_px}"
    (fx,) = _numbers(page.get_by_test_id("param-fx").inner_text())
    assert abs(fx - 536) < 0.02 * 536, f"fx shown {fx}"  # MANIFEST: fx ~ 536
    expect(page.locator('[data-param="fx"] td').nth(2)).to_contain_text(re.compile(r"\d"))  # its sigma
    expect(page.get_by_test_id("view-row")).to_have_count(len(lefts))
    expect(page.get_by_test_id("worst-points").locator("tbody tr")).to_have_count(10)
    expect(page.get_by_test_id("view-points").locator("tbody tr")).to_have_count(54)  # 9 x 6 corners
    page.get_by_test_id("view-pick").select_option(index=2)
    expect(page.get_by_test_id("view-points").locator("caption")).to_contain_text(lefts[2].name)
    expect(page.get_by_test_id("download-calibration")).to_have_attribute(
        "href", re.compile(r"calibration\.json\?exp=\d+&sig=[^&]+$")
    )
    expect(page.get_by_test_id("job-detail")).to_have_text("Finished: the camera is calibrated.")
    expect(page.get_by_test_id("map")).to_have_count(0)
    page.wait_for_load_state("networkidle")
    _screenshot(page, "calibration")
    assert not any("/api/flights/" in u or "/tiles/" in u for u in watch.request_urls), "a calibration has no flight"
    watch.assert_clean(live_service.url)


@pytest.mark.realdata
def test_failed_calibration_shows_its_error(signed_in_page, live_service, tmp_path) -> None:
    import cv2
    import numpy as np
    from playwright.sync_api import expect

    page, watch = signed_in_page
    blank = tmp_path / "blank.jpg"  # no board: 2 usable views where a calibration needs 3
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    photos = [*sorted(shared_data("calib_chessboard").glob("left*.jpg"))[:2], blank]
    options = json.dumps({"pattern": [9, 6], "square_mm": 25})
    response = httpx.post(
        f"{live_service.url}/api/calibrations",
        files=_jpegs(photos, "files"),
        data={"options": options},
        timeout=60,
        headers=live_service.headers,
    )
    assert response.status_code == 202, response.text
    job = live_service.wait_for_job(response.json()["id"], timeout=120)
    assert job["status"] == "failed"

    page.goto(f"{live_service.url}/#/jobs/{job['id']}")
    expect(page.get_by_test_id("job-status")).to_have_text("failed")
    expect(page.get_by_test_id("job-error")).to_contain_text("a calibration needs 3")
    expect(page.get_by_test_id("job-error")).to_contain_text("blank.jpg")
    expect(page.get_by_test_id("retry-job")).to_be_visible()
    page.wait_for_load_state("networkidle")
    assert not any("/api/calibrations/" in u for u in watch.request_urls), "no result to read for a failed job"
    watch.assert_clean(live_service.url)


@pytest.mark.realdata
def test_stereo_rig_page_and_measure(signed_in_page, live_service) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    folder = shared_data("calib_chessboard")
    files = _jpegs(sorted(folder.glob("left*.jpg"))[:6], "left") + _jpegs(
        sorted(folder.glob("right*.jpg"))[:6], "right"
    )
    job = _post_job(live_service, "/api/stereo-rigs", files, {"pattern": [9, 6], "square_mm": 25})

    page.goto(f"{live_service.url}/#/jobs/{job['id']}")
    baseline = page.get_by_test_id("baseline")
    expect(baseline).to_contain_text("mm")
    assert 0 < _numbers(baseline.inner_text())[0] < 500  # OpenCV's sample rig: a few board squares apart
    expect(page.get_by_test_id("pair-row")).to_have_count(6)
    expect(page.get_by_test_id("rig-cameras")).to_contain_text("fx")
    expect(page.get_by_test_id("rig-cameras")).to_contain_text("Distorts the ideal projection (OpenCV's)")

    page.get_by_test_id("measure-input").fill("1 2 3")
    page.get_by_test_id("measure-submit").click()
    expect(page.get_by_test_id("measure-error")).to_contain_text("Line 1")  # checked before sending
    page.get_by_test_id("measure-input").fill("300 200 250 200\n400 220 350 221\n")
    page.get_by_test_id("measure-submit").click()
    expect(page.get_by_test_id("measured-point")).to_have_count(2)
    expect(page.get_by_test_id("measured-distance")).to_have_count(1)
    expect(page.get_by_test_id("measured-distance")).to_contain_text("±")
    expect(page.get_by_test_id("measure-error")).to_have_text("")

    page.get_by_test_id("measure-input").fill("9000 200 250 200")
    page.get_by_test_id("measure-submit").click()
    expect(page.get_by_test_id("measure-error")).to_contain_text("outside")  # the API's 422 detail
    expect(page.get_by_test_id("measured-point")).to_have_count(0)
    _screenshot(page, "stereo_rig")
    watch.forget("/measure")
    watch.assert_clean(live_service.url)


def test_quality_card_of_planar_mosaic(signed_in_page, live_service, planar_job) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    quality = page.get_by_test_id("quality")
    expect(quality).to_be_visible()
    expect(page.get_by_test_id("quality-mode")).to_have_text("Planar (flat ground)")
    expect(page.get_by_test_id("frames-used")).to_have_text("5 of 5")
    expect(page.get_by_test_id("frames-rejected")).to_contain_text("No frame was rejected")
    rms = _numbers(page.get_by_test_id("tie-point-rms").inner_text())
    assert len(rms) == 2 and 0 <= rms[0] < 2, f"tie-point RMS shown as {rms}"
    expect(page.get_by_test_id("gsd")).to_contain_text(re.compile(r"\d+(\.\d+)? c?m"))
    expect(page.get_by_test_id("triangulation")).to_have_count(0)  # planar: no photo-triangulation
    expect(page.get_by_test_id("gps-drift")).to_have_count(0)  # 5 fixes: too few to tell drift from noise
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)


def test_quality_card_shows_triangulation(signed_in_page, live_service, planar_job) -> None:
    """The ortho part of the card, from a planar report with an ortho ``triangulation`` spliced in (and
    some fields removed): the rendering is checked here whatever the state of the ortho pipeline."""
    from playwright.sync_api import expect

    page, watch = signed_in_page

    def splice(route: Any) -> None:
        report = route.fetch().json()
        warning = "frame_028.jpg was placed again after the adjustment (it kept 3 of 410 tie points)"
        surface = {
            "kind": "dense",
            "points": 8446,
            "pairs": 14,
            "dense_points": 635186,
            "coverage": 0.9696,
            "cell_m": 0.342,
            "height_range_m": [-3.78, 6.36],
        }
        # a strip's field, here to check its rendering (and that a file name in it stays text)
        precision = {"median_m": 0.35, "max_m": 1.24, "max_photo_px": 4.96, "worst_frame": "<img src=x>strip_000.tif"}
        report.update(
            mode="ortho",
            triangulation=TRIANGULATION,
            warnings=[warning],
            ortho_surface=surface,
            gps_drift_m=0.42,
            corner_precision=precision,
        )
        del report["gps_residual_rms_m"]
        route.fulfill(json=report)

    page.route(re.compile(r"/outputs/report\.json(?:\?|$)"), splice)
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    expect(page.get_by_test_id("registered")).to_have_text("28 / 29")
    expect(page.get_by_test_id("not-registered")).to_contain_text("frame_028.jpg: too few tie points")
    expect(page.get_by_test_id("rms-reprojection")).to_have_text("0.61 px (1.22 px at full resolution)")
    expect(page.get_by_test_id("gps-residual-rms")).to_have_text("–")  # missing field
    expect(page.get_by_test_id("gps-drift")).to_have_text("42.0 cm")
    expect(page.get_by_test_id("corner-precision")).to_have_text("35.0 cm median, 1.24 m at <img src=x>strip_000.tif")
    expect(page.get_by_test_id("corner-precision").locator("img")).to_have_count(0)
    expect(page.get_by_test_id("image-residual-row")).to_have_count(28)
    expect(page.get_by_test_id("image-residual-row").first.locator("td").nth(5)).to_have_text("–")  # GPS residual
    expect(page.get_by_test_id("quality-warning")).to_have_text(
        "frame_028.jpg was placed again after the adjustment (it kept 3 of 410 tie points)"
    )
    expect(page.get_by_test_id("self-calibration")).to_contain_text("3012.40")
    # identifiers by their display names (core/labels.py), never as the JSON spells them
    expect(page.get_by_test_id("self-calibration")).to_contain_text("Focal length (px of the full-size photo)")
    expect(page.get_by_test_id("datum")).to_have_text(
        "Fitted to the GPS positions along the flight line (cameras taken as level)"
    )
    expect(page.get_by_test_id("image-residual-row").nth(3).locator("td").nth(1)).to_have_text(
        "Placed again after a misfit"
    )
    expect(page.get_by_test_id("gcp-row").first.locator("td").nth(1)).to_have_text("Control point")
    card = page.get_by_test_id("quality").inner_text()
    for raw in ("gps_line_level_cameras", "focal_px_original", "checkpoint"):
        assert raw not in card, f"{raw!r} shown as the API spells it"
    rows = page.get_by_test_id("gcp-row")
    expect(rows).to_have_count(2)
    expect(rows.first).to_contain_text("0.010, -0.020, 0.030 m")
    expect(page.locator('[data-testid="gcp-row"][data-role="checkpoint"] td').nth(5)).to_have_text("–")
    expect(page.get_by_test_id("ortho-surface-kind")).to_have_text(
        "a surface from dense stereo between overlapping photos, the tie points' elsewhere"
    )
    expect(page.get_by_test_id("ortho-surface-dense")).to_have_text(
        "14 pairs, 635186 points, 97 % of the ground two photos see"
    )
    expect(page.get_by_test_id("ortho-surface")).to_contain_text("8446 points, 34.2 cm cells")
    page.wait_for_load_state("networkidle")
    _screenshot(page, "quality_ortho")
    watch.assert_clean(live_service.url)


def test_flight_page_mode_and_gcps(signed_in_page, live_service, planar_job, tmp_path) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    flight_id = planar_job["flight_id"]
    gcps = tmp_path / "gcp_list.txt"
    gcps.write_text(
        "WGS84 UTM 15N\n"
        "271000.0 3294000.0 10.0 240 180 frame_000.jpg gcp1\n"
        "271000.0 3294000.0 10.0 120 170 frame_001.jpg gcp1\n"
        "271050.0 3294010.0 12.0 300 90 frame_001.jpg gcp2\n"
        "271050.0 3294010.0 12.0 30 60 elsewhere.jpg gcp2\n"
    )
    bad = tmp_path / "bad.txt"
    bad.write_text("not a coordinate system\n")

    page.goto(f"{live_service.url}/#/flights/{flight_id}")
    expect(page.get_by_test_id("mode-planar")).to_be_checked()
    expect(page.get_by_test_id("gcp-upload")).to_contain_text("ortho jobs")
    expect(page.get_by_test_id("gps-upload")).to_contain_text("navigation log")
    page.get_by_test_id("gcp-input").set_input_files(str(gcps))
    expect(page.get_by_test_id("gcp-status")).to_have_text(
        "Stored gcp_list.txt: 2 points (2 with a position), 4 observations. Not in this flight: elsewhere.jpg."
    )
    page.get_by_test_id("gcp-input").set_input_files(str(bad))
    expect(page.get_by_test_id("gcp-error")).to_contain_text("Not stored")
    expect(page.get_by_test_id("gcp-error")).to_contain_text("bad.txt: line 1: unknown coordinate system")  # detail
    expect(page.get_by_test_id("gcp-status")).to_have_text("")
    # A GPS side file with a latitude off the globe is refused naming its line; the flight keeps its EXIF GPS.
    bad_gps = tmp_path / "gps.csv"
    bad_gps.write_text("name,lat,lon,alt\nframe_000.jpg,29.76,-95.36,100\nframe_001.jpg,123.0,-95.36,100\n")
    page.get_by_test_id("gps-input").set_input_files(str(bad_gps))
    expect(page.get_by_test_id("gps-error")).to_contain_text("Not stored")
    expect(page.get_by_test_id("gps-error")).to_contain_text("line 3")
    expect(page.get_by_test_id("gps-status")).to_have_text("")
    _screenshot(page, "flight_gcps")
    watch.forget("/gcps")
    watch.forget("/gps")

    # The job request itself is answered here (with the existing planar job) so that no ortho job runs.
    sent: list[dict] = []

    def answer(route: Any) -> None:
        sent.append(route.request.post_data_json)
        route.fulfill(status=202, json=planar_job)

    page.route(re.compile(r"/api/jobs$"), answer)
    page.get_by_label("Ortho").check()
    page.get_by_test_id("start-job").click()
    page.wait_for_url(re.compile(rf"#/jobs/{planar_job['id']}$"))
    assert sent == [{"flight_id": flight_id, "kind": "mosaic", "options": {"mode": "ortho"}}]
    expect(page.get_by_test_id("quality")).to_be_visible()
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)


def test_ortho_job_from_the_flight_page(signed_in_page, live_service, tmp_path) -> None:
    """A user picks Ortho on the flight page; the finished job's card shows the real triangulation."""
    from playwright.sync_api import expect

    from tests.browser.support import JOB_TIMEOUT_MS, MOSAIC_TILES_SETTLED_JS, TERMINAL_STATUS_JS, wait_for
    from tests.terrain_scenes import make_terrain_flight

    page, watch = signed_in_page
    flight = make_terrain_flight(tmp_path / "terrain", rows=2, per_row=4, frame_size=(480, 360), seed=6)
    url = live_service.url
    created = httpx.post(f"{url}/api/flights", json={"name": "Relief"}, timeout=10, headers=live_service.headers).json()
    uploaded = httpx.post(
        f"{url}/api/flights/{created['id']}/images",
        files=_jpegs(flight.paths, "files"),
        timeout=60,
        headers=live_service.headers,
    )
    assert uploaded.status_code == 201, uploaded.text
    page.goto(f"{url}/#/flights/{created['id']}")
    page.get_by_test_id("mode-ortho").check()
    page.get_by_test_id("start-job").click()
    page.wait_for_url(re.compile(r"#/jobs/\d+$"))
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the ortho job did not finish")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    expect(page.get_by_test_id("registered")).to_have_text("8 / 8")
    rms = _numbers(page.get_by_test_id("rms-reprojection").inner_text())
    assert rms and rms[0] < 0.5
    expect(page.get_by_test_id("image-residual-row")).to_have_count(8)
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the orthomosaic tiles did not settle")
    gps = _numbers(page.get_by_test_id("gps-residual-rms").first.inner_text())
    assert gps and gps[0] < 100  # cm: the synthetic GPS is exact, the prior assumes 5 m
    _screenshot(page, "quality_ortho_real")
    watch.assert_clean(url)


def test_quality_card_pictures_and_the_printable_report(signed_in_page, live_service, planar_job) -> None:
    """The card shows the report's four pictures (the SVG outputs, signed) and links report.html, which opens
    as a page of its own: every picture inline, the tables, nothing fetched from anywhere."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    pictures = page.get_by_test_id("quality-pictures")
    expect(pictures.locator("img")).to_have_count(4)
    for name in ("overlap", "positions", "tie-points", "residuals"):
        figure = page.get_by_test_id(f"figure-report-{name}")
        figure.scroll_into_view_if_needed()
        page.wait_for_function("(img) => img.complete && img.naturalWidth > 0", arg=figure.element_handle())
        expect(figure).to_have_attribute("src", re.compile(rf"/outputs/report-{name}\.svg\?exp=\d+&sig="))
    link = page.get_by_test_id("report-html")
    expect(link).to_have_attribute("target", "_blank")
    page.wait_for_load_state("networkidle")
    _screenshot(page, "quality_pictures")
    watch.assert_clean(live_service.url)

    with page.context.expect_page() as opened:
        link.click()
    report = opened.value
    report.wait_for_load_state("load")
    report_requests: list[str] = []
    report.on("request", lambda request: report_requests.append(request.url))
    expect(report.locator("h1")).to_have_text("Mosaic quality report")
    expect(report.locator("figure svg")).to_have_count(4)
    expect(report.locator("h2", has_text="Photo pairs")).to_be_visible()
    expect(report.locator("body")).to_contain_text("Finding features")  # stage times, in words
    assert "detect_features" not in report.locator("body").inner_text()
    report.reload()
    report.wait_for_load_state("networkidle")
    assert all(url.split("?")[0].endswith("/outputs/report.html") for url in report_requests), report_requests
    ARTIFACTS.mkdir(exist_ok=True)
    report.screenshot(path=str(ARTIFACTS / "report_html.png"), full_page=True)
    report.close()


def test_quality_card_without_pictures(signed_in_page, live_service, planar_job) -> None:
    """A report without its SVG pictures (an older job, or one whose pictures were not drawn): the card has no
    Pictures block at all, and nothing else in it (no empty frame, no stray text)."""
    from playwright.sync_api import expect

    page, watch = signed_in_page

    def without_svgs(route: Any) -> None:
        listing = route.fetch().json()
        listing["outputs"] = [o for o in listing["outputs"] if not o["name"].endswith(".svg")]
        route.fulfill(json=listing)

    page.route(re.compile(rf"/api/jobs/{planar_job['id']}/outputs(?:\?|$)"), without_svgs)
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    quality = page.get_by_test_id("quality")
    expect(page.get_by_test_id("frames-used")).to_have_text("5 of 5")
    expect(page.get_by_test_id("quality-pictures")).to_have_count(0)
    expect(quality.locator("figure, img")).to_have_count(0)
    assert "null" not in quality.inner_text() and "undefined" not in quality.inner_text()
    page.wait_for_load_state("networkidle")
    watch.assert_clean(live_service.url)


def test_the_progress_card_says_the_time_left(signed_in_page, live_service, planar_job) -> None:
    """A running job's ETA as the API answers it (spliced into the job's record and its event stream): the time
    left of the job, the running stage's rate and time left, the expected time of the stages to come."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    running = {
        **planar_job,
        "status": "running",
        "stage": "match_features",
        "progress": 40.0,
        "progress_detail": "pair 12/30",
        "timings": {"load_images": 1.2, "detect_features": 3.4},
        "warnings": None,
        "eta": {
            "seconds_left": 95.0,
            "stage_seconds_left": 35.0,
            "stages": {
                "load_images": {"seconds_left": 0, "basis": "done", "unit": None, "units_per_second": None},
                "detect_features": {"seconds_left": 0, "basis": "done", "unit": None, "units_per_second": None},
                "match_features": {"seconds_left": 35.0, "basis": "measured", "unit": "pair", "units_per_second": 0.51},
                "align_frames": {"seconds_left": 6.0, "basis": "history", "unit": None, "units_per_second": None},
                "georeference": {"seconds_left": 0.1, "basis": "history", "unit": None, "units_per_second": None},
                "compose_mosaic": {"seconds_left": 50.0, "basis": "history", "unit": None, "units_per_second": None},
                "write_report": {"seconds_left": 3.9, "basis": "defaults", "unit": None, "units_per_second": None},
            },
        },
    }
    job_path = re.compile(rf"/api/jobs/{planar_job['id']}$")
    page.route(job_path, lambda route: route.fulfill(json={**running, "signature": route.fetch().json()["signature"]}))
    stream = f"retry: 60000\nevent: progress\ndata: {json.dumps(running)}\n\n"
    page.route(
        re.compile(rf"/api/jobs/{planar_job['id']}/events"),
        lambda route: route.fulfill(body=stream, headers={"Content-Type": "text/event-stream"}),
    )
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    expect(page.get_by_test_id("job-eta")).to_have_text("About 1 min 35 s left (this step 35 s)")
    expect(page.get_by_test_id("stage-meta-match_features")).to_have_text("pair 12/30 · 0.51 pairs/s · 35 s left")
    expect(page.get_by_test_id("stage-meta-compose_mosaic")).to_have_text("≈ 50 s")
    expect(page.get_by_test_id("stage-meta-compose_mosaic")).to_have_attribute("title", "time left from earlier jobs")
    expect(page.get_by_test_id("stage-meta-detect_features")).to_have_text("3.4 s")
    expect(page.locator('[data-stage="match_features"] .stage-name')).to_have_text("Matching photo pairs")
    _screenshot(page, "progress_eta")
    watch.assert_clean(live_service.url)


def test_a_strips_footprints_are_coloured_by_how_well_their_corners_are_known(
    signed_in_page, live_service, planar_job
) -> None:
    """A strip's footprints carry their corners' standard error (``corner_sigma_m``): spliced into the planar job's
    footprints with the report's mode made "strip", the one mode that has them."""
    from playwright.sync_api import expect

    page, watch = signed_in_page

    def as_strip(route: Any) -> None:
        report = route.fetch().json()
        route.fulfill(json={**report, "mode": "strip"})

    def with_precision(route: Any) -> None:
        collection = route.fetch().json()
        for i, feature in enumerate(collection["features"]):
            feature["properties"]["corner_sigma_m"] = 0.2 + 0.3 * i
        route.fulfill(json=collection)

    page.route(re.compile(r"/outputs/report\.json(?:\?|$)"), as_strip)
    page.route(re.compile(r"/outputs/footprints\.geojson(?:\?|$)"), with_precision)
    page.goto(f"{live_service.url}/#/jobs/{planar_job['id']}")
    footprints = page.locator('[data-testid="map"] .leaflet-overlay-pane path')
    expect(footprints).to_have_count(5)
    page.get_by_test_id("colour-by").select_option("corner_sigma_m")
    expect(page.get_by_test_id("footprint-legend")).to_contain_text("1.40 m")  # the worst frame's, at the red end
    strokes = footprints.evaluate_all("(paths) => paths.map((p) => p.getAttribute('stroke'))")
    assert len(set(strokes)) == 5, strokes
    page.get_by_test_id("photo-pick").select_option("4")
    expect(page.get_by_test_id("photo-corner-sigma")).to_have_text("1.40 m")
    page.wait_for_load_state("networkidle")
    _screenshot(page, "strip_corner_precision")
    watch.assert_clean(live_service.url)
