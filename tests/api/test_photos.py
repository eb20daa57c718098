"""A flight's photos before processing: the upload-time check's findings in the flight's answer, previews (by
the token, or by the flight's signature as an <img> opens them), deleting a photo, and a job's photos."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from tests.conftest import user_headers
from tests.scenes import make_flight


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Five sound frames, then a blurred one and a dark one of the same flight."""
    flight = make_flight(tmp_path_factory.mktemp("photos"), n_frames=7, frame_size=(400, 300), seed=5)
    blurred = cv2.GaussianBlur(cv2.imread(str(flight.paths[5])), (0, 0), 3.5)
    cv2.imwrite(str(flight.paths[5]), blurred)  # EXIF is lost: no GPS either
    dark = (cv2.imread(str(flight.paths[6])) * 0.1).astype(np.uint8)
    cv2.imwrite(str(flight.paths[6]), dark)
    return flight.paths


def _upload(client: TestClient, paths: list[Path], headers: dict[str, str] | None = None) -> int:
    flight = client.post("/api/flights", json={"name": "checked"}, headers=headers).json()["id"]
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]
    response = client.post(f"/api/flights/{flight}/images", files=files, headers=headers)
    assert response.status_code == 201, response.text
    return int(flight)


def _codes(images: list[dict]) -> dict[str, list[str]]:
    return {i["filename"]: [issue["code"] for issue in i["issues"]] for i in images}


def test_the_flight_says_what_the_check_found_and_why(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames)
    detail = client.get(f"/api/flights/{flight}").json()
    codes = _codes(detail["images"])
    assert codes == {
        **{p.name: [] for p in frames[:5]},
        frames[5].name: ["blurred", "no_gps"],
        frames[6].name: ["under_exposed", "no_gps"],
    }
    blurred = next(i for i in detail["images"] if i["filename"] == frames[5].name)
    assert "variance of the Laplacian" in blurred["issues"][0]["message"]
    assert blurred["quality"]["sharpness"] < detail["images"][0]["quality"]["sharpness"] / 3
    assert all(i["gps_source"] == ("exif" if i["gps"] else None) for i in detail["images"])
    assert detail["images"][0]["position"] == detail["images"][0]["gps"]


def test_the_upload_answer_is_judged_against_the_flight(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames[:5])
    copy = io.BytesIO()
    Image.open(frames[2]).save(copy, "JPEG", quality=60, exif=Image.open(frames[2]).info.get("exif", b""))
    files = [("files", ("copy.jpg", copy.getvalue(), "image/jpeg"))]  # the same picture, other bytes
    answer = client.post(f"/api/flights/{flight}/images", files=files)
    assert answer.status_code == 201, answer.text
    (image,) = answer.json()["images"]
    assert [i["code"] for i in image["issues"]] == ["duplicate"]
    assert frames[2].name in image["issues"][0]["message"]


def test_a_side_file_gives_the_position_a_job_takes(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames[5:6] + frames[:2])
    gps = f"name,lat,lon,alt\n{frames[5].name},29.7601,-95.3702,61\n"
    assert client.put(f"/api/flights/{flight}/gps", files={"file": ("gps.csv", gps.encode(), "text/csv")}).is_success
    image = next(i for i in client.get(f"/api/flights/{flight}").json()["images"] if i["filename"] == frames[5].name)
    assert image["gps"] is None and image["gps_source"] == "side_file"
    assert image["position"] == {"lat": 29.7601, "lon": -95.3702, "alt": 61.0}
    assert "no_gps" not in [i["code"] for i in image["issues"]]


def test_previews_by_token_and_by_the_flights_signature(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames[:2])
    detail = client.get(f"/api/flights/{flight}").json()
    image = detail["images"][0]
    assert detail["signature"] and image["preview_url"].endswith(detail["signature"])
    with_token = client.get(f"/api/flights/{flight}/images/{image['id']}/preview?size=128")
    assert with_token.status_code == 200 and with_token.headers["content-type"] == "image/jpeg"
    assert max(Image.open(io.BytesIO(with_token.content)).size) == 128
    anonymous = TestClient(client.app)
    signed = anonymous.get(image["preview_url"])
    assert signed.status_code == 200 and max(Image.open(io.BytesIO(signed.content)).size) == 256
    forged = image["preview_url"].replace("sig=", "sig=0")
    assert anonymous.get(forged).status_code == 401
    assert anonymous.get(f"/api/flights/{flight}/images/{image['id']}/preview").status_code == 401
    other = _upload(client, frames[2:3])
    elsewhere = f"/api/flights/{other}/images/{image['id']}/preview?{detail['signature']}"
    assert anonymous.get(elsewhere).status_code == 401  # a flight's signature opens that flight only


