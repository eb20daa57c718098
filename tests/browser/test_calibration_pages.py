"""Calibration and stereo-rig pages in headless Chromium against the real service: a job started by dropping
chessboard photos, the corners found drawn on each photo, a mark moved and a photo left out, then solved again;
a rig from pairs of photos with its corners shown, one mark moved and one removed, then solved again (real
photos: ../shared/data/calib_chessboard)."""

from __future__ import annotations

import re
from typing import Any

import pytest

from tests.browser.support import ARTIFACTS, JOB_TIMEOUT_MS, TERMINAL_STATUS_JS, wait_for
from tests.conftest import shared_data

pytestmark = [pytest.mark.browser, pytest.mark.realdata]
OVERLAY_LOADED_JS = """() => {
  const img = document.querySelector('[data-testid="marks-map"] img.leaflet-image-layer');
  return img !== null && img.complete && img.naturalWidth > 0;
}"""


def _finished(page: Any, watch: Any) -> None:
    wait_for(page, TERMINAL_STATUS_JS, JOB_TIMEOUT_MS, watch, "the calibration did not finish")
    assert page.get_by_test_id("job-status").text_content().strip() == "succeeded", watch.summary()


def _solved_again(page: Any, watch: Any, button: Any) -> None:
    """Click ``button`` (it saves marks), then wait for the page drawn again to show the new solve finished."""
    page.evaluate("() => { document.querySelector('[data-testid=\"job-status\"]').dataset.before = '1'; }")
    button.click()
    page.wait_for_function(
        "() => { const b = document.querySelector('[data-testid=\"job-status\"]'); return b && !b.dataset.before; }"
    )
    _finished(page, watch)


def _screenshot(page: Any, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def _drag(page: Any, mark: Any, photo_px: float) -> None:
    """Drag ``mark`` right by ``photo_px`` pixels of the 640 px wide photo shown."""
    box = mark.bounding_box()
    scale = page.evaluate(
        "() => { const m = document.querySelector('[data-testid=\"marks-map\"] img.leaflet-image-layer');"
        " return m.getBoundingClientRect().width / 640; }"
    )
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + photo_px / 2 * scale, y, steps=3)
    page.mouse.move(x + photo_px * scale, y, steps=3)
    page.mouse.up()


def test_a_calibration_from_dropped_photos_with_marks_fixed_and_removed(signed_in_page, live_service) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    photos = sorted(shared_data("calib_chessboard").glob("left*.jpg"))[:6]
    page.get_by_test_id("nav-calibrations").click()
    page.get_by_test_id("new-calibration").click()
    page.get_by_test_id("files-input").set_input_files([str(p) for p in photos])
    expect(page.get_by_test_id("files-chosen")).to_contain_text("6 photos")
    expect(page.get_by_test_id("pattern-columns")).to_have_value("9")
    _screenshot(page, "calibration_new")
    page.get_by_test_id("start-calibration").click()
    page.wait_for_url(re.compile(r"#/jobs/\d+$"))
    job_id = int(page.url.rsplit("/", 1)[1])
    _finished(page, watch)

    # the corners found, drawn on the photo, coloured by their error
    section = page.get_by_test_id("calibration-photos")
    expect(section.get_by_test_id("marks-photo").locator("option")).to_have_count(6)
    marks = page.locator('[data-testid="marks-map"] .mark-icon')
    expect(marks).to_have_count(54)
    page.wait_for_function(OVERLAY_LOADED_JS)
    expect(page.get_by_test_id("marks-readout")).to_contain_text("54 marks, RMS")
    marks.nth(20).click()
    expect(page.get_by_test_id("marks-readout")).to_contain_text(
        re.compile(r"^Mark 20 at x \d+\.\d\d, y \d+\.\d\d: reprojection error \d\.\d{3} px")
    )
    _screenshot(page, "calibration_marks")

    # move mark 20 of the photo shown by about 8 photo px, save: the solve runs again and names that mark
    shown = page.get_by_test_id("marks-photo").locator("option:checked").inner_text().split(" (")[0]
    page.get_by_test_id("marks-edit").check()
    _drag(page, marks.nth(20), 8)
    expect(page.get_by_test_id("marks-save")).to_be_enabled()
    _solved_again(page, watch, page.get_by_test_id("marks-save"))
    worst = page.get_by_test_id("worst-points").locator("tbody tr").first.locator("td")
    expect(worst.nth(0)).to_have_text(shown)
    expect(worst.nth(1)).to_have_text("20")
    assert float(worst.nth(2).inner_text()) > 3.0
    expect(page.get_by_test_id("marks-photo").locator("option").first).to_contain_text("54 marks")

    # leave the second photo out: five photos are solved, the left-out list says why
    page.get_by_test_id("marks-photo").select_option("1")
    left_out = page.get_by_test_id("marks-photo").locator("option:checked").inner_text().split(" (")[0]
    _solved_again(page, watch, page.get_by_test_id("photo-leave-out"))
    expect(page.get_by_test_id("views-used")).to_have_text("5")
    expect(page.get_by_test_id("left-out")).to_contain_text(f"{left_out}: removed by the user")
    page.get_by_test_id("marks-photo").select_option("1")
    expect(page.get_by_test_id("marks-photo").locator("option:checked")).to_contain_text("left out by you")
    expect(page.get_by_test_id("photo-restore")).to_be_visible()
    assert any(f"/api/jobs/{job_id}/photos/" in u for u in watch.request_urls)
    watch.assert_clean(live_service.url)


