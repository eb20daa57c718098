"""No HTML injection in the viewer: names that are HTML are shown as text on every page, in headless Chromium.

A flight, its photos and a crack survey are made through the real API with names that are markup (an
``<img>`` whose ``onerror`` sets ``window.__pwned``, a ``<details ontoggle>``, a ``<script>``, entities); a
planar mosaic and the survey run for real, so the footprints' tooltips and the survey's load-step labels
carry the names as the workers wrote them. What no quick job gives (a job's error and a running job's
detail, a quality report's rejected frames and GCPs, a calibration, a survey's warnings, an output whose
url is a ``javascript:`` URL) is answered by ``page.route`` with markup in every user-supplied field. Every
page must show the strings literally and run none of them: ``window.__pwned`` stays undefined, no dialog
opens, no element of the markup is in the page (no request for the ``<img>``'s src ``x``), and nothing is
logged as an error.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path
from typing import Any

import httpx
import pytest
from PIL import Image

from tests.browser.support import ARTIFACTS, MOSAIC_TILES_SETTLED_JS, PageWatch, wait_for
from tests.crack_scenes import CrackSurveyScene, make_crack_survey
from tests.scenes import make_flight

pytestmark = pytest.mark.browser

PWN = "window.__pwned=1;alert(document.domain)"
IMG = f"<img src=x onerror={PWN}>"  # no quote, no slash: survives as a file name
FLIGHT_NAME = f'Quarry "><img src=x onerror="{PWN}">'
FLIGHT_DESCRIPTION = "North face <script>window.__pwned=1</script> Tom &amp; Jerry <b>bold</b>"
PHOTO_NAMES = [
    f"{IMG}.JPG",
    "<svg onload=window.__pwned=1>.JPG",
    "<details open ontoggle=window.__pwned=1>.jpg",
    "<iframe src=javascript:window.parent.__pwned=1>.jpg",
    "&lt;b&gt;bold&lt;&#47;b&gt; &amp; <b>x.jpg",
]
GCP_IMAGES = ["<svg/onload=window.__pwned=1>.JPG", "<b>x</b>&amp;.JPG"]  # whitespace-free: gcp_list.txt fields
STEP_LABELS = [f"10 kN {IMG}", "20 kN <details open ontoggle=window.__pwned=1>"]
SURVEY_PHOTOS = [f"{IMG} step {s + 1}.png" for s in range(2)]
JS_URL = "javascript:window.__pwned=1"

USER_NAME = f'admin"><img src=x onerror={PWN}><b>root</b><script>window.__pwned=1</script>'

# Elements or attributes the payloads would have created had they been parsed as HTML, in the page (#app) or
# in the top bar (the signed-in user's name); the viewer itself makes no <b>.
MARKUP_FOUND_JS = """() => [...document.querySelectorAll(['#app', '.topbar']
  .flatMap((root) => ['img[src="x"]', '[onerror]', '[onload]', '[ontoggle]', 'iframe', 'script', 'details', 'b']
    .map((s) => `${root} ${s}`))
  .concat(['.leaflet-tooltip *:not(span)', 'a[href^="javascript:" i]']).join(', '))].map((node) => node.outerHTML)"""


@pytest.fixture
def page_watch(signed_in_page: tuple[Any, PageWatch]) -> tuple[Any, PageWatch, list[str]]:
    """The watched page, and every dialog it opened (an ``alert`` run by an injected handler)."""
    page, watch = signed_in_page
    dialogs: list[str] = []

    def on_dialog(dialog: Any) -> None:
        dialogs.append(f"{dialog.type}: {dialog.message}")
        dialog.dismiss()

    page.on("dialog", on_dialog)
    return page, watch, dialogs


def _assert_inert(page: Any, watch: PageWatch, dialogs: list[str], service_url: str) -> None:
    page.wait_for_load_state("networkidle")
    assert page.evaluate("() => window.__pwned") is None, "an injected handler ran"
    assert not dialogs, f"dialogs opened: {dialogs}"
    assert page.evaluate(MARKUP_FOUND_JS) == [], "markup from a name was parsed into the page"
    assert not [u for u in watch.request_urls if u.rstrip("/").endswith("/x")], "an injected <img> was loaded"
    watch.assert_clean(service_url)


def _humanized(text: str) -> str:
    """``text`` as the viewer's ``humanize`` shows a name: underscores as spaces, the first letter capital."""
    text = text.replace("_", " ")
    return text[:1].upper() + text[1:]


