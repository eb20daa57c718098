"""End to end: real Redis, real Celery worker process, real uvicorn; a flight goes in over HTTP and a
georeferenced COG and tiles come out."""

from __future__ import annotations

import io
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
import rasterio
from PIL import Image

from tests.conftest import LiveService, shared_data
from tests.scenes import make_flight

pytestmark = pytest.mark.e2e


def upload_flight(service: LiveService, name: str, paths: list[Path]) -> int:
    flight = httpx.post(f"{service.url}/api/flights", json={"name": name}, headers=service.headers, timeout=10).json()
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]
    response = httpx.post(
        f"{service.url}/api/flights/{flight['id']}/images", files=files, headers=service.headers, timeout=120
    )
    assert response.status_code == 201, response.text
    assert len(response.json()["images"]) == len(paths)
    return int(flight["id"])


def run_job(service: LiveService, flight_id: int, options: dict | None = None) -> dict:
    body = {"flight_id": flight_id, "kind": "mosaic", "options": options or {}}
    response = httpx.post(f"{service.url}/api/jobs", json=body, headers=service.headers, timeout=10)
    assert response.status_code == 202, response.text
    job = service.wait_for_job(response.json()["id"])
    assert job["status"] == "succeeded", f"{job['error']} (logs in {service.logs})"
    return job


def download(service: LiveService, job_id: int, name: str, to: Path) -> Path:
    outputs = httpx.get(f"{service.url}/api/jobs/{job_id}/outputs", headers=service.headers, timeout=10).json()
    url = next(o["url"] for o in outputs["outputs"] if o["name"] == name)
    response = httpx.get(url, timeout=60)  # no token: the listed url is signed, as a browser's link needs
    assert response.status_code == 200, response.text
    to.write_bytes(response.content)
    return to


def test_synthetic_flight_becomes_cog_and_tiles(live_service: LiveService, tmp_path: Path) -> None:
    flight = make_flight(tmp_path / "flight", n_frames=6, frame_size=(640, 480), seed=3)
    job = run_job(live_service, upload_flight(live_service, "synthetic", flight.paths), {"working_max_px": 640})
    assert job["progress"] == 100 and set(job["timings"]) == set(job["stages"])

    cog = download(live_service, job["id"], "mosaic.tif", tmp_path / "mosaic.tif")
    with rasterio.open(cog) as src:
        assert src.crs.to_epsg() == flight.epsg
        assert src.count == 3 and src.overviews(1), "COG must have overviews"
        assert src.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]
        assert abs(src.transform.a - flight.gsd_m) < 0.1 * flight.gsd_m  # frames are at ~1 texture px per px
        mask = src.dataset_mask()
        assert 0.3 < (mask > 0).mean() < 1.0  # data inside, transparent corners outside

    tilejson = httpx.get(
        f"{live_service.url}/tiles/{job['id']}/tilejson.json", headers=live_service.headers, timeout=10
    )
    tilejson = tilejson.json()
    assert tilejson["georeferenced"] is True
    west, south, east, north = tilejson["bounds"]
    for lat, lon, _ in flight.gps:
        assert west < lon < east and south < lat < north
    z = tilejson["maxzoom"]
    x, y = _tile_of(tilejson["center"][0], tilejson["center"][1], z)
    response = httpx.get(tilejson["tiles"][0].format(z=z, x=x, y=y), timeout=30)  # no token: the template is signed
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"
    tile = np.asarray(Image.open(io.BytesIO(response.content)).convert("RGBA"))
    assert tile.shape == (256, 256, 4)
    assert (tile[..., 3] > 0).mean() > 0.5 and tile[..., :3][tile[..., 3] > 0].std() > 10  # textured mosaic
    far = httpx.get(f"{live_service.url}/tiles/{job['id']}/{z}/0/0.png", headers=live_service.headers, timeout=10)
    assert far.status_code == 404
    unsigned = httpx.get(f"{live_service.url}/tiles/{job['id']}/{z}/{x}/{y}.png", timeout=10)
    assert unsigned.status_code == 401, "a tile needs a token or a signed URL"


def test_event_stream_reports_progress_until_the_end(live_service: LiveService, tmp_path: Path) -> None:
    flight = make_flight(tmp_path / "flight", n_frames=6, frame_size=(800, 600), seed=5)
    flight_id = upload_flight(live_service, "sse", flight.paths)
    job = httpx.post(
        f"{live_service.url}/api/jobs", json={"flight_id": flight_id}, headers=live_service.headers, timeout=10
    ).json()
    events_url = f"{live_service.url}/api/jobs/{job['id']}/events"
    assert httpx.get(events_url, timeout=10).status_code == 401, "the stream needs a token or the job's signature"
    signature = httpx.get(f"{live_service.url}/api/jobs/{job['id']}", headers=live_service.headers, timeout=10)
    signature = signature.json()["signature"]
    events = []
    # As the viewer's EventSource opens it: no header can be sent, the job's signature is in the query.
    with httpx.stream("GET", f"{events_url}?{signature}", timeout=240) as stream:
        assert stream.status_code == 200
        event = ""
        for line in stream.iter_lines():
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                events.append((event, json.loads(line[6:])))
    assert events[-1][0] == "end" and events[-1][1]["status"] == "succeeded"
    progress = [data["progress"] for _, data in events]
    assert progress == sorted(progress), "progress never goes backwards"
    # stages were reported as they advanced, in the pipeline's order (the stream samples the job record every
    # 0.1 s here: a stage shorter than that may pass unseen, and its time is in the next event's timings)
    stages = events[-1][1]["stages"]
    seen = [stages.index(data["stage"]) for _, data in events if data["stage"] in stages]
    assert seen == sorted(seen) and len(set(seen)) >= 3, [data["stage"] for _, data in events]
    assert set(events[-1][1]["timings"]) >= set(stages), "the end event holds every stage's time"