@pytest.mark.parametrize(("query", "status"), [("size=16", 422), ("size=4096", 422), ("size=x", 422)])
def test_a_preview_size_out_of_range_is_422(client: TestClient, frames: list[Path], query: str, status: int) -> None:
    flight = _upload(client, frames[:1])
    image = client.get(f"/api/flights/{flight}").json()["images"][0]
    answer = client.get(f"/api/flights/{flight}/images/{image['id']}/preview?{query}")
    assert answer.status_code == status and "detail" in answer.json()


def test_another_users_photos_are_not_found(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames[:2])
    image = client.get(f"/api/flights/{flight}").json()["images"][0]["id"]
    mallory = user_headers(client, "mallory")
    assert client.get(f"/api/flights/{flight}/images/{image}/preview", headers=mallory).status_code == 404
    assert client.delete(f"/api/flights/{flight}/images/{image}", headers=mallory).status_code == 404
    mine = _upload(client, frames[2:3], headers=mallory)
    assert client.delete(f"/api/flights/{mine}/images/{image}", headers=mallory).status_code == 404  # not of it
    assert client.get(f"/api/flights/{flight}/images/{image}/preview").status_code == 200  # still there


def test_deleting_a_photo_removes_it_and_its_file(client: TestClient, api_settings, frames: list[Path]) -> None:
    flight = _upload(client, frames[:3])
    images = client.get(f"/api/flights/{flight}").json()["images"]
    folder = api_settings.data_dir / "flights" / str(flight) / "images"
    assert client.delete(f"/api/flights/{flight}/images/{images[1]['id']}").status_code == 204
    assert not (folder / images[1]["stored_name"]).exists() and (folder / images[0]["stored_name"]).exists()
    assert [i["id"] for i in client.get(f"/api/flights/{flight}").json()["images"]] == [
        images[0]["id"],
        images[2]["id"],
    ]
    again = client.delete(f"/api/flights/{flight}/images/{images[1]['id']}")
    assert again.status_code == 404 and "not found" in again.json()["detail"]
    assert client.delete(f"/api/flights/{flight}/images/99999999").status_code == 404
    assert client.delete(f"/api/flights/{flight}/images/0").status_code == 422


def test_no_photo_is_deleted_while_a_job_of_the_flight_waits(client: TestClient, api_settings, frames) -> None:  # type: ignore[no-untyped-def]
    flight = _upload(client, frames[:3])
    images = client.get(f"/api/flights/{flight}").json()["images"]
    job = client.post("/api/jobs", json={"flight_id": flight, "kind": "mosaic"}).json()
    refused = client.delete(f"/api/flights/{flight}/images/{images[0]['id']}")
    assert refused.status_code == 409 and f"job {job['id']}" in refused.json()["detail"]
    assert len(client.get(f"/api/flights/{flight}").json()["images"]) == 3
    assert client.post(f"/api/jobs/{job['id']}/cancel").status_code == 200
    assert client.delete(f"/api/flights/{flight}/images/{images[0]['id']}").status_code == 204


def test_a_jobs_photos_by_index(client: TestClient, frames: list[Path]) -> None:
    flight = _upload(client, frames[:3])
    job = client.post("/api/jobs", json={"flight_id": flight, "kind": "mosaic"}).json()
    preview = client.get(f"/api/jobs/{job['id']}/photos/2/preview?size=200")
    assert preview.status_code == 200 and max(Image.open(io.BytesIO(preview.content)).size) == 200
    signature = client.get(f"/api/jobs/{job['id']}").json()["signature"]
    assert TestClient(client.app).get(f"/api/jobs/{job['id']}/photos/0/preview?{signature}").status_code == 200
    missing = client.get(f"/api/jobs/{job['id']}/photos/3/preview")
    assert missing.status_code == 404 and "has no photo 3 (it has 3)" in missing.json()["detail"]
    mallory = user_headers(client, "mallory")
    assert client.get(f"/api/jobs/{job['id']}/photos/0/preview", headers=mallory).status_code == 404


def test_a_long_file_name_is_shortened_before_its_extension(client: TestClient, frames: list[Path]) -> None:
    flight = client.post("/api/flights", json={"name": "long names"}).json()["id"]
    name = "N" * 250 + ".jpg"
    files = [("files", (name, frames[0].read_bytes(), "image/jpeg"))]
    response = client.post(f"/api/flights/{flight}/images", files=files)
    assert response.status_code == 201, response.text
    (image,) = response.json()["images"]
    assert image["filename"] == "N" * 196 + ".jpg"
