"""Crack surveys of a plate through the API, their stages run in-process, against a rendered
specimen whose cracks are known (``tests/crack_scenes.py``): counts, lengths, positions and the comparison
of the two load stages, per viewing angle; and the requests refused with 422."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from fastapi.testclient import TestClient

from tests.api.test_calibrations import run_job
from tests.conftest import RecordingQueue
from tests.crack_scenes import CrackSurveyScene, TrueCrack, make_crack_survey

MM_PER_PX = 0.25
ANGLES = (30.0, 45.0, 60.0)  # elevation above the plate, degrees; view k of the scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    return make_crack_survey(tmp_path_factory.mktemp("crack_survey"), [(a, 0.0) for a in ANGLES], seed=3)


def upload(paths: list[Path]) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("files", (p.name, p.read_bytes(), "image/png")) for p in paths]


def dense(line: np.ndarray, step: float = 0.05) -> np.ndarray:
    """(M, 2) points every ``step`` mm along a polyline (N, 2)."""
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]
    s = np.arange(0.0, along[-1] + step, step)
    return np.column_stack([np.interp(s, along, line[:, 0]), np.interp(s, along, line[:, 1])])


def distances(found: dict, truth: TrueCrack) -> np.ndarray:
    """Distance (mm) from every point of a reported crack's polylines to the true centreline."""
    points = np.concatenate([np.array(p) for p in found["paths_mm"]])
    return np.min(np.linalg.norm(points[:, None] - dense(truth.line_mm)[None], axis=2), axis=1)


def pair_up(found: list[dict], truth: list[TrueCrack]) -> list[tuple[dict, TrueCrack, np.ndarray]]:
    """Each true crack with the reported crack lying closest along it; every reported crack used once."""
    pairs = []
    for crack in truth:
        best = min(found, key=lambda f: float(np.median(distances(f, crack))))
        pairs.append((best, crack, distances(best, crack)))
    assert len({id(f) for f, _, _ in pairs}) == len(truth), "two true cracks matched one reported crack"
    return pairs


def survey(client: TestClient, api_settings, scene: CrackSurveyScene, views: tuple[int, ...]) -> dict:
    response = client.post(
        "/api/crack-surveys",
        files=upload(scene.paths(views)),
        data={"options": json.dumps(scene.options(MM_PER_PX, views))},
    )
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["flight_id"] is None and job["kind"] == "crack_survey"
    record = run_job(client, api_settings, job)
    assert record["status"] == "succeeded", record["error"]
    got = client.get(f"/api/crack-surveys/{job['id']}").json()
    assert got["job"]["id"] == job["id"]
    return dict(got["result"]) | {"job_id": job["id"]}


def check_against_truth(result: dict, scene: CrackSurveyScene) -> list[str]:
    """Assert counts, lengths, positions and statuses; return one line of numbers per stage."""
    lines = []
    for stage, truth in zip(result["stages"], scene.stages, strict=True):
        found = [c for c in stage["cracks"] if c["length_mm"] > 5 * MM_PER_PX]
        assert len(found) == len(truth), [round(c["length_mm"], 1) for c in stage["cracks"]]
        true_total = sum(c.length_mm for c in truth)
        assert abs(stage["total_length_mm"] / true_total - 1) < 0.05
        errors, width_errors = [], []
        for reported, crack, dist in pair_up(found, truth):
            errors.append(reported["length_mm"] / crack.length_mm - 1)
            width_errors.append(reported["mean_width_mm"] - crack.width_mm)
            assert abs(width_errors[-1]) < 0.15, (reported["mean_width_mm"], crack.width_mm)  # 0.6 px
            assert abs(errors[-1]) < 0.05, (reported["length_mm"], crack.length_mm)
            assert np.percentile(dist, 95) <= 2 * MM_PER_PX, np.percentile(dist, 95)  # positions within 2 output px
            if crack.status == "grown":
                assert reported["status"] == "grown" and abs(reported["growth_mm"] - 15.0) < 3.0
            else:
                assert reported["status"] == crack.status, (reported["status"], crack.status)
        lines.append(
            f"{stage['label']}: {len(found)} cracks, total {stage['total_length_mm'] / true_total - 1:+.1%}, "
            f"worst crack {max(errors, key=abs):+.1%}, mean width {np.mean(width_errors):+.2f} mm off"
        )
    return lines


@pytest.mark.parametrize("view", range(len(ANGLES)), ids=[f"{a:.0f}deg" for a in ANGLES])
def test_cracks_measured_in_mm_at_each_viewing_angle(
    client: TestClient, api_settings, scene: CrackSurveyScene, view: int
) -> None:
    result = survey(client, api_settings, scene, (view,))
    for photo in result["photos"]:  # control points carry 0.3 px of noise
        assert photo["rms_px"] < 0.6 and photo["rms_mm"] < 0.3 and len(photo["points"]) == 7
    print(*check_against_truth(result, scene), sep="\n")  # the figures, with pytest -s
    second = result["comparisons"][0]
    assert (second["from"], second["to"], second["new"], second["grown"], second["unchanged"]) == (0, 1, 2, 1, 4)


