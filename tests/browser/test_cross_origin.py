"""Another site's page cannot act on the service: in headless Chromium, a page served from another origin
posts an HTML form that would cancel a job and a ``no-cors`` fetch that would store a photo, as the attack in
issue 11 did. The token lives in the viewer's sessionStorage and is sent as a header, so these requests carry
none: both are answered 401 and nothing changes."""

from __future__ import annotations

import functools
import http.server
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.browser.support import PageWatch, wait_for
from tests.conftest import LiveService, free_port
from tests.scenes import make_flight

pytestmark = pytest.mark.browser

ATTACK_PAGE = """<!doctype html>
<html><body>
<iframe name="sink"></iframe>
<form id="cancel" method="post" action="{api}/api/jobs/{job}/cancel" target="sink"></form>
<script>
  document.getElementById("cancel").submit();
  const form = new FormData();
  form.append("files", new Blob([new Uint8Array({photo})], {{type: "image/jpeg"}}), "planted.jpg");
  fetch("{api}/api/flights/{flight}/images", {{method: "POST", mode: "no-cors", body: form}})
    .finally(() => {{ window.__fetched = true; }});
</script>
</body></html>"""


@pytest.fixture
def attacker_site(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """A static web server on another port of loopback: another origin than the service's."""
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", tmp_path
    finally:
        server.shutdown()


def test_a_page_of_another_origin_cannot_cancel_a_job_or_store_a_photo(
    watched_page: tuple[Any, PageWatch], live_service: LiveService, attacker_site: tuple[str, Path], tmp_path: Path
) -> None:
    page, watch = watched_page
    site, folder = attacker_site
    paths = make_flight(tmp_path / "flight", n_frames=2).paths
    with live_service.client() as api:
        flight = api.post("/api/flights", json={"name": "target"}).json()["id"]
        files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]
        assert api.post(f"/api/flights/{flight}/images", files=files).status_code == 201
        job = api.post("/api/jobs", json={"flight_id": flight, "options": {"working_max_px": 256}}).json()["id"]
        photo = list(paths[0].read_bytes()[:4096])
        (folder / "attack.html").write_text(
            ATTACK_PAGE.format(api=live_service.url, job=job, flight=flight, photo=photo)
        )
        cancel_url = f"{live_service.url}/api/jobs/{job}/cancel"
        upload_url = f"{live_service.url}/api/flights/{flight}/images"
        with (
            page.expect_response(lambda r: r.url == cancel_url) as cancel,
            page.expect_response(lambda r: r.url == upload_url) as upload,
        ):
            page.goto(f"{site}/attack.html")
        assert cancel.value.status == 401 and upload.value.status == 401
        wait_for(page, "() => window.__fetched === true", 10_000, watch, "the page's fetch ended")
        assert len(api.get(f"/api/flights/{flight}").json()["images"]) == 2
        assert api.get(f"/api/jobs/{job}").json()["status"] != "cancelled"
