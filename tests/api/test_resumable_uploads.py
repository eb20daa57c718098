"""Resumable uploads (tus 1.0.0) through the API: creation, resume from the offset, checksums (460), the wrong
offset (409), termination, expiry, refusals, owners; the last byte makes a photo checked as a multipart one is."""

from __future__ import annotations

import base64
import hashlib
import itertools
import time
from datetime import timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.resumable import expire_uploads
from core.db import Database, utcnow
from tests.conftest import user_headers
from tests.scenes import make_flight, write_bad_files

TUS = {"Tus-Resumable": "1.0.0"}
PATCH = {**TUS, "Content-Type": "application/offset+octet-stream"}


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=2, frame_size=(320, 240), seed=5).paths


def b64(text: str | bytes) -> str:
    return base64.b64encode(text.encode() if isinstance(text, str) else text).decode()


def digest(algorithm: str, data: bytes) -> str:
    return f"{algorithm} {b64(hashlib.new(algorithm, data).digest())}"


def new_flight(client: TestClient, headers: dict[str, str] | None = None) -> int:
    return int(client.post("/api/flights", json={"name": "route 17"}, headers=headers).json()["id"])


def create(client: TestClient, flight: int, length: int, name: str = "frame.jpg", **headers: str):
    sent = {
        **TUS,
        "Upload-Length": str(length),
        "Upload-Metadata": f"filename {b64(name)},filetype {b64('image/jpeg')}",
    }
    return client.post(f"/api/flights/{flight}/uploads", headers={**sent, **headers})


def patch(client: TestClient, url: str, offset: int, chunk: bytes, checksum: str | None = "sha256", **headers: str):
    sent = {**PATCH, "Upload-Offset": str(offset), **headers}
    if checksum:
        sent["Upload-Checksum"] = digest(checksum, chunk)
    return client.patch(url, content=chunk, headers=sent)


def offset_of(client: TestClient, url: str) -> int:
    response = client.head(url, headers=TUS)
    assert response.status_code == 200, response.headers
    return int(response.headers["Upload-Offset"])


def part_files(settings, flight: int) -> list[Path]:
    return sorted((settings.data_dir / "flights" / str(flight) / "uploads").glob("*.part"))


def test_options_say_what_the_server_does(client: TestClient, api_settings) -> None:
    response = client.options(f"/api/flights/{new_flight(client)}/uploads")
    assert response.status_code == 204
    assert response.headers["Tus-Version"] == "1.0.0" and response.headers["Tus-Resumable"] == "1.0.0"
    assert set(response.headers["Tus-Extension"].split(",")) == {"creation", "checksum", "termination", "expiration"}
    assert {"sha1", "sha256", "md5"} <= set(response.headers["Tus-Checksum-Algorithm"].split(","))
    assert response.headers["Tus-Max-Size"] == str(api_settings.max_upload_bytes)


