"""Ortho mode against a rendered flight with known cameras over relief: triangulation and map placement."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from tests.conftest import shared_data
from tests.terrain_scenes import TerrainFlight, level_ground_colour_error, make_terrain_flight, relief_colour_error
from workers.algorithms.geometry import Camera
from workers.pipeline import process_directory, run_stage
from workers.workspace import JobWorkspace


@pytest.fixture(scope="module")
def ortho(tmp_path_factory: pytest.TempPathFactory) -> tuple[TerrainFlight, dict, JobWorkspace]:
    root = tmp_path_factory.mktemp("terrain")
    flight = make_terrain_flight(root / "frames", rows=3, per_row=4, frame_size=(640, 480), seed=3)
    # the synthetic GPS is exact: say so (the default, 5 m, is a consumer receiver's accuracy)
    report = process_directory(root / "frames", root / "job", {"mode": "ortho", "gps_sigma_m": 0.05})
    return flight, report, JobWorkspace(root / "job")


def test_every_camera_is_registered_where_it_was(ortho) -> None:
    flight, report, ws = ortho
    tri = report["triangulation"]
    assert tri["registered"] == tri["total"] == 12 and tri["not_registered"] == []
    assert tri["rms_px"] < 0.5
    cams = ws.load_cameras()
    world = cams["world"]
    shift = np.array([world["easting0"] - flight.origin_utm[0], world["northing0"] - flight.origin_utm[1], 0.0])
    errors = [np.linalg.norm(np.array(p["C"]) + shift - flight.centres[int(k)]) for k, p in cams["poses"].items()]
    span = np.ptp(np.array(flight.centres), axis=0).max()
    assert max(errors) < 0.001 * span, f"worst camera centre {max(errors):.3f} m over a {span:.0f} m flight"
    # self-calibration from a focal length EXIF rounded to 1 mm (1.2 % off) and an unknown lens distortion
    camera = cams["camera"]
    assert abs(camera["fx"] - flight.camera.fx) < 0.005 * flight.camera.fx
    assert abs(camera["k1"] - flight.camera.k1) < 0.005
    assert tri["gps_residual_rms_m"] < 0.05


def test_true_ground_reprojects_where_the_photos_show_it(ortho) -> None:
    """Ground points traced through the true cameras land within a pixel in the adjusted ones."""
    flight, _, ws = ortho
    cams = ws.load_cameras()
    camera = Camera.from_json(cams["camera"])
    world = cams["world"]
    shift = np.array([world["easting0"] - flight.origin_utm[0], world["northing0"] - flight.origin_utm[1], 0.0])
    u, v = np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 479, 7))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    errors = []
    for k, pose in cams["poses"].items():
        R, C = flight.rotations[int(k)], flight.centres[int(k)]
        ground = flight.ground_point(flight.camera.unproject(pixels) @ R, C)
        seen = camera.project((ground - np.array(pose["C"]) - shift) @ np.array(pose["R"]).T)
        errors.append(np.linalg.norm(seen - pixels, axis=1))
    rms = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    assert rms < 0.5, f"true ground reprojects {rms:.2f} px RMS from where it was photographed"


def test_orthomosaic_shows_the_ground_at_its_map_position(ortho) -> None:
    """Where the terrain is at the ortho plane's height, every mosaic pixel shows the texture of that spot."""
    flight, report, ws = ortho
    diff, pixels = level_ground_colour_error(flight, ws.mosaic_path(), ws.load_alignment().ground_z)
    assert pixels > 2000
    assert diff < 8.0, f"mean colour difference {diff:.1f} levels where the ground is at the ortho plane"
    assert report["mode"] == "ortho" and report["georeferenced"]


def test_relief_displacement_goes_away_on_the_tie_point_surface(ortho, tmp_path) -> None:
    """Over the hills and hollows (more than 1 m off the ortho plane) the mosaic projected onto the surface of
    the adjusted tie points shows the ground where it is; the same job projected onto the plane shows it
    displaced by its relief (measured: 6.2 against 28.9 levels; 3.5 on level ground)."""
    flight, report, ws = ortho
    z0 = ws.load_alignment().ground_z
    surface = report["ortho_surface"]
    assert surface["kind"] == "tie_points" and surface["points"] > 1000
    assert surface["height_range_m"][1] - surface["height_range_m"][0] < 3 * flight.relief_m  # no runaway point
    on_surface, pixels = relief_colour_error(flight, ws.mosaic_path(), z0)
    plane = JobWorkspace(tmp_path / "plane")
    shutil.copytree(ws.root, plane.root)
    plane.save_config({**plane.load_config(), "ortho_surface": "plane"})
    for stage in ("orthorectify_frames", "compose_mosaic", "write_report"):
        run_stage(plane, "mosaic.ortho", stage, rerun=True)
    assert plane.load_report()["ortho_surface"]["kind"] == "plane"
    on_plane, _ = relief_colour_error(flight, plane.mosaic_path(), z0)
    assert pixels > 100_000
    assert on_plane > 20.0 and on_surface < 8.0 and on_surface < 0.3 * on_plane, (on_surface, on_plane)


@pytest.mark.realdata
def test_brighton_strip_is_triangulated_and_orthorectified(tmp_path) -> None:
    """The real DJI strip: every frame registered, sub-pixel reprojection, GPS fit and GSD as the EXIF expects."""
    report = process_directory(shared_data("drone_brighton_strip1"), tmp_path / "job", {"mode": "ortho"})
    tri = report["triangulation"]
    assert tri["registered"] == tri["total"] == 6 and report["frames_rejected"] == []
    assert tri["rms_px"] < 0.5 and tri["points"] > 500  # working px (2048 of 4000)
    assert tri["gps_residual_rms_m"] < 2.0  # consumer GPS
    # FC300S: 20 mm (35 mm equivalent) at 40 m above the take-off point: 18 mm per photo pixel
    assert abs(report["gsd_original_m"] - 0.018) < 0.15 * 0.018
    assert report["crs"] == "EPSG:32615"