def _job_record(**fields: Any) -> dict[str, Any]:
    """A job record as GET /api/jobs/{id} answers it."""
    record = {
        "flight_id": None,
        "stage": "",
        "stages": [],
        "progress": 100.0,
        "progress_detail": "",
        "timings": {},
        "error": "",
        "options": {},
        "created_at": "2026-01-02T03:04:05",
        "updated_at": "2026-01-02T03:05:06",
    }
    return {**record, **fields}


# -- Made through the real API ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def hostile_mosaic(live_service: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A flight named with markup, its 5 synthetic frames uploaded under markup names, and its finished
    planar mosaic: {"flight", "images" (the upload's answer), "job"}."""
    url = live_service.url
    flight = make_flight(tmp_path_factory.mktemp("hostile") / "frames", n_frames=5, frame_size=(480, 360), seed=7)
    created = httpx.post(
        f"{url}/api/flights",
        json={"name": FLIGHT_NAME, "description": FLIGHT_DESCRIPTION},
        headers=live_service.headers,
    )
    assert created.status_code == 201, created.text
    files = [("files", (name, p.read_bytes(), "image/jpeg")) for name, p in zip(PHOTO_NAMES, flight.paths, strict=True)]
    uploaded = httpx.post(
        f"{url}/api/flights/{created.json()['id']}/images", files=files, timeout=60, headers=live_service.headers
    )
    assert uploaded.status_code == 201, uploaded.text
    images = uploaded.json()["images"]
    assert [img["filename"] for img in images] == PHOTO_NAMES, "the API keeps the names for display"
    body = {"flight_id": created.json()["id"], "kind": "mosaic", "options": {}}
    response = httpx.post(f"{url}/api/jobs", json=body, timeout=10, headers=live_service.headers)
    assert response.status_code == 202, response.text
    job = live_service.wait_for_job(response.json()["id"], timeout=180)
    assert job["status"] == "succeeded", f"mosaic job ended {job['status']}: {job['error']}"
    return {"flight": created.json(), "images": images, "job": job}


@pytest.fixture(scope="module")
def hostile_survey(live_service: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A finished two-step crack survey whose load-step labels and photo names are markup."""
    scene: CrackSurveyScene = make_crack_survey(tmp_path_factory.mktemp("hostile_survey"), [(60.0, 0.0)], seed=3)
    options = json.loads(json.dumps(scene.options(0.25)))
    photos = {p.path.name: p.path for p in scene.photos}
    files = []
    for s, step in enumerate(options["stages"]):
        step["label"] = STEP_LABELS[s]
        (photo,) = step["photos"]
        files.append(("files", (SURVEY_PHOTOS[s], photos[photo["image"]].read_bytes(), "image/png")))
        photo["image"] = SURVEY_PHOTOS[s]
    job = live_service.wait_for_job(live_service.submit("/api/crack-surveys", files, options), timeout=180)
    assert job["status"] == "succeeded", f"crack survey ended {job['status']}: {job['error']}"
    return job


# -- Flights -----------------------------------------------------------------------------------------


def test_flight_list_and_flight_page(page_watch, live_service, hostile_mosaic) -> None:
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    flight_id = hostile_mosaic["flight"]["id"]
    page.goto(f"{live_service.url}/")
    row = page.get_by_test_id("flight-row").filter(has=page.locator(f'a[href="#/flights/{flight_id}"]'))
    expect(row).to_contain_text(FLIGHT_NAME)
    expect(row).to_contain_text(FLIGHT_DESCRIPTION)
    _assert_inert(page, watch, dialogs, live_service.url)

    row.get_by_role("link", name=FLIGHT_NAME).click()
    page.wait_for_url(re.compile(rf"#/flights/{flight_id}$"))
    expect(page).to_have_title(f"{FLIGHT_NAME} · Fotoskhema")
    expect(page.locator("h1")).to_have_text(FLIGHT_NAME)
    expect(page.locator(".page-head .lead")).to_have_text(FLIGHT_DESCRIPTION)
    expect(page.locator(".breadcrumb")).to_contain_text(FLIGHT_NAME)
    rows = page.get_by_test_id("image-row")
    expect(rows).to_have_count(len(PHOTO_NAMES))
    for k, name in enumerate(PHOTO_NAMES):
        cell = rows.nth(k).locator("td.filename")
        expect(cell).to_have_text(name)
        expect(cell).to_have_attribute("title", name)

    # The API's own answers naming what the user sent: a photo that is not one, a GCP file naming photos.
    page.get_by_test_id("file-input").set_input_files({"name": f"{IMG}.JPG", "mimeType": "image/jpeg", "buffer": b"no"})
    expect(page.locator(".upload-status.error")).to_contain_text(IMG)
    gcps = "WGS84 UTM 15N\n" + "".join(
        f"271000.0 3294000.0 10.0 240 180 {name} gcp{k}\n" for k, name in enumerate(GCP_IMAGES)
    )
    page.get_by_test_id("gcp-input").set_input_files(
        {"name": "gcp_list.txt", "mimeType": "text/plain", "buffer": gcps.encode()}
    )
    expect(page.get_by_test_id("gcp-status")).to_contain_text(f"Not in this flight: {', '.join(sorted(GCP_IMAGES))}.")
    bad = {"name": f"{IMG}.txt", "mimeType": "text/plain", "buffer": b"not a coordinate system\n"}
    page.get_by_test_id("gcp-input").set_input_files(bad)
    expect(page.get_by_test_id("gcp-error")).to_contain_text(f"{IMG}.txt: line 1")
    watch.forget("/images")
    watch.forget("/gcps")
    _assert_inert(page, watch, dialogs, live_service.url)


# -- A mosaic job ------------------------------------------------------------------------------------

# A report.json's user-supplied strings (photo names, GCP ids, reasons), spliced into the real report.
HOSTILE_TRIANGULATION = {
    "registered": 4,
    "total": 5,
    "datum": f"datum {IMG}",
    "not_registered": [{"name": PHOTO_NAMES[2], "reason": f"reason {IMG}"}],
    "self_calibration": {f"k1 {IMG}": {"initial": 0.0, "adjusted": -0.01}},
    "images": [{"name": name, "rms_px": 0.5, "observations": 100} for name in PHOTO_NAMES],
    "gcps": [{"id": f"gcp {IMG}", "role": f"role {IMG}", "observations": 2, "residual_px": 0.4}],
}


def test_job_page_map_footprints_and_quality(page_watch, live_service, hostile_mosaic, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    job = hostile_mosaic["job"]

    def splice_report(route: Any) -> None:
        report = route.fetch().json()
        report.update(mode=f"mode {IMG}", triangulation=HOSTILE_TRIANGULATION)
        report["frames_rejected"] = [{"index": 9, "name": PHOTO_NAMES[0], "reason": f"blurred {IMG}"}]
        route.fulfill(json=report)

    def splice_outputs(route: Any) -> None:  # an output url that is a script: shown, never linked
        answer = route.fetch().json()
        for output in answer["outputs"]:
            if output["name"] == "mosaic.tif":
                output["url"] = JS_URL
        route.fulfill(json=answer)

    page.route(re.compile(r"/outputs/report\.json(?:\?|$)"), splice_report)
    page.route(re.compile(rf"/api/jobs/{job['id']}/outputs$"), splice_outputs)
    page.goto(f"{live_service.url}/#/jobs/{job['id']}")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    expect(page.locator(".breadcrumb")).to_contain_text(FLIGHT_NAME)
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic tiles did not settle")

    # Each footprint's tooltip, its photo's name as text: hovered one by one, then the real mouse on one.
    footprints = page.request.get(page.get_by_test_id("download-footprints").get_attribute("href")).json()
    names = {f["properties"]["index"]: f["properties"]["name"] for f in footprints["features"]}
    assert sorted(names.values()) == sorted(PHOTO_NAMES), "the worker kept the photos' names"
    paths = page.locator('[data-testid="map"] .leaflet-overlay-pane path')
    expect(paths).to_have_count(len(names))
    tooltip = page.locator(".leaflet-tooltip")
    for k in range(len(names)):
        paths.nth(k).dispatch_event("mouseover")
        expect(tooltip).to_have_count(1)
        shown = tooltip.inner_text()
        index = int(re.match(r"Frame (\d+): ", shown)[1])
        assert shown == f"Frame {index}: {names[index]}"
        paths.nth(k).dispatch_event("mouseout")
        expect(tooltip).to_have_count(0)
    box = page.get_by_test_id("map").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    expect(tooltip).to_contain_text(re.compile(r"^(Camera of f|F)rame \d+: "))  # a footprint, or its camera centre
    expect(tooltip).to_contain_text(re.compile("|".join(re.escape(n) for n in PHOTO_NAMES)))

    # The Quality card: every string of the report as text.
    quality = page.get_by_test_id("quality")
    expect(page.get_by_test_id("quality-mode")).to_have_text(f"mode {IMG}")
    expect(page.get_by_test_id("frames-rejected")).to_contain_text(f"{PHOTO_NAMES[0]}: blurred {IMG}")
    expect(page.get_by_test_id("not-registered")).to_contain_text(f"{PHOTO_NAMES[2]}: reason {IMG}")
    expect(page.get_by_test_id("datum")).to_have_text(f"datum {IMG}")
    expect(page.get_by_test_id("self-calibration")).to_contain_text(f"k1 {IMG}")
    for k, name in enumerate(PHOTO_NAMES):
        expect(page.get_by_test_id("image-residual-row").nth(k).locator(".filename")).to_have_text(name)
    expect(page.get_by_test_id("gcp-row")).to_contain_text(f"gcp {IMG}")
    expect(page.get_by_test_id("gcp-row")).to_contain_text(f"role {IMG}")  # an unknown role: as it is
    expect(quality).to_contain_text(IMG)
    expect(page.get_by_test_id("download-cog")).to_have_count(0)  # its url was a javascript: URL
    expect(page.locator(".downloads")).to_contain_text("Mosaic (Cloud-Optimized GeoTIFF) (not available)")
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)  # the tooltip in the picture
    page.screenshot(path=str(tmp_path / "injection_job.png"), full_page=True)
    _assert_inert(page, watch, dialogs, live_service.url)


def test_job_error_and_progress_detail(page_watch, live_service, hostile_mosaic) -> None:
    """A running job's detail (by Server-Sent Events), then the error of its cancel, both answered here."""
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    real = hostile_mosaic["job"]
    job_id = 9001
    stages = real["stages"]
    running = _job_record(
        **{k: real[k] for k in ("flight_id", "kind", "created_at", "updated_at")},
        id=job_id,
        status="running",
        stage=stages[1],
        stages=stages,
        progress=20.0,
        progress_detail=f"frame 1/5 {IMG}",
    )
    later = {**running, "progress": 30.0, "progress_detail": f"frame 2/5 {PHOTO_NAMES[2]}"}
    cancelled = {**later, "status": "cancelled", "error": f"cancelled: {PHOTO_NAMES[0]} <script>x</script>"}
    # One progress event, then a reconnection asked for in 10 minutes: the page stays on the running job.
    stream = f"retry: 600000\nevent: progress\ndata: {json.dumps(later)}\n\n"
    page.route(re.compile(rf"/api/jobs/{job_id}$"), lambda route: route.fulfill(json=running))
    page.route(
        re.compile(rf"/api/jobs/{job_id}/events(?:\?|$)"),
        lambda route: route.fulfill(status=200, headers={"Content-Type": "text/event-stream"}, body=stream),
    )
    page.route(re.compile(rf"/api/jobs/{job_id}/cancel$"), lambda route: route.fulfill(json=cancelled))
    page.goto(f"{live_service.url}/#/jobs/{job_id}")
    expect(page.locator(".breadcrumb")).to_contain_text(FLIGHT_NAME)
    expect(page.get_by_test_id("job-detail")).to_contain_text(f"frame 2/5 {PHOTO_NAMES[2]}")
    expect(page.locator("li.stage-running .stage-meta")).to_have_text(f"frame 2/5 {PHOTO_NAMES[2]}")
    page.get_by_test_id("cancel-job").click()
    expect(page.get_by_test_id("job-status")).to_have_text("cancelled")
    expect(page.get_by_test_id("job-error")).to_have_text(f"Error: {cancelled['error']}")
    _assert_inert(page, watch, dialogs, live_service.url)


# -- The signed-in user ------------------------------------------------------------------------------


def test_signed_in_user_name(page_watch, live_service) -> None:
    """The name GET /api/me answers (the server allows only letters, digits and ._-, so it is answered here)
    is shown as text in "Signed in as", after a reload and after signing in with the form."""
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    me = {"name": USER_NAME, "is_admin": True, "tokens": []}
    page.route(re.compile(r"/api/me$"), lambda route: route.fulfill(json=me))
    page.reload()
    expect(page.get_by_test_id("signed-in-as")).to_have_text(f"Signed in as {USER_NAME}")
    expect(page.get_by_test_id("user-name")).to_have_text(USER_NAME)
    expect(page.get_by_test_id("signed-in-as")).to_have_attribute("title", f"{USER_NAME} (administrator)")
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "injection_user_name.png"))
    _assert_inert(page, watch, dialogs, live_service.url)

    page.get_by_test_id("sign-out").click()
    page.get_by_test_id("token-input").fill(live_service.token)
    page.get_by_test_id("sign-in-submit").click()
    expect(page.get_by_test_id("user-name")).to_have_text(USER_NAME)
    expect(page.get_by_role("heading", name="Flights", exact=True)).to_be_visible()
    _assert_inert(page, watch, dialogs, live_service.url)


# -- Crack surveys -----------------------------------------------------------------------------------


def test_crack_survey_list_and_page(page_watch, live_service, hostile_survey) -> None:
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    job_id = hostile_survey["id"]

    def splice_survey(route: Any) -> None:  # a warning and a crack status naming what the user typed
        answer = route.fetch().json()
        if answer.get("result"):
            answer["result"]["warnings"] = [f"load step '{STEP_LABELS[0]}': the photos resolve 0.3 mm per pixel"]
            answer["result"]["stages"][0]["cracks"][0]["status"] = f"status {IMG}"
        route.fulfill(json=answer)

    def splice_outputs(route: Any) -> None:
        answer = route.fetch().json()
        answer["outputs"].append({"name": f"{IMG}.png", "url": JS_URL, "size_bytes": 1})
        answer["outputs"].append({"name": "elsewhere.png", "url": "https://example.invalid/a.png", "size_bytes": 1})
        route.fulfill(json=answer)

    page.route(re.compile(rf"/api/crack-surveys/{job_id}$"), splice_survey)
    page.route(re.compile(rf"/api/jobs/{job_id}/outputs$"), splice_outputs)
    page.goto(f"{live_service.url}/#/crack-surveys")
    row = page.get_by_test_id("survey-row").filter(has=page.locator(f'a[href="#/crack-surveys/{job_id}"]'))
    expect(row).to_contain_text(", ".join(STEP_LABELS))
    _assert_inert(page, watch, dialogs, live_service.url)

    row.get_by_role("link", name=f"Survey #{job_id}").click()
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    expect(page.get_by_test_id("stage-title")).to_have_text(STEP_LABELS[0] + " · load 10")
    expect(page.get_by_test_id("survey-warning")).to_contain_text(f"load step '{STEP_LABELS[0]}'")
    expect(page.locator("#crack-table-heading")).to_contain_text(f"Cracks of {STEP_LABELS[0]}")
    expect(page.get_by_test_id("crack-row").first).to_contain_text(f"status {IMG}")
    expect(page.get_by_test_id("stage-slider")).to_have_attribute("aria-valuetext", f"Load step 1: {STEP_LABELS[0]}")
    residuals = page.get_by_test_id("residual-row")
    expect(residuals).to_have_count(2)
    for s in range(2):
        expect(residuals.nth(s).locator(".filename")).to_have_text(SURVEY_PHOTOS[s])
        expect(residuals.nth(s).locator("td").nth(1)).to_have_text(STEP_LABELS[s])
    downloads = page.locator(".survey-downloads")
    expect(downloads).to_contain_text(f"{STEP_LABELS[1]}: rectified specimen (COG)")
    expect(downloads).to_contain_text(f"{IMG}.png (not available)")
    expect(downloads).to_contain_text("elsewhere.png (not available)")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the load step's tiles did not settle")

    cracks = page.locator(".leaflet-overlay-pane path.crack")
    expect(cracks).not_to_have_count(0)
    tooltip = page.locator(".leaflet-tooltip")
    for k in range(cracks.count()):
        cracks.nth(k).dispatch_event("mouseover")
        expect(tooltip).to_contain_text(re.compile(r"^Crack \d+: "))
        cracks.nth(k).dispatch_event("mouseout")
        expect(tooltip).to_have_count(0)
    page.get_by_test_id("crack-row").first.click()  # shows the crack with the hostile status on the map
    crack = page.locator(".leaflet-overlay-pane path.crack-selected")
    expect(crack).to_have_count(1)
    crack.dispatch_event("mouseover")
    expect(tooltip).to_contain_text(f"status {IMG}")

    page.get_by_test_id("stage-slider").fill("1")
    expect(page.get_by_test_id("stage-title")).to_contain_text(STEP_LABELS[1])
    expect(page.get_by_test_id("stage-changes")).to_contain_text(f"Since {STEP_LABELS[0]}: ")
    expect(page.get_by_test_id("stage-slider")).to_have_attribute("aria-valuetext", f"Load step 2: {STEP_LABELS[1]}")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the second load step's tiles did not settle")
    _assert_inert(page, watch, dialogs, live_service.url)


def test_new_crack_survey_form(page_watch, live_service, tmp_path: Path) -> None:
    """A photo added under a markup name, and the API's refusal naming it (answered here: no job runs)."""
    import cv2
    import numpy as np
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    photo = tmp_path / "photo.png"
    cv2.imwrite(str(photo), np.full((60, 80), 128, np.uint8))
    detail = f"options.stages name photo(s) that were not uploaded: {IMG}.png"
    page.route(re.compile(r"/api/crack-surveys$"), lambda route: route.fulfill(status=422, json={"detail": detail}))
    page.goto(f"{live_service.url}/#/crack-surveys/new")
    page.get_by_test_id("camera-from-json").check()
    page.get_by_test_id("camera-json").fill('{"width": 80, "height": 60, "fx": 100, "fy": 100, "cx": 40, "cy": 30}')
    page.get_by_test_id("specimen-width").fill("200")
    page.get_by_test_id("specimen-height").fill("150")
    page.get_by_test_id("stage-label").fill(STEP_LABELS[0])
    page.get_by_test_id("stage-photos").set_input_files(
        {"name": f"{IMG}.png", "mimeType": "image/png", "buffer": photo.read_bytes()}
    )
    editor = page.get_by_test_id("photo")
    expect(editor.locator(".filename")).to_have_text(f"{IMG}.png")
    expect(editor.get_by_test_id("photo-image")).to_have_attribute("alt", re.compile(re.escape(IMG)))
    image = editor.get_by_test_id("photo-image")
    expect(image).to_have_js_property("naturalWidth", 80)
    for x, y in [(16, 12), (64, 12), (16, 48), (64, 48)]:  # the photo is shown 80 x 60 px
        image.click(position={"x": x, "y": y})
    for k, (x, y) in enumerate([(0, 0), (200, 0), (0, 150), (200, 150)]):
        editor.get_by_test_id("point-model-x").nth(k).fill(str(x))
        editor.get_by_test_id("point-model-y").nth(k).fill(str(y))
    page.get_by_test_id("submit-survey").click()
    expect(page.get_by_test_id("survey-error")).to_have_text(f"Not started: {detail}")
    watch.forget("/api/crack-surveys")
    _assert_inert(page, watch, dialogs, live_service.url)


# -- Calibrations ------------------------------------------------------------------------------------


def _calibration_routes(page: Any, service_url: str, job_id: int, kind: str, path: str, result: dict) -> None:
    job = _job_record(id=job_id, kind=kind, status="succeeded")
    outputs = [
        {
            "name": "calibration.json",
            "url": f"{service_url}/api/jobs/{job_id}/outputs/calibration.json",
            "size_bytes": 9,
        },
        {"name": f"{IMG}.json", "url": JS_URL, "size_bytes": 9},
    ]
    page.route(re.compile(rf"/api/jobs/{job_id}$"), lambda route: route.fulfill(json=job))
    page.route(re.compile(rf"/api/{path}/{job_id}$"), lambda route: route.fulfill(json={"job": job, "result": result}))
    page.route(re.compile(rf"/api/jobs/{job_id}/outputs$"), lambda route: route.fulfill(json={"outputs": outputs}))
    photos = {
        "pattern": [9, 6],
        "photos": [
            {
                "index": k,
                "name": name,
                "side": "left" if kind != "calibration" else "",
                "pair": k,
                "width": 64,
                "height": 48,
                "corners": [[1.0, 2.0]],
                "reason": f"reason {IMG}",
                "marks": None,
            }
            for k, name in enumerate(PHOTO_NAMES)
        ],
    }
    page.route(re.compile(rf"/api/{path}/{job_id}/photos$"), lambda route: route.fulfill(json=photos))
    jpeg = io.BytesIO()
    Image.new("RGB", (64, 48), (90, 90, 90)).save(jpeg, "JPEG")
    page.route(
        re.compile(rf"/api/jobs/{job_id}/photos/\d+/preview"),
        lambda route: route.fulfill(body=jpeg.getvalue(), content_type="image/jpeg"),
    )


def test_calibration_and_stereo_rig_pages(page_watch, live_service) -> None:
    from playwright.sync_api import expect

    page, watch, dialogs = page_watch
    points = [{"index": 0, "image_xy": [1.0, 2.0], "board_xyz": [0.0, 0.0, 0.0], "error_px": 0.2}]
    camera = {"width": 640, "height": 480, "fx": 536.0, "fy": 536.0, "cx": 320.0, "cy": 240.0, "convention": IMG}
    calibration = {
        "method": f"chessboard {IMG}",
        "note": f"note {IMG}",
        "rms_px": 0.2,
        "camera": camera,
        "views": [{"image": name, "source": f"source {IMG}", "rms_px": 0.2, "points": points} for name in PHOTO_NAMES],
        "worst_points": [{"image": PHOTO_NAMES[3], "index": 0, "error_px": 0.2}],
        "left_out": [f"{PHOTO_NAMES[4]}: no board found"],
    }
    _calibration_routes(page, live_service.url, 9101, "calibration", "calibrations", calibration)
    page.goto(f"{live_service.url}/#/jobs/9101")
    expect(page.get_by_test_id("calibration-rms")).to_contain_text("0.200 px")
    result = page.locator("section.result")
    expect(result).to_contain_text(f"Method: {_humanized(f'chessboard {IMG}')}")
    expect(result).to_contain_text(f"note {IMG}")
    rows = page.get_by_test_id("view-row")
    expect(rows).to_have_count(len(PHOTO_NAMES))
    for k, name in enumerate(PHOTO_NAMES):
        expect(rows.nth(k).locator(".filename")).to_have_text(name)
        expect(rows.nth(k)).to_contain_text(f"source {IMG}")
    expect(page.get_by_test_id("view-pick").locator("option")).to_have_text(PHOTO_NAMES)
    page.get_by_test_id("view-pick").select_option(index=3)
    expect(page.get_by_test_id("view-points").locator("caption")).to_have_text(f"Marks of {PHOTO_NAMES[3]}")
    expect(page.get_by_test_id("worst-points")).to_contain_text(PHOTO_NAMES[3])
    expect(page.get_by_test_id("left-out")).to_contain_text(f"{PHOTO_NAMES[4]}: no board found")
    expect(result.locator(".downloads")).to_contain_text(f"{IMG}.json (not available)")
    # the photos and their marks: every name as text, in the photo list and the readout
    expect(page.get_by_test_id("marks-photo").locator("option").first).to_contain_text(PHOTO_NAMES[0])
    expect(page.locator('[data-testid="marks-map"] .mark-icon')).to_have_count(1)
    expect(page.get_by_test_id("download-calibration")).to_have_attribute("href", re.compile(r"/api/jobs/9101/"))
    _assert_inert(page, watch, dialogs, live_service.url)

    rig = {
        "baseline_mm": 60.0,
        "rms_px": 0.3,
        "units": f"mm {IMG}",
        "cameras": {
            "left": {"source": f"left {IMG}", "camera": camera},
            "right": {"source": "right", "camera": camera},
        },
        "pairs": [{"left": PHOTO_NAMES[0], "right": PHOTO_NAMES[1], "rms_px": 0.3}],
        "left_out": [f"{PHOTO_NAMES[2]}: no board found"],
    }
    measured = {"units": f"mm {IMG}", "points": [{"xyz": [1.0, 2.0, 3.0], "sigma": 0.1, "ray_gap": 0.01}]}
    _calibration_routes(page, live_service.url, 9102, "stereo_calibration", "stereo-rigs", rig)
    page.route(re.compile(r"/api/stereo-rigs/9102/measure$"), lambda route: route.fulfill(json=measured))
    page.goto(f"{live_service.url}/#/jobs/9102")
    pair = page.get_by_test_id("pair-row")
    expect(pair.locator(".filename")).to_have_text(PHOTO_NAMES[:2])
    expect(page.get_by_test_id("rig-cameras")).to_contain_text(f"left {IMG}")
    expect(page.get_by_test_id("rig-cameras")).to_contain_text(IMG)  # the camera's convention
    expect(page.locator("section.result")).to_contain_text(f"mm {IMG}")
    page.get_by_test_id("measure-input").fill("300 200 250 200\n")
    page.get_by_test_id("measure-submit").click()
    expect(page.get_by_test_id("measure-result")).to_contain_text(f"Units: mm {IMG}")
    _assert_inert(page, watch, dialogs, live_service.url)
