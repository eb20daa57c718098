"""Flights and uploads through the API: metadata, validation, and nothing stored on a bad request."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.scenes import make_flight, write_bad_files


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=3, frame_size=(320, 240), seed=2).paths


def multipart(paths: list[Path], names: list[str] | None = None) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [
        ("files", (name, p.read_bytes(), "image/jpeg"))
        for p, name in zip(paths, names or [p.name for p in paths], strict=True)
    ]


def new_flight(client: TestClient, name: str = "park") -> int:
    response = client.post("/api/flights", json={"name": name, "description": "north field"})
    assert response.status_code == 201
    return int(response.json()["id"])


def stored_files(api_settings, flight_id: int) -> list[str]:
    folder = api_settings.data_dir / "flights" / str(flight_id) / "images"
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


def test_create_list_and_get_flights(client: TestClient) -> None:
    first, second = new_flight(client, "a"), new_flight(client, "b")
    listed = client.get("/api/flights").json()
    assert [f["id"] for f in listed] == [second, first] and listed[0]["image_count"] == 0
    detail = client.get(f"/api/flights/{first}").json()
    assert detail["name"] == "a" and detail["images"] == [] and detail["created_at"].endswith("Z")


def test_upload_answers_metadata_and_stores_files(client: TestClient, api_settings, frames: list[Path]) -> None:
    flight_id = new_flight(client)
    response = client.post(f"/api/flights/{flight_id}/images", files=multipart(frames))
    assert response.status_code == 201, response.text
    images = response.json()["images"]
    assert [i["filename"] for i in images] == [p.name for p in frames]
    assert all(i["width"] == 320 and i["height"] == 240 and i["focal_length_mm"] == pytest.approx(8.8) for i in images)
    assert all(abs(i["gps"]["lat"] - 29.76) < 0.01 and i["gps"]["alt"] == pytest.approx(60.0) for i in images)
    assert stored_files(api_settings, flight_id) == sorted(i["stored_name"] for i in images)
    assert client.get(f"/api/flights/{flight_id}").json()["image_count"] == 3


@pytest.mark.parametrize(
    ("kind", "status", "reason"),
    [
        ("not_image", 422, "not a readable image"),
        ("truncated", 422, "truncated"),
        ("empty", 422, "empty file"),
        ("bomb", 413, "decompression bomb"),
    ],
)
def test_bad_file_is_refused_and_nothing_of_the_request_is_kept(
    client: TestClient, api_settings, frames: list[Path], tmp_path: Path, kind: str, status: int, reason: str
) -> None:
    flight_id = new_flight(client)
    client.post(f"/api/flights/{flight_id}/images", files=multipart(frames[:1]))
    before = stored_files(api_settings, flight_id)
    bad = write_bad_files(tmp_path)[kind]
    response = client.post(f"/api/flights/{flight_id}/images", files=multipart([frames[1], bad]))
    assert response.status_code == status
    assert response.json()["detail"].startswith(f"{bad.name}: ") and reason in response.json()["detail"]
    assert stored_files(api_settings, flight_id) == before  # the good file of the request is not kept either
    assert client.get(f"/api/flights/{flight_id}").json()["image_count"] == 1


def test_unsafe_and_duplicate_names_stay_inside_the_flight_folder(
    client: TestClient, api_settings, frames: list[Path]
) -> None:
    flight_id = new_flight(client)
    names = ["../../x.jpg", "..\\..\\x.jpg"]
    response = client.post(f"/api/flights/{flight_id}/images", files=multipart(frames[:2], names))
    assert response.status_code == 201
    assert [i["filename"] for i in response.json()["images"]] == ["x.jpg", "x.jpg"]
    assert len(stored_files(api_settings, flight_id)) == 2
    assert not (api_settings.data_dir / "x.jpg").exists() and not (api_settings.data_dir.parent / "x.jpg").exists()


def test_the_same_photo_twice_is_a_conflict(client: TestClient, frames: list[Path]) -> None:
    flight_id = new_flight(client)
    assert client.post(f"/api/flights/{flight_id}/images", files=multipart(frames[:1])).status_code == 201
    response = client.post(f"/api/flights/{flight_id}/images", files=multipart(frames[:1], ["copy.jpg"]))
    assert response.status_code == 409 and "already in this flight" in response.json()["detail"]


def test_too_large_upload_is_413(client: TestClient, api_settings, frames: list[Path]) -> None:
    api_settings.max_upload_bytes = 1000
    flight_id = new_flight(client)
    response = client.post(f"/api/flights/{flight_id}/images", files=multipart(frames[:1]))
    assert response.status_code == 413 and "larger than 1000 bytes" in response.json()["detail"]
    assert stored_files(api_settings, flight_id) == []


def test_unknown_flight_and_bad_bodies(client: TestClient, frames: list[Path]) -> None:
    assert client.get("/api/flights/999").status_code == 404
    response = client.post("/api/flights/999/images", files=multipart(frames[:1]))
    assert response.status_code == 404 and response.json() == {"detail": "flight 999 not found"}
    assert client.post("/api/flights", json={"name": ""}).status_code == 422
    assert client.post("/api/flights", json={"name": "x", "bogus": 1}).status_code == 422
    assert client.post(f"/api/flights/{new_flight(client)}/images").status_code == 422


def test_ground_control_points_are_checked_then_stored(client: TestClient, api_settings, tmp_path: Path) -> None:
    flight = make_flight(tmp_path, n_frames=2, frame_size=(320, 240), seed=2)
    flight_id = client.post("/api/flights", json={"name": "with gcps"}).json()["id"]
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in flight.paths]
    assert client.post(f"/api/flights/{flight_id}/images", files=files).status_code == 201
    good = (
        "WGS84 UTM 15N\n"
        "271000.0 3294000.0 12.5 100 120 frame_000.jpg gcp1\n"
        "271000.0 3294000.0 12.5 300 110 frame_001.jpg gcp1\n"
        "271020.0 3294010.0 11.0 50 60 frame_001.jpg gcp2\n"
    )
    response = client.put(f"/api/flights/{flight_id}/gcps", files={"file": ("gcp_list.txt", good.encode())})
    assert response.status_code == 200, response.text
    assert response.json() == {
        "file": "gcp_list.txt",
        "points": 2,
        "with_position": 2,
        "observations": 3,
        "images_not_in_flight": [],
    }
    stored = api_settings.data_dir / "flights" / str(flight_id) / "gcp_list.txt"
    assert stored.read_text() == good
    for content, fragment in [
        (good.replace("12.5 300", "x 300"), "line 3"),
        (b"\xff\xfe".decode("latin-1"), "UTF-8"),
        ("EPSG:nonsense\n1 2 3 4 5 a.jpg", "line 1"),
        ("{}", "points"),
    ]:
        name = "ground_control_points.json" if content == "{}" else "gcp_list.txt"
        bad = client.put(f"/api/flights/{flight_id}/gcps", files={"file": (name, content.encode("latin-1"))})
        assert bad.status_code == 422 and fragment in bad.json()["detail"], bad.text
    assert stored.read_text() == good  # a bad file never replaces the good one
    assert client.put("/api/flights/999/gcps", files={"file": ("gcp_list.txt", good.encode())}).status_code == 404
    job = client.post("/api/jobs", json={"flight_id": flight_id, "options": {"mode": "ortho"}}).json()
    assert job["stages"][3:5] == ["adjust_bundle", "orthorectify_frames"]
    assert (api_settings.data_dir / "jobs" / str(job["id"]) / "gcp" / "gcp_list.txt").read_text() == good
