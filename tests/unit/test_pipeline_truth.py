"""The whole mosaic pipeline on synthetic flights with known homographies and georeference."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from tests.scenes import SyntheticFlight, make_flight
from workers.algorithms.geometry import fit_similarity
from workers.algorithms.mosaic import apply_homography
from workers.pipeline import process_directory
from workers.workspace import JobWorkspace


def frame_corners_cv(flight: SyntheticFlight) -> np.ndarray:
    w, h = flight.frame_size
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], float) - 0.5


@pytest.fixture(scope="module")
def tilted(tmp_path_factory: pytest.TempPathFactory) -> tuple[SyntheticFlight, dict, JobWorkspace]:
    """Two flight lines, rotated, rescaled, mildly tilted frames, no GPS: exhaustive matching."""
    root = tmp_path_factory.mktemp("tilted")
    flight = make_flight(
        root / "frames",
        n_frames=10,
        layout="grid",
        rotation_deg=12,
        scale_jitter=0.08,
        perspective=0.03,
        gps=False,
        seed=11,
    )
    report = process_directory(root / "frames", root / "job", {"working_max_px": 1024})
    return flight, report, JobWorkspace(root / "job")


def test_frame_corners_within_one_pixel_of_truth(tilted) -> None:
    flight, report, ws = tilted
    assert len(ws.load_alignment().homographies) == 10 and not report["frames_rejected"]
    errors = corner_errors(flight, ws)
    assert errors.max() < 1.0, f"worst corner {errors.max():.3f} px"


def test_tie_point_rms_under_half_a_pixel(tilted) -> None:
    _, report, _ = tilted
    assert report["tie_point_rms_px"] < 0.5
    assert report["georeferenced"] is False and "GPS" in report["georeference_note"]
    used = [p for p in report["pairs"] if p["used"]]
    assert len(used) >= 9 and all(p["inliers"] >= 25 and p["tie_point_rms_px"] < 0.5 for p in used)
    assert all(p["reason_unused"] for p in report["pairs"] if not p["used"])


def test_outputs_are_valid_cogs(tilted, nadir) -> None:
    from rio_cogeo.cogeo import cog_validate

    for _, _, ws in (tilted, nadir):
        valid, errors, _warnings = cog_validate(str(ws.mosaic_path()), quiet=True)
        assert valid, errors


def test_mosaic_without_gps_is_a_pixel_raster(tilted) -> None:
    _, report, ws = tilted
    with rasterio.open(ws.mosaic_path()) as src:
        assert src.crs is None
        assert (src.width, src.height) == (report["mosaic"]["width"], report["mosaic"]["height"])
        assert src.overviews(1)
    assert "footprints.geojson" not in ws.outputs()  # no map coordinates to draw footprints in


@pytest.fixture(scope="module")
def nadir(tmp_path_factory: pytest.TempPathFactory) -> tuple[SyntheticFlight, dict, JobWorkspace]:
    root = tmp_path_factory.mktemp("nadir")
    flight = make_flight(root / "frames", n_frames=8, rotation_deg=10, scale_jitter=0.05, gps=True, seed=4)
    report = process_directory(root / "frames", root / "job", {"working_max_px": 1024})
    return flight, report, JobWorkspace(root / "job")


def test_gps_flight_is_placed_within_one_gsd(nadir) -> None:
    flight, report, ws = nadir
    assert report["georeferenced"] and report["crs"] == f"EPSG:{flight.epsg}"
    geo, align = ws.load_georef(), ws.load_alignment()
    plane_to_map = geo.plane_to_map
    errors = []
    for k, H in align.homographies.items():
        corners = frame_corners_cv(flight)
        predicted = apply_homography(plane_to_map @ np.array(H), corners)
        truth = apply_homography(flight.texture_to_utm @ flight.homographies[int(k)], corners)
        errors.append(np.linalg.norm(predicted - truth, axis=1))
    worst = float(np.max(errors))
    assert worst < flight.gsd_m, f"worst corner {worst:.4f} m, GSD {flight.gsd_m} m"
    ref = flight.homographies[align.reference]  # the plane has the reference frame's scale
    assert abs(report["gsd_m"] - flight.gsd_m * np.sqrt(abs(np.linalg.det(ref[:2, :2])))) < 0.01 * flight.gsd_m


def test_cog_pixels_show_the_ground_at_their_map_position(nadir) -> None:
    """Every mosaic pixel, taken to the texture through its map coordinates, shows the same colour."""
    flight, _, ws = nadir
    diff = ground_colour_error(flight, ws.mosaic_path())
    assert diff < 10.0, f"mean colour difference {diff:.1f} levels: mosaic misplaced or blurred"


def ground_colour_error(flight: SyntheticFlight, path: Path) -> float:
    """Mean |mosaic - texture| colour, levels, over the mosaic's inner pixels, each taken to the texture
    through its map coordinates."""
    with rasterio.open(path) as src:
        rgb = np.moveaxis(src.read(), 0, 2).astype(np.float32)
        mask = src.dataset_mask() > 0
        rows, cols = np.mgrid[0 : src.height, 0 : src.width]
        east, north = rasterio.transform.xy(src.transform, rows.ravel(), cols.ravel())
    en = np.column_stack([east, north, np.ones(len(east))])
    tex = en @ np.linalg.inv(flight.texture_to_utm).T
    mx = tex[:, 0].reshape(rows.shape).astype(np.float32)
    my = tex[:, 1].reshape(rows.shape).astype(np.float32)
    expected = cv2.remap(flight.texture, mx, my, cv2.INTER_LINEAR)[..., ::-1].astype(np.float32)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert inner.mean() > 0.3
    return float(np.abs(rgb - expected)[inner].mean())


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> tuple[SyntheticFlight, dict, dict, JobWorkspace]:
    """One GPS flight composed twice from half-size working copies: at their resolution and the photos'."""
    root = tmp_path_factory.mktemp("native")
    flight = make_flight(root / "frames", n_frames=6, rotation_deg=10, scale_jitter=0.05, gps=True, seed=4)
    half = {"working_max_px": max(flight.frame_size) // 2}
    working = process_directory(root / "frames", root / "working", half)
    native = process_directory(root / "frames", root / "native", {**half, "output_resolution": "native"})
    return flight, working, native, JobWorkspace(root / "native")


def test_native_output_has_the_photos_resolution(native) -> None:
    flight, working, report, ws = native
    assert report["mosaic"]["resolution"] == "native" and working["mosaic"]["resolution"] == "working"
    assert report["mosaic"]["photo_px_per_px"] == pytest.approx(1.0, rel=1e-3)
    assert working["mosaic"]["photo_px_per_px"] == pytest.approx(2.0, rel=1e-3)
    assert report["gsd_m"] == pytest.approx(working["gsd_m"] / 2, rel=1e-3)
    assert report["gsd_original_m"] == pytest.approx(working["gsd_original_m"], rel=1e-3)
    for side in ("width", "height"):
        assert abs(report["mosaic"][side] - 2 * working["mosaic"][side]) <= 1
    with rasterio.open(ws.mosaic_path()) as src:
        assert (src.width, src.height) == (report["mosaic"]["width"], report["mosaic"]["height"])
        assert src.res[0] == pytest.approx(report["gsd_m"], rel=1e-6)
    assert not (ws.root / "native").exists()  # the full decodes are scratch


def test_native_output_holds_detail_the_working_copies_lost(native) -> None:
    """Placed as exactly, and closer to the ground texture than the working-resolution mosaic is: the
    photos' own pixels, not the working copies' upsampled."""
    flight, working, _, ws = native
    fine = ground_colour_error(flight, ws.mosaic_path())
    coarse = ground_colour_error(flight, ws.root.parent / "working" / "mosaic.tif")
    assert fine < 10.0 and fine < 0.8 * coarse, (fine, coarse)


def test_report_lists_what_a_user_needs(nadir) -> None:
    flight, report, ws = nadir
    on_disk = ws.load_report()
    assert on_disk == json.loads(json.dumps(report))
    assert len(report["frames_used"]) == 8 and report["frames_rejected"] == []
    assert set(report["stage_seconds"]) >= {
        "load_images",
        "detect_features",
        "match_features",
        "align_frames",
        "georeference",
        "compose_mosaic",
    }
    footprint = report["mosaic"]["footprint"]
    assert footprint["type"] == "MultiPolygon" and footprint["coordinates"]
    lon, lat = np.array(footprint["coordinates"][0][0]).T
    for glat, glon, _ in flight.gps:
        assert lon.min() < glon < lon.max() and lat.min() < glat < lat.max()
    features = ws.load_footprints()["features"]
    assert [f["properties"]["name"] for f in features] == [p.name for p in flight.paths]


def corner_errors(flight: SyntheticFlight, ws: JobWorkspace) -> np.ndarray:
    """Every frame corner's distance to its truth on the ground, after removing the global similarity, px.

    The mosaic plane is levelled (``level_plane``): the ground itself when the frames' tilts average out, as
    the scenes' do, not the reference frame's tilted plane."""
    homs = ws.load_alignment().homographies
    corners = frame_corners_cv(flight)
    predicted = np.concatenate([apply_homography(homs[k], corners) for k in sorted(homs)])
    truth = np.concatenate([apply_homography(flight.homographies[k], corners) for k in sorted(homs)])
    S = fit_similarity(predicted, truth)
    return np.linalg.norm(apply_homography(S, predicted) - truth, axis=1)


def test_harris_ncc_aligns_an_aerial_strip(tmp_path: Path) -> None:
    """Frames that keep their orientation and scale (a multi-lens aerial strip): Harris + NCC."""
    flight = make_flight(tmp_path / "frames", n_frames=6, rotation_deg=1.5, scale_jitter=0.02, gps=True, seed=21)
    report = process_directory(
        tmp_path / "frames", tmp_path / "job", {"working_max_px": 1024, "feature_type": "harris_ncc"}
    )
    ws = JobWorkspace(tmp_path / "job")
    assert ws.load_stage_report("detect_features")["detector"] == "gpu_kernels-harris_ncc"
    assert len(report["frames_used"]) == 6 and report["georeferenced"]
    assert corner_errors(flight, ws).max() < 1.0
    assert report["tie_point_rms_px"] < 0.8  # integer-pixel corners: about 0.4 px per point and axis


@pytest.mark.gpu
def test_gpu_sift_pipeline_matches_the_truth(tmp_path: Path) -> None:
    from gpu_kernels.backend import cuda_available

    if not cuda_available():
        pytest.skip("needs CuPy and a CUDA device")
    flight = make_flight(
        tmp_path / "frames", n_frames=8, layout="grid", rotation_deg=12, perspective=0.02, gps=False, seed=11
    )
    report = process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 1024, "device": "cuda"})
    ws = JobWorkspace(tmp_path / "job")
    assert ws.load_stage_report("detect_features")["device"] == "cuda"
    assert corner_errors(flight, ws).max() < 1.0 and report["tie_point_rms_px"] < 0.5


def test_registration_at_half_size_keeps_the_truth_bounds(tmp_path: Path) -> None:
    """Features found on half-size registration copies, tie points refined on the working copies: the
    alignment meets the same bounds as registration at full size, in working pixels."""
    flight = make_flight(
        tmp_path / "frames", n_frames=6, frame_size=(1280, 960), rotation_deg=8, perspective=0.02, gps=True, seed=5
    )
    options = {"working_max_px": 1280, "registration_max_px": 640}
    report = process_directory(tmp_path / "frames", tmp_path / "job", options)
    ws = JobWorkspace(tmp_path / "job")
    assert len(report["frames_used"]) == 6 and not report["frames_rejected"]
    points = np.concatenate([ws.load_features(k)[0] for k in range(6)])
    assert points[:, 0].max() > 1000  # keypoints come back in working pixels, not the 640 px copy's
    assert corner_errors(flight, ws).max() < 1.0
    assert report["tie_point_rms_px"] < 0.5
