"""Crack surveys in headless Chromium against the real service (Redis, Celery worker, uvicorn).

A new user runs a two-stage survey of a rendered specimen (``tests/crack_scenes.py``, cracks known) entirely
in the browser: camera JSON, specimen, two load stages with a photo each, the control points clicked on the
photos where the scene put them and their model coordinates typed; a refused request first (too few
points), then the survey. The finished survey's page is read as a user would: stage tiles, crack table,
the slider to the second stage, a row shown on the map. A curved panel given as a mesh model is surveyed
the same way, some control points' X, Y, Z picked from the model's vertices in its plan view, after a
malformed model was refused in the page. A failed survey's page shows the job's error; a camera picked from
the calibration jobs is sent by the job's id.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.browser.support import ARTIFACTS, JOB_TIMEOUT_MS, MOSAIC_TILES_SETTLED_JS, TERMINAL_STATUS_JS, wait_for
from tests.crack_scenes import CrackSurveyScene, make_crack_survey
from workers.algorithms.specimen import read_mesh

pytestmark = pytest.mark.browser

MM_PER_PX = 0.25
STAGE_TILE = re.compile(r"/tiles/\d+/load-steps/(\d+)/\d+/\d+/\d+\.png(?:\?|$)")  # signed: ?exp=...&sig=...
SECOND_STEP_TILES_SETTLED_JS = """() => {
  const tiles = [...document.querySelectorAll('[data-testid="map"] img.leaflet-tile')]
    .filter((img) => img.src.includes('/tiles/'));
  return tiles.length > 0 && tiles.every((img) => img.src.includes('/load-steps/1/') && img.complete
    && getComputedStyle(img).opacity === '1');
}"""
# The scene's control points 0-3 are the specimen's corners: in a panel's X-Y plan view top left, top right,
# bottom left, bottom right. A click just outside the mesh there picks that corner, a vertex of the mesh.
PLAN_CORNERS = {0: (0.01, 0.01), 1: (0.99, 0.01), 2: (0.01, 0.99), 3: (0.99, 0.99)}


@pytest.fixture(scope="module")
def panel(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    """A curved panel (arc 200 mm, radius 120 mm) seen from 45 degrees above, its mesh in ``panel.obj``."""
    return make_crack_survey(tmp_path_factory.mktemp("panel_browser"), [(45.0, 0.0)], seed=3, panel_radius_mm=120.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    """A 200 x 150 mm plate seen from 60 degrees above it: one 900 x 700 photo per load stage."""
    return make_crack_survey(tmp_path_factory.mktemp("crack_browser"), [(60.0, 0.0)], seed=3)


def _screenshot(page: Any, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)
    # After a full-page screenshot Chromium's scroll offset lags behind what the page reports, and the next
    # click by position lands ~100 px off (measured: on the form instead of its button); scrolling resyncs it.
    page.evaluate("() => window.scrollTo(0, 0)")


def _click_points(
    page: Any,
    photo: Any,
    points: list[dict[str, list[float]]],
    first: int = 0,
    axes: str = "xy",
    picked: tuple[int, ...] = (),
) -> None:
    """Click each control point where it lies on the displayed photo, then type its model coordinates along
    ``axes``; the points numbered in ``picked`` (corners, see ``PLAN_CORNERS``) take theirs from the mesh's
    vertex picked in the plan view instead."""
    image = photo.get_by_test_id("photo-image")
    width, height = image.evaluate("(img) => [img.naturalWidth, img.naturalHeight]")
    for k, point in enumerate(points, start=first):
        image.scroll_into_view_if_needed()  # each time: typing or picking may have scrolled the page
        box = image.bounding_box()
        x, y = point["pixel"]  # (0, 0): the centre of the first pixel
        page.mouse.click(box["x"] + (x + 0.5) * box["width"] / width, box["y"] + (y + 0.5) * box["height"] / height)
        if k in picked:  # the point just added is the selected one
            plan = photo.get_by_test_id("mesh-plan")
            size = plan.bounding_box()
            fx, fy = PLAN_CORNERS[k]
            plan.click(position={"x": fx * size["width"], "y": fy * size["height"]})
            continue
        row = photo.get_by_test_id("point-row").nth(k)
        for axis, value in zip(axes, point["model"], strict=False):
            row.get_by_test_id(f"point-model-{axis}").fill(f"{value:g}")


def _typed_model(photo: Any, k: int) -> list[float]:
    row = photo.get_by_test_id("point-row").nth(k)
    return [float(row.get_by_test_id(f"point-model-{axis}").input_value()) for axis in "xyz"]


def _stage_tiles(watch: Any, stage: int) -> list[tuple[str, int, str]]:
    return [r for r in watch.tile_responses if (m := STAGE_TILE.search(r[0])) and int(m[1]) == stage]


def test_two_stage_survey_made_and_read_in_the_browser(signed_in_page, live_service, scene: CrackSurveyScene) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    photos = [[p for p in scene.photos if p.stage == s][0] for s in range(2)]
    page.goto(f"{live_service.url}/")
    page.get_by_test_id("start-crack-survey").click()
    page.wait_for_url(re.compile(r"#/crack-surveys/new$"))

    page.get_by_test_id("camera-from-json").check()
    page.get_by_test_id("camera-json").fill(json.dumps(scene.camera.to_json()))
    page.get_by_test_id("specimen-width").fill(f"{scene.width_mm:g}")
    page.get_by_test_id("specimen-height").fill(f"{scene.height_mm:g}")
    page.get_by_test_id("mm-per-px").fill(str(MM_PER_PX))
    page.get_by_test_id("add-stage").click()
    stages = page.get_by_test_id("stage")
    expect(stages).to_have_count(2)
    for s, photo in enumerate(photos):
        stages.nth(s).get_by_test_id("stage-label").fill(f"{10 * (s + 1)} kN")
        stages.nth(s).get_by_test_id("stage-load").fill(str(10 * (s + 1)))
        stages.nth(s).get_by_test_id("stage-photos").set_input_files(str(photo.path))
    editors = [stages.nth(s).get_by_test_id("photo") for s in range(2)]
    _click_points(page, editors[0], photos[0].control_points)
    _click_points(page, editors[1], photos[1].control_points[:3])
    expect(editors[1].get_by_test_id("point-count")).to_have_text("3 control points: at least 4 are needed")

    page.get_by_test_id("submit-survey").click()  # refused by the API: what was entered stays
    expect(page.get_by_test_id("survey-error")).to_contain_text("3 control point(s); at least 4 are needed")
    _screenshot(page, "crack_survey_form")
    expect(editors[0].get_by_test_id("marker")).to_have_count(len(photos[0].control_points))
    expect(editors[1].get_by_test_id("point-model-x").nth(2)).to_have_value(
        f"{photos[1].control_points[2]['model'][0]:g}"
    )
    watch.forget("/api/crack-surveys")
    _click_points(page, editors[1], photos[1].control_points[3:], first=3)
    expect(editors[1].get_by_test_id("point-count")).to_have_text(f"{len(photos[1].control_points)} control points")
    page.get_by_test_id("submit-survey").click()

    page.wait_for_url(re.compile(r"#/crack-surveys/\d+$"))
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the crack survey did not finish")
    expect(page.get_by_test_id("job-error")).to_be_hidden()
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the stage tiles did not settle")
    tiles = _stage_tiles(watch, 0)
    assert tiles and all(status == 200 and kind == "image/png" for _, status, kind in tiles), tiles
    rows = page.get_by_test_id("crack-row")
    expect(rows).to_have_count(len(scene.stages[0]))
    expect(page.get_by_test_id("residual-row")).to_have_count(2)
    expect(page.locator(".leaflet-overlay-pane path.crack")).to_have_count(len(scene.stages[0]))
    # how finely this setup sees, per load step: the photos' sampling, the detection raster (finer), and the
    # narrowest crack found at the survey's crack contrast, over the specimen and at lower contrasts
    expect(page.get_by_test_id("stage-photo-sampling")).to_have_text(re.compile(r"^0\.\d{3} mm/px$"))
    expect(page.get_by_test_id("stage-detection-raster")).to_have_text(re.compile(r"^0\.\d{3} mm/px$"))
    expect(page.get_by_test_id("stage-smallest-width")).to_have_text(re.compile(r"^0\.\d\d mm$"))
    detectability = page.get_by_test_id("stage-detectability")
    expect(detectability).to_contain_text(re.compile(r"darker than the coating, as this survey's widest are: "))
    expect(detectability).to_contain_text(re.compile(r"\d\.\d\d–\d\.\d\d mm over the specimen\. At 30 %: \d\.\d\d mm"))
    expect(detectability).to_contain_text("fainter than 15 %, none reliably")
    _screenshot(page, "crack_survey_stage1")

    page.get_by_test_id("stage-slider").fill("1")
    expect(page.get_by_test_id("stage-title")).to_contain_text("20 kN")
    added = sum(c.status == "new" for c in scene.stages[1])
    expect(rows).to_have_count(len(scene.stages[1]))
    expect(page.locator('[data-testid="crack-row"][data-status="new"]')).to_have_count(added)
    expect(page.get_by_test_id("stage-changes")).to_contain_text(f"{added} new, 1 grown, 4 unchanged")
    # the old step's tiles may look settled before the new TileJSON arrives: wait for the new step's own tiles
    wait_for(page, SECOND_STEP_TILES_SETTLED_JS, 30_000, watch, "the second load step's tiles did not settle")
    assert _stage_tiles(watch, 1) and all(status == 200 for _, status, _ in _stage_tiles(watch, 1))

    new_row = page.locator('[data-testid="crack-row"][data-status="new"]').first
    new_row.click()
    expect(new_row).to_have_class(re.compile(r"\bselected\b"))
    selected = page.locator(".leaflet-overlay-pane path.crack-selected")
    expect(selected).to_have_count(1)
    expect(selected).to_have_class(re.compile(r"\bcrack-new\b"))
    page.wait_for_load_state("networkidle")
    _screenshot(page, "crack_survey_stage2")
    expect(page.get_by_test_id("survey-warning")).to_have_count(0)  # the 0.25 mm raster suits these photos

    def with_warning(route: Any) -> None:
        """The report of a survey rasterised far finer than its photos, whose first crack is a hairline below
        photo resolution and none wide enough to tell the cracks' contrast."""
        answer = route.fetch().json()
        answer["result"]["warnings"] = ["stage '10 kN': the photos resolve 0.3 mm per pixel on the specimen"]
        answer["result"]["crack_contrast"] = None
        hairline = answer["result"]["stages"][0]["cracks"][0]
        hairline.update(width_mm=0.1, width_uncertainty_mm=0.12, below_photo_resolution=True)
        route.fulfill(json=answer)

    page.route(re.compile(r"/api/crack-surveys/\d+$"), with_warning)
    page.reload()
    expect(page.get_by_test_id("survey-warning")).to_contain_text("the photos resolve 0.3 mm per pixel")
    expect(page.get_by_test_id("below-resolution")).to_have_text("≈ 0.10 (≤ 0.22, below photo resolution)")
    expect(page.get_by_test_id("stage-detectability")).to_contain_text("no crack here was wide enough to tell")
    _screenshot(page, "crack_survey_hairline")
    watch.assert_clean(live_service.url)


