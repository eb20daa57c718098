"""Tiles of each load step's rectified specimen: a crack survey run once in-process (module scope), then
its load-step routes read as the viewer reads them; the tiles are the step's COG pixel for pixel, in the frame
the report's crack paths use. The former ``/stages/{stage}/`` paths answer the same.

One SQLite app for the module (not the SQLite and PostgreSQL pair of ``api_settings``): the pipeline run is
the slow part, and the tile routes read the job record only to find its kind and status.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rasterio
from fastapi.testclient import TestClient
from rasterio.crs import CRS

from core.settings import Settings
from tests.api.test_calibrations import blank_photos, run_job
from tests.api.test_crack_surveys import upload
from tests.conftest import RecordingQueue, admin_client
from tests.crack_scenes import CrackSurveyScene, make_crack_survey
from workers.raster_io import translate_to_cog
from workers.workspace import job_workspace

MM_PER_PX = 0.25  # the 200 x 150 mm specimen is 801 x 601 px: tiles 0..3 x 0..2 at the finest zoom
SPECIMEN_WKT = (
    'LOCAL_CS["specimen",LOCAL_DATUM["specimen",32767],UNIT["millimetre",0.001],AXIS["X",EAST],AXIS["Y",SOUTH]]'
)


class Survey:
    def __init__(self, client: TestClient, settings: Settings, scene: CrackSurveyScene, tmp: Path) -> None:
        self.client, self.settings, self.scene, self.tmp = client, settings, scene, tmp

    def post(self) -> dict[str, Any]:
        response = self.client.post(
            "/api/crack-surveys",
            files=upload(self.scene.paths()),
            data={"options": json.dumps(self.scene.options(MM_PER_PX))},
        )
        assert response.status_code == 202, response.text
        return dict(response.json())

    def cog(self, job_id: int, step: int) -> Path:
        return job_workspace(self.settings.data_dir, job_id).load_step_cog_path(step)


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Survey]:
    tmp = tmp_path_factory.mktemp("crack_tiles")
    scene = make_crack_survey(tmp / "scene", [(60.0, 0.0)], seed=3)
    settings = Settings(data_dir=tmp / "data", database_url="", redis_url="redis://127.0.0.1:1/0")
    with admin_client(settings, RecordingQueue()) as client:
        yield Survey(client, settings, scene, tmp)


@pytest.fixture(scope="module")
def finished(survey: Survey) -> dict[str, Any]:
    """The survey's job id and report, every stage run."""
    record = run_job(survey.client, survey.settings, survey.post())
    assert record["status"] == "succeeded", record["error"]
    return {"id": record["id"], **survey.client.get(f"/api/crack-surveys/{record['id']}").json()["result"]}


def tile_rgba(survey: Survey, url: str) -> np.ndarray:
    response = survey.client.get(url)
    assert response.status_code == 200 and response.headers["content-type"] == "image/png", response.text
    image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_UNCHANGED)
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA))


def test_load_step_tilejson_is_a_pixel_grid_of_that_step(survey: Survey, finished: dict[str, Any]) -> None:
    job_id = finished["id"]
    for step in (0, 1):
        tilejson = survey.client.get(f"/tiles/{job_id}/load-steps/{step}/tilejson.json").json()
        assert tilejson["georeferenced"] is False and tilejson["tile_size"] == 256
        assert tilejson["bounds"] == [0.0, -601.0, 801.0, 0.0]
        assert (tilejson["minzoom"], tilejson["maxzoom"]) == (0, 2)
        template, _, signature = tilejson["tiles"][0].partition("?")
        assert template.endswith(f"/tiles/{job_id}/load-steps/{step}/{{z}}/{{x}}/{{y}}.png")
        assert "exp=" in signature and "sig=" in signature  # an image tag sends no token
        assert finished["stages"][step]["rectified"] == survey.cog(job_id, step).name


def test_load_step_tiles_are_the_step_cog_pixel_for_pixel(survey: Survey, finished: dict[str, Any]) -> None:
    job_id = finished["id"]
    for step in (0, 1):
        with rasterio.open(survey.cog(job_id, step)) as cog:
            rgb = np.moveaxis(cog.read(window=((256, 512), (512, 768))), 0, 2)
            last = cog.read(window=((512, 601), (768, 801)))
        tile = tile_rgba(survey, f"/tiles/{job_id}/load-steps/{step}/2/2/1.png")
        assert np.array_equal(tile[..., :3], rgb) and (tile[..., 3] == 255).all()
        corner = tile_rgba(survey, f"/tiles/{job_id}/load-steps/{step}/2/3/2.png")  # 33 x 89 px of data
        assert (corner[:89, :33, 3] == 255).all() and (corner[89:, :, 3] == 0).all() and (corner[:, 33:, 3] == 0).all()
        assert np.array_equal(np.moveaxis(corner[:89, :33, :3], 2, 0), last)