def test_stage_of_three_photos_is_composed_and_its_outputs_written(
    client: TestClient, api_settings, scene: CrackSurveyScene
) -> None:
    result = survey(client, api_settings, scene, (0, 1, 2))
    check_against_truth(result, scene)
    # 900 px photos of a 200 mm plate resolve ~0.3 mm, the 60 degree view best: the 0.25 mm raster is fine
    assert all(0.2 < stage["photo_mm_per_px"] < 0.4 for stage in result["stages"]), result["stages"]
    assert result["warnings"] == []
    outputs = {o["name"] for o in client.get(f"/api/jobs/{result['job_id']}/outputs").json()["outputs"]}
    assert {
        "report.json",
        "cracks.geojson",
        "cracks.csv",
        "stage_00_rectified.tif",
        "stage_01_rectified.tif",
        "stage_00_overlay.png",
        "stage_01_overlay.png",
    } <= outputs
    cog = client.get(f"/api/jobs/{result['job_id']}/outputs/stage_01_rectified.tif")
    with rasterio.MemoryFile(cog.content) as memory, memory.open() as dataset:
        assert (dataset.width, dataset.height, dataset.count) == (801, 601, 3)
        assert dataset.res == (MM_PER_PX, MM_PER_PX) and dataset.overviews(1)
        # a local engineering frame in mm: neither geographic nor projected, units of 0.001 m
        crs = dataset.crs
        assert not crs.is_geographic and not crs.is_projected and "specimen" in crs.to_wkt()
        assert crs.units_factor[1] == 0.001
    geojson = client.get(f"/api/jobs/{result['job_id']}/outputs/cracks.geojson").json()
    assert len(geojson["features"]) == sum(s["count"] for s in result["stages"])
    statuses = [f["properties"]["status"] for f in geojson["features"] if f["properties"]["stage"] == 1]
    assert sorted(statuses) == sorted(c["status"] for c in result["stages"][1]["cracks"])
    rows = list(csv.DictReader(io.StringIO(client.get(f"/api/jobs/{result['job_id']}/outputs/cracks.csv").text)))
    assert len(rows) == len(geojson["features"]) and float(rows[0]["length_mm"]) > 0


def test_a_misplaced_control_point_fails_the_job_naming_it(
    client: TestClient, api_settings, scene: CrackSurveyScene
) -> None:
    options = scene.options(MM_PER_PX, (1,))
    options["stages"][1]["photos"][0]["control_points"][5]["pixel"][0] += 60.0
    response = client.post("/api/crack-surveys", files=upload(scene.paths((1,))), data={"options": json.dumps(options)})
    assert response.status_code == 202, response.text
    record = run_job(client, api_settings, response.json())
    assert record["status"] == "failed" and record["stage"] == "orient_camera"
    assert "stage2_view2_45deg.png" in record["error"] and "point 5" in record["error"]


def _fewer_points(o: dict) -> None:
    del o["stages"][0]["photos"][0]["control_points"][3:]


def _collinear(o: dict) -> None:
    o["stages"][0]["photos"][0]["control_points"] = [
        {"pixel": [100.0 + k, 100.0], "model": [10.0 * k, 20.0, 0.0]} for k in range(5)
    ]


def _outside(o: dict) -> None:
    o["stages"][0]["photos"][0]["control_points"][2]["model"] = [250.0, 10.0, 0.0]


def _wrong_size(o: dict) -> None:
    o["camera"]["width"] = 1000


def _not_uploaded(o: dict) -> None:
    o["stages"][1]["photos"].append(
        {"image": "missing.png", "control_points": o["stages"][1]["photos"][0]["control_points"]}
    )


def _not_named(o: dict) -> None:
    o["stages"][1]["photos"] = []
    o["stages"].pop()


def _bad_camera(o: dict) -> None:
    o["camera"]["fx"] = -5


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        (_fewer_points, "3 control point(s); at least 4"),
        (_collinear, "lie on one line"),
        (_outside, "outside the specimen"),
        (_wrong_size, "but the camera is 1000x700"),
        (_not_uploaded, "not uploaded: missing.png"),
        (_not_named, "no stage of options.stages names: stage2_view2_45deg.png"),
        (_bad_camera, "options.camera: camera.fx and camera.fy must be positive"),
    ],
)
def test_bad_crack_survey_requests_are_422_and_store_nothing(
    client: TestClient, api_settings, recording_queue: RecordingQueue, scene: CrackSurveyScene, change, fragment: str
) -> None:
    options = json.loads(json.dumps(scene.options(MM_PER_PX, (1,))))
    change(options)
    response = client.post("/api/crack-surveys", files=upload(scene.paths((1,))), data={"options": json.dumps(options)})
    assert response.status_code == 422 and fragment in response.json()["detail"], response.text
    assert recording_queue.sent == [] and client.get("/api/jobs").json() == []
    assert not (api_settings.data_dir / "jobs").exists() or not any((api_settings.data_dir / "jobs").iterdir())


def test_unknown_crack_survey_is_404(client: TestClient) -> None:
    assert client.get("/api/crack-surveys/999").status_code == 404
    assert client.post("/api/crack-surveys", data={"options": "{not json"}).status_code == 422


@pytest.mark.parametrize(("seed", "angle"), [(0, 35.0), (1, 55.0)])
def test_other_specimens_and_angles(client: TestClient, api_settings, tmp_path: Path, seed: int, angle: float) -> None:
    """Specimens and angles the detector and thresholds were never looked at with: the same tolerances."""
    other = make_crack_survey(tmp_path / "other", [(angle, 20.0)], seed=seed)
    result = survey(client, api_settings, other, (0,))
    print(*check_against_truth(result, other), sep="\n")
    second = result["comparisons"][0]
    assert (second["new"], second["grown"], second["unchanged"]) == (2, 1, 4)