def test_an_upload_in_chunks_becomes_the_photo_a_multipart_upload_makes(
    client: TestClient, api_settings, frames: list[Path]
) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    created = create(client, flight, len(data), "DSC 0001.jpg")
    assert created.status_code == 201, created.text
    url = created.headers["Location"]
    assert url.startswith(f"/api/flights/{flight}/uploads/") and created.headers["Tus-Resumable"] == "1.0.0"
    assert "GMT" in created.headers["Upload-Expires"] and created.json()["offset"] == 0
    head = client.head(url, headers=TUS)
    assert head.headers["Upload-Length"] == str(len(data)) and head.headers["Cache-Control"] == "no-store"
    assert head.headers["Upload-Metadata"] == f"filename {b64('DSC 0001.jpg')},filetype {b64('image/jpeg')}"
    cuts = [0, 1000, 7000, len(data) // 2, len(data)]
    for (start, end), algorithm in zip(itertools.pairwise(cuts), ["sha256", "sha1", "md5", None], strict=True):
        assert offset_of(client, url) == start  # where a client resumes from
        answer = patch(client, url, start, data[start:end], algorithm)
        assert answer.status_code == 204, answer.text
        assert answer.headers["Upload-Offset"] == str(end)
    state = client.get(url).json()
    assert state["complete"] and state["offset"] == state["length"] == len(data) and state["expires_at"] is None
    image = state["image"]
    assert offset_of(client, url) == len(data)  # a finished upload still answers HEAD: the client is done
    stored = api_settings.data_dir / "flights" / str(flight) / "images" / image["stored_name"]
    assert stored.read_bytes() == data and part_files(api_settings, flight) == []
    # the same photo as a multipart upload makes of the same file
    other = new_flight(client)
    multipart = client.post(f"/api/flights/{other}/images", files=[("files", ("DSC 0001.jpg", data, "image/jpeg"))])
    expected = multipart.json()["images"][0]
    same = ("filename", "size_bytes", "width", "height", "gps", "focal_length_mm", "seq")
    assert {k: image[k] for k in same} == {k: expected[k] for k in same}
    assert client.get(f"/api/flights/{flight}").json()["images"] == [image]
    assert client.get(f"/api/flights/{flight}/uploads").json() == []  # no unfinished upload left


def test_a_chunk_at_the_wrong_offset_is_409_and_changes_nothing(client: TestClient, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data[:500]).status_code == 204
    for wrong in (0, 499, 501):
        answer = patch(client, url, wrong, data[wrong : wrong + 100])
        assert answer.status_code == 409 and answer.headers["Tus-Resumable"] == "1.0.0"
        assert answer.json()["detail"] == f"frame.jpg: Upload-Offset is {wrong} but the upload has 500 bytes"
    assert offset_of(client, url) == 500
    assert patch(client, url, 500, data[500:]).status_code == 204
    assert client.get(url).json()["image"]["size_bytes"] == len(data)


def test_a_checksum_mismatch_is_460_and_keeps_nothing_of_the_chunk(
    client: TestClient, api_settings, frames: list[Path]
) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data[:4000]).status_code == 204
    damaged = data[4000:9000][:-1] + b"\x00"
    for algorithm in ("sha256", "sha1", "md5", "sha512"):
        answer = patch(client, url, 4000, damaged, None, **{"Upload-Checksum": digest(algorithm, data[4000:9000])})
        assert answer.status_code == 460, answer.text
        assert (
            answer.json()["detail"] == f"frame.jpg: the chunk's {algorithm} is not the one sent; nothing of it was kept"
        )
        assert offset_of(client, url) == 4000
    assert part_files(api_settings, flight)[0].stat().st_size == 4000  # the refused bytes are not on disk either
    for header, reason in [
        ("crc32 AAAAAA==", "algorithm 'crc32' is not supported"),
        ("sha256 not-base64!", "not Base64"),
        (f"sha256 {b64(b'short')}", "a sha256 digest has 32 bytes"),
    ]:
        answer = patch(client, url, 4000, data[4000:9000], None, **{"Upload-Checksum": header})
        assert answer.status_code == 400 and reason in answer.json()["detail"]
        assert offset_of(client, url) == 4000
    assert patch(client, url, 4000, data[4000:]).status_code == 204  # the good bytes then complete it
    assert client.get(url).json()["complete"]


def test_termination_deletes_the_upload_and_its_bytes(client: TestClient, api_settings, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data[:3000]).status_code == 204
    assert len(part_files(api_settings, flight)) == 1
    listed = client.get(f"/api/flights/{flight}/uploads").json()
    assert [(u["url"], u["offset"], u["length"]) for u in listed] == [(url, 3000, len(data))]
    answer = client.delete(url, headers=TUS)
    assert answer.status_code == 204 and answer.headers["Tus-Resumable"] == "1.0.0"
    assert part_files(api_settings, flight) == []
    assert client.head(url, headers=TUS).status_code == 404
    assert patch(client, url, 3000, data[3000:]).status_code == 404
    assert client.get(f"/api/flights/{flight}").json()["images"] == []
    # a finished upload's termination forgets the upload, not the photo
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data).status_code == 204
    assert client.delete(url, headers=TUS).status_code == 204
    assert len(client.get(f"/api/flights/{flight}").json()["images"]) == 1


