"""A flight's GPS side file through the API: checked before it replaces the previous one, refused with the line at
fault (nothing stored), and the source of the positions a job's inputs carry."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.limits import MAX_GPS_BYTES
from tests.conftest import user_headers
from tests.scenes import make_flight
from workers.workspace import job_workspace

GEO_TXT = (
    "EPSG:4326\n"
    "# image lon lat z omega phi kappa horizontal vertical\n"
    "frame_000.jpg -95.3710 29.7610 120.5 0 0 0 0.05 0.10\n"
    "frame_001.jpg -95.3711 29.7611 121.0\n"
    "not_uploaded.jpg -95.3712 29.7612 122.0\n"
)
CSV = "name,lat,lon,alt,accuracy\nframe_001.jpg,29.7621,-95.3721,130.0,2.5\n"


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=3, frame_size=(320, 240), seed=2).paths


def flight_with_photos(client: TestClient, frames: list[Path], headers: dict[str, str] | None = None) -> int:
    flight = client.post("/api/flights", json={"name": "gps"}, headers=headers).json()["id"]
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in frames]
    assert client.post(f"/api/flights/{flight}/images", files=files, headers=headers).status_code == 201
    return int(flight)


def put_gps(client: TestClient, flight: int, name: str, content: str | bytes, **kwargs) -> dict:
    data = content.encode() if isinstance(content, str) else content
    response = client.put(f"/api/flights/{flight}/gps", files={"file": (name, data, "text/plain")}, **kwargs)
    return {"status": response.status_code, **response.json()}


def stored(api_settings, flight: int) -> dict[str, str]:
    folder = api_settings.data_dir / "flights" / str(flight)
    return {n: (folder / n).read_text() for n in ("geo.txt", "gps.csv") if (folder / n).exists()}


def test_a_good_geo_txt_is_stored_and_summarised(client: TestClient, api_settings, frames: list[Path]) -> None:
    flight = flight_with_photos(client, frames)
    answer = put_gps(client, flight, "geo.txt", GEO_TXT)
    assert answer == {
        "status": 200,
        "file": "geo.txt",
        "crs": "EPSG:4326",
        "fixes": 3,
        "with_altitude": 3,
        "with_accuracy": 1,
        "images_not_in_flight": ["not_uploaded.jpg"],
        "gps_source": {"side_file": 2, "exif": 1, "none": 0},  # frame_002.jpg keeps its EXIF position
    }
    assert stored(api_settings, flight) == {"geo.txt": GEO_TXT}
    # a CSV (told by its name, or by its content) replaces it
    answer = put_gps(client, flight, "navigation.txt", CSV)
    assert answer["file"] == "gps.csv" and answer["gps_source"] == {"side_file": 1, "exif": 2, "none": 0}
    assert stored(api_settings, flight) == {"gps.csv": CSV}


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("geo.txt", GEO_TXT.replace("29.7611", "95.5"), "geo.txt: line 4: latitude 95.5 is outside -90..90"),
        ("geo.txt", GEO_TXT.replace("-95.3711", "east"), "geo.txt: line 4: x 'east' is not a number"),
        ("geo.txt", GEO_TXT.replace("121.0", "nan"), "geo.txt: line 4: z 'nan' is not a finite number"),
        (
            "geo.txt",
            GEO_TXT + "frame_000.jpg 1 2\n",
            "geo.txt: line 6: frame_000.jpg is listed twice, on lines 3 and 6",
        ),
        ("geo.txt", "EPSG:nonsense\nframe_000.jpg 1 2\n", "geo.txt: line 1: unknown coordinate system"),
        ("geo.txt", "EPSG:4326\nframe_000.jpg 1 2 3 4 5\n", "geo.txt: line 2: expected 'image_name x y"),
        ("geo.txt", "EPSG:4326\n", "geo.txt: no image positions in it"),
        ("nav.csv", "name,lat,lon,alt\nframe_000.jpg,29.76,-195,60\n", "nav.csv: line 2: longitude -195.0 is outside"),
        ("nav.csv", "frame_000.jpg,29.76,-95.37,60,0\n", "nav.csv: line 1: accuracy 0.0 m is not positive"),
        ("nav.csv", "name,lon,lat,alt\n", "nav.csv: line 1: header 'name,lon,lat,alt' is not name,lat,lon,alt"),
        ("nav.csv", b"\xff\xfe\x00a", "nav.csv: not a UTF-8 text file"),
        ("nav.csv", "", "nav.csv: no image positions in it"),
    ],
)
def test_a_bad_file_is_422_naming_the_line_and_the_previous_one_stays(
    client: TestClient, api_settings, frames: list[Path], name: str, content: str | bytes, message: str
) -> None:
    flight = flight_with_photos(client, frames[:2])
    assert put_gps(client, flight, "geo.txt", GEO_TXT)["status"] == 200
    answer = put_gps(client, flight, name, content)
    assert answer["status"] == 422 and answer["detail"].startswith(message), answer
    assert stored(api_settings, flight) == {"geo.txt": GEO_TXT}


def test_size_owner_and_unknown_flight(client: TestClient, api_settings, frames: list[Path]) -> None:
    flight = flight_with_photos(client, frames[:2])
    big = "EPSG:4326\n" + "#" * MAX_GPS_BYTES
    answer = put_gps(client, flight, "geo.txt", big)
    assert answer["status"] == 413 and answer["detail"].startswith("geo.txt: a GPS file over"), answer
    answer = put_gps(client, flight, "geo.txt", big * 2)  # over the request cap: refused before it is read
    assert answer["status"] == 413 and answer["detail"].startswith("request body: "), answer
    assert put_gps(client, 999, "geo.txt", GEO_TXT) == {"status": 404, "detail": "flight 999 not found"}
    bob = user_headers(client, "bob")
    assert put_gps(client, flight, "geo.txt", GEO_TXT, headers=bob)["status"] == 404
    assert stored(api_settings, flight) == {}


def test_a_job_takes_the_side_file_positions(client: TestClient, api_settings, frames: list[Path]) -> None:
    flight = flight_with_photos(client, frames)
    exif = {i["filename"]: i["gps"] for i in client.get(f"/api/flights/{flight}").json()["images"]}
    assert put_gps(client, flight, "geo.txt", GEO_TXT)["status"] == 200
    job = client.post("/api/jobs", json={"flight_id": flight}).json()["id"]
    inputs = {item["name"]: item for item in job_workspace(api_settings.data_dir, job).load_inputs()}
    assert inputs["frame_000.jpg"]["gps"] == {"lat": 29.761, "lon": -95.371, "alt": 120.5}
    assert inputs["frame_000.jpg"]["gps_accuracy_m"] == 0.05 and inputs["frame_000.jpg"]["gps_source"] == "geo.txt"
    assert inputs["frame_001.jpg"]["gps"] == {"lat": 29.7611, "lon": -95.3711, "alt": 121.0}
    assert inputs["frame_001.jpg"]["gps_accuracy_m"] is None
    assert inputs["frame_002.jpg"]["gps"] == exif["frame_002.jpg"] and "gps_accuracy_m" not in inputs["frame_002.jpg"]
    # a later CSV changes later jobs only
    assert put_gps(client, flight, "gps.csv", CSV)["status"] == 200
    later = client.post("/api/jobs", json={"flight_id": flight}).json()["id"]
    again = {item["name"]: item for item in job_workspace(api_settings.data_dir, later).load_inputs()}
    assert again["frame_000.jpg"]["gps"] == exif["frame_000.jpg"]
    assert again["frame_001.jpg"]["gps"] == {"lat": 29.7621, "lon": -95.3721, "alt": 130.0}
    assert again["frame_001.jpg"]["gps_accuracy_m"] == 2.5
    assert job_workspace(api_settings.data_dir, job).load_inputs()[0]["gps"]["alt"] == 120.5


def test_a_side_file_spoiled_by_hand_fails_the_job_request_not_the_server(
    client: TestClient, api_settings, frames: list[Path]
) -> None:
    flight = flight_with_photos(client, frames[:2])
    assert put_gps(client, flight, "geo.txt", GEO_TXT)["status"] == 200
    (api_settings.data_dir / "flights" / str(flight) / "geo.txt").write_text("EPSG:4326\na.jpg 1\n")
    response = client.post("/api/jobs", json={"flight_id": flight})
    assert response.status_code == 422 and "geo.txt no longer reads (line 2: expected" in response.json()["detail"]
    assert client.get("/api/jobs").json() == []
