"""Resumable uploads against a real uvicorn: a partial upload survives the API's death (kill -9 in the middle of a
PATCH) and resumes from the offset it had stored for good; a body cut off by the client keeps what arrived,
unless it came with a checksum."""

from __future__ import annotations

import base64
import hashlib
import io
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.live_api import ApiProcess, api_process


@pytest.fixture
def api(tmp_path: Path) -> Iterator[ApiProcess]:
    server = api_process(tmp_path / "data")
    server.start()
    yield server
    if server.process is not None and server.process.poll() is None:
        server.kill()


@pytest.fixture(scope="module")
def photo() -> bytes:
    """A 3 MB JPEG (noise compresses badly): several of the API's 1 MiB writes."""
    pixels = np.random.default_rng(3).integers(0, 256, (1500, 2000, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=95)
    assert out.tell() > 3_000_000
    return out.getvalue()


def create(client: httpx.Client, flight: int, data: bytes) -> str:
    metadata = f"filename {base64.b64encode(b'big.jpg').decode()}"
    answer = client.post(
        f"/api/flights/{flight}/uploads", headers={"Upload-Length": str(len(data)), "Upload-Metadata": metadata}
    )
    assert answer.status_code == 201, answer.text
    return answer.headers["Location"]


def patch(client: httpx.Client, url: str, offset: int, chunk: bytes) -> httpx.Response:
    sha = base64.b64encode(hashlib.sha256(chunk).digest()).decode()
    headers = {
        "Content-Type": "application/offset+octet-stream",
        "Upload-Offset": str(offset),
        "Upload-Checksum": f"sha256 {sha}",
    }
    return client.patch(url, content=chunk, headers=headers)


def patch_when_free(client: httpx.Client, url: str, offset: int, chunk: bytes) -> httpx.Response:
    """PATCH, again while the server still writes the request a test cut off (423), as a tus client does."""
    deadline = time.monotonic() + 10
    while (answer := patch(client, url, offset, chunk)).status_code == 423 and time.monotonic() < deadline:
        time.sleep(0.1)
    return answer


def offset_of(client: httpx.Client, url: str) -> int:
    return int(client.head(url).headers["Upload-Offset"])


def test_a_partial_upload_survives_the_api_being_killed_mid_patch(api: ApiProcess, photo: bytes) -> None:
    first = 1_200_000
    with api.client() as client:
        flight = client.post("/api/flights", json={"name": "route"}).json()["id"]
        url = create(client, flight, photo)
        assert patch(client, url, 0, photo[:first]).status_code == 204
    part = next((api.data_dir / "flights" / str(flight) / "uploads").glob("*.part"))
    sock = api.raw_patch(url, first, len(photo) - first, photo[first : first + 1_500_000])
    deadline = time.monotonic() + 10
    while part.stat().st_size <= first and time.monotonic() < deadline:  # the server has written some of it
        time.sleep(0.02)
    assert part.stat().st_size > first
    api.kill()  # dies in the middle of the PATCH: that PATCH was never counted
    sock.close()
    api.start()
    with api.client() as client:
        assert offset_of(client, url) == first
        answer = patch(client, url, first, photo[first:])
        assert answer.status_code == 204, answer.text
        image = client.get(url).json()["image"]
    stored = api.data_dir / "flights" / str(flight) / "images" / image["stored_name"]
    assert stored.read_bytes() == photo and image["width"] == 2000  # the tail written before the kill was dropped


def test_a_body_cut_off_keeps_what_arrived_unless_it_had_a_checksum(api: ApiProcess, photo: bytes) -> None:
    with api.client() as client:
        flight = client.post("/api/flights", json={"name": "route"}).json()["id"]
        url = create(client, flight, photo)
        api.raw_patch(url, 0, len(photo), photo[:2_000_000]).close()  # no checksum: the bytes that came are kept
        deadline = time.monotonic() + 10
        while offset_of(client, url) == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        kept = offset_of(client, url)
        assert 0 < kept <= 2_000_000  # what the server had read when it saw the client go
        digest = base64.b64encode(hashlib.sha256(photo[kept:]).digest()).decode()
        sock = api.raw_patch(url, kept, len(photo) - kept, photo[kept : kept + 500_000], f"sha256 {digest}")
        time.sleep(0.3)
        sock.close()  # cut off with a checksum: none of it can be checked, none of it is kept
        answer = patch_when_free(client, url, kept, photo[kept:])  # 409 if any of the cut chunk had been kept
        assert answer.status_code == 204, answer.text
        assert client.get(url).json()["image"]["size_bytes"] == len(photo)
