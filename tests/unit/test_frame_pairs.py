"""Dense stereo between posed frames (``stereo.frame_pairs``) and the surface fused from it
(``sfm.dense_surface``), against a known terrain."""

from __future__ import annotations

import cv2
import numpy as np

from tests.scenes import make_texture
from workers.algorithms.disparity import match_pair
from workers.algorithms.geometry import Camera, rotation_from_vector
from workers.algorithms.sfm import GroundSurface, cell_medians, dense_grid, dense_surface
from workers.algorithms.stereo import (
    disparity_range,
    grey8,
    neighbour_pairs,
    posed_pair,
    remap_pair,
    view_counts,
)

CAMERA = Camera(320, 240, 290.0, 290.0, 159.5, 119.5, k1=-0.05, k2=0.01)
TEXTURE_GSD = 0.08  # m per texture px


def terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (m): a 5 m hill, a 3 m hollow and a slope."""
    return 5.0 * np.exp(-((x - 5) ** 2 + (y - 3) ** 2) / 60.0) - 3.0 * np.exp(-((x + 8) ** 2 + y**2) / 40.0) + 0.02 * x


def nadir(yaw_deg: float, tilt_deg: tuple[float, float], centre: tuple[float, float, float]) -> tuple:
    down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    yaw = rotation_from_vector(np.array([0.0, 0.0, np.radians(yaw_deg)]))
    tilt = rotation_from_vector(np.array([*np.radians(tilt_deg), 0.0]))
    return tilt @ down @ yaw.T, np.array(centre, np.float64)


def render(pose: tuple, texture: np.ndarray) -> np.ndarray:
    """The camera's photo of the textured terrain (rays traced to it by fixed-point iteration on height)."""
    R, C = pose
    u, v = np.meshgrid(np.arange(CAMERA.width, dtype=np.float64), np.arange(CAMERA.height, dtype=np.float64))
    rays = CAMERA.unproject(np.column_stack([u.ravel(), v.ravel()])) @ R
    z = np.zeros(len(rays))
    for _ in range(15):
        t = (z - C[2]) / rays[:, 2]
        xy = C[:2] + t[:, None] * rays[:, :2]
        z = terrain(xy[:, 0], xy[:, 1])
    h, w = texture.shape[:2]
    col = (xy[:, 0] / TEXTURE_GSD + (w - 1) / 2).reshape(u.shape).astype(np.float32)
    row = (-xy[:, 1] / TEXTURE_GSD + (h - 1) / 2).reshape(u.shape).astype(np.float32)
    return cv2.remap(texture, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


# The second frame follows the first along the photos' columns (a drone flying with the photo's top ahead):
# a calibrated rectification of the usual kind (cv2.stereoRectify) would rectify this pair along columns.
LEFT = nadir(3.0, (2.0, -1.5), (0.0, -7.0, 50.0))
RIGHT = nadir(-4.0, (-1.0, 2.5), (1.0, 8.0, 51.0))


def test_rectified_rows_agree_and_disparities_triangulate_back_exactly() -> None:
    pair = posed_pair(CAMERA, LEFT, RIGHT, 0.0, 200.0)
    assert pair is not None and 100 < pair.width < 500 and 100 < pair.height < 500
    rng = np.random.default_rng(1)
    xy = rng.uniform(-12, 12, (500, 2))
    points = np.column_stack([xy, terrain(xy[:, 0], xy[:, 1])])
    left_px, right_px, front = pair.project(points)
    assert front.all()
    np.testing.assert_allclose(left_px[:, 1], right_px[:, 1], atol=1e-9)  # the same row in both views
    back = pair.triangulate(left_px[:, 0], left_px[:, 1], left_px[:, 0] - right_px[:, 0])
    np.testing.assert_allclose(back, points, atol=1e-7)
    # the maps, traced at nodes and interpolated, send a view's pixel where the photo sees its ray
    maps = pair.maps(CAMERA, LEFT[0], "left")
    inside = (left_px[:, 0] >= 0) & (left_px[:, 0] < pair.width - 1) & (left_px[:, 1] >= 0)
    inside &= left_px[:, 1] < pair.height - 1
    cols, rows = np.rint(left_px[inside]).astype(int).T  # at whole view pixels: read the maps directly
    exact = pair.triangulate(cols.astype(float), rows.astype(float), (left_px - right_px)[inside, 0])
    expected = CAMERA.project((exact - LEFT[1]) @ LEFT[0].T)
    error = np.hypot(maps[0][rows, cols] - expected[:, 0], maps[1][rows, cols] - expected[:, 1])
    assert inside.sum() > 100 and error.max() < 0.02, error.max()  # a fiftieth of a pixel


def test_a_rendered_pair_gives_the_terrain_heights() -> None:
    """Rendered photos, rectified, matched by SGBM and triangulated: heights within a third of the photos'
    ground pixel (0.17 m) of the terrain (measured: bias 0.019 m, median error 0.057 m, 84 % of the view)."""
    texture = make_texture(600, 600, seed=4)
    photos = [grey8(render(pose, texture)) for pose in (LEFT, RIGHT)]
    pair = posed_pair(CAMERA, LEFT, RIGHT, 0.0, CAMERA.fx)
    assert pair is not None
    maps = (*pair.maps(CAMERA, LEFT[0], "left"), *pair.maps(CAMERA, RIGHT[0], "right"))
    left, right, valid_l, valid_r = remap_pair(maps, photos[0], photos[1])
    xy = np.random.default_rng(2).uniform(-15, 15, (2000, 2))
    left_px, right_px, _ = pair.project(np.column_stack([xy, terrain(xy[:, 0], xy[:, 1])]))
    span = disparity_range(left_px, right_px)
    assert span is not None
    result = match_pair(left, right, "sgbm", *span, valid_left=valid_l, valid_right=valid_r, fill=False)
    rows, cols = np.nonzero(np.isfinite(result.disparity))
    points = pair.triangulate(cols, rows, result.disparity[rows, cols])
    error = points[:, 2] - terrain(points[:, 0], points[:, 1])
    assert len(points) > 0.7 * valid_l.sum()
    assert abs(np.median(error)) < 0.05 and np.median(np.abs(error)) < 0.09, (np.median(error), np.abs(error))
    assert np.mean(np.abs(error) > 1.0) < 0.01  # few mismatches


def test_neighbour_pairs_take_overlapping_frames_with_a_baseline() -> None:
    poses = {
        0: nadir(0, (0, 0), (0.0, 0.0, 50.0)),
        1: nadir(0, (0, 0), (15.0, 0.0, 50.0)),
        2: nadir(0, (0, 0), (30.0, 0.0, 50.0)),
        3: nadir(0, (0, 0), (30.5, 0.0, 50.0)),  # a near duplicate of 2: no baseline
        4: nadir(0, (0, 0), (300.0, 0.0, 50.0)),  # far away: no overlap
    }
    pairs = neighbour_pairs(CAMERA, poses, 0.0)
    assert (2, 3) not in pairs and not any(4 in p for p in pairs)
    assert {(0, 1), (1, 2), (1, 3)} <= set(pairs)
    counts = view_counts(CAMERA, poses, np.array([[7.5, 0.0, 0.0], [-20.0, 0.0, 0.0], [-100.0, 0.0, 0.0]]))
    assert counts.tolist() == [4, 1, 0]


def test_dense_surface_fuses_pairs_rejects_mismatches_and_fills_from_the_base() -> None:
    rng = np.random.default_rng(5)
    base = GroundSurface(np.full((11, 11), 0.5), -25.0, -25.0, 5.0)  # a flat tie-point surface, 0.5 m up
    grid = dense_grid(base, np.array([[-10.0, -11.0], [10.0, 10.0]]), 0.5)
    assert (grid.x0, grid.y0, grid.cell, grid.rows, grid.cols) == (-27.5, -27.5, 0.5, 111, 111)
    parts = []
    for pair in range(3):  # three pairs over the same ground; the third one's matches are mostly wrong
        xy = rng.uniform(-10, 10, (30_000, 2))
        z = terrain(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.05, len(xy))
        wrong = rng.random(len(xy)) < (0.1 if pair < 2 else 0.6)
        z[wrong] += rng.choice([-8.0, 8.0], wrong.sum())
        parts.append(cell_medians(np.column_stack([xy, z]), grid))
    parts.append(cell_medians(np.array([[0.0, -10.5, 30.0]] * 4 + [[99.0, 0.0, 0.0]] * 4), grid))  # runaway, off
    cells, heights = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    surface, measured = dense_surface(cells, heights, base, grid)
    assert surface.cell == 0.5 and measured.shape == surface.heights.shape == (111, 111)
    gx, gy = np.meshgrid(np.linspace(-9, 9, 50), np.linspace(-9, 9, 50))
    error = surface.height_at(gx, gy) - terrain(gx, gy)
    assert np.sqrt(np.mean(error**2)) < 0.08, np.sqrt(np.mean(error**2))
    assert surface.height_at(np.array([0.0]), np.array([-10.5]))[0] < 2.0  # the runaway cell was dropped
    assert abs(surface.height_at(np.array([-24.0]), np.array([20.0]))[0] - 0.5) < 1e-6  # far: the base
    assert 0.1 < measured.mean() < 0.16  # the points' 20 m square in the base's 55 m one
