"""``sfm.relief_maps``: a frame rendered as if its ground were a plane, sampling the surface's points where the
photo sees them, and the plane's where it does not (its border repeated had streaked an ortho mosaic's edge)."""

from __future__ import annotations

import numpy as np

from workers.algorithms.geometry import Camera
from workers.algorithms.sfm import GroundSurface, relief_maps

WIDTH, HEIGHT, FOCAL = 400, 300, 300.0
NADIR = np.diag([1.0, -1.0, -1.0])  # camera x east, y south, z down
CENTRE = np.array([0.0, 0.0, 100.0])  # 100 m above the plane z = 0


def _maps(height_m: float) -> tuple[np.ndarray, np.ndarray]:
    camera = Camera(WIDTH, HEIGHT, FOCAL, FOCAL, (WIDTH - 1) / 2, (HEIGHT - 1) / 2)
    canopy = GroundSurface(np.full((3, 3), height_m), -200.0, -200.0, 200.0)  # a flat top, everywhere
    return relief_maps(NADIR, CENTRE, camera, 0.0, (0, 0, WIDTH, HEIGHT), canopy)


def test_the_surface_is_sampled_where_the_photo_sees_it_and_the_plane_elsewhere() -> None:
    map_x, map_y = _maps(30.0)
    cx = (WIDTH - 1) / 2
    # a plane point's ray meets z = 0 at X = (u - cx) / f * 100 m; the canopy above it, 70 m below the camera,
    # is seen at cx + (u - cx) * 100 / 70: the inner 70 % of the frame's half-width sees it inside the photo
    u = np.arange(WIDTH, dtype=np.float64)
    raised = cx + (u - cx) * 100.0 / 70.0
    inside = (raised >= 0) & (raised <= WIDTH - 1)
    row = map_x[HEIGHT // 2]
    np.testing.assert_allclose(row[inside], raised[inside], atol=1e-3)
    np.testing.assert_allclose(row[~inside], u[~inside], atol=1e-3)  # the plane's own projection there
    assert inside.sum() < 0.75 * WIDTH and (~inside).sum() > 0.2 * WIDTH
    # nowhere outside the photo: no pixel repeats its border
    assert map_x.min() >= 0 and map_x.max() <= WIDTH - 1 and map_y.min() >= 0 and map_y.max() <= HEIGHT - 1


def test_ground_at_the_plane_is_the_plane() -> None:
    map_x, map_y = _maps(0.0)
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float32), np.arange(HEIGHT, dtype=np.float32))
    np.testing.assert_allclose(map_x, u, atol=1e-3)
    np.testing.assert_allclose(map_y, v, atol=1e-3)
