"""Ortho mode against a rendered flight with known cameras over relief: triangulation and map placement."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio

from tests.conftest import shared_data
from tests.terrain_scenes import (
    TerrainFlight,
    block_colour_error,
    level_ground_colour_error,
    make_buildings_flight,
    make_terrain_flight,
    relief_colour_error,
    roof_height_rms,
    roof_shifts_m,
    surface_height_rms,
)
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


def test_relief_displacement_goes_away_on_the_dense_surface(ortho, tmp_path) -> None:
    """Over the hills and hollows (more than 1 m off the ortho plane) the mosaic projected onto the surface of
    dense stereo between neighbouring frames (the default) shows the ground where it is; its heights are within
    0.08 m RMS of the terrain (a displacement under 0.1 px at the frames' edges), under the tie-point surface's;
    the same job projected onto the plane shows the ground displaced by its relief. Measured: heights 0.048 m
    RMS against the tie points' 0.094 m; colour errors 6.1 (dense), 6.2 (tie points) and 28.9 levels (plane);
    3.5 on level ground, so what is left over the relief is the resampling of its slopes, not displacement."""
    flight, report, ws = ortho
    z0 = ws.load_alignment().ground_z
    surface = report["ortho_surface"]
    assert surface["kind"] == "dense" and surface["pairs"] >= 10 and surface["dense_points"] > 100_000, surface
    assert surface["coverage"] > 0.9  # of the ground two or more frames see
    assert surface["height_range_m"][1] - surface["height_range_m"][0] < 3 * flight.relief_m  # no runaway point
    on_dense, pixels = relief_colour_error(flight, ws.mosaic_path(), z0)
    dense_rms = surface_height_rms(flight, ws)
    other = {}
    for kind in ("tie_points", "plane"):
        job = reprojected(ws, kind, tmp_path)
        other[kind] = (job.load_report()["ortho_surface"], relief_colour_error(flight, job.mosaic_path(), z0)[0], job)
    tie, on_tie, tie_job = other["tie_points"]
    assert tie["kind"] == "tie_points" and tie["points"] > 1000
    tie_rms = surface_height_rms(flight, tie_job)
    assert dense_rms is not None and tie_rms is not None
    assert dense_rms < 0.08 and dense_rms < 0.7 * tie_rms, (dense_rms, tie_rms)
    plane, on_plane, plane_job = other["plane"]
    assert plane["kind"] == "plane" and plane_job.load_ortho_surface() is None
    assert pixels > 100_000
    assert on_plane > 20.0 and on_dense < 8.0 and on_dense < 0.3 * on_plane, (on_dense, on_plane)
    assert on_tie < 8.0 and on_dense < on_tie + 0.25, (on_dense, on_tie)  # no worse where both are good


def reprojected(ws: JobWorkspace, kind: str, tmp_path) -> JobWorkspace:
    """A copy of the adjusted job ``ws`` orthorectified and composed again onto ``ortho_surface: kind``."""
    job = JobWorkspace(tmp_path / kind)
    shutil.copytree(ws.root, job.root)
    job.save_config({**job.load_config(), "ortho_surface": kind})
    for stage in ("orthorectify_frames", "compose_mosaic", "write_report"):
        run_stage(job, "mosaic.ortho", stage, rerun=True)
    return job


@pytest.fixture(scope="module")
def buildings(tmp_path_factory: pytest.TempPathFactory) -> tuple[TerrainFlight, JobWorkspace]:
    """Eight frames of 480 x 360 px from 40 m over 2 m hills and four box-shaped buildings (``BUILDINGS``)."""
    root = tmp_path_factory.mktemp("buildings")
    flight = make_buildings_flight(root / "frames")
    process_directory(root / "frames", root / "job", {"mode": "ortho", "gps_sigma_m": 0.05})
    return flight, JobWorkspace(root / "job")


def test_dense_surface_puts_sharp_relief_where_it_stands(buildings, tmp_path) -> None:
    """Buildings with sheer walls and roofs 3-6 m above the ground around them: dense stereo measures their roofs
    (heights within 0.4 m RMS, 0.5 m in from the eaves), so the mosaic shows every roof where it stands and far
    less ghosting on and around them; the tie points' surface (cells of about 2 m, smoothed) and the plane leave
    roofs a metre or more off and ghosted. Measured (bench/ortho_surface.py): roofs off by 0.00 m at most on the
    dense surface, 1.30 m on the tie points', 3.24 m on the plane; colour error on the buildings and 2 m around
    them 10.4, 18.5 and 22.5 levels; roof heights 0.21 m RMS against the tie points' 4.7 m."""
    flight, ws = buildings
    assert ws.load_report()["ortho_surface"]["kind"] == "dense"
    runs = {"dense": ws, **{kind: reprojected(ws, kind, tmp_path) for kind in ("tie_points", "plane")}}
    shift = {kind: max(roof_shifts_m(flight, job.mosaic_path())) for kind, job in runs.items()}
    near = {kind: block_colour_error(flight, job.mosaic_path()) for kind, job in runs.items()}
    roof = {kind: roof_height_rms(flight, job) for kind, job in runs.items()}
    assert shift["dense"] < 0.3 and shift["tie_points"] > 0.8 and shift["plane"] > 0.8, shift
    assert near["dense"][1] > 20_000  # pixels on and around the buildings
    assert near["dense"][0] < 14.0 and near["dense"][0] < 0.7 * min(near["tie_points"][0], near["plane"][0]), near
    assert roof["plane"] is None and roof["dense"] is not None and roof["tie_points"] is not None
    assert roof["dense"] < 0.4 and roof["dense"] < 0.2 * roof["tie_points"], roof


def test_the_surface_is_the_jobs_dsm_on_the_mosaics_grid(buildings, tmp_path) -> None:
    """``dsm.tif``: a float32 COG in the mosaic's CRS on its grid coarsened by a whole factor (the same corner),
    nodata set, heights only where measured (flagged 1 in ``dsm_mask.tif``) or interpolated between measurements
    (2) where two frames see the ground; there the buildings' roofs and the ground around them come out within a
    few centimetres of the truth (measured: median -0.003 m, 90 % within 0.03 m). Run again onto the plane, the
    job has no DSM."""
    from rio_cogeo.cogeo import cog_validate

    flight, ws = buildings
    assert cog_validate(str(ws.dsm_path()), quiet=True)[0]
    with rasterio.open(ws.dsm_path()) as dsm, rasterio.open(ws.mosaic_path()) as mosaic:
        assert dsm.dtypes[0] == "float32" and dsm.nodata == -9999.0 and dsm.crs == mosaic.crs
        step = dsm.transform.a / mosaic.transform.a
        assert abs(step - round(step)) < 1e-9 and step >= 1 and dsm.transform.e == -dsm.transform.a
        assert (dsm.transform.c, dsm.transform.f) == (mosaic.transform.c, mosaic.transform.f)
        assert dsm.width == -(-mosaic.width // round(step)) and dsm.height == -(-mosaic.height // round(step))
        heights = dsm.read(1, masked=True)
        transform = dsm.transform
    with rasterio.open(ws.dsm_mask_path()) as mask:
        state = mask.read(1)
    assert np.array_equal(state > 0, ~np.ma.getmaskarray(heights))
    assert state[0, 0] == 0 and state[-1, -1] == 0  # the mosaic's corners: one frame or none sees them
    rows, cols = np.nonzero(state > 0)
    east, north = rasterio.transform.xy(transform, rows, cols)
    x, y = np.asarray(east) - flight.origin_utm[0], np.asarray(north) - flight.origin_utm[1]
    error = heights.data[rows, cols] - flight.height(x, y)
    on_roofs = np.zeros(len(x), bool)
    for block in flight.blocks:
        on_roofs |= block.inside(x, y, -0.5)
    assert on_roofs.sum() > 500 and np.median(np.abs(error[on_roofs])) < 0.1, np.median(np.abs(error[on_roofs]))
    assert abs(np.median(error)) < 0.05 and np.percentile(np.abs(error), 90) < 0.15
    assert (state[rows, cols] == 1).mean() > 0.8  # dense stereo measured most of it
    report = ws.load_report()["dsm"]
    assert report["epsg"] == flight.epsg and report["cells"] == len(rows) and report["legend"]["units"] == "m"
    assert "dsm.tif" in ws.outputs() and "dsm_mask.tif" in ws.outputs()
    plane = reprojected(ws, "plane", tmp_path)
    assert plane.load_report()["dsm"] is None and "dsm.tif" not in plane.outputs()
    assert not plane.dsm_view_path().exists()


def test_without_overlapping_pairs_the_tie_point_surface_stands_in_and_says_why(ortho, tmp_path, monkeypatch) -> None:
    from workers.algorithms.stereo import frame_pairs

    _, _, ws = ortho
    job = JobWorkspace(tmp_path / "job")
    shutil.copytree(ws.root, job.root)
    monkeypatch.setattr(frame_pairs, "MIN_OVERLAP", 1.01)  # no two frames share that much ground
    run_stage(job, "mosaic.ortho", "orthorectify_frames", rerun=True)
    surface = job.load_stage_report("orthorectify_frames")["surface"]
    assert surface["kind"] == "tie_points" and surface["why"] == "no pair of frames overlaps enough for dense stereo"
    saved = job.load_ortho_surface()
    assert saved is not None and list(saved.heights.shape[::-1]) == surface["size"]


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
    # dense stereo between neighbours (measured: 6 pairs, 167 000 points, 55 % of the ground two frames see)
    surface = report["ortho_surface"]
    assert surface["kind"] == "dense" and surface["pairs"] >= 5 and surface["dense_points"] > 50_000, surface
    assert surface["coverage"] > 0.4
    assert surface["height_range_m"][1] - surface["height_range_m"][0] < 30.0  # a park and a wood: no runaway
