"""The result map's tools in headless Chromium against the real service: a distance and an area measured between
ground control points against the geodesic truth, the layer switcher, footprints coloured by residual that open
their photo, the basemap online and offline, and two jobs of one flight side by side.

The flight: 5 synthetic GPS frames with a GCP file of three surveyed points; two planar mosaics of it, one at the
default working size and one at 256 px (coarse: the swipe shows the difference)."""

from __future__ import annotations

import io
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image
from pyproj import Geod

from tests.browser.support import ARTIFACTS, MOSAIC_TILES_SETTLED_JS, wait_for
from tests.scenes import make_flight

pytestmark = pytest.mark.browser
GEOD = Geod(ellps="WGS84")
OSM = "https://tile.openstreetmap.org/"
# every tile of both panes loaded and faded in (the two jobs' deepest zoom levels may differ, so their tiles may)
BOTH_SETTLED_JS = """() => {
  const tiles = ['mosaic', 'compare'].map((p) => [...document.querySelectorAll(`.leaflet-${p}-pane img.leaflet-tile`)]);
  return tiles.every((t) => t.length > 0 && t.every((img) => img.complete && getComputedStyle(img).opacity === '1'));
}"""


@pytest.fixture(scope="module")
def flight_jobs(live_service: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("tools") / "frames"
    flight = make_flight(folder, n_frames=5, frame_size=(480, 360), gps=True, seed=7)
    url, headers = live_service.url, live_service.headers
    created = httpx.post(f"{url}/api/flights", json={"name": "Tools"}, timeout=10, headers=headers).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in flight.paths]
    assert httpx.post(f"{url}/api/flights/{created['id']}/images", files=files, timeout=60, headers=headers).is_success
    lines = [f"EPSG:{flight.epsg}"]
    w, h = flight.frame_size
    for n, (frame, fx, fy) in enumerate([(0, 0.3, 0.3), (2, 0.5, 0.7), (4, 0.7, 0.4)]):
        ground = flight.homographies[frame] @ np.array([w * fx, h * fy, 1.0])
        east, north, _ = flight.texture_to_utm @ (ground / ground[2])
        for i, H in enumerate(flight.homographies):
            x, y, s = np.linalg.inv(H) @ ground
            if 5 < x / s < w - 5 and 5 < y / s < h - 5:
                lines.append(f"{east:.3f} {north:.3f} 10 {x / s:.2f} {y / s:.2f} {flight.paths[i].name} GCP-{n}")
    gcp = {"file": ("gcp_list.txt", "\n".join(lines).encode(), "text/plain")}
    assert httpx.put(f"{url}/api/flights/{created['id']}/gcps", files=gcp, timeout=30, headers=headers).is_success
    jobs = {}
    for key, options in {"fine": {}, "coarse": {"working_max_px": 256}}.items():
        body = {"flight_id": created["id"], "kind": "mosaic", "options": options}
        response = httpx.post(f"{url}/api/jobs", json=body, timeout=10, headers=headers)
        assert response.status_code == 202, response.text
        jobs[key] = response.json()["id"]
    for job_id in jobs.values():
        job = live_service.wait_for_job(job_id, timeout=240)
        assert job["status"] == "succeeded", f"mosaic job ended {job['status']}: {job['error']}"
    return {**jobs, "flight": created["id"]}


def _open(page: Any, watch: Any, live_service: Any, job_id: int) -> None:
    from playwright.sync_api import expect

    page.goto(f"{live_service.url}/#/jobs/{job_id}")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic tiles did not settle")


def _gcps(page: Any) -> list[dict[str, Any]]:
    return page.request.get(page.get_by_test_id("download-gcps").get_attribute("href")).json()["features"]


def _number(text: str, before: str) -> float:
    """The number just before ``before`` in ``text`` ("1 234.56 m" -> 1234.56)."""
    head = text.split(before)[0].rstrip()
    token = head.rsplit(" ", 2)
    number = token[-1] if token[-1][:1].isdigit() and not token[-2][-1:].isdigit() else "".join(token[-2:])
    return float(number.replace(" ", ""))


