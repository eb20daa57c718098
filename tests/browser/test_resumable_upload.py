"""The viewer's resumable upload in headless Chromium: a server that sends every file by tus in 64 KiB PATCHes;
the network drops the second PATCH, the page says it is resuming, asks the server where it stands (HEAD) and
sends only the rest, each chunk with its SHA-256; the photo that arrives is the file, byte for byte. A page
reloaded in the middle of an upload continues it when the same file is chosen again. A file the server refuses
at its last byte shows the server's reason."""

from __future__ import annotations

import base64
import hashlib
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.browser.support import ARTIFACTS, sign_in_by_link
from tests.live_api import ApiProcess, api_process

pytestmark = pytest.mark.browser
CHUNK = 64 * 1024
STATUS_LOG_JS = """() => {
  window.__statuses = [];
  const status = document.querySelector('.upload-status');
  new MutationObserver(() => window.__statuses.push(status.textContent))
    .observe(status, { childList: true, characterData: true, subtree: true });
}"""


@pytest.fixture(scope="module")
def tus_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiProcess]:
    """The API alone, sending every file by resumable upload (threshold 0) in 64 KiB chunks."""
    server = api_process(
        tmp_path_factory.mktemp("tus") / "data", resumable_upload_bytes="0", resumable_chunk_bytes=str(CHUNK)
    )
    server.start()
    yield server
    server.kill()


