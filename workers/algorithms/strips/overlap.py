"""Where two strip frames overlap, predicted by a homography, and how far tie points spread along it."""

from __future__ import annotations

import cv2
import numpy as np

from workers.algorithms.mosaic.alignment import apply_homography


def frame_outline(size: tuple[int, int]) -> np.ndarray:
    """``(4, 2) float64`` outer corners of a ``(width, height)`` frame, pixel edges (-0.5 .. side - 0.5)."""
    w, h = size
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])


def long_axis(size: tuple[int, int]) -> int:
    """0 (x) when the frame is wider than tall, else 1 (y): the strip's long axis in frame px."""
    return 0 if size[0] >= size[1] else 1


def overlap_polygon(H_ab: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]) -> np.ndarray:
    """``(K, 2) float64`` convex polygon, frame ``a`` px, of the part of ``a`` that ``H_ab`` maps into ``b``;
    ``(0, 2)`` when they do not overlap (``cv2.intersectConvexConvex``)."""
    outline_b = apply_homography(np.linalg.inv(H_ab), frame_outline(size_b))
    area, poly = cv2.intersectConvexConvex(
        frame_outline(size_a).astype(np.float32), outline_b.astype(np.float32), handleNested=True
    )
    if poly is None or area <= 0:
        return np.zeros((0, 2))
    return poly.reshape(-1, 2).astype(np.float64)


def overlap_box(
    H_ab: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]
) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)`` frame ``a`` px bounding the predicted overlap; all zeros when there is none."""
    poly = overlap_polygon(H_ab, size_a, size_b)
    if len(poly) == 0:
        return (0.0, 0.0, 0.0, 0.0)
    (x0, y0), (x1, y1) = poly.min(axis=0), poly.max(axis=0)
    return (float(x0), float(y0), float(x1), float(y1))


def spread_along(
    H_ab: np.ndarray, points_a: np.ndarray, points_b: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]
) -> tuple[float, tuple[float, float], tuple[float, float]]:
    """The spread criterion's measure: how much of the overlap's long side the tie points span.

    Parameters
    ----------
    H_ab : (3, 3) frame a px -> frame b px.
    points_a, points_b : (N, 2) float, pixel (x, y), matched rows.

    Returns
    -------
    spread : min over both frames of (points' extent) / (overlap's extent), along each frame's long axis;
        0 with fewer than 2 points or no overlap.
    extent_px : the points' extent in a and in b, px.
    overlap_px : the overlap's extent in a and in b, px.
    """
    ratios, extents, overlaps = [], [], []
    H_ba = np.linalg.inv(H_ab)
    for H, pts, size, other in ((H_ab, points_a, size_a, size_b), (H_ba, points_b, size_b, size_a)):
        axis = long_axis(size)
        poly = overlap_polygon(H, size, other)
        side = float(np.ptp(poly[:, axis])) if len(poly) else 0.0
        extent = float(np.ptp(pts[:, axis])) if len(pts) >= 2 else 0.0
        extents.append(extent)
        overlaps.append(side)
        ratios.append(extent / side if side > 0 else 0.0)
    return min(ratios), (extents[0], extents[1]), (overlaps[0], overlaps[1])