def test_a_distance_and_an_area_between_gcps_match_the_geodesic_truth(
    signed_in_page, live_service, flight_jobs
) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    _open(page, watch, live_service, flight_jobs["fine"])
    gcps = _gcps(page)
    assert [g["properties"]["id"] for g in gcps] == ["GCP-0", "GCP-1", "GCP-2"]
    lonlat = [g["geometry"]["coordinates"] for g in gcps]
    _, _, truth = GEOD.inv(*lonlat[0], *lonlat[2])
    assert truth > 10  # metres apart: a real distance to measure
    markers = page.locator('[data-testid="map"] .leaflet-gcps-pane path.gcp-marker')
    expect(markers).to_have_count(3)

    page.get_by_test_id("measure-distance").click()
    markers.nth(0).click()
    markers.nth(2).click()
    page.get_by_test_id("measure-finish").click()
    text = page.get_by_test_id("measure-result").inner_text()
    measured = _number(text, "m on the ground")
    assert abs(measured - truth) / truth < 0.01, (text, truth)
    assert "on the grid of EPSG:32615" in text and "2 points" in text
    grid = _number(text, "m on the grid")
    assert abs(grid - truth) / truth < 0.002  # UTM's scale factor: parts in 10 000

    area_truth, perimeter_truth = GEOD.polygon_area_perimeter([p[0] for p in lonlat], [p[1] for p in lonlat])
    page.get_by_test_id("measure-area").click()
    for k in range(3):
        markers.nth(k).click()
    page.get_by_test_id("measure-finish").click()
    text = page.get_by_test_id("measure-result").inner_text()
    assert abs(_number(text, "m² on the ground") - abs(area_truth)) / abs(area_truth) < 0.01, (text, area_truth)
    assert abs(_number(text.split("perimeter")[1] + " ", "m ") - perimeter_truth) / perimeter_truth < 0.01

    # a line clicked on the map itself (not on markers): two points 200 screen px apart, at the map's scale
    page.get_by_test_id("measure-distance").click()
    box = page.get_by_test_id("map").bounding_box()
    page.mouse.click(box["x"] + 150, box["y"] + 420)
    page.mouse.dblclick(box["x"] + 350, box["y"] + 420)
    text = page.get_by_test_id("measure-result").inner_text()
    assert "2 points" in text and _number(text, "m on the ground") > 0
    expect(page.get_by_test_id("cursor-coords")).to_contain_text("EPSG:32615")
    expect(page.get_by_test_id("cursor-coords")).to_contain_text(" N (")
    page.get_by_test_id("measure-distance").click()
    markers.nth(0).click()
    markers.nth(2).click()
    page.mouse.move(box["x"] + 300, box["y"] + 300)
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "map_measure.png"), full_page=False)
    page.keyboard.press("Escape")
    expect(page.get_by_test_id("measure-finish")).to_be_disabled()
    watch.assert_clean(live_service.url)


def test_the_layer_switcher_and_footprints_by_residual(signed_in_page, live_service, flight_jobs) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    _open(page, watch, live_service, flight_jobs["fine"])
    footprints = page.locator('[data-testid="map"] .leaflet-overlay-pane path')
    cameras = page.locator('[data-testid="map"] .leaflet-cameras-pane path')
    gcps = page.locator('[data-testid="map"] .leaflet-gcps-pane path.gcp-marker')
    tiles = page.locator('[data-testid="map"] .leaflet-mosaic-pane img.leaflet-tile')
    expect(footprints).to_have_count(5)
    expect(cameras).to_have_count(10)  # a centre and a line to its GPS fix per photo
    expect(gcps).to_have_count(3)
    switcher = page.get_by_test_id("layer-switcher")
    expect(switcher).to_contain_text("Mosaic")
    expect(page.get_by_test_id("basemap-none")).to_be_checked()  # the tests' service has no basemap
    for testid, shown in [("footprints-toggle", footprints), ("layer-cameras", cameras), ("layer-gcps", gcps)]:
        page.get_by_test_id(testid).uncheck()
        expect(shown).to_have_count(0)
        page.get_by_test_id(testid).check()
        expect(shown).to_have_count(10 if testid == "layer-cameras" else 5 if testid == "footprints-toggle" else 3)
    page.get_by_test_id("layer-mosaic").uncheck()
    expect(tiles).to_have_count(0)
    page.get_by_test_id("layer-mosaic").check()
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic did not come back")

    # footprints coloured by their photo's tie-point RMS, then by GPS residual: the legend says the range
    expect(page.get_by_test_id("footprint-legend")).to_contain_text("px")
    strokes = footprints.evaluate_all("(paths) => paths.map((p) => p.getAttribute('stroke'))")
    assert len(set(strokes)) > 1, strokes  # not one colour: each photo's own residual
    page.get_by_test_id("colour-by").select_option("gps_residual_m")
    expect(page.get_by_test_id("footprint-legend")).to_contain_text(" m")
    # a click on a footprint opens its photo and its figures
    box = footprints.nth(2).bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    detail = page.get_by_test_id("photo-detail")
    expect(detail).to_be_visible()
    expect(detail).to_contain_text("frame_00")
    expect(page.get_by_test_id("photo-rms")).to_contain_text("px")
    preview = page.get_by_test_id("photo-preview")
    page.wait_for_function(
        "() => { const i = document.querySelector('[data-testid=\"photo-preview\"]');"
        " return i && i.complete && i.naturalWidth > 0; }"
    )
    assert "/photos/" in (preview.get_attribute("src") or "") and "sig=" in (preview.get_attribute("src") or "")
    page.get_by_test_id("photo-pick").select_option("0")
    expect(detail.locator("h4")).to_have_text("Frame 0: frame_000.jpg")
    page.wait_for_load_state("networkidle")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "map_layers.png"), full_page=False)
    watch.assert_clean(live_service.url)