def test_a_stereo_rig_from_pairs_with_a_mark_moved_and_one_removed(signed_in_page, live_service) -> None:
    from playwright.sync_api import expect

    page, watch = signed_in_page
    data = shared_data("calib_chessboard")
    left, right = sorted(data.glob("left*.jpg"))[:4], sorted(data.glob("right*.jpg"))[:4]
    page.goto(f"{live_service.url}/#/stereo-rigs/new")
    page.get_by_test_id("left-input").set_input_files([str(p) for p in left])
    page.get_by_test_id("right-input").set_input_files([str(p) for p in right])
    expect(page.get_by_test_id("rig-pair")).to_have_count(4)
    expect(page.get_by_test_id("rig-pair").first).to_contain_text(left[0].name)
    page.get_by_test_id("start-calibration").click()
    page.wait_for_url(re.compile(r"#/jobs/\d+$"))
    _finished(page, watch)
    expect(page.get_by_test_id("baseline")).to_contain_text("mm")
    expect(page.get_by_test_id("marks-photo").locator("option")).to_have_count(8)
    expect(page.get_by_test_id("marks-photo").locator("option").first).to_contain_text(f"left 1: {left[0].name}")
    expect(page.locator('[data-testid="marks-map"] .mark-icon')).to_have_count(54)
    page.get_by_test_id("marks-photo").select_option("4")  # the first right photo
    expect(page.locator('[data-testid="marks-map"] .mark-icon')).to_have_count(54)
    page.wait_for_function(OVERLAY_LOADED_JS)
    _screenshot(page, "stereo_rig_marks")

    # on the second left photo, mark 20 moved by about 8 photo px and mark 30 removed, then solved again
    page.get_by_test_id("marks-photo").select_option("1")
    page.wait_for_function(OVERLAY_LOADED_JS)
    marks = page.locator('[data-testid="marks-map"] .mark-icon')
    page.get_by_test_id("marks-edit").check()
    _drag(page, marks.nth(20), 8)
    marks.nth(30).click()
    expect(page.get_by_test_id("marks-readout")).to_contain_text("Mark 30 at x")
    page.get_by_test_id("mark-remove").click()
    expect(marks).to_have_count(53)
    expect(page.get_by_test_id("marks-save")).to_be_enabled()
    _solved_again(page, watch, page.get_by_test_id("marks-save"))
    worst = page.get_by_test_id("worst-points").locator("tbody tr").first.locator("td")
    expect(worst.nth(0)).to_have_text(left[1].name)
    expect(worst.nth(1)).to_have_text("20")
    assert float(worst.nth(2).inner_text()) > 3.0
    # the pair keeps the marks both photos have: mark 30 and the one opposite it on the board are left out
    page.get_by_test_id("marks-photo").select_option("1")
    expect(page.get_by_test_id("marks-photo").locator("option:checked")).to_contain_text("52 marks")
    expect(marks).to_have_count(52)
    page.wait_for_function(OVERLAY_LOADED_JS)
    expect(page.get_by_test_id("marks-readout")).to_contain_text("52 marks, RMS")
    expect(page.get_by_test_id("photo-restore")).to_be_visible()
    expect(page.get_by_test_id("pair-row")).to_have_count(4)
    _screenshot(page, "stereo_rig_marks_edited")
    watch.assert_clean(live_service.url)
