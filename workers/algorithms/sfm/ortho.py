"""Orthorectification geometry of a posed camera over a ground plane ``Z = z0``: the part of its frame that
sees the ground nearby (frames that see the horizon are cut below it, since ground far away is smeared
over a huge area by the projection)."""

from __future__ import annotations

import numpy as np

from workers.algorithms.geometry import Camera

MIN_KEPT_ROWS = 0.1  # a frame cut to less than this share of its rows (or columns) is left out


def ground_crop(
    R: np.ndarray, C: np.ndarray, z0: float, camera: Camera, max_range: float
) -> tuple[int, int, int, int] | None:
    """The part of the frame, ``(x0, y0, x1, y1)`` px (end exclusive), that sees the ground nearby.

    A pixel qualifies if its ray meets the plane ``z0`` in front of the camera within ``max_range``
    flying heights of the nadir point. That region of the plane is a disk, so its image is convex and
    a rectangle whose four corners qualify lies wholly inside it. The whole frame when it qualifies;
    else the frame with one edge moved in as little as needed; None when less than
    ``MIN_KEPT_ROWS`` of the frame would remain.
    """
    height = C[2] - z0
    to_world = R.T @ np.linalg.inv(camera.matrix())  # pixel -> ray direction in the world

    def corners_ok(x0: float, y0: float, x1: float, y1: float) -> bool:
        px = np.array([[x0, y0, 1], [x1 - 1, y0, 1], [x1 - 1, y1 - 1, 1], [x0, y1 - 1, 1]], float)
        rays = px @ to_world.T
        if np.any(rays[:, 2] >= -1e-9):  # level or upwards: never meets the ground in front
            return False
        reach = height / -rays[:, 2]  # ray length to the plane
        return bool(np.all(np.linalg.norm(rays[:, :2] * reach[:, None], axis=1) <= max_range * height))

    w, h = camera.width, camera.height
    if corners_ok(0, 0, w, h):
        return 0, 0, w, h
    best: tuple[int, int, int, int] | None = None
    for edge in range(4):  # move the top, bottom, left or right edge inwards
        size = h if edge < 2 else w
        lo, hi = 0, int(size * (1 - MIN_KEPT_ROWS))
        if not corners_ok(*_moved(edge, hi, w, h)):
            continue
        while hi - lo > 1:  # smallest move that qualifies
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if corners_ok(*_moved(edge, mid, w, h)) else (mid, hi)
        crop = _moved(edge, hi, w, h)
        if best is None or _area(crop) > _area(best):
            best = crop
    return best


def _moved(edge: int, by: int, w: int, h: int) -> tuple[int, int, int, int]:
    return [(0, by, w, h), (0, 0, w, h - by), (by, 0, w, h), (0, 0, w - by, h)][edge]


def _area(crop: tuple[int, int, int, int]) -> int:
    return (crop[2] - crop[0]) * (crop[3] - crop[1])