def photo_file(folder: Path) -> Path:
    """A 156 KB JPEG (noise): three chunks."""
    pixels = np.random.default_rng(11).integers(0, 256, (360, 480, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=90)
    path = folder / "strip frame.jpg"
    path.write_bytes(out.getvalue())
    return path


def open_new_flight(page: Any, service: ApiProcess) -> int:
    with httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {service.token}"}) as client:
        flight = int(client.post("/api/flights", json={"name": "resumable"}).json()["id"])
    sign_in_by_link(page, service.url, service.token, route=f"/flights/{flight}")
    return flight


def test_an_upload_cut_by_the_network_resumes_where_it_stopped(watched_page, tus_service, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    flight = open_new_flight(page, tus_service)
    path = photo_file(tmp_path)
    data = path.read_bytes()
    seen: list[tuple[str, str, str]] = []  # (method, Upload-Offset, Upload-Checksum) of each tus request

    def network(route: Any, request: Any) -> None:
        headers = request.headers
        seen.append((request.method, headers.get("upload-offset", ""), headers.get("upload-checksum", "")))
        if request.method == "PATCH" and sum(m == "PATCH" for m, _, _ in seen) == 2:
            route.abort("connectionreset")  # the second chunk never reaches the server
        else:
            route.continue_()

    page.route("**/api/flights/*/uploads/*", network)
    page.evaluate(STATUS_LOG_JS)
    page.get_by_test_id("file-input").set_input_files(str(path))
    expect(page.get_by_test_id("image-row")).to_have_count(1, timeout=30_000)
    expect(page.get_by_test_id("upload-progress")).to_have_attribute("aria-valuenow", "100")
    expect(page.locator(".upload-status")).to_have_text("Uploaded 1 photo.")
    page.screenshot(path=str(ARTIFACTS / "resumable-upload.png"), full_page=True)

    patches = [(offset, checksum) for method, offset, checksum in seen if method == "PATCH"]
    offsets = [int(offset) for offset, _ in patches]
    assert offsets[:3] == [0, CHUNK, CHUNK], f"the cut chunk is sent again from where the server stood: {seen}"
    assert offsets[2:] == list(range(CHUNK, len(data), CHUNK)), seen
    cut = next(i for i, (method, _, _) in enumerate(seen) if method == "PATCH" and i > 0 and seen[i - 1][0] == "PATCH")
    assert ("HEAD", "", "") in seen[cut:], "after the error the page asked the server for its offset"
    for offset, checksum in patches:  # every chunk carried its SHA-256 (127.0.0.1 is a secure context)
        chunk = data[int(offset) : int(offset) + CHUNK]
        assert checksum == "sha256 " + base64.b64encode(hashlib.sha256(chunk).digest()).decode()
    statuses = page.evaluate("window.__statuses")
    assert any(text.startswith("Connection lost; resuming strip frame.jpg") for text in statuses), statuses

    with httpx.Client(base_url=tus_service.url, headers={"Authorization": f"Bearer {tus_service.token}"}) as client:
        image = client.get(f"/api/flights/{flight}").json()["images"][0]
        assert client.get(f"/api/flights/{flight}/uploads").json() == []  # no unfinished upload left behind
    stored = tus_service.data_dir / "flights" / str(flight) / "images" / image["stored_name"]
    assert image["filename"] == "strip frame.jpg" and stored.read_bytes() == data
    expect(page.get_by_test_id("image-row")).to_contain_text("480 × 360")
    watch.failed_requests[:] = [r for r in watch.failed_requests if "/uploads/" not in r]  # the cut we made
    watch.console_errors[:] = [c for c in watch.console_errors if "ERR_CONNECTION_RESET" not in c]
    watch.assert_clean(tus_service.url)


def test_a_file_refused_at_its_last_byte_shows_the_servers_reason(watched_page, tus_service, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    open_new_flight(page, tus_service)
    bad = tmp_path / "notes.jpg"
    bad.write_bytes(b"field notes, not a photo\n" * 5000)  # 125 KB: two chunks, refused when complete
    page.get_by_test_id("file-input").set_input_files(str(bad))
    status = page.locator(".upload-status.error")
    expect(status).to_contain_text("Upload failed, notes.jpg: not a readable image")
    expect(page.get_by_test_id("image-row")).to_have_count(0)
    page.screenshot(path=str(ARTIFACTS / "resumable-upload-refused.png"))
    watch.forget("/uploads/")  # the 422 we provoked
    watch.assert_clean(tus_service.url)


def test_the_same_file_chosen_after_a_reload_continues_its_upload(watched_page, tus_service, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    page, watch = watched_page
    flight = open_new_flight(page, tus_service)
    path = photo_file(tmp_path)
    seen: list[tuple[str, str]] = []
    held: list[Any] = []  # the second PATCH, held until the page goes away

    def network(route: Any, request: Any) -> None:
        seen.append((request.method, request.headers.get("upload-offset", "")))
        if request.method == "PATCH" and len(held) == 0 and sum(m == "PATCH" for m, _ in seen) == 2:
            held.append(route)  # never answered: the page is reloaded while it waits
        else:
            route.continue_()

    page.route("**/api/flights/*/uploads**", network)
    page.get_by_test_id("file-input").set_input_files(str(path))
    for _ in range(200):  # the route handler runs while the page is waited on
        if held:
            break
        page.wait_for_timeout(50)
    assert held, f"the second PATCH was not sent: {seen}"
    page.reload()
    expect(page.get_by_test_id("file-input")).to_be_attached()
    page.get_by_test_id("file-input").set_input_files(str(path))
    expect(page.get_by_test_id("image-row")).to_have_count(1, timeout=30_000)
    after = seen[seen.index(("PATCH", str(CHUNK))) + 1 :]
    assert ("POST", "") not in after, f"a new upload was made instead of continuing the first: {seen}"
    assert after[0] == ("HEAD", "") and after[1] == ("PATCH", str(CHUNK)), seen
    with httpx.Client(base_url=tus_service.url, headers={"Authorization": f"Bearer {tus_service.token}"}) as client:
        image = client.get(f"/api/flights/{flight}").json()["images"][0]
    stored = tus_service.data_dir / "flights" / str(flight) / "images" / image["stored_name"]
    assert stored.read_bytes() == path.read_bytes()
    watch.failed_requests[:] = [r for r in watch.failed_requests if "/uploads/" not in r]  # the held PATCH
    watch.assert_clean(tus_service.url)