def test_crack_paths_lie_on_dark_pixels_of_their_load_step_tiles(survey: Survey, finished: dict[str, Any]) -> None:
    """The report's paths (mm; pixel (col, row) centred on (col, row) * mm_per_px) run along the cracks of
    the tiles: the frame in which the viewer draws them over the tiles."""
    job_id = finished["id"]
    for stage in finished["stages"]:
        tiles = {
            (x, y): tile_rgba(survey, f"/tiles/{job_id}/load-steps/{stage['index']}/2/{x}/{y}.png")[..., :3].mean(
                axis=2
            )
            for x in range(4)
            for y in range(3)
        }
        coating = np.median(tiles[(1, 1)])
        for crack in stage["cracks"]:
            points = np.rint(np.concatenate([np.array(p) for p in crack["paths_mm"]]) / finished["mm_per_px"])
            grey = [tiles[(int(c) // 256, int(r) // 256)][int(r) % 256, int(c) % 256] for c, r in points]
            assert np.median(grey) < 0.8 * coating, (stage["index"], crack["id"], np.median(grey), coating)


def test_load_step_tiles_outside_unknown_or_not_yet_written(survey: Survey, finished: dict[str, Any]) -> None:
    job_id, client = finished["id"], survey.client
    for path, fragment in [
        (f"/tiles/{job_id}/load-steps/0/2/4/0.png", "outside load step 0 of crack survey"),
        (f"/tiles/{job_id}/load-steps/0/0/0/1.png", "outside"),
        (f"/tiles/{job_id}/load-steps/1/27/0/0.png", "does not exist"),
        (f"/tiles/{job_id}/load-steps/2/tilejson.json", "has no load step 2 (it has 2)"),
        (f"/tiles/{job_id}/load-steps/-1/0/0/0.png", "has no load step -1"),
        ("/tiles/999/load-steps/0/tilejson.json", "crack survey 999 not found"),
        (f"/tiles/{job_id}/tilejson.json", "has no mosaic"),
    ]:
        response = client.get(path)
        expected = 409 if "mosaic" in fragment else 404
        assert response.status_code == expected and fragment in response.json()["detail"], (path, response.text)
    calibration = client.post("/api/calibrations", files=upload(blank_photos(survey.tmp, 3))).json()
    response = client.get(f"/tiles/{calibration['id']}/load-steps/0/tilejson.json")
    assert response.status_code == 404 and response.json()["detail"] == f"crack survey {calibration['id']} not found"


def test_a_specimen_cog_in_a_local_mm_crs_is_served_in_its_pixel_grid(survey: Survey, finished: dict[str, Any]) -> None:
    """A queued survey: 409 until a load step's COG is written; then a COG in a local engineering CRS (mm,
    neither geographic nor projected) is tiled on its pixel grid, as one without a CRS is."""
    queued = survey.post()["id"]
    response = survey.client.get(f"/tiles/{queued}/load-steps/0/1/0/0.png")
    assert response.status_code == 409 and "not rectified yet (status: queued)" in response.json()["detail"]
    source = survey.tmp / "local.tif"
    with rasterio.open(survey.cog(finished["id"], 0)) as cog:
        profile = {**cog.profile, "crs": CRS.from_wkt(SPECIMEN_WKT), "driver": "GTiff"}
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(source, "w", **profile) as out:
            out.write(cog.read())
            out.write_mask(cog.dataset_mask())
    translate_to_cog(source, survey.cog(queued, 0), "deflate")
    with rasterio.open(survey.cog(queued, 0)) as cog:
        assert cog.crs is not None and not cog.crs.is_geographic and not cog.crs.is_projected
    tilejson = survey.client.get(f"/tiles/{queued}/load-steps/0/tilejson.json").json()
    assert tilejson["georeferenced"] is False and tilejson["bounds"] == [0.0, -601.0, 801.0, 0.0]
    local = tile_rgba(survey, f"/tiles/{queued}/load-steps/0/2/1/1.png")
    assert np.array_equal(local, tile_rgba(survey, f"/tiles/{finished['id']}/load-steps/0/2/1/1.png"))
    assert survey.client.get(f"/tiles/{queued}/load-steps/1/tilejson.json").status_code == 409


def test_the_former_stages_paths_answer_as_the_load_step_paths(survey: Survey, finished: dict[str, Any]) -> None:
    """``/tiles/{job}/stages/{stage}/...``, the routes' name before load steps: the same answers, found or not,
    a TileJSON pointing at the load-steps tiles, and no place in the OpenAPI schema."""
    job_id, client = finished["id"], survey.client
    for suffix in [
        "0/tilejson.json",
        "1/tilejson.json",
        "0/2/2/1.png",
        "1/2/3/2.png",
        "0/2/4/0.png",
        "1/27/0/0.png",
        "2/tilejson.json",
        "-1/0/0/0.png",
        "x/tilejson.json",
    ]:
        old, new = client.get(f"/tiles/{job_id}/stages/{suffix}"), client.get(f"/tiles/{job_id}/load-steps/{suffix}")
        assert (old.status_code, old.headers["content-type"]) == (new.status_code, new.headers["content-type"])
        if suffix.endswith(".png") and new.status_code == 200:
            assert old.content == new.content, suffix
        elif suffix != "x/tilejson.json":  # a 422 names the path parameter, stage or step
            assert old.json() == new.json(), suffix
    unknown = [client.get(f"/tiles/999/{route}/0/tilejson.json") for route in ("stages", "load-steps")]
    assert unknown[0].status_code == unknown[1].status_code == 404 and unknown[0].json() == unknown[1].json()
    paths = client.get("/openapi.json").json()["paths"]
    assert "/tiles/{job_id}/load-steps/{step}/tilejson.json" in paths
    assert "/tiles/{job_id}/load-steps/{step}/{z}/{x}/{y}.png" in paths
    assert not [p for p in paths if "/stages/" in p]
