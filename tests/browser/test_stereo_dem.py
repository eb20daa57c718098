"""Stereo DEMs in headless Chromium against the real service (Redis, Celery worker, uvicorn).

An RPC pair rendered from a known terrain (``tests/stereo_scenes.py``) is posted and run by the worker; its
job page shows the DSM as shaded relief tiles with a legend, and the elevation under the cursor is the
terrain's. A rectified pair's page shows its disparity map in pixels, with the disparity under the cursor.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from pyproj import Transformer

from tests.browser.support import ARTIFACTS, JOB_TIMEOUT_MS, MOSAIC_TILES_SETTLED_JS, TERMINAL_STATUS_JS, wait_for
from tests.stereo_scenes import RpcPair, make_rectified_pair, make_rpc_pair

pytestmark = pytest.mark.browser

STEREO_TILE = re.compile(r"/tiles/\d+/stereo/(dsm|disparity)/\d+/\d+/\d+\.png\?")  # signed: ?exp=...&sig=...
ELEVATION = re.compile(r"^(\d+\.\d\d) m \((measured|filled)\) at (-?\d+\.\d+), (-?\d+\.\d+)$")
READOUT_SAYS_JS = """(pattern) => new RegExp(pattern).test(
  document.querySelector('[data-testid="point-readout"]').textContent)"""
DISPARITY = re.compile(r"^(-?\d+\.\d\d) px \((confidence \d\.\d\d|filled)\) at x (\d+\.\d), y (\d+\.\d)$")


@pytest.fixture(scope="module")
def rpc_pair(tmp_path_factory: pytest.TempPathFactory) -> RpcPair:
    return make_rpc_pair(tmp_path_factory.mktemp("rpc_browser"))


def _screenshot(page: Any, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)
    page.evaluate("() => window.scrollTo(0, 0)")


def _open_finished(page: Any, live_service: Any, watch: Any, job_id: int) -> None:
    page.goto(f"{live_service.url}/#/jobs/{job_id}")
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the job did not finish")
    assert page.get_by_test_id("job-status").text_content().strip() == "succeeded"
    wait_for(page, MOSAIC_TILES_SETTLED_JS, 30_000, watch, "the tiles did not settle")


def _hover_map(page: Any, fx: float, fy: float) -> None:
    box = page.get_by_test_id("map").bounding_box()
    page.mouse.move(box["x"] + fx * box["width"] - 5, box["y"] + fy * box["height"] - 5)
    page.mouse.move(box["x"] + fx * box["width"], box["y"] + fy * box["height"])


def test_dsm_page_shows_relief_legend_and_elevation(signed_in_page, live_service, rpc_pair: RpcPair) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    files = [("left", ("left.tif", rpc_pair.left.read_bytes())), ("right", ("right.tif", rpc_pair.right.read_bytes()))]
    job_id = live_service.submit("/api/stereo-dems", files, {"method": "sgbm"})
    _open_finished(page, live_service, watch, job_id)
    tiles = [url for url in watch.request_urls if STEREO_TILE.search(url)]
    assert tiles and all("/dsm/" in url for url in tiles)
    assert page.get_by_test_id("stereo-geometry").text_content().startswith("RPC pair")
    labels = page.get_by_test_id("legend").locator(".ramp-labels span").all_text_contents()
    assert len(labels) == 3 and all(label.endswith(" m") for label in labels)
    low, high = float(labels[0].split()[0]), float(labels[2].split()[0])
    assert rpc_pair.base_height - 10 < low < high < rpc_pair.base_height + rpc_pair.relief_m + 10

    readout = page.get_by_test_id("point-readout")
    _hover_map(page, 0.5, 0.5)
    page.wait_for_function(READOUT_SAYS_JS, arg=" m \\((measured|filled)\\) at ")
    match = ELEVATION.match(readout.text_content().strip())
    assert match, readout.text_content()
    lat, lon = float(match[3]), float(match[4])
    east, north = Transformer.from_crs(4326, rpc_pair.epsg, always_xy=True).transform(lon, lat)
    assert abs(float(match[1]) - float(rpc_pair.height(np.array(east), np.array(north)))) < 1.5

    # the volume above the lowest point of a square's edge, drawn on the map (the route's own test checks the sum)
    page.get_by_test_id("volume-base").select_option("lowest")
    page.get_by_test_id("measure-volume").click()
    box = page.get_by_test_id("map").bounding_box()
    for fx, fy in ((0.4, 0.4), (0.6, 0.4), (0.6, 0.6), (0.4, 0.6)):
        page.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
    page.get_by_test_id("measure-finish").click()
    result = page.get_by_test_id("measure-result")
    expect(result).to_contain_text("volume above the edge's lowest point", timeout=15_000)
    text = result.text_content()
    assert "on the ground (geodesic, WGS 84)" in text and "m³, below:" in text and f"EPSG:{rpc_pair.epsg}" in text
    expect(page.get_by_test_id("cursor-coords")).to_contain_text(f"EPSG:{rpc_pair.epsg}")
    _screenshot(page, "stereo_dem_dsm")
    watch.assert_clean(live_service.url)


def test_disparity_page_of_a_rectified_pair(signed_in_page, live_service, tmp_path: Path) -> None:
    page, watch = signed_in_page
    left, right, truth = make_rectified_pair(seed=7, size=(320, 240))
    files = []
    for side, image in (("left", left), ("right", right)):
        path = tmp_path / f"{side}.png"
        cv2.imwrite(str(path), image)
        files.append((side, (path.name, path.read_bytes())))
    job_id = live_service.submit("/api/stereo-dems", files, {"rectified": True})
    _open_finished(page, live_service, watch, job_id)
    assert all("/disparity/" in url for url in watch.request_urls if STEREO_TILE.search(url))
    _hover_map(page, 0.55, 0.5)
    page.wait_for_function(READOUT_SAYS_JS, arg=" px \\(")
    match = DISPARITY.match(page.get_by_test_id("point-readout").text_content().strip())
    assert match, page.get_by_test_id("point-readout").text_content()
    x, y = float(match[3]), float(match[4])
    assert abs(float(match[1]) - float(truth[int(y), int(x)])) < 1.0
    _screenshot(page, "stereo_dem_disparity")
    watch.assert_clean(live_service.url)
