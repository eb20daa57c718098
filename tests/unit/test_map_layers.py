"""What the result map's layers read from ``write_report``: footprints with each photo's residuals and camera
position, and ``gcps.geojson`` with the ground control points where they were surveyed and where the map puts
them (planar mode: carried from their marks in the photos through the homographies)."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Geod

from tests.scenes import make_flight
from workers.algorithms.geometry import lonlat_to_utm, utm_to_lonlat
from workers.pipeline import process_directory, run_stage
from workers.workspace import JobWorkspace

GEOD = Geod(ellps="WGS84")


@pytest.fixture(scope="module")
def job(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    root = tmp_path_factory.mktemp("layers")
    flight = make_flight(root / "frames", n_frames=4, frame_size=(360, 270), seed=2)
    process_directory(root / "frames", root / "job", {"working_max_px": 360})
    ws = JobWorkspace(root / "job")
    # three points of the ground, each marked in every frame that sees it
    lines, truth = [f"EPSG:{flight.epsg}"], {}
    w, h = flight.frame_size
    for n, frame in enumerate((0, 1, 3)):
        texture = flight.homographies[frame] @ np.array([w * (0.3 + 0.2 * n), h * 0.5, 1.0])
        texture /= texture[2]
        east, north, _ = flight.texture_to_utm @ texture
        truth[f"gcp{n}"] = (east, north)
        for i, H in enumerate(flight.homographies):
            px = np.linalg.inv(H) @ texture
            x, y = px[:2] / px[2]
            if 10 < x < w - 10 and 10 < y < h - 10:
                lines.append(f"{east:.3f} {north:.3f} 12.5 {x:.2f} {y:.2f} {flight.paths[i].name} gcp{n}")
    ws.gcp_dir().mkdir(parents=True, exist_ok=True)
    (ws.gcp_dir() / "gcp_list.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    ws.forget_stage_report("write_report")
    run_stage(ws, "mosaic", "write_report")
    return ws, flight, truth


def test_gcps_are_where_surveyed_and_the_planar_map_puts_them_within_a_pixel(job) -> None:  # type: ignore[no-untyped-def]
    ws, flight, truth = job
    features = ws.load_gcp_points()["features"]
    assert {f["properties"]["id"] for f in features} == set(truth) and "gcps.geojson" in ws.outputs()
    for feature in features:
        p = feature["properties"]
        east, north = truth[p["id"]]
        lon, lat = feature["geometry"]["coordinates"]
        assert np.allclose(lonlat_to_utm(np.array([[lon, lat]]), flight.epsg)[0], [east, north], atol=0.01)
        assert p["role"] == "checkpoint" and p["observations"] >= 1 and p["elevation_m"] == 12.5
        # planar mode: the homographies put each mark within about a ground pixel of the truth
        assert p["error_horizontal_m"] < 2 * flight.gsd_m, p
        _, _, moved = GEOD.inv(lon, lat, *p["mapped"])
        assert abs(moved - p["error_horizontal_m"]) < 0.01


def test_footprints_carry_residuals_and_the_camera_inside_them(job) -> None:  # type: ignore[no-untyped-def]
    ws, flight, _ = job
    features = ws.load_footprints()["features"]
    assert len(features) == 4
    for feature in features:
        p = feature["properties"]
        assert 0 <= p["rms_px"] < 1.0 and p["gps_residual_m"] >= 0
        ring = np.array(feature["geometry"]["coordinates"][0])
        camera = np.array(p["camera"])
        assert ring[:, 0].min() < camera[0] < ring[:, 0].max() and ring[:, 1].min() < camera[1] < ring[:, 1].max()
        centre = utm_to_lonlat(flight.frame_center_utm(p["index"])[None, :], flight.epsg)[0]
        _, _, off = GEOD.inv(*camera, *centre)
        assert off < 3 * flight.gsd_m  # the frame's centre, where planar mode puts the camera
        assert p["gps"] is not None and len(p["gps"]) == 2
