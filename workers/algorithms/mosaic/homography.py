"""Robust two-view models of matched tie points: USAC homography and fundamental matrix, and a
well-spread subset of tie points."""

from __future__ import annotations

import cv2
import numpy as np


def estimate_homography(
    points_a: np.ndarray, points_b: np.ndarray, threshold_px: float
) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust homography ``b ~ H a`` with OpenCV's USAC (MAGSAC++), refined on its inliers.

    Parameters
    ----------
    points_a, points_b : (N, 2) float, pixel (x, y), row k of each is one putative match.
    threshold_px : inlier reprojection threshold in ``b`` pixels.

    Returns
    -------
    H : (3, 3) float64 normalised so H[2, 2] = 1, or None when fewer than 4 matches or no model.
    inliers : (N,) bool
    """
    n = len(points_a)
    if n < 4:
        return None, np.zeros(n, bool)
    cv2.setRNGSeed(n)  # same matches, same model: reruns of a job give the same mosaic
    H, mask = cv2.findHomography(
        points_a.astype(np.float64),
        points_b.astype(np.float64),
        cv2.USAC_MAGSAC,
        threshold_px,
        maxIters=10000,
        confidence=0.9999,
    )
    if H is None or mask is None or abs(H[2, 2]) < 1e-12:
        return None, np.zeros(n, bool)
    return H / H[2, 2], mask.ravel().astype(bool)


def estimate_fundamental(
    points_a: np.ndarray, points_b: np.ndarray, threshold_px: float
) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust fundamental matrix ``b^T F a = 0`` with OpenCV's USAC (MAGSAC++), for scenes with relief.

    A homography holds only for a plane (or a camera that only rotates); views of 3D scenes from
    different places agree only through the epipolar constraint, which is what triangulation needs.

    Parameters
    ----------
    points_a, points_b : (N, 2) float, pixel (x, y), row k of each is one putative match.
    threshold_px : inlier distance to the epipolar line, pixels.

    Returns
    -------
    F : (3, 3) float64, or None when fewer than 8 matches or no model.
    inliers : (N,) bool
    """
    n = len(points_a)
    if n < 8:
        return None, np.zeros(n, bool)
    cv2.setRNGSeed(n)
    F, mask = cv2.findFundamentalMat(
        points_a.astype(np.float64), points_b.astype(np.float64), cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000
    )
    if F is None or mask is None or F.shape != (3, 3):
        return None, np.zeros(n, bool)
    return F, mask.ravel().astype(bool)


def spread_subset(points: np.ndarray, image_size: tuple[int, int], limit: int, seed: int = 0) -> np.ndarray:
    """Indices of at most ``limit`` points spread over the image: one per grid cell, cells in turn.

    A few hundred well-spread tie points constrain a homography as well as thousands clustered in
    one textured corner, and keep the adjustment small.

    Parameters
    ----------
    points : (N, 2) float, pixel (x, y)
    image_size : (width, height) px
    """
    n = len(points)
    if n <= limit:
        return np.arange(n)
    side = max(1, int(np.ceil(np.sqrt(limit))))
    w, h = image_size
    cx = np.clip((points[:, 0] / max(w, 1) * side).astype(int), 0, side - 1)
    cy = np.clip((points[:, 1] / max(h, 1) * side).astype(int), 0, side - 1)
    order = np.random.default_rng(seed).permutation(n)
    cell = (cy * side + cx)[order]
    # rank of each point within its cell: take rank 0 of every cell first, then rank 1, ...
    sort = np.argsort(cell, kind="stable")
    starts = np.searchsorted(cell[sort], cell[sort])
    rank = np.empty(n, int)
    rank[sort] = np.arange(n) - starts
    chosen = order[np.lexsort((cell, rank))][:limit]
    return np.sort(chosen)
