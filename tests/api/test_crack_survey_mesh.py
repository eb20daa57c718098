"""Crack surveys of a curved panel given as a triangle mesh, through the API, against a rendered panel whose
cracks are known on its surface (``tests/crack_scenes.py``): counts, lengths along the surface, 3D
positions in the model frame and the comparison of two load stages; the requests refused with 422; and a
camera taken from a calibration job."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.api.test_calibrations import run_job
from tests.api.test_crack_surveys import dense, upload
from tests.conftest import RecordingQueue
from tests.crack_scenes import CrackSurveyScene, CurvedPanel, make_crack_survey

MM_PER_PX = 0.25
RADIUS_MM = 120.0  # the arc of 200 mm spans 95 degrees, bulges 38 mm; cracks projected on a plane are up to 8% short


@pytest.fixture(scope="module")
def panel(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    return make_crack_survey(
        tmp_path_factory.mktemp("panel"), [(45.0, 0.0), (35.0, 30.0)], seed=3, panel_radius_mm=RADIUS_MM
    )


def post(client: TestClient, scene: CrackSurveyScene, options: dict, views: tuple[int, ...], model: Path | None) -> Any:
    files = upload(scene.paths(views))
    if model is not None:
        files.append(("model", (model.name, model.read_bytes(), "application/octet-stream")))
    return client.post("/api/crack-surveys", files=files, data={"options": json.dumps(options)})


def model_distances(feature: dict, truth_model: np.ndarray) -> np.ndarray:
    points = np.concatenate([np.array(line) for line in feature["geometry"]["coordinates"]])
    return np.min(np.linalg.norm(points[:, None] - truth_model[None], axis=2), axis=1)


@pytest.mark.parametrize("views", [(0,), (0, 1)], ids=["one-view", "two-views"])
def test_cracks_on_a_curved_panel_measured_along_its_surface(
    client: TestClient, api_settings, panel: CrackSurveyScene, views: tuple[int, ...]
) -> None:
    response = post(client, panel, panel.options(MM_PER_PX, views), views, panel.mesh_path)
    assert response.status_code == 202, response.text
    record = run_job(client, api_settings, response.json())
    assert record["status"] == "succeeded", record["error"]
    job_id = response.json()["id"]
    result = client.get(f"/api/crack-surveys/{job_id}").json()["result"]
    for photo in result["photos"]:
        assert photo["rms_px"] < 0.6 and all(len(p["residual_mm"]) == 3 for p in photo["points"])
    normal = np.array(result["plane"]["normal"])
    assert abs(normal[2]) > 0.99  # the panel's best-fit plane is parallel to its edges' plane Z = 0
    geojson = client.get(f"/api/jobs/{job_id}/outputs/cracks.geojson").json()
    specimen = panel.specimen
    assert isinstance(specimen, CurvedPanel)
    for s, truth in enumerate(panel.stages):
        stage = result["stages"][s]
        found = [
            f
            for f in geojson["features"]
            if f["properties"]["stage"] == s and f["properties"]["length_mm"] > 5 * MM_PER_PX
        ]
        assert len(found) == len(truth), [round(f["properties"]["length_mm"], 1) for f in found]
        total_error = stage["total_length_mm"] / sum(c.length_mm for c in truth) - 1
        assert abs(total_error) < 0.05
        errors, width_errors = [], []
        for crack in truth:
            truth_model = specimen.to_model(dense(crack.line_mm))
            best = min(found, key=lambda f: float(np.median(model_distances(f, truth_model))))
            # positions in the model's 3D frame within 2 output pixels, lengths along the curved surface
            assert np.percentile(model_distances(best, truth_model), 95) <= 2 * MM_PER_PX
            errors.append(best["properties"]["length_mm"] / crack.length_mm - 1)
            assert abs(errors[-1]) < 0.05, (best["properties"]["length_mm"], crack.length_mm)
            width_errors.append(best["properties"]["mean_width_mm"] - crack.width_mm)
            assert abs(width_errors[-1]) < 0.15, (best["properties"]["mean_width_mm"], crack.width_mm)
            expected = "first" if s == 0 else crack.status
            assert best["properties"]["status"] == expected
        print(
            f"panel {views} stage {s + 1}: {len(found)} cracks, total {total_error:+.1%}, "
            f"worst crack {max(errors, key=abs):+.1%}, mean width {np.mean(width_errors):+.2f} mm off, "
            f"worst {max(width_errors, key=abs):+.2f} mm"
        )  # the figures, with pytest -s
    assert (result["comparisons"][0]["new"], result["comparisons"][0]["grown"]) == (2, 1)


def test_a_survey_takes_its_camera_from_a_calibration_job(
    client: TestClient, api_settings, panel: CrackSurveyScene
) -> None:
    # a plumb-line calibration of the panel's camera from straight lines through it (no photos needed)
    truth = panel.camera
    along = np.linspace(-0.4, 0.4, 25)
    lines = [
        truth.normalised_to_pixel(line).tolist()
        for offset in np.linspace(-0.3, 0.3, 5)
        for line in (np.column_stack([along, np.full(25, offset)]), np.column_stack([np.full(25, offset), along]))
    ]
    calibration = client.post(
        "/api/calibrations",
        data={
            "options": json.dumps(
                {
                    "method": "plumb_line",
                    "lines": lines,
                    "image_size": [truth.width, truth.height],
                    "terms": ["k1", "k2"],
                    "camera": truth.replace(k1=0.0, k2=0.0, t1=0.0, t2=0.0).to_json(),
                }
            )
        },
    )
    assert calibration.status_code == 202, calibration.text
    calibration_id = calibration.json()["id"]
    options = panel.options(MM_PER_PX, (0,))
    del options["camera"]
    options["calibration_job"] = calibration_id
    refused = post(client, panel, options, (0,), panel.mesh_path)
    assert refused.status_code == 422 and "is queued; use one that has succeeded" in refused.json()["detail"]
    assert run_job(client, api_settings, calibration.json())["status"] == "succeeded"
    camera = client.get(f"/api/calibrations/{calibration_id}").json()["result"]["camera"]
    accepted = post(client, panel, options, (0,), panel.mesh_path)
    assert accepted.status_code == 202, accepted.text
    config = json.loads((api_settings.data_dir / "jobs" / str(accepted.json()["id"]) / "config.json").read_text())
    assert config["camera"] == camera and config["calibration_job"] == calibration_id
    stored = api_settings.data_dir / "jobs" / str(accepted.json()["id"]) / "specimen" / "model.obj"
    assert panel.mesh_path is not None and stored.read_bytes() == panel.mesh_path.read_bytes()


def _write(tmp: Path, name: str, text: str) -> Path:
    path = tmp / name
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ("few", "5 control point(s); at least 6"),
        ("off_surface", "mm from the model's surface"),
        ("broken", "panel.obj: not a valid OBJ file"),
        ("no_model", "upload that file as the 'model' field"),
        ("plate_and_mesh", "leave out width_mm and height_mm"),
        ("plane_on_a_line", "not on one line"),
        ("both_cameras", "give camera or calibration_job, not both"),
        ("no_calibration", "there is no calibration job 999"),
    ],
)
def test_bad_mesh_survey_requests_are_422_and_store_nothing(
    client: TestClient,
    api_settings,
    recording_queue: RecordingQueue,
    panel: CrackSurveyScene,
    tmp_path: Path,
    change: str,
    fragment: str,
) -> None:
    options = json.loads(json.dumps(panel.options(MM_PER_PX, (0,))))
    points = options["stages"][0]["photos"][0]["control_points"]
    model: Path | None = panel.mesh_path
    if change == "few":
        del points[5:]
    elif change == "off_surface":
        points[4]["model"][2] -= 5.0
    elif change == "broken":
        model = _write(tmp_path, "panel.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n")
    elif change == "no_model":
        model = None
    elif change == "plate_and_mesh":
        options["specimen"]["width_mm"] = 200.0
    elif change == "plane_on_a_line":
        options["specimen"]["plane"] = [[0, 0, 0], [10, 0, 0], [20, 0, 0]]
    elif change == "both_cameras":
        options["calibration_job"] = 1
    elif change == "no_calibration":
        del options["camera"]
        options["calibration_job"] = 999
    response = post(client, panel, options, (0,), model)
    assert response.status_code == 422 and fragment in response.json()["detail"], response.text
    assert recording_queue.sent == [] and client.get("/api/jobs").json() == []
    assert not (api_settings.data_dir / "jobs").exists() or not any((api_settings.data_dir / "jobs").iterdir())
