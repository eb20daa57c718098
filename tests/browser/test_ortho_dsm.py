"""An ortho mosaic's DSM in headless Chromium against the real service (Redis, Celery worker, uvicorn).

A flight over box-shaped buildings (``tests/terrain_scenes.BUILDINGS``) is uploaded and run as an ortho job; the
surface its photos were projected onto is the job's ``dsm.tif``, so its page has a DSM layer in the switcher, the
DSM's legend, the elevation under the cursor (a roof's and the ground's beside it, as rendered) and a volume tool
(a building's volume above the ground around it).
"""

from __future__ import annotations

import re
from typing import Any

import httpx
import numpy as np
import pytest
from pyproj import Transformer

from tests.browser.support import ARTIFACTS, JOB_TIMEOUT_MS, MOSAIC_TILES_SETTLED_JS, TERMINAL_STATUS_JS, wait_for
from tests.terrain_scenes import BUILDINGS, TerrainFlight, make_buildings_flight

pytestmark = pytest.mark.browser

DSM_TILE = re.compile(r"/tiles/\d+/stereo/dsm/\d+/\d+/\d+\.png\?")  # signed: ?exp=...&sig=...
ELEVATION = re.compile(r"^(-?\d+\.\d\d) m \((measured|filled)\) at (-?\d+\.\d+), (-?\d+\.\d+)$")
VOLUME = re.compile(r"volume above a plane along the edge .*?: ([\d\u202f ,.]+) m³")
DSM_TILES_SETTLED_JS = """() => {
  const tiles = [...document.querySelectorAll('[data-testid="map"] img.leaflet-tile')]
    .filter((img) => img.src.includes('/stereo/dsm/'));
  return tiles.length > 0 && tiles.every((img) => img.complete && getComputedStyle(img).opacity === '1');
}"""  # the DSM's tiles (coarser than the mosaic's: another zoom level) loaded and faded in
READOUT_CHANGED_JS = """([pattern, before]) => {
  const text = document.querySelector('[data-testid="point-readout"]').textContent;
  return text !== before && new RegExp(pattern).test(text);
}"""


def _ortho_job(live_service: Any, flight: TerrainFlight) -> int:
    url, headers = live_service.url, live_service.headers
    created = httpx.post(f"{url}/api/flights", json={"name": "Buildings"}, timeout=10, headers=headers).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in flight.paths]
    uploaded = httpx.post(f"{url}/api/flights/{created['id']}/images", files=files, timeout=60, headers=headers)
    assert uploaded.status_code == 201, uploaded.text
    body = {"flight_id": created["id"], "kind": "mosaic", "options": {"mode": "ortho", "gps_sigma_m": 0.05}}
    response = httpx.post(f"{url}/api/jobs", json=body, timeout=10, headers=headers)
    assert response.status_code == 202, response.text
    return int(response.json()["id"])


class MapFrame:
    """Where a world point of the flight is on the page's map, from two readouts of the cursor's lon/lat (Web
    Mercator is linear in lon and, over a few tens of metres, in lat)."""

    def __init__(self, page: Any, flight: TerrainFlight) -> None:
        self.page, self.flight = page, flight
        self.box = page.get_by_test_id("map").bounding_box()
        (_, lat0, lon0), (_, lat1, lon1) = self.read(0.4, 0.4), self.read(0.6, 0.6)
        self.lon = (lon0, (lon1 - lon0) / 0.2)
        self.lat = (lat0, (lat1 - lat0) / 0.2)
        self.to_lonlat = Transformer.from_crs(flight.epsg, 4326, always_xy=True)
        self.to_map = Transformer.from_crs(4326, flight.epsg, always_xy=True)

    def read(self, fx: float, fy: float) -> tuple[float, float, float]:
        """Hover at a fraction of the map; the elevation, lat and lon the readout then says."""
        readout = self.page.get_by_test_id("point-readout")
        before = readout.text_content()
        self.page.mouse.move(*self.at(fx - 0.01, fy - 0.01))
        self.page.mouse.move(*self.at(fx, fy))
        self.page.wait_for_function(READOUT_CHANGED_JS, arg=[ELEVATION.pattern, before])
        match = ELEVATION.match(readout.text_content().strip())
        assert match, readout.text_content()
        return float(match[1]), float(match[3]), float(match[4])

    def at(self, fx: float, fy: float) -> tuple[float, float]:
        return self.box["x"] + fx * self.box["width"], self.box["y"] + fy * self.box["height"]

    def fraction(self, x: float, y: float) -> tuple[float, float]:
        """The map fraction of world x, y (m from the flight's origin)."""
        lon, lat = self.to_lonlat.transform(self.flight.origin_utm[0] + x, self.flight.origin_utm[1] + y)
        return 0.4 + (lon - self.lon[0]) / self.lon[1], 0.4 + (lat - self.lat[0]) / self.lat[1]

    def truth(self, lat: float, lon: float) -> float:
        east, north = self.to_map.transform(lon, lat)
        x, y = east - self.flight.origin_utm[0], north - self.flight.origin_utm[1]
        return float(self.flight.height(np.array(x), np.array(y)))