def test_an_expired_upload_is_gone_with_its_bytes(client: TestClient, api_settings, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    urls = [create(client, flight, len(data)).headers["Location"] for _ in range(3)]
    for url in urls:
        assert patch(client, url, 0, data[:2000]).status_code == 204
    db = Database(api_settings.resolved_database_url())
    later = utcnow() + timedelta(seconds=api_settings.upload_expiry_seconds + 1)
    assert expire_uploads(db, api_settings, now=utcnow()) == 0  # none expired yet
    assert expire_uploads(db, api_settings, now=later) == 3
    assert part_files(api_settings, flight) == []
    assert all(client.head(url, headers=TUS).status_code == 404 for url in urls)


def test_an_idle_upload_expires_by_itself(client: TestClient, api_settings, frames: list[Path]) -> None:
    """With a 1 s expiry the API's sweeper (every 0.5 s) deletes an idle upload; asked for before that, it is 410."""
    data = frames[0].read_bytes()
    api_settings.upload_expiry_seconds = 1  # read by the requests; the sweeper of this app kept its 24 h period
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data[:2000]).headers["Upload-Offset"] == "2000"
    time.sleep(1.2)
    gone = client.head(url, headers=TUS)
    assert gone.status_code == 410 and part_files(api_settings, flight) == []
    assert client.head(url, headers=TUS).status_code == 404  # deleted when it was found expired
    # and the sweeper thread of an app started with that setting deletes one nobody asks for
    from api.resumable import UploadSweeper

    sweeper = UploadSweeper(client.app.state.db, api_settings)  # type: ignore[attr-defined]
    assert sweeper.interval == 0.5
    url = create(client, flight, len(data)).headers["Location"]
    sweeper.start()
    try:
        deadline = time.monotonic() + 5
        while part_files(api_settings, flight) and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        sweeper.stop()
    assert part_files(api_settings, flight) == [] and client.get(f"/api/flights/{flight}/uploads").json() == []


@pytest.mark.parametrize(
    ("headers", "status", "detail"),
    [
        ({"Tus-Resumable": "0.2.2"}, 412, "this server speaks tus 1.0.0"),
        ({"Upload-Length": "-5"}, 400, "Upload-Length: a non-negative integer is required"),
        ({"Upload-Length": "10", "Upload-Metadata": "filetype aW1hZ2U="}, 422, "a 'filename' is required"),
        ({"Upload-Metadata": "filename ***"}, 422, "the value of 'filename' is not Base64 of UTF-8 text"),
        ({"Upload-Metadata": f"filename {b64('a')},filename {b64('b')}"}, 422, "the key 'filename' is given twice"),
        ({"Upload-Defer-Length": "1"}, 400, "Upload-Defer-Length is not supported"),
        ({"Upload-Length": str(10**12)}, 413, "frame.jpg: file is larger than"),
        ({"Upload-Length": "0"}, 422, "frame.jpg: empty file"),
    ],
)
def test_a_bad_creation_is_refused_saying_why(client: TestClient, api_settings, headers, status, detail) -> None:
    flight = new_flight(client)
    response = create(client, flight, 1000, **headers)
    assert response.status_code == status and detail in response.json()["detail"], response.text
    assert response.headers["Tus-Resumable"] == "1.0.0"
    if status == 412:
        assert response.headers["Tus-Version"] == "1.0.0"
    assert part_files(api_settings, flight) == [] and client.get(f"/api/flights/{flight}/uploads").json() == []