def test_mesh_survey_of_a_curved_panel_made_in_the_browser(
    signed_in_page, live_service, panel: CrackSurveyScene
) -> None:
    """The panel's model chosen (after a malformed one, refused before anything is sent), two stages of one
    photo each, corners picked in the plan view and marks typed (X, Y, Z); a refusal for too few points, then
    the survey, whose crack counts are the truth's."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    assert panel.mesh_path is not None
    mesh = read_mesh(panel.mesh_path.read_bytes(), panel.mesh_path.name)
    photos = [[p for p in panel.photos if p.stage == s][0] for s in range(2)]
    page.goto(f"{live_service.url}/#/crack-surveys/new")
    page.get_by_test_id("camera-from-json").check()
    page.get_by_test_id("camera-json").fill(json.dumps(panel.camera.to_json()))
    page.get_by_test_id("specimen-mesh").check()
    expect(page.get_by_test_id("specimen-width")).to_be_hidden()
    model = page.get_by_test_id("specimen-model")
    model.set_input_files({"name": "panel.obj", "mimeType": "text/plain", "buffer": b"v 0 0 0\nv 1 0 0\nf 1 2 x\n"})
    parse_error = "panel.obj: line 3: 'x' is not a vertex index"
    expect(page.get_by_test_id("mesh-error")).to_contain_text(parse_error)
    page.get_by_test_id("submit-survey").click()
    expect(page.get_by_test_id("survey-error")).to_have_text(f"Specimen: {parse_error}")
    assert not [url for url in watch.request_urls if url.endswith("/api/crack-surveys")], "nothing is sent"

    model.set_input_files(str(panel.mesh_path))
    expect(page.get_by_test_id("mesh-error")).to_be_hidden()
    expect(page.get_by_test_id("mesh-vertices")).to_have_text(f"{len(mesh.vertices):,}")
    expect(page.get_by_test_id("mesh-triangles")).to_have_text(f"{len(mesh.triangles):,}")
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    expect(page.get_by_test_id("mesh-z")).to_have_text(f"{low[2]:.1f} to {high[2]:.1f} mm")
    page.get_by_test_id("mm-per-px").fill(str(MM_PER_PX))
    page.get_by_test_id("add-stage").click()
    stages = page.get_by_test_id("stage")
    for s, photo in enumerate(photos):
        stages.nth(s).get_by_test_id("stage-label").fill(f"{10 * (s + 1)} kN")
        stages.nth(s).get_by_test_id("stage-photos").set_input_files(str(photo.path))
    editors = [stages.nth(s).get_by_test_id("photo") for s in range(2)]
    _click_points(page, editors[0], photos[0].control_points, axes="xyz", picked=(0, 1, 2, 3))
    for k in range(4):  # the corners are vertices: picked exactly (the model prints 6 decimals)
        assert _typed_model(editors[0], k) == pytest.approx(photos[0].control_points[k]["model"], abs=1e-4)
    expect(editors[0].get_by_test_id("plan-status")).to_contain_text("Point 3 ← vertex")
    _click_points(page, editors[1], photos[1].control_points[:5], axes="xyz", picked=(3,))
    expect(editors[1].get_by_test_id("point-count")).to_have_text("5 control points: at least 6 are needed")

    page.get_by_test_id("submit-survey").click()  # refused by the API: what was entered stays
    expect(page.get_by_test_id("survey-error")).to_contain_text("5 control point(s); at least 6 are needed")
    assert _typed_model(editors[1], 3) == pytest.approx(photos[1].control_points[3]["model"], abs=1e-4)
    _screenshot(page, "crack_survey_mesh_form")
    watch.forget("/api/crack-surveys")
    _click_points(page, editors[1], photos[1].control_points[5:], first=5, axes="xyz")
    page.get_by_test_id("submit-survey").click()

    page.wait_for_url(re.compile(r"#/crack-surveys/\d+$"))
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the mesh crack survey did not finish")
    expect(page.get_by_test_id("job-error")).to_be_hidden()
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    expect(page.get_by_test_id("specimen")).to_contain_text("mesh model panel.obj")
    expect(page.get_by_test_id("mesh-note")).to_contain_text("measured along its surface")
    expect(page.get_by_test_id("plane-origin")).to_contain_text(" mm")
    rows = page.get_by_test_id("crack-row")
    expect(rows).to_have_count(len(panel.stages[0]))
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the stage tiles did not settle")
    _screenshot(page, "crack_survey_mesh_stage1")
    page.get_by_test_id("stage-slider").fill("1")
    expect(rows).to_have_count(len(panel.stages[1]))
    added = sum(c.status == "new" for c in panel.stages[1])
    expect(page.locator('[data-testid="crack-row"][data-status="new"]')).to_have_count(added)
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the second stage's tiles did not settle")
    _screenshot(page, "crack_survey_mesh_stage2")
    watch.assert_clean(live_service.url)


def test_failed_survey_shows_its_error(signed_in_page, live_service, scene: CrackSurveyScene, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    options = json.loads(json.dumps(scene.options(MM_PER_PX)))  # the scene's own lists stay as they are
    options["stages"][1]["photos"][0]["control_points"][5]["pixel"][0] += 60.0  # a point clicked off its mark
    files = [("files", (p.name, p.read_bytes(), "image/png")) for p in scene.paths()]
    job = live_service.wait_for_job(live_service.submit("/api/crack-surveys", files, options), timeout=120)
    assert job["status"] == "failed"

    page.goto(f"{live_service.url}/#/jobs/{job['id']}")  # a crack survey's job page is its survey page
    page.wait_for_url(re.compile(rf"#/crack-surveys/{job['id']}$"))
    expect(page.get_by_test_id("job-status")).to_have_text("failed")
    expect(page.get_by_test_id("job-error")).to_contain_text("point 5")
    expect(page.get_by_test_id("map")).to_have_count(0)
    page.get_by_test_id("nav-crack-surveys").click()
    expect(page.get_by_test_id("survey-row").filter(has_text=f"Survey #{job['id']}")).to_contain_text("failed")
    page.wait_for_load_state("networkidle")
    assert not any("/tiles/" in url for url in watch.request_urls), "a failed survey has no tiles to show"
    watch.assert_clean(live_service.url)


def test_camera_of_a_calibration_job_is_sent_by_its_id(signed_in_page, live_service, scene: CrackSurveyScene) -> None:
    """The finished calibration jobs are offered (the job list is answered here); the survey names the one
    picked, and the API's refusal of it is shown. No job runs."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    job = {"flight_id": None, "status": "succeeded", "created_at": "2026-01-02T03:04:05", "options": {}}
    jobs = [
        {**job, "id": 41, "kind": "calibration"},
        {**job, "id": 42, "kind": "calibration", "status": "failed"},
        {**job, "id": 43, "kind": "crack_survey"},
    ]
    sent: list[bytes] = []

    def refuse(route: Any) -> None:
        sent.append(route.request.post_data_buffer)
        route.fulfill(status=422, json={"detail": "options.calibration_job: calibration job 41 is gone"})

    page.route(re.compile(r"/api/jobs$"), lambda route: route.fulfill(json=jobs))
    page.route(re.compile(r"/api/crack-surveys$"), refuse)
    page.goto(f"{live_service.url}/#/crack-surveys/new")
    expect(page.get_by_test_id("calibration-job").locator("option")).to_have_count(1)
    expect(page.get_by_test_id("calibration-job")).to_have_value("41")
    expect(page.get_by_test_id("camera-from-job")).to_be_checked()
    page.get_by_test_id("specimen-width").fill(f"{scene.width_mm:g}")
    page.get_by_test_id("specimen-height").fill(f"{scene.height_mm:g}")
    photo = scene.photos[0]
    page.get_by_test_id("stage-photos").set_input_files(str(photo.path))
    _click_points(page, page.get_by_test_id("photo"), photo.control_points[:4])
    page.get_by_test_id("submit-survey").click()
    refusal = "Not started: options.calibration_job: calibration job 41 is gone"
    expect(page.get_by_test_id("survey-error")).to_have_text(refusal)
    (body,) = sent
    field = re.search(rb'name="options"\r\n\r\n(.*?)\r\n--', body, re.S)
    assert field is not None, body[:500]
    options = json.loads(field[1])
    # no resolution typed: the server rectifies at the photos' own sampling
    assert options["calibration_job"] == 41 and "camera" not in options and "mm_per_px" not in options
    (stage,) = options["stages"]
    assert stage["label"] == "Load step 1" and "load" not in stage and stage["photos"][0]["image"] == photo.path.name
    points = stage["photos"][0]["control_points"]
    assert [p["model"] for p in points] == [p["model"] for p in photo.control_points[:4]]
    clicked = np.array([p["pixel"] for p in points])
    # a click lands on a whole CSS pixel: up to 1.3 photo pixels at this photo's display scale
    assert np.abs(clicked - [p["pixel"] for p in photo.control_points[:4]]).max() < 1.5
    watch.forget("/api/crack-surveys")
    watch.assert_clean(live_service.url)