def test_brighton_real_flight(live_service: LiveService, tmp_path: Path) -> None:
    folder = shared_data("drone_brighton_strip1")
    paths = sorted(folder.glob("*.JPG"))
    job = run_job(live_service, upload_flight(live_service, "brighton", paths))
    report = json.loads(download(live_service, job["id"], "report.json", tmp_path / "report.json").read_text())
    assert report["tie_point_rms_px"] < 1.0
    assert len(report["frames_used"]) == 6 and not report["frames_rejected"]
    assert all(p["tie_point_rms_px"] < 1.5 for p in report["pairs"] if p["used"])
    # The GSD fitted to GPS agrees with the camera's: 40 m above ground, 20 mm (35 mm equivalent, 36 mm
    # frame width) over 4000 px gives 18 mm per pixel.
    assert abs(report["gsd_original_m"] - 40.0 * 36.0 / 20.0 / 4000) < 0.2 * 0.018
    cog = download(live_service, job["id"], "mosaic.tif", tmp_path / "mosaic.tif")
    with rasterio.open(cog) as src:
        assert src.crs.to_epsg() == 32615
        from pyproj import Transformer

        to_utm = Transformer.from_crs(4326, 32615, always_xy=True)
        mask = src.dataset_mask()
        for frame in report["frames_used"]:
            e, n = to_utm.transform(frame["gps"]["lon"], frame["gps"]["lat"])
            row, col = src.index(e, n)
            assert 0 <= row < src.height and 0 <= col < src.width and mask[row, col] > 0, frame["name"]


def _tile_of(lon: float, lat: float, z: int) -> tuple[int, int]:
    n = 2**z
    x = int((lon + 180.0) / 360.0 * n)
    y = int((1.0 - np.arcsinh(np.tan(np.radians(lat))) / np.pi) / 2.0 * n)
    return x, y


def test_ortho_job_with_ground_control(live_service: LiveService, tmp_path: Path) -> None:
    """Photo-triangulation with GCPs through the service: controls fit, a held-out checkpoint is
    reported with its error, and the orthomosaic comes out in the flight's UTM zone."""
    from tests.terrain_scenes import make_terrain_flight

    flight = make_terrain_flight(tmp_path / "terrain", rows=3, per_row=3, frame_size=(640, 480), seed=5)
    flight_id = upload_flight(live_service, "terrain", flight.paths)
    gcp_text = gcp_list_for(flight, [(-8.0, 5.0), (9.0, -6.0), (10.0, 8.0), (-9.0, -7.0), (0.5, 0.5)])
    response = httpx.put(
        f"{live_service.url}/api/flights/{flight_id}/gcps",
        files={"file": ("gcp_list.txt", gcp_text.encode())},
        headers=live_service.headers,
        timeout=10,
    )
    assert response.status_code == 200 and response.json()["with_position"] == 5, response.text
    job = run_job(live_service, flight_id, {"mode": "ortho", "checkpoints": ["g4"]})
    assert job["stages"][3:5] == ["adjust_bundle", "orthorectify_frames"]
    report = json.loads(download(live_service, job["id"], "report.json", tmp_path / "report.json").read_text())
    tri = report["triangulation"]
    assert tri["registered"] == tri["total"] == 9 and tri["rms_px"] < 0.5 and "gcp" in tri["datum"]
    gcps = {g["id"]: g for g in tri["gcps"]}
    assert [gcps[f"g{k}"]["role"] for k in range(5)] == ["control"] * 4 + ["checkpoint"]
    assert all(gcps[f"g{k}"]["error_3d_m"] < 0.01 for k in range(4))  # measured 0.4-0.6 mm
    assert gcps["g4"]["error_3d_m"] < 0.03 and tri["checkpoint_rmse_m"] == pytest.approx(gcps["g4"]["error_3d_m"])
    # the map's GCP layer: each point where surveyed, with the adjustment's role and residual
    points = json.loads(download(live_service, job["id"], "gcps.geojson", tmp_path / "gcps.geojson").read_text())
    mapped = {f["properties"]["id"]: f["properties"] for f in points["features"]}
    assert [mapped[f"g{k}"]["role"] for k in range(5)] == ["control"] * 4 + ["checkpoint"]
    for k in range(5):
        error = gcps[f"g{k}"]["error_m"]
        assert mapped[f"g{k}"]["error_m"] == pytest.approx(error, abs=1e-4)
        assert mapped[f"g{k}"]["error_horizontal_m"] == pytest.approx(float(np.hypot(*error[:2])), abs=1e-4)
    with rasterio.open(download(live_service, job["id"], "mosaic.tif", tmp_path / "ortho.tif")) as src:
        assert src.crs.to_epsg() == flight.epsg and src.overviews(1)


def gcp_list_for(flight, spots: list[tuple[float, float]]) -> str:
    """ODM's gcp_list.txt for ground points at world (x, y): UTM position and every photo that sees them."""
    lines = [f"EPSG:{flight.epsg}"]
    for k, (x, y) in enumerate(spots):
        ground = np.array([x, y, float(flight.height(np.array(x), np.array(y)))])
        east, north = flight.origin_utm[0] + x, flight.origin_utm[1] + y
        for path, R, C in zip(flight.paths, flight.rotations, flight.centres, strict=True):
            px = flight.camera.project(((ground - C) @ R.T)[None])[0]
            if 20 <= px[0] < flight.camera.width - 20 and 20 <= px[1] < flight.camera.height - 20:
                lines.append(f"{east:.3f} {north:.3f} {ground[2]:.3f} {px[0]:.2f} {px[1]:.2f} {path.name} g{k}")
    return "\n".join(lines) + "\n"
