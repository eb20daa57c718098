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


def along_strip(
    pairs: list[tuple[int, int]],
    positions: np.ndarray,
    size: tuple[int, int],
    reference: tuple[int, int],
    H_ref: np.ndarray,
    same_line_deg: float = 20.0,
) -> dict[tuple[int, int], tuple[float, float, float]]:
    """Where GPS puts the ``pairs`` on the strip's line, scaled by one registered pair: ``(shift, apart, thin)`` px.

    ``reference`` (frames a, b) and its homography ``H_ref`` (a px -> b px) give how many frame px a metre of GPS
    displacement is (the shift of a's centre over the distance between the fixes) and in which direction of the
    frame the strip moves. A pair of frames of ``size`` (width, height) px, both on that line (its displacement
    within ``same_line_deg`` of the reference's, either way), is predicted ``shift`` px apart along it; two such
    frames stop overlapping ``apart`` px apart, and their overlap is ``thin`` px across its thinner side (negative:
    a gap). Pairs off the line (a crossing strip) are left out: their direction in the frame is not known from one
    pair; so is every pair when the reference is degenerate. ``positions``: (n, 2) metres, by frame index."""
    a, b = reference
    step = positions[b] - positions[a]
    metres = float(np.hypot(*step))
    w, h = size
    centre = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
    moved = apply_homography(H_ref, centre)[0] - centre[0]  # where a's centre lies in b, from b's centre
    pixels = float(np.hypot(*moved))
    if metres <= 0 or pixels <= 0 or not np.isfinite(pixels):
        return {}
    ux, uy = np.abs(moved / pixels)
    # two w x h frames t px apart along (ux, uy) overlap in (w - t ux) x (h - t uy): until t = apart
    apart = min(w / ux if ux > 0 else np.inf, h / uy if uy > 0 else np.inf)
    cos_line = np.cos(np.radians(same_line_deg))
    found = {}
    for i, j in pairs:
        d = positions[j] - positions[i]
        dist = float(np.hypot(*d))
        if dist > 0 and abs(float(d @ step)) / (dist * metres) >= cos_line:
            shift = dist * pixels / metres
            found[(i, j)] = (shift, float(apart), float(min(w - shift * ux, h - shift * uy)))
    return found


def distant_pairs(
    placed: dict[tuple[int, int], tuple[float, float, float]], margin: float = 1.25
) -> list[tuple[int, int]]:
    """Of the pairs :func:`along_strip` placed, those that cannot overlap: more than ``margin`` x the shift at which
    two frames stop overlapping apart (the margin for GPS noise and attitude). Pairs off the line are never in it."""
    return [pair for pair, (shift, apart, _) in placed.items() if shift > margin * apart]