def _map_pixels(page: Any) -> np.ndarray:
    """The map's pixels (grey) without the controls drawn over it, once every tile has settled."""
    page.wait_for_timeout(300)
    page.wait_for_function(BOTH_SETTLED_JS)
    drawn_over = [page.locator(".leaflet-control-container"), page.locator(".swipe-line, .swipe-tag, .swipe-range")]
    shot = page.get_by_test_id("map").screenshot(mask=drawn_over)
    return np.asarray(Image.open(io.BytesIO(shot)).convert("L"), np.float64)


def test_two_jobs_of_the_flight_side_by_side(signed_in_page, live_service, flight_jobs) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    _open(page, watch, live_service, flight_jobs["fine"])
    choice = page.get_by_test_id("compare-with")
    expect(choice.locator("option")).to_have_count(2)
    choice.select_option(str(flight_jobs["coarse"]))
    expect(page.get_by_test_id("swipe")).to_be_visible()
    compare_tiles = page.locator('[data-testid="map"] .leaflet-compare-pane img.leaflet-tile')
    expect(compare_tiles.first).to_be_attached()
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the two mosaics' tiles did not settle")
    assert any(f"/tiles/{flight_jobs['coarse']}/" in u for u in watch.request_urls)
    for _ in range(2):  # closer: the fine mosaic's detail shows where the coarse one's cannot
        page.locator(".leaflet-control-zoom-in").click()
        page.wait_for_timeout(400)
    wait_for(page, BOTH_SETTLED_JS, 30_000, watch, "the zoomed tiles did not settle")
    page.get_by_test_id("swipe-range").fill("50")
    clips = page.evaluate(
        """() => ['mosaic', 'compare'].map((p) => document.querySelector(`.leaflet-${p}-pane`).style.clip)"""
    )
    left, right = (
        [float(v) for v in c.removeprefix("rect(").removesuffix(")").replace("px", "").split(",")] for c in clips
    )
    assert left[1] == right[3], clips  # the mosaic ends where the comparison begins
    width = page.get_by_test_id("map").bounding_box()["width"]
    assert abs((left[1] - left[3]) - (14 + (width - 28) * 0.5)) < 1.5, clips  # half way along the thumb's travel
    page.wait_for_load_state("networkidle")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "map_swipe.png"), full_page=False)
    divider = int(left[1] - left[3])
    halves = _map_pixels(page)
    page.get_by_test_id("swipe-range").fill("100")  # this job over the whole map
    whole = _map_pixels(page)
    rows = slice(whole.shape[0] // 4, 3 * whole.shape[0] // 4)
    same = np.abs(halves[rows, 20 : divider - 20] - whole[rows, 20 : divider - 20]).mean()
    changed = np.abs(halves[rows, divider + 20 : -20] - whole[rows, divider + 20 : -20]).mean()
    assert same < 0.5 and changed > 4 * max(same, 1.0), (same, changed)  # left: this job; right: the other
    choice.select_option("")
    expect(page.get_by_test_id("swipe")).to_be_hidden()
    assert page.evaluate("() => document.querySelector('.leaflet-mosaic-pane').style.clip") == ""
    watch.assert_clean(live_service.url)


@pytest.mark.parametrize("online", [True, False])
def test_openstreetmap_is_the_basemap_online_and_none_offline(
    signed_in_page, live_service, flight_jobs, online
) -> None:
    """The service's own config says OpenStreetMap (answered here by the page's router: the machine is offline);
    the browser shows it while online, and asks nothing of it offline."""
    from playwright.sync_api import expect

    page, watch = signed_in_page
    tile = io.BytesIO()
    Image.new("RGB", (256, 256), (200, 230, 200)).save(tile, "PNG")
    asked: list[str] = []

    def config(route: Any) -> None:
        body = route.fetch().json()
        route.fulfill(json={**body, "basemap_url": OSM + "{z}/{x}/{y}.png", "basemap_name": "OpenStreetMap"})

    def osm(route: Any) -> None:
        asked.append(route.request.url)
        route.fulfill(body=tile.getvalue(), content_type="image/png")

    page.route("**/api/config", config)
    page.route(OSM + "**", osm)
    if not online:
        page.add_init_script("Object.defineProperty(navigator, 'onLine', { get: () => false })")
    page.goto(f"{live_service.url}/")  # a fresh page: the viewer reads its config once
    page.reload()
    _open(page, watch, live_service, flight_jobs["fine"])
    if online:
        expect(page.get_by_test_id("basemap-osm")).to_be_checked()
        expect(page.locator(".leaflet-control-attribution")).to_contain_text("OpenStreetMap contributors")
        page.wait_for_function(
            "() => document.querySelectorAll('.leaflet-tile-pane img.leaflet-tile-loaded').length > 0"
        )
        assert asked
        page.get_by_test_id("basemap-none").check()
        expect(page.locator(".leaflet-tile-pane img")).to_have_count(0)
    else:
        expect(page.get_by_test_id("basemap-none")).to_be_checked()
        expect(page.get_by_test_id("basemap-osm")).not_to_be_checked()  # offered, for when the network is back
        page.wait_for_load_state("networkidle")
        assert asked == []
    watch.request_urls[:] = [u for u in watch.request_urls if not u.startswith(OSM)]
    watch.assert_clean(live_service.url)
