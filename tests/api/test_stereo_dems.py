"""Stereo DEM jobs through the API: an RPC pair rendered from a known terrain posted, run, and read back as
a user would (the report, the outputs as GeoTIFFs, the DSM and disparity tiles, the elevation under a point);
a rig job's options taking the rig of a finished stereo-rig job; and every bad request answered 4xx naming
what is wrong, with nothing recorded."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import cv2
import morecantile
import numpy as np
import pytest
import rasterio
from fastapi.testclient import TestClient
from PIL import Image
from rasterio.io import MemoryFile

from api import stereo_dem_service
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from tests.conftest import user_headers
from tests.stereo_scenes import RpcPair, make_rectified_pair, make_rpc_pair
from workers.algorithms.calibration import StereoRig
from workers.algorithms.geometry import Camera
from workers.algorithms.geometry.geodesy import utm_to_lonlat
from workers.config import JOB_KINDS
from workers.tasks import execute_stage
from workers.workspace import job_workspace

WEB_MERCATOR = morecantile.tms.get("WebMercatorQuad")


@pytest.fixture(scope="module")
def rpc_pair(tmp_path_factory: pytest.TempPathFactory) -> RpcPair:
    return make_rpc_pair(tmp_path_factory.mktemp("rpc_api"), size=(240, 220))


def tif_files(pair: RpcPair) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [
        ("left", ("left.tif", pair.left.read_bytes(), "image/tiff")),
        ("right", ("right.tif", pair.right.read_bytes(), "image/tiff")),
    ]


def png(image: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(image).save(out, "PNG")
    return out.getvalue()


def png_files(left: np.ndarray, right: np.ndarray, extra_left: int = 0) -> list[tuple[str, tuple[str, bytes, str]]]:
    files = [("left", ("l.png", png(left), "image/png")), ("right", ("r.png", png(right), "image/png"))]
    return files + [("left", (f"l{k}.png", png(left), "image/png")) for k in range(extra_left)]


def run(client: TestClient, settings: Any, job: dict[str, Any]) -> dict[str, Any]:
    db = Database(settings.resolved_database_url())
    for stage in job["stages"]:
        execute_stage(job["id"], stage, db=db, data_dir=settings.data_dir)
    db.engine.dispose()
    return dict(client.get(f"/api/jobs/{job['id']}").json())


def download(client: TestClient, outputs: dict[str, str], name: str) -> MemoryFile:
    response = client.get(outputs[name])
    assert response.status_code == 200, response.text
    return MemoryFile(response.content)


def test_rpc_pair_from_upload_to_tiles_and_points(client: TestClient, api_settings: Any, rpc_pair: RpcPair) -> None:
    response = client.post("/api/stereo-dems", files=tif_files(rpc_pair), data={"options": "{}"})
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "stereo_dem" and job["flight_id"] is None
    assert job["stages"] == ["rectify_pair", "compute_disparity", "build_dsm", "write_stereo_report"]
    config = job_workspace(api_settings.data_dir, job["id"]).load_config()
    assert config["geometry"] == "rpc"  # auto, decided from the uploads' RPCs
    assert run(client, api_settings, job)["status"] == "succeeded"

    result = client.get(f"/api/stereo-dems/{job['id']}").json()["result"]
    assert result["geometry"] == "rpc" and result["surface"]["epsg"] == rpc_pair.epsg
    assert result["surface"]["legend"]["units"] == "m" and len(result["surface"]["legend"]["stops"]) == 6
    outputs = {o["name"]: o["url"] for o in client.get(f"/api/jobs/{job['id']}/outputs").json()["outputs"]}
    assert set(outputs) == {"dsm.tif", "dsm_mask.tif", "disparity.tif", "confidence.tif", "report.json"}
    with download(client, outputs, "dsm.tif") as memory, memory.open() as dsm:
        assert dsm.dtypes[0] == "float32" and dsm.nodata == -9999.0 and dsm.crs.to_epsg() == rpc_pair.epsg
        heights = dsm.read(1, masked=True)
        centre = dsm.xy(dsm.height // 2, dsm.width // 2)
    assert abs(float(np.median(heights.compressed())) - float(np.median(rpc_pair.height(*centre)))) < 40
    with download(client, outputs, "disparity.tif") as memory, memory.open() as disparity:
        assert disparity.dtypes[0] == "float32" and disparity.crs is None

    # the DSM's tiles: georeferenced, a PNG at its centre; the elevation there is the terrain's
    tilejson = client.get(f"/tiles/{job['id']}/dsm/tilejson.json").json()
    assert tilejson["georeferenced"] is True and "/stereo/dsm/{z}/{x}/{y}.png" in tilejson["tiles"][0]
    lon, lat = utm_to_lonlat(np.array([centre]), rpc_pair.epsg)[0]
    tile = WEB_MERCATOR.tile(lon, lat, tilejson["maxzoom"])
    signed = tilejson["tiles"][0].format(z=tile.z, x=tile.x, y=tile.y)  # as a map's image tags fetch it
    png_tile = client.get(signed, headers={"Authorization": ""})
    assert png_tile.status_code == 200 and png_tile.headers["content-type"] == "image/png"
    unsigned = f"/tiles/{job['id']}/stereo/dsm/{tile.z}/{tile.x}/{tile.y}.png"
    assert client.get(unsigned, headers={"Authorization": ""}).status_code == 401
    point_url = f"/tiles/{job['id']}/dsm/point?lon=1&lat=1&{signed.split('?')[1]}"
    assert client.get(point_url, headers={"Authorization": ""}).status_code == 401  # the token's, not a link's
    point = client.get(f"/tiles/{job['id']}/dsm/point", params={"lon": lon, "lat": lat}).json()
    assert point["state"] in ("measured", "filled")
    assert abs(point["elevation_m"] - float(rpc_pair.height(*centre))) < 1.0
    far = client.get(f"/tiles/{job['id']}/dsm/point", params={"lon": lon + 1, "lat": lat}).json()
    assert far["elevation_m"] is None and far["state"] is None
    meridian = -183.0 + 6 * (rpc_pair.epsg % 100)  # the UTM zone's; 90 degrees off it is beyond its projection
    for lon_out, lat_out in ((meridian + 90.0, 0.0), (meridian - 89.0, 1.0), (0.0, 0.0)):
        beyond = client.get(f"/tiles/{job['id']}/dsm/point", params={"lon": lon_out, "lat": lat_out})
        assert beyond.status_code == 200 and beyond.json()["elevation_m"] is None, (lon_out, beyond.text)

    # the disparity map: a pixel grid, with its value and confidence under a pixel
    grid = client.get(f"/tiles/{job['id']}/disparity/tilejson.json").json()
    assert grid["georeferenced"] is False
    assert client.get(f"/tiles/{job['id']}/stereo/disparity/{grid['maxzoom']}/0/0.png").status_code == 200
    value = client.get(f"/tiles/{job['id']}/disparity/point", params={"x": 120.5, "y": 110.5}).json()
    assert isinstance(value["disparity_px"], float) and 0.0 <= value["confidence"] <= 1.0
    assert client.get(f"/tiles/{job['id']}/disparity/point", params={"x": -5, "y": 3}).json()["disparity_px"] is None


def test_stereo_tile_routes_name_only_a_stereo_dem_and_its_layers(client: TestClient, api_settings: Any) -> None:
    left, right, _ = make_rectified_pair(seed=1)
    job = client.post("/api/stereo-dems", files=png_files(left, right), data={"options": '{"rectified": true}'}).json()
    assert client.get(f"/tiles/{job['id']}/dsm/tilejson.json").status_code == 409  # queued: not yet
    assert client.get(f"/tiles/{job['id']}/elevation/tilejson.json").status_code == 422  # no such layer
    assert run(client, api_settings, job)["status"] == "succeeded"
    missing = client.get(f"/tiles/{job['id']}/dsm/tilejson.json")
    assert missing.status_code == 404 and "no RPCs" in missing.json()["detail"]  # a rectified pair has no DSM
    assert client.get(f"/tiles/{job['id']}/dsm/point", params={"lon": 1, "lat": 2}).status_code == 404
    assert client.get(f"/tiles/{job['id']}/disparity/tilejson.json").status_code == 200
    assert client.get(f"/tiles/{job['id'] + 1}/disparity/tilejson.json").status_code == 404
    bad = client.get(f"/tiles/{job['id']}/dsm/point", params={"lon": 500, "lat": 2})
    assert bad.status_code == 422 and "detail" in bad.json()


def seed_rig_job(api_settings: Any, status: JobStatus, camera: Camera) -> int:
    """A stereo-rig job in ``status`` whose result is a rig of two ``camera``s 100 mm apart."""
    db = Database(api_settings.resolved_database_url())
    rig = StereoRig(camera, camera, np.eye(3), np.array([-100.0, 0.0, 0.0]))
    with db.session() as s:
        job = Job(flight_id=None, kind=JobKind.stereo_calibration, options={}, status=status)
        s.add(job)
        s.flush()
        ws = job_workspace(api_settings.data_dir, job.id)
        ws.save_config(JOB_KINDS[JobKind.stereo_calibration]().model_dump())
        ws.save_inputs([])
        if status == JobStatus.succeeded:
            ws.save_calibration({"rig": rig.to_json()})
        job_id = int(job.id)
    db.engine.dispose()
    return job_id


def test_a_rig_job_lends_its_rig(client: TestClient, api_settings: Any) -> None:
    left, right, _ = make_rectified_pair(seed=2, size=(200, 120))
    camera = Camera(200, 120, 150.0, 150.0, 99.5, 59.5)
    rig_id = seed_rig_job(api_settings, JobStatus.succeeded, camera)
    response = client.post(
        "/api/stereo-dems", files=png_files(left, right), data={"options": json.dumps({"rig_job": rig_id})}
    )
    assert response.status_code == 202, response.text
    config = job_workspace(api_settings.data_dir, response.json()["id"]).load_config()
    assert config["geometry"] == "rig" and StereoRig.from_json(config["rig"]).baseline == 100.0
    assert response.json()["options"] == {"rig_job": rig_id}  # the request as it was sent


def test_someone_elses_rig_job_is_unknown(client: TestClient, api_settings: Any) -> None:
    left, right, _ = make_rectified_pair(seed=5, size=(200, 120))
    rig_id = seed_rig_job(api_settings, JobStatus.succeeded, Camera(200, 120, 150.0, 150.0, 99.5, 59.5))
    options = {"options": json.dumps({"rig_job": rig_id})}
    response = client.post(
        "/api/stereo-dems", files=png_files(left, right), data=options, headers=user_headers(client, "bob")
    )
    assert response.status_code == 422 and f"there is no stereo-rig job {rig_id}" in response.json()["detail"]


def _refusals(api_settings: Any) -> list[tuple[list[Any], dict[str, Any] | str, str]]:
    left, right, _ = make_rectified_pair(seed=3, size=(200, 120))
    small = cv2.resize(right, (180, 120))
    queued_rig = seed_rig_job(api_settings, JobStatus.queued, Camera(200, 120, 150.0, 150.0, 99.5, 59.5))
    other_size_rig = seed_rig_job(api_settings, JobStatus.succeeded, Camera(64, 48, 60.0, 60.0, 31.5, 23.5))
    pair = png_files(left, right)
    return [
        (pair, {"geometry": "rpc"}, "l.png has no usable RPC metadata"),
        (
            png_files(left, small),
            {"rectified": True},
            "a rectified pair has one size: l.png is 200x120 px, r.png 180x120",
        ),
        (pair, {"rig_job": 999_999}, "options.rig_job: there is no stereo-rig job 999999"),
        (pair, {"rig_job": queued_rig}, f"stereo-rig job {queued_rig} is queued"),
        (pair, {"rig_job": other_size_rig}, "l.png is 200x120 px but the rig's left camera is 64x48"),
        (pair, {"rig_job": other_size_rig, "rig": {"left": 1}}, "give rig or rig_job, not both"),
        (pair, {"rig": {"left": {"width": 3}}}, "options.rig: stereo rig is missing right, R, T"),
        (pair, {"method": "fast"}, "options.method"),
        (pair, {"rectified": True, "geometry": "rpc"}, "rectified: true contradicts geometry 'rpc'"),
        (pair, {"min_disparity": 4}, "min_disparity needs num_disparities"),
        (pair, {"height_range_m": [500, 400]}, "height_range_m"),
        (pair, "{not json", "not valid JSON"),
        (png_files(left, right, extra_left=1), {}, "left: a stereo DEM takes exactly one left photo, got 2"),
        (pair[:1], {}, "right"),
        ([("left", ("l.png", b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "image/png")), pair[1]], {}, "l.png"),
    ]


def test_bad_requests_are_refused_naming_the_fault_and_leave_nothing(client: TestClient, api_settings: Any) -> None:
    before = client.get("/api/jobs").json()
    for files, options, fragment in _refusals(api_settings):
        data = {"options": options if isinstance(options, str) else json.dumps(options)}
        response = client.post("/api/stereo-dems", files=files, data=data)
        assert 400 <= response.status_code < 500, (fragment, response.status_code, response.text)
        assert fragment in json.dumps(response.json()["detail"]), (fragment, response.json())
    after = client.get("/api/jobs").json()
    assert [j["id"] for j in after if j["kind"] == "stereo_dem"] == [
        j["id"] for j in before if j["kind"] == "stereo_dem"
    ]
    incoming = api_settings.data_dir / "incoming"
    assert not incoming.exists() or not any(incoming.iterdir())


def test_photos_over_the_pixel_limit_are_refused(
    client: TestClient, api_settings: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(stereo_dem_service, "MAX_STEREO_PIXELS", 20_000)
    left, right, _ = make_rectified_pair(seed=4, size=(200, 120))
    response = client.post("/api/stereo-dems", files=png_files(left, right), data={"options": "{}"})
    assert response.status_code == 422 and "l.png is 200x120 px, over the 20000 px" in response.json()["detail"]


def test_an_unknown_stereo_dem_is_404(client: TestClient) -> None:
    response = client.get("/api/stereo-dems/12345")
    assert response.status_code == 404 and response.json()["detail"] == "stereo DEM 12345 not found"


def test_geotiff_rpcs_are_read_at_upload(rpc_pair: RpcPair, tmp_path: Path) -> None:
    """The flag the API decides ``auto`` by comes from GDAL's reading of the upload."""
    from workers.image_meta import inspect_image

    assert inspect_image(rpc_pair.left).get("rpc") is True
    plain = tmp_path / "plain.tif"
    with rasterio.open(rpc_pair.left) as src:
        profile = {k: src.profile[k] for k in ("driver", "width", "height", "count", "dtype")}
        data = src.read()
    with rasterio.open(plain, "w", **profile) as dst:
        dst.write(data)
    assert "rpc" not in inspect_image(plain)