def test_mesh_plane_and_model_are_sent(signed_in_page, live_service, panel: CrackSurveyScene) -> None:
    """A plane through three model points is sent with the mesh's name and the model file as the ``model``
    field; the API's refusal is shown and nothing entered is lost. No job runs."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    assert panel.mesh_path is not None
    sent: list[bytes] = []

    def refuse(route: Any) -> None:
        sent.append(route.request.post_data_buffer)
        route.fulfill(status=422, json={"detail": "options.specimen: the three plane points are on one line"})

    page.route(re.compile(r"/api/crack-surveys$"), refuse)
    page.goto(f"{live_service.url}/#/crack-surveys/new")
    page.get_by_test_id("camera-from-json").check()
    page.get_by_test_id("camera-json").fill(json.dumps(panel.camera.to_json()))
    page.get_by_test_id("specimen-mesh").check()
    photo = panel.photos[0]
    page.get_by_test_id("stage-photos").set_input_files(str(photo.path))
    editor = page.get_by_test_id("photo")
    expect(editor).to_contain_text("Choose the mesh model under Specimen")
    page.get_by_test_id("specimen-model").set_input_files(str(panel.mesh_path))
    expect(editor.get_by_test_id("mesh-plan")).to_be_visible()
    page.get_by_test_id("plane-points").check()
    plane = [[0.0, 0.0, 0.0], [150.0, 0.0, 0.0], [0.0, 150.0, 0.0]]
    for r, point in enumerate(plane):
        for axis, value in zip("xyz", point, strict=True):
            page.get_by_test_id(f"plane-{r}-{axis}").fill(f"{value:g}")
    _click_points(page, editor, photo.control_points[:6], axes="xyz")
    page.get_by_test_id("submit-survey").click()
    expect(page.get_by_test_id("survey-error")).to_have_text(
        "Not started: options.specimen: the three plane points are on one line"
    )
    expect(editor.get_by_test_id("point-model-z").nth(5)).to_have_value(f"{photo.control_points[5]['model'][2]:g}")
    (body,) = sent
    field = re.search(rb'name="options"\r\n\r\n(.*?)\r\n--', body, re.S)
    assert field is not None, body[:500]
    options = json.loads(field[1])
    assert options["specimen"] == {"mesh": "panel.obj", "plane": plane}
    points = options["stages"][0]["photos"][0]["control_points"]
    typed = np.array([p["model"] for p in points]) - [p["model"] for p in photo.control_points[:6]]
    assert np.abs(typed).max() < 1e-3  # typed with 6 significant digits
    # the intercepted body holds the files' parts without their bytes (Chromium leaves blobs out of it); the
    # model's bytes reaching the API is the mesh survey test's
    assert re.search(rb'name="model"; filename="panel.obj"\r\n', body), body[:500]
    watch.forget("/api/crack-surveys")
    watch.assert_clean(live_service.url)