def test_bad_patches_are_refused_and_keep_nothing(client: TestClient, api_settings, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    answer = client.patch(url, content=data[:10], headers={**TUS, "Upload-Offset": "0"})
    assert answer.status_code == 415 and "application/offset+octet-stream" in answer.json()["detail"]
    answer = client.patch(url, content=data[:10], headers={**PATCH, "Upload-Offset": "0", "Tus-Resumable": "2"})
    assert answer.status_code == 412
    answer = patch(client, url, 0, data + b"more")  # past Upload-Length
    assert answer.status_code == 413 and "goes past Upload-Length" in answer.json()["detail"]
    assert offset_of(client, url) == 0 and part_files(api_settings, flight)[0].stat().st_size == 0
    assert client.head(url.replace(url[-32:], "0" * 32), headers=TUS).status_code == 404
    assert client.head(url[:-1] + "Z", headers=TUS).status_code == 422  # not an upload id


@pytest.mark.parametrize("kind", ["not_image", "truncated"])
def test_a_finished_file_that_is_no_photo_is_refused_and_deleted(
    client: TestClient, api_settings, tmp_path: Path, kind: str
) -> None:
    data = write_bad_files(tmp_path)[kind].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data), f"{kind}.jpg").headers["Location"]
    answer = patch(client, url, 0, data)
    assert answer.status_code == 422 and answer.json()["detail"].startswith(f"{kind}.jpg: ")
    assert client.head(url, headers=TUS).status_code == 404  # the upload went with it: start again
    assert part_files(api_settings, flight) == []
    images = api_settings.data_dir / "flights" / str(flight) / "images"
    assert not images.exists() or list(images.iterdir()) == []
    assert client.get(f"/api/flights/{flight}").json()["images"] == []


def test_a_photo_already_in_the_flight_is_409(client: TestClient, api_settings, frames: list[Path]) -> None:
    data = frames[1].read_bytes()
    flight = new_flight(client)
    client.post(f"/api/flights/{flight}/images", files=[("files", ("first.jpg", data, "image/jpeg"))])
    url = create(client, flight, len(data), "again.jpg").headers["Location"]
    answer = patch(client, url, 0, data)
    assert answer.status_code == 409
    assert answer.json()["detail"] == "again.jpg: the same photo is already in this flight as first.jpg"
    assert part_files(api_settings, flight) == [] and len(client.get(f"/api/flights/{flight}").json()["images"]) == 1


def test_uploads_are_their_owners_only(client: TestClient, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    alice, bob = user_headers(client, "alice"), user_headers(client, "bob")
    flight = new_flight(client, alice)
    url = create(client, flight, len(data), Authorization=alice["Authorization"]).headers["Location"]
    assert patch(client, url, 0, data[:100], Authorization=alice["Authorization"]).status_code == 204
    assert create(client, flight, len(data), Authorization=bob["Authorization"]).status_code == 404
    assert client.head(url, headers={**TUS, **bob}).status_code == 404
    assert patch(client, url, 100, data[100:], Authorization=bob["Authorization"]).status_code == 404
    assert client.delete(url, headers={**TUS, **bob}).status_code == 404
    assert client.get(f"/api/flights/{flight}/uploads", headers=bob).status_code == 404
    anonymous = {"Authorization": ""}
    assert client.head(url, headers={**TUS, **anonymous}).status_code == 401
    assert patch(client, url, 100, data[100:], Authorization="").status_code == 401
    assert offset_of(client, url) == 100  # (the admin's token) nothing of those reached it
    assert create(client, 10**6, len(data)).status_code == 404  # no such flight


def test_a_post_that_overrides_its_method_is_a_patch(client: TestClient, frames: list[Path]) -> None:
    data = frames[0].read_bytes()
    url = create(client, new_flight(client), len(data)).headers["Location"]
    headers = {**PATCH, "Upload-Offset": "0", "X-HTTP-Method-Override": "PATCH"}
    answer = client.post(url, content=data, headers=headers)
    assert answer.status_code == 204 and answer.headers["Upload-Offset"] == str(len(data))
    assert client.post(url, headers={**TUS, "X-HTTP-Method-Override": "DELETE"}).status_code == 204
    assert client.head(url, headers=TUS).status_code == 404


def test_deleting_the_flight_deletes_its_unfinished_uploads(client: TestClient, api_settings, frames) -> None:
    data = frames[0].read_bytes()
    flight = new_flight(client)
    url = create(client, flight, len(data)).headers["Location"]
    assert patch(client, url, 0, data[:100]).status_code == 204
    assert client.delete(f"/api/flights/{flight}").status_code == 204
    assert part_files(api_settings, flight) == [] and client.head(url, headers=TUS).status_code == 404
