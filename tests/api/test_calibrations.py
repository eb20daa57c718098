"""Calibration and stereo-rig jobs through the API, their stages run in-process, and measuring with a rig."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.db import Database
from tests.conftest import RecordingQueue, shared_data, user_headers
from workers.algorithms.geometry import Camera
from workers.tasks import execute_stage


def chessboards(side: str) -> list[Path]:
    return sorted(shared_data("calib_chessboard").glob(f"{side}*.jpg"))


def upload(paths: list[Path], field: str = "files") -> list[tuple[str, tuple[str, bytes, str]]]:
    return [(field, (p.name, p.read_bytes(), "image/jpeg")) for p in paths]


def run_job(client: TestClient, api_settings, job: dict) -> dict:
    db = Database(api_settings.resolved_database_url())
    for stage in job["stages"]:
        try:
            execute_stage(job["id"], stage, db=db, data_dir=api_settings.data_dir)
        except Exception:
            break
    return dict(client.get(f"/api/jobs/{job['id']}").json())


def blank_photos(tmp_path: Path, n: int, size: tuple[int, int] = (320, 240), prefix: str = "wall") -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for k in range(n):
        path = tmp_path / f"{prefix}{k}.png"
        cv2.imwrite(str(path), rng.integers(0, 255, (size[1], size[0]), dtype=np.uint8))
        paths.append(path)
    return paths


@pytest.mark.realdata
def test_chessboard_calibration_then_corrected_marks(client: TestClient, api_settings) -> None:
    options = json.dumps({"pattern": [9, 6], "square_mm": 25})
    response = client.post("/api/calibrations", files=upload(chessboards("left")), data={"options": options})
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["flight_id"] is None and job["stages"] == ["detect_corners", "calibrate_camera"]
    assert run_job(client, api_settings, job)["status"] == "succeeded"
    result = client.get(f"/api/calibrations/{job['id']}").json()["result"]
    camera = Camera.from_json(result["camera"])
    assert result["rms_px"] < 0.5 and abs(camera.fx - 536) < 0.02 * 536  # MANIFEST: fx ~ 536
    assert len(result["views"]) == 13 and all(len(v["points"]) == 54 for v in result["views"])
    assert result["worst_points"][0]["error_px"] == max(p["error_px"] for v in result["views"] for p in v["points"])
    photos = client.get(f"/api/calibrations/{job['id']}/photos").json()["photos"]
    assert len(photos) == 13 and all(len(p["corners"]) == 54 and p["marks"] is None for p in photos)
    assert photos[3]["corners"] == [q["image_xy"] for q in result["views"][3]["points"]]  # what the solve used

    # a user moves one mark 6 px off and removes a photo: the solve reruns and points at the bad mark
    view = result["views"][3]
    points = [p["image_xy"] for p in view["points"]]
    points[20] = [points[20][0] + 6.0, points[20][1]]
    marks = {
        "markers": [
            {"image": view["image"], "image_points": points, "board_points": [p["board_xyz"] for p in view["points"]]},
            {"image": result["views"][0]["image"], "remove": True},
        ]
    }
    corners_written = (api_settings.data_dir / "jobs" / str(job["id"]) / "corners.json").stat().st_mtime_ns
    again = client.put(f"/api/calibrations/{job['id']}/markers", json=marks)
    assert again.status_code == 202 and again.json()["status"] == "queued"
    assert run_job(client, api_settings, again.json())["status"] == "succeeded"
    resolved = client.get(f"/api/calibrations/{job['id']}").json()["result"]
    assert len(resolved["views"]) == 12 and any("removed" in r for r in resolved["left_out"])
    worst = resolved["worst_points"][0]
    assert (worst["image"], worst["index"]) == (view["image"], 20) and worst["error_px"] > 3.0
    marked = next(v for v in resolved["views"] if v["image"] == view["image"])
    assert marked["source"] == "markers"
    marks_now = {p["name"]: p["marks"] for p in client.get(f"/api/calibrations/{job['id']}/photos").json()["photos"]}
    assert marks_now[view["image"]] == "marked" and marks_now[result["views"][0]["image"]] == "removed"
    assert (api_settings.data_dir / "jobs" / str(job["id"]) / "corners.json").stat().st_mtime_ns == corners_written


@pytest.mark.realdata
def test_stereo_rig_measures_the_board_it_was_calibrated_on(client: TestClient, api_settings) -> None:
    left, right = chessboards("left"), chessboards("right")
    options = json.dumps({"pattern": [9, 6], "square_mm": 25})
    response = client.post(
        "/api/stereo-rigs", files=upload(left, "left") + upload(right, "right"), data={"options": options}
    )
    assert response.status_code == 202, response.text
    job = response.json()
    assert (
        client.post(f"/api/stereo-rigs/{job['id']}/measure", json={"left": [[1, 1]], "right": [[1, 1]]}).status_code
        == 409
    )  # not calibrated yet
    assert run_job(client, api_settings, job)["status"] == "succeeded"
    result = client.get(f"/api/stereo-rigs/{job['id']}").json()["result"]
    assert result["rms_px"] < 0.6 and 50 < result["baseline_mm"] < 200
    # corners 0 and 8 of one row are 8 squares (200 mm) apart; 0 and 45 are 5 rows (125 mm) apart
    corners = json.loads((api_settings.data_dir / "jobs" / str(job["id"]) / "corners.json").read_text())["images"]
    pair = result["pairs"][2]
    lpx, rpx = np.array(corners[pair["left"]]["points"]), np.array(corners[pair["right"]]["points"])
    picks = [0, 8, 45]
    measured = client.post(
        f"/api/stereo-rigs/{job['id']}/measure", json={"left": lpx[picks].tolist(), "right": rpx[picks].tolist()}
    )
    assert measured.status_code == 200, measured.text
    distances = {(d["from"], d["to"]): d for d in measured.json()["distances"]}
    assert abs(distances[(0, 1)]["distance"] - 200.0) < 2.0 and abs(distances[(0, 2)]["distance"] - 125.0) < 1.5
    assert 0 < distances[(0, 1)]["sigma"] < 5.0
    bad = client.post(f"/api/stereo-rigs/{job['id']}/measure", json={"left": [[1, 1], [2, 2]], "right": [[1, 1]]})
    assert bad.status_code == 422 and "pairs" in bad.json()["detail"]
    outside = client.post(f"/api/stereo-rigs/{job['id']}/measure", json={"left": [[900, 1]], "right": [[1, 1]]})
    assert outside.status_code == 422 and "outside" in outside.json()["detail"]
    assert (
        client.post(
            f"/api/stereo-rigs/{job['id'] + 100}/measure", json={"left": [[1, 1]], "right": [[1, 1]]}
        ).status_code
        == 404
    )


def test_plumb_line_job_recovers_planted_distortion(client: TestClient, api_settings) -> None:
    truth = Camera(800, 600, 700.0, 700.0, 401.0, 298.0, k1=-0.18, k2=0.05)
    lines = []
    for offset in np.linspace(-0.35, 0.35, 6):  # straight lines in the world, horizontal and vertical
        along = np.linspace(-0.5, 0.5, 25)
        for ideal in (np.column_stack([along, np.full(25, offset)]), np.column_stack([np.full(25, offset), along])):
            lines.append(truth.normalised_to_pixel(ideal).tolist())
    options = {
        "method": "plumb_line",
        "lines": lines,
        "image_size": [800, 600],
        "terms": ["k1", "k2"],
        "camera": truth.replace(k1=0.0, k2=0.0).to_json(),
    }
    response = client.post("/api/calibrations", data={"options": json.dumps(options)})
    assert response.status_code == 202, response.text
    assert response.json()["stages"] == ["fit_plumb_line"]
    assert run_job(client, api_settings, response.json())["status"] == "succeeded"
    result = client.get(f"/api/calibrations/{response.json()['id']}").json()["result"]
    fitted = Camera.from_json(result["camera"])
    assert abs(fitted.k1 - truth.k1) < 1e-3 and abs(fitted.k2 - truth.k2) < 1e-3 and result["rms_px"] < 1e-3


def test_photos_without_a_board_fail_the_job_saying_which(client: TestClient, api_settings, tmp_path: Path) -> None:
    response = client.post("/api/calibrations", files=upload(blank_photos(tmp_path, 3)))
    assert response.status_code == 202
    record = run_job(client, api_settings, response.json())
    assert record["status"] == "failed"
    assert "only 0 photo(s) have a usable board" in record["error"]
    assert "wall1.png: no 9x6 chessboard" in record["error"]


def test_a_calibrations_photos_say_what_was_found_in_each(client: TestClient, api_settings, tmp_path: Path) -> None:
    job = client.post("/api/calibrations", files=upload(blank_photos(tmp_path, 3))).json()
    before = client.get(f"/api/calibrations/{job['id']}/photos").json()
    assert [p["name"] for p in before["photos"]] == ["wall0.png", "wall1.png", "wall2.png"]
    assert before["photos"][0]["reason"] == "the corners are not found yet" and before["photos"][0]["corners"] is None
    run_job(client, api_settings, job)
    photos = client.get(f"/api/calibrations/{job['id']}/photos").json()
    assert photos["pattern"] == [9, 6]
    assert [(p["index"], p["width"], p["height"], p["side"]) for p in photos["photos"]] == [
        (k, 320, 240, "") for k in range(3)
    ]
    assert all(p["corners"] is None and p["reason"] == "no 9x6 chessboard found" for p in photos["photos"])
    preview = client.get(f"/api/jobs/{job['id']}/photos/1/preview?size=160")
    assert preview.status_code == 200 and preview.headers["content-type"] == "image/jpeg"
    assert client.get(f"/api/stereo-rigs/{job['id']}/photos").status_code == 404  # not a rig
    assert client.get(f"/api/calibrations/{job['id'] + 100}/photos").status_code == 404
    eve = user_headers(client, "eve")
    assert client.get(f"/api/calibrations/{job['id']}/photos", headers=eve).status_code == 404


@pytest.mark.parametrize(
    ("data", "count", "fragment"),
    [
        ({}, 2, "at least 3 photos"),
        ({"options": "{not json"}, 3, "not valid JSON"),
        ({"options": "[1, 2]"}, 3, "JSON object"),
        ({"options": json.dumps({"pattern": [1, 6]})}, 3, "options.pattern"),
        ({"options": json.dumps({"convention": "fisheye"})}, 3, "options.convention"),
        (
            {
                "options": json.dumps(
                    {"markers": [{"image": "other.png", "image_points": [[1, 2]] * 6, "board_points": [[0, 0, 0]] * 6}]}
                )
            },
            3,
            "no photo named",
        ),
        (
            {
                "options": json.dumps(
                    {"markers": [{"image": "wall0.png", "image_points": [[1, 2]] * 6, "board_points": [[0, 0, 0]] * 5}]}
                )
            },
            3,
            "6 image points but 5",
        ),
        ({"options": json.dumps({"method": "plumb_line", "lines": [[[0, 0], [1, 1]]]})}, 0, "at least 2 lines"),
    ],
)
def test_bad_calibration_requests_are_422_and_store_nothing(
    client: TestClient,
    api_settings,
    tmp_path: Path,
    recording_queue: RecordingQueue,
    data: dict,
    count: int,
    fragment: str,
) -> None:
    files = upload(blank_photos(tmp_path, count)) if count else None
    response = client.post("/api/calibrations", files=files, data=data)
    assert response.status_code == 422 and fragment in str(response.json()["detail"]), response.text
    assert recording_queue.sent == [] and client.get("/api/jobs").json() == []
    assert not (api_settings.data_dir / "jobs").exists() or not any((api_settings.data_dir / "jobs").iterdir())


def test_bad_stereo_requests_are_422(client: TestClient, tmp_path: Path, recording_queue: RecordingQueue) -> None:
    photos = blank_photos(tmp_path, 5)
    response = client.post("/api/stereo-rigs", files=upload(photos[:3], "left") + upload(photos[3:], "right"))
    assert response.status_code == 422 and "3 left and 2 right" in response.json()["detail"]
    mixed = blank_photos(tmp_path, 1, (640, 480), prefix="big")
    response = client.post("/api/stereo-rigs", files=upload(photos[:3], "left") + upload(photos[3:] + mixed, "right"))
    assert response.status_code == 422 and "share one size" in response.json()["detail"]
    assert recording_queue.sent == []


def test_marks_need_a_finished_calibration_and_known_ids(client: TestClient, tmp_path: Path) -> None:
    job = client.post("/api/calibrations", files=upload(blank_photos(tmp_path, 3))).json()
    marks = {"markers": [{"image": "wall0.png", "remove": True}]}
    assert client.put(f"/api/calibrations/{job['id']}/markers", json=marks).status_code == 409
    assert client.put("/api/calibrations/999/markers", json=marks).status_code == 404
    assert client.get("/api/calibrations/999").status_code == 404
    assert client.get(f"/api/stereo-rigs/{job['id']}").status_code == 404  # a calibration is not a rig


@pytest.mark.realdata
def test_a_rigs_marks_moved_and_removed_then_solved_again(client: TestClient, api_settings) -> None:
    left, right = chessboards("left")[:4], chessboards("right")[:4]
    options = json.dumps({"pattern": [9, 6], "square_mm": 25})
    job = client.post(
        "/api/stereo-rigs", files=upload(left, "left") + upload(right, "right"), data={"options": options}
    )
    marks = {"markers": [{"image": left[0].name, "remove": True}]}
    assert client.put(f"/api/stereo-rigs/{job.json()['id']}/markers", json=marks).status_code == 409  # not solved yet
    assert run_job(client, api_settings, job.json())["status"] == "succeeded"
    job_id = job.json()["id"]
    result = client.get(f"/api/stereo-rigs/{job_id}").json()["result"]
    views = {v["image"]: v for v in result["views"]}
    assert len(views) == 8 and all(len(v["points"]) == 54 and v["source"] == "chessboard" for v in views.values())
    assert result["worst_points"][0]["error_px"] == max(p["error_px"] for v in views.values() for p in v["points"])

    # mark 20 of the second left photo moved 6 px, mark 30 of the first right photo removed, the last pair left out
    moved, trimmed = views[left[1].name]["points"], views[right[0].name]["points"]
    xy = [p["image_xy"] for p in moved]
    xy[20] = [xy[20][0] + 6.0, xy[20][1]]
    kept = [p for p in trimmed if p["index"] != 30]
    marks = {
        "markers": [
            {"image": left[1].name, "image_points": xy, "board_points": [p["board_xyz"] for p in moved]},
            {
                "image": right[0].name,
                "image_points": [p["image_xy"] for p in kept],
                "board_points": [p["board_xyz"] for p in kept],
            },
            {"image": left[3].name, "remove": True},
        ]
    }
    again = client.put(f"/api/stereo-rigs/{job_id}/markers", json=marks)
    assert again.status_code == 202 and again.json()["status"] == "queued"
    assert client.put(f"/api/calibrations/{job_id}/markers", json=marks).status_code == 404  # a rig is no calibration
    assert run_job(client, api_settings, again.json())["status"] == "succeeded"
    solved = client.get(f"/api/stereo-rigs/{job_id}").json()["result"]
    assert len(solved["pairs"]) == 3 and any(f"{left[3].name}: removed by the user" == r for r in solved["left_out"])
    worst = solved["worst_points"][0]
    assert (worst["image"], worst["index"]) == (left[1].name, 20) and worst["error_px"] > 3.0
    views = {v["image"]: v for v in solved["views"]}
    assert views[left[1].name]["source"] == "markers" and views[right[0].name]["source"] == "markers"
    # the first pair keeps the marks both photos have: mark 30 and the one opposite it (53 - 30) are gone
    board = [p["board_xyz"] for p in views[left[0].name]["points"]]
    assert len(board) == 52 and [75.0, 75.0, 0.0] not in board and [125.0, 50.0, 0.0] not in board
    assert abs(solved["baseline_mm"] - result["baseline_mm"]) < 0.02 * result["baseline_mm"]
    photos = {p["name"]: p["marks"] for p in client.get(f"/api/stereo-rigs/{job_id}/photos").json()["photos"]}
    assert (photos[left[1].name], photos[right[0].name], photos[left[3].name]) == ("marked", "marked", "removed")


def test_a_rigs_bad_marks_are_422_and_change_nothing(client: TestClient, api_settings, tmp_path: Path) -> None:
    photos = blank_photos(tmp_path, 6)
    job = client.post("/api/stereo-rigs", files=upload(photos[:3], "left") + upload(photos[3:], "right")).json()
    assert run_job(client, api_settings, job)["status"] == "failed"  # no board in a blank photo
    config = api_settings.data_dir / "jobs" / str(job["id"]) / "config.json"
    before = config.read_bytes()
    for body, fragment in [
        ({"markers": [{"image": "other.png", "remove": True}]}, "no photo named"),
        (
            {"markers": [{"image": "wall0.png", "image_points": [[1, 2]] * 6, "board_points": [[0, 0, 0]] * 5}]},
            "6 image",
        ),
        (
            {"markers": [{"image": "wall4.png", "image_points": [[1, 2]] * 3, "board_points": [[0, 0, 0]] * 3}]},
            "at least 6",
        ),
        ({"markers": []}, "markers"),
        ({"markers": [{"image": "wall0.png", "image_points": [[1, "x"]] * 6}]}, "markers"),
    ]:
        response = client.put(f"/api/stereo-rigs/{job['id']}/markers", json=body)
        assert response.status_code == 422 and fragment in str(response.json()["detail"]), response.text
    assert config.read_bytes() == before and client.get(f"/api/jobs/{job['id']}").json()["status"] == "failed"
    assert (
        client.put("/api/stereo-rigs/999/markers", json={"markers": [{"image": "a", "remove": True}]}).status_code
        == 404
    )
    eve = user_headers(client, "eve")
    marks = {"markers": [{"image": "wall0.png", "remove": True}]}
    assert client.put(f"/api/stereo-rigs/{job['id']}/markers", json=marks, headers=eve).status_code == 404
