"""The volume of a stereo DEM's DSM above a base inside a polygon (``POST /tiles/{job}/dsm/volume``), on a DSM
written with a known stockpile: a 20 x 20 m block 5 m high on a sloping plane, 2000 m³ exactly."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from tests.conftest import user_headers
from workers.algorithms.geometry.geodesy import utm_to_lonlat
from workers.config import JOB_KINDS
from workers.raster_io import write_array_cog
from workers.workspace import job_workspace

EPSG = 32632
WEST, NORTH, CELL = 500_000.0, 5_000_100.0, 0.5  # the DSM's corner and cell, m
SIZE = 200  # cells a side: 100 m


def _surface() -> tuple[np.ndarray, np.ndarray]:
    """Heights over the grid: 100 m + a 2 % slope eastward, and the block on cells 60..99 (20 m) each way."""
    cols = np.arange(SIZE)
    x = WEST + (cols + 0.5) * CELL
    z = np.tile(100.0 + 0.02 * (x - WEST), (SIZE, 1)).astype(np.float32)
    z[60:100, 60:100] += 5.0
    state = np.ones((SIZE, SIZE), np.uint8)
    state[70:75, 70:75] = 2  # filled cells
    return z, state


@pytest.fixture
def dem(client: TestClient, api_settings: Any) -> int:
    db = Database(api_settings.resolved_database_url())
    with db.session() as s:
        job = Job(flight_id=None, kind=JobKind.stereo_dem, options={}, status=JobStatus.succeeded, owner_id=None)
        s.add(job)
        s.flush()
        job_id = job.id
    ws = job_workspace(api_settings.data_dir, job_id)
    ws.save_config(JOB_KINDS[JobKind.stereo_dem](geometry="rpc").model_dump())
    ws.save_inputs([])
    z, state = _surface()
    transform = (CELL, 0.0, WEST, 0.0, -CELL, NORTH)
    write_array_cog(ws.dsm_path(), z, transform=transform, epsg=EPSG, nodata=-9999.0)
    write_array_cog(ws.dsm_mask_path(), state, transform=transform, epsg=EPSG, nodata=0)
    db.engine.dispose()
    return job_id


def _lonlat(cells: list[tuple[float, float]]) -> list[list[float]]:
    """(col, row) positions on the grid -> [lon, lat]."""
    en = np.array([[WEST + c * CELL, NORTH - r * CELL] for c, r in cells])
    return utm_to_lonlat(en, EPSG).tolist()


AROUND_THE_BLOCK = [(40, 40), (120, 40), (120, 120), (40, 120)]  # 40 m square, the block well inside


@pytest.mark.parametrize("base", ["fit", "lowest", 100.0])
def test_the_block_above_its_base(client: TestClient, dem: int, base: Any) -> None:
    answer = client.post(f"/tiles/{dem}/dsm/volume", json={"polygon": _lonlat(AROUND_THE_BLOCK), "base": base})
    assert answer.status_code == 200, answer.text
    v = answer.json()
    assert v["crs"] == f"EPSG:{EPSG}" and v["cell_m"] == CELL
    assert abs(v["area_m2"] - 40 * 40) < 0.02 * 1600  # cells whose centre is inside (the ring is lon/lat)
    assert v["with_value_share"] == 1.0 and v["measured_share"] == pytest.approx(1 - 25 / v["cells"], abs=1e-3)
    if base == "fit":  # the slope is fitted away: the block alone
        assert v["volume_above_m3"] == pytest.approx(2000.0, rel=0.005) and v["volume_below_m3"] < 5.0
        assert v["base"]["slope_percent"] == pytest.approx(2.0, abs=0.05) and v["base"]["edge_rms_m"] < 0.05
    elif base == "lowest":  # the lowest edge cell, on the west side: the slope adds its wedge
        slope_wedge = 0.02 * 40 / 2 * v["area_m2"]
        assert v["volume_above_m3"] == pytest.approx(2000.0 + slope_wedge, rel=0.02)
    else:  # 100 m: the plane's height at the west edge of the grid
        assert v["base"] == {"kind": "elevation", "elevation_m": 100.0} and v["volume_above_m3"] > 2000


def test_a_polygon_outside_or_too_small_is_422(client: TestClient, dem: int) -> None:
    far = [[10.0, 10.0], [10.001, 10.0], [10.001, 10.001]]
    outside = client.post(f"/tiles/{dem}/dsm/volume", json={"polygon": far})
    assert outside.status_code == 422 and "outside the DSM" in outside.json()["detail"]
    meridian = -183.0 + 6 * (EPSG % 100)  # zone 32's: 90 degrees off it is beyond its projection
    polygon = [[meridian + 90.0, 0.0], [meridian + 90.0, 1.0], [meridian + 89.0, 1.0]]
    beyond = client.post(f"/tiles/{dem}/dsm/volume", json={"polygon": polygon})
    assert beyond.status_code == 422 and "outside the DSM" in beyond.json()["detail"]
    point = _lonlat([(50, 50)]) * 3
    assert client.post(f"/tiles/{dem}/dsm/volume", json={"polygon": point}).status_code == 422
    for bad in ({"polygon": far[:2]}, {"polygon": far, "base": "median"}, {"polygon": [[200.0, 0.0]] * 3}):
        answer = client.post(f"/tiles/{dem}/dsm/volume", json=bad)
        assert answer.status_code == 422 and "detail" in answer.json()


def test_another_users_dsm_and_a_mosaic_are_not_found(client: TestClient, dem: int) -> None:
    body = {"polygon": _lonlat(AROUND_THE_BLOCK)}
    assert client.post(f"/tiles/{dem}/dsm/volume", json=body, headers=user_headers(client, "eve")).status_code == 404
    assert client.post("/tiles/99999/dsm/volume", json=body).status_code == 404
    anonymous = TestClient(client.app)
    assert anonymous.post(f"/tiles/{dem}/dsm/volume", json=body).status_code == 401
