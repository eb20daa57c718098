"""The stereo domain's pieces against planted truth: RPC models (against GDAL's own RPC transformer),
affine rectification of an RPC pair, triangulation through RPCs, DSM gridding with its measured and filled
cells, Hartley's projective rectification, the disparity range from matches, and the relief rendering."""

from __future__ import annotations

import numpy as np
import pytest
from rasterio.rpc import RPC
from rasterio.transform import RPCTransformer

from workers.algorithms.stereo import (
    FILLED,
    MEASURED,
    NO_DATA,
    TERRAIN,
    Rpc,
    colour_ramp,
    disparity_range,
    fit_rpc,
    grid_dsm,
    ground_sample_distance,
    hillshade,
    legend,
    rectified_disparities,
    rpc_correspondences,
    rpc_rectification,
    triangulate_rpc,
    uncalibrated_rectification,
)
from workers.algorithms.stereo.rectification import _apply, _local_jacobian

LON0, LAT0 = 8.55, 47.37


def affine_view(tilt: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """A near-parallel projection seen ``tilt`` (m of image shift per m of height) along track, turned by
    ``yaw`` radians, with a faint perspective: pixel = f(lon, lat, h)."""

    def project(lon: np.ndarray, lat: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        east = (lon - LON0) * 75_300.0
        north = (lat - LAT0) * 111_200.0 + tilt * (h - 430.0)
        x = np.cos(yaw) * east + np.sin(yaw) * north
        y = -np.sin(yaw) * east + np.cos(yaw) * north
        w = 1.0 + 2e-6 * x
        return x / w + 150.0, -y / w + 140.0

    return project  # type: ignore[return-value]


def fitted(project) -> Rpc:  # type: ignore[no-untyped-def]
    lon, lat, h = np.meshgrid(
        LON0 + np.linspace(-0.003, 0.003, 15), LAT0 + np.linspace(-0.002, 0.002, 15), np.linspace(380, 480, 5)
    )
    col, row = project(lon.ravel(), lat.ravel(), h.ravel())
    return fit_rpc(lon.ravel(), lat.ravel(), h.ravel(), col, row)


LEFT, RIGHT = affine_view(0.27, 0.07), affine_view(-0.27, -0.12)
RPC_L, RPC_R = fitted(LEFT), fitted(RIGHT)


def test_rpc_fit_projection_and_localisation_are_exact() -> None:
    rng = np.random.default_rng(0)
    lon, lat = LON0 + rng.uniform(-0.003, 0.003, 500), LAT0 + rng.uniform(-0.002, 0.002, 500)
    h = rng.uniform(380, 480, 500)
    col, row = RPC_L.project(lon, lat, h)
    true_col, true_row = LEFT(lon, lat, h)
    assert np.abs(col - true_col).max() < 1e-6 and np.abs(row - true_row).max() < 1e-6
    back_lon, back_lat = RPC_L.localize(col, row, h)
    assert np.abs(back_lon - lon).max() < 1e-11 and np.abs(back_lat - lat).max() < 1e-11
    assert RPC_L.height_range == (380.0, 480.0)
    assert ground_sample_distance(RPC_L, 150.0, 140.0, 430.0) == pytest.approx(1.0, rel=0.01)


def test_rpc_agrees_with_gdal_half_a_pixel_apart() -> None:
    """GDAL's RPC transformer (rasterio) answers with (0, 0) at the first pixel's corner, we at its centre."""
    lon, lat, h = (
        LON0 + np.array([-0.002, 0.0, 0.0025]),
        LAT0 + np.array([0.001, 0.0, -0.0015]),
        np.array([390.0, 430, 470]),
    )
    with RPCTransformer(RPC(**RPC_L.to_json())) as gdal:
        rows, cols = gdal.rowcol(lon, lat, zs=h, op=lambda v: v)
    col, row = RPC_L.project(lon, lat, h)
    assert np.allclose(np.asarray(cols) - 0.5, col, atol=1e-6) and np.allclose(np.asarray(rows) - 0.5, row, atol=1e-6)
    assert Rpc.from_dict(RPC(**RPC_L.to_json()).to_dict()).to_json() == RPC_L.to_json()


def test_rpc_metadata_is_refused_with_its_fault() -> None:
    data = RPC_L.to_json()
    with pytest.raises(ValueError, match="lacks line_off"):
        Rpc.from_dict({k: v for k, v in data.items() if k != "line_off"})
    with pytest.raises(ValueError, match="samp_scale must be a finite non-zero"):
        Rpc.from_dict({**data, "samp_scale": 0.0})
    with pytest.raises(ValueError, match="20 finite numbers"):
        Rpc.from_dict({**data, "line_num_coeff": [1.0] * 19})


def test_affine_rectification_puts_matches_on_rows_and_triangulates_exactly() -> None:
    size = (300, 280)
    corr = rpc_correspondences(RPC_L, RPC_R, size, (380.0, 480.0))
    rect = rpc_rectification(corr, size)
    assert rect.residual_px < 0.05  # the faint perspective is all the affine model leaves
    x, y, d = rectified_disparities(corr, rect)
    assert np.abs(d[corr.reference]).max() < 0.05  # the middle height has zero disparity
    assert abs(np.corrcoef(d, corr.height)[0, 1]) > 0.999  # disparity is height
    # ground points that are not correspondences: their rectified match, then back to the ground
    rng = np.random.default_rng(1)
    lon, lat = LON0 + rng.uniform(-0.0015, 0.0015, 300), LAT0 + rng.uniform(-0.001, 0.001, 300)
    h = rng.uniform(400, 460, 300)
    xl, yl = _apply(rect.left, *RPC_L.project(lon, lat, h))
    xr, yr = _apply(rect.right, *RPC_R.project(lon, lat, h))
    assert np.abs(yl - yr).max() < 0.05
    got_lon, got_lat, got_h, residual = triangulate_rpc(RPC_L, RPC_R, corr, rect, xl, yl, xl - xr)
    metres = np.hypot((got_lon - lon) * 75_300, (got_lat - lat) * 111_200)
    assert metres.max() < 0.01 and np.abs(got_h - h).max() < 0.02 and residual.max() < 0.05


def test_grid_dsm_measures_fills_and_flags() -> None:
    """A tilted plane sampled at one point per 0.7 m with a 10 m hole; filled points on one corner."""
    rng = np.random.default_rng(2)
    e, n = rng.uniform(500_000, 500_060, 8000), rng.uniform(5_000_000, 5_000_060, 8000)
    hole = np.hypot(e - 500_030, n - 5_000_030) < 5
    h = 100.0 + 0.2 * (e - 500_000) - 0.1 * (n - 5_000_000)
    measured = ~((e > 500_050) & (n > 5_000_050))
    dsm = grid_dsm(e[~hole], n[~hole], h[~hole], measured[~hole], 1.0, 32632)
    east, north = dsm.centres()
    truth = 100.0 + 0.2 * (east - 500_000) - 0.1 * (north - 5_000_000)
    assert dsm.transform[0] == 1.0 and dsm.transform[4] == -1.0 and dsm.transform[2] % 1.0 == 0.0
    error = dsm.height - truth
    interior = np.zeros(error.shape, bool)
    interior[2:-2, 2:-2] = True
    # a cell is the weighted mean of the two or so random points near it: off by the slope times their mean
    # offset from its centre (0.2 x a few decimetres), without bias; more at the edge, where they lie on one side
    assert abs(np.nanmean(error[interior])) < 0.005 and np.nanmax(np.abs(error[interior])) < 0.2
    assert np.nanmax(np.abs(error)) < 0.3
    inner_hole = np.hypot(east - 500_030, north - 5_000_030) < 3.5
    assert (dsm.state[inner_hole] == FILLED).all()  # the hole: no point reached it, filled linearly
    assert np.abs(error[inner_hole]).max() < 0.15  # no worse than the cells around it
    corner = (east > 500_052) & (north > 5_000_052) & (east < 500_059) & (north < 5_000_059)
    assert (dsm.state[corner] == FILLED).all()  # reached by filled points only
    assert (dsm.state == MEASURED).mean() > 0.85
    bare = grid_dsm(e[~hole], n[~hole], h[~hole], measured[~hole], 1.0, 32632, fill=False)
    assert (bare.state[inner_hole] == NO_DATA).all() and np.isnan(bare.height[inner_hole]).all()


def test_grid_dsm_never_fills_beyond_the_footprint() -> None:
    """Points on an L: the empty square beside it is outside their convex hull only in part; nothing farther
    than ``max_fill_cells`` from a height is invented."""
    e, n = np.meshgrid(np.arange(0, 40, 0.5), np.arange(0, 40, 0.5))
    keep = (e < 10) | (n < 10)
    dsm = grid_dsm(
        e[keep] + 500_000,
        n[keep] + 5_000_000,
        np.full(keep.sum(), 50.0),
        np.ones(keep.sum(), bool),
        1.0,
        32632,
        max_fill_cells=5,
    )
    east, north = dsm.centres()
    far = (east - 500_000 > 20) & (north - 5_000_000 > 20)
    assert (dsm.state[far] == NO_DATA).all() and (dsm.state[~far & np.isfinite(dsm.height)] != NO_DATA).all()


def test_hartley_rectification_aligns_rows_of_a_turned_pair() -> None:
    """Points of a scene seen by two perspective cameras, the second turned and moved: after rectification
    from the true F, their rows agree exactly and nothing is mirrored."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(6, 12, 200)])
    k = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    angle = np.radians([2.0, -4.0, 3.0])
    from workers.algorithms.geometry import rotation_from_vector

    r, t = rotation_from_vector(angle), np.array([-0.6, 0.05, 0.1])
    left = (points @ k.T)[:, :2] / points[:, 2:3]
    cam_r = points @ r.T + t
    right = (cam_r @ k.T)[:, :2] / cam_r[:, 2:3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    f = np.linalg.inv(k).T @ tx @ r @ np.linalg.inv(k)
    rect = uncalibrated_rectification(f / np.linalg.norm(f), left, right, (640, 480))
    assert rect.residual_px < 1e-6
    xl, _ = _apply(rect.left, left[:, 0], left[:, 1])
    xr, _ = _apply(rect.right, right[:, 0], right[:, 1])
    centre = np.array([319.5, 239.5])
    for h in (rect.left, rect.right):  # neither photo mirrored nor turned upside down
        jacobian = _local_jacobian(h, centre)
        assert np.linalg.det(jacobian) > 0 and jacobian[0, 0] > 0 and jacobian[1, 1] > 0
    assert rect.width * rect.height < 2.0 * 640 * 480


def test_disparity_range_covers_the_matches() -> None:
    rng = np.random.default_rng(4)
    left = rng.uniform(0, 300, (200, 2))
    d = rng.uniform(5, 40, 200)
    right = left - np.column_stack([d, rng.normal(0, 0.3, 200)])
    right[:5, 1] += 30  # wrong matches, off their rows
    low, count = disparity_range(left, right)
    assert low <= 5 and low + count >= 40 and count % 16 == 0 and count <= 80
    assert disparity_range(left[:5], right[:5]) is None


def test_relief_is_ramped_and_shaded() -> None:
    y, x = np.mgrid[0:64, 0:64].astype(np.float64)
    cone = 100.0 - np.hypot(x - 32, y - 32)  # a cone: each side faces its own way
    shade = hillshade(cone, 1.0)
    assert shade[20, 20] > shade[44, 44]  # the north-west side faces the light
    assert abs(float(hillshade(np.zeros((8, 8)), 1.0)[4, 4]) - np.cos(np.radians(45))) < 1e-6
    rgb = colour_ramp(np.array([[0.0, 50.0, 100.0, np.nan]]), 0.0, 100.0, TERRAIN)
    assert rgb[0, 0].tolist() == list(TERRAIN[0][1]) and rgb[0, 2].tolist() == list(TERRAIN[-1][1])
    stops = legend(10.0, 20.0, TERRAIN)
    assert [s["value"] for s in stops][0] == 10.0 and stops[-1]["value"] == 20.0 and stops[0]["colour"] == "#2c7b52"
