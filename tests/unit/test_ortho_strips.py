"""Ortho mode on rendered survey strips flown back and forth (opposite headings) with DJI attitude metadata
in mixed heading conventions and noisy GPS: every frame is placed by its own pairs, and every footprint lands
where the true camera puts it."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Transformer

from tests.terrain_scenes import TerrainFlight, level_ground_colour_error, make_terrain_flight
from workers.algorithms.geometry import Camera
from workers.pipeline import process_directory
from workers.workspace import JobWorkspace

GPS_NOISE_M = 0.5


def _fly(root, gps_noise_m: float, calibrated: bool) -> tuple[TerrainFlight, dict, JobWorkspace]:
    """Two strips of six frames, the second flown back, its metadata in the other convention (image top at
    yaw + 180). Before the per-frame check, the second strip was outvoted: its frames kept 3-16 of their
    ~2000 tie points, lay up to 6 m from their GPS, and the report said success."""
    flight = make_terrain_flight(
        root / "frames",
        rows=2,
        per_row=6,
        frame_size=(640, 480),
        seed=5,
        heading_follows_flight=True,
        attitude=("yaw", "yaw+180"),
        gps_noise_m=gps_noise_m,
    )
    options = {"mode": "ortho", "gps_sigma_m": max(gps_noise_m, 0.01)}  # exact GPS: say so
    if calibrated:
        options.update(camera=flight.camera.to_json(), self_calibrate=[])
    report = process_directory(root / "frames", root / "job", options)
    return flight, report, JobWorkspace(root / "job")


@pytest.fixture(scope="module")
def two_strips(tmp_path_factory: pytest.TempPathFactory) -> tuple[TerrainFlight, dict, JobWorkspace]:
    """Exact GPS and a calibrated camera: what is left is the accuracy of the poses. (Self-calibrating from two
    parallel strips leaves the focal length 0.07-0.2 % off, which moves the outer corners by 1.3-2 GSD, as much
    as on the same flight without any attitude metadata.)"""
    return _fly(tmp_path_factory.mktemp("strips"), 0.0, calibrated=True)


@pytest.fixture(scope="module")
def noisy_strips(tmp_path_factory: pytest.TempPathFactory) -> tuple[TerrainFlight, dict, JobWorkspace]:
    """GPS 0.5 m off per axis, as a consumer receiver gives."""
    return _fly(tmp_path_factory.mktemp("noisy"), GPS_NOISE_M, calibrated=False)


@pytest.mark.parametrize("flight", ["two_strips", "noisy_strips"])
def test_each_frame_is_placed_by_its_pairs_in_its_convention(flight: str, request: pytest.FixtureRequest) -> None:
    _, report, _ = request.getfixturevalue(flight)
    sigma = GPS_NOISE_M if flight == "noisy_strips" else 0.01
    tri = report["triangulation"]
    assert tri["registered"] == tri["total"] == 12 and tri["initialisation"] == "gps_attitude"
    assert [i["attitude"] for i in tri["images"]] == ["yaw"] * 6 + ["yaw+180"] * 6
    for image in tri["images"]:
        assert image["status"] == "registered" and image["observations"] >= 0.9 * image["tie_points_offered"]
        assert image["gps_residual_m"] < 4 * sigma, image
    assert report["warnings"] == [] and tri["rms_px"] < 0.5


def test_every_footprint_corner_lands_where_the_true_camera_puts_it(two_strips) -> None:
    """Where the ground is at the ortho plane, each frame's footprint corners (the report's lon/lat) are within
    one ground pixel of the true camera's rays through the same photo pixels."""
    flight, report, ws = two_strips
    cams = ws.load_cameras()
    adjusted = Camera.from_json(cams["camera"])
    ideal = adjusted.replace(k1=0.0, k2=0.0, k3=0.0, t1=0.0, t2=0.0)
    z0 = ws.load_alignment().ground_z
    to_utm = Transformer.from_crs(4326, flight.epsg, always_xy=True)
    worst = 0.0
    for entry in report["frames_used"]:
        k = entry["index"]
        ring = np.array(entry["footprint"][:4])  # lon/lat of the frame's corners
        east, north = to_utm.transform(ring[:, 0], ring[:, 1])
        mapped = np.column_stack([east, north]) - flight.origin_utm
        w, h = adjusted.width, adjusted.height
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64) - 0.5  # the undistorted frame's edges
        photo_px = adjusted.project(ideal.unproject(corners))  # the photo pixels those corners show
        rays = flight.camera.unproject(photo_px) @ flight.rotations[k]  # R^T ray: world directions
        C = flight.centres[k]
        truth = C[:2] + ((z0 - C[2]) / rays[:, 2])[:, None] * rays[:, :2]
        worst = max(worst, float(np.linalg.norm(mapped - truth, axis=1).max()))
    gsd = report["gsd_m"]
    assert worst < gsd, f"worst footprint corner {worst:.3f} m off, GSD {gsd:.3f} m"


def test_the_orthomosaic_shows_the_ground_at_its_map_position(two_strips) -> None:
    """Both strips in place: where the terrain is at the ortho plane, the mosaic shows the texture of each spot
    (before the check, the second strip was ghosted over the first: 55 levels off; the single-strip bound is 8)."""
    flight, _, ws = two_strips
    diff, pixels = level_ground_colour_error(flight, ws.mosaic_path(), ws.load_alignment().ground_z)
    assert pixels > 2000
    assert diff < 8.0, f"mean colour difference {diff:.1f} levels where the ground is at the ortho plane"