def test_an_ortho_jobs_dsm_layer_elevation_and_volume(signed_in_page, live_service, tmp_path) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    flight = make_buildings_flight(tmp_path / "frames")
    job_id = _ortho_job(live_service, flight)
    page.goto(f"{live_service.url}/#/jobs/{job_id}")
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the ortho job did not finish")
    expect(page.get_by_test_id("job-status")).to_have_text("succeeded")
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the mosaic tiles did not settle")
    expect(page.get_by_test_id("download-dsm")).to_be_visible()

    # the DSM is a layer of the switcher, off at first; switched on, its shaded relief tiles arrive
    toggle = page.get_by_test_id("layer-dsm")
    expect(toggle).not_to_be_checked()
    assert not [url for url in watch.request_urls if DSM_TILE.search(url)]
    toggle.check()
    page.wait_for_function(DSM_TILES_SETTLED_JS)
    assert [url for url in watch.request_urls if DSM_TILE.search(url)]
    labels = page.get_by_test_id("elevation").locator(".ramp-labels span").all_text_contents()
    assert len(labels) == 3 and all(label.endswith(" m") for label in labels)
    expect(page.get_by_test_id("dsm-facts")).to_contain_text("% measured by stereo")

    # the elevation under the cursor: a roof 7 m up and the ground 2 m beside it, as the scene has them
    frame = MapFrame(page, flight)
    roof_block = BUILDINGS[1]
    roof, lat, lon = frame.read(*frame.fraction(0.5 * (roof_block.x0 + roof_block.x1), -4.0))
    assert abs(frame.truth(lat, lon) - roof_block.top_m) < 1e-9  # the cursor is on the roof
    assert abs(roof - roof_block.top_m) < 0.3, roof
    ground, lat, lon = frame.read(*frame.fraction(0.5 * (roof_block.x0 + roof_block.x1), roof_block.y0 - 2.0))
    assert abs(ground - frame.truth(lat, lon)) < 0.3 and roof - ground > 3.0, (roof, ground)

    # a building's volume above a plane along a square drawn 1.5 m around it (the route's own test checks the sum)
    block = BUILDINGS[0]
    page.get_by_test_id("measure-volume").click()
    for x, y in ((block.x0 - 1.5, block.y0 - 1.5), (block.x1 + 1.5, block.y0 - 1.5), (block.x1 + 1.5, block.y1 + 1.5)):
        page.mouse.click(*frame.at(*frame.fraction(x, y)))
    page.mouse.click(*frame.at(*frame.fraction(block.x0 - 1.5, block.y1 + 1.5)))
    page.get_by_test_id("measure-finish").click()
    result = page.get_by_test_id("measure-result")
    expect(result).to_contain_text("volume above a plane along the edge", timeout=15_000)
    match = VOLUME.search(result.text_content())
    assert match, result.text_content()
    volume = float(re.sub(r"[^\d.]", "", match[1]))
    x, y = np.meshgrid(np.arange(block.x0, block.x1, 0.05), np.arange(block.y0, block.y1, 0.05))
    truth = float(np.sum(block.top_m - flight.terrain_height(x, y)) * 0.05**2)
    assert abs(volume - truth) < 0.15 * truth, (volume, truth)
    expect(page.get_by_test_id("cursor-coords")).to_contain_text(f"EPSG:{flight.epsg}")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "ortho_dsm.png"), full_page=True)
    watch.assert_clean(live_service.url)
