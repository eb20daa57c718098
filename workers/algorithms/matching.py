"""Feature detection and pairwise matching: SIFT, ratio test, USAC homography, tie-point spread."""

from __future__ import annotations

import cv2
import numpy as np


def detect_sift(gray: np.ndarray, max_features: int) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and RootSIFT descriptors (Lowe 2004; Arandjelovic & Zisserman 2012).

    Parameters
    ----------
    gray : (H, W) uint8
    max_features : keep the strongest this many keypoints.

    Returns
    -------
    points : (N, 2) float32, pixel (x, y)
    descriptors : (N, 128) float32, L2-normalised RootSIFT
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError("detect_sift expects a (H, W) uint8 image")
    sift = cv2.SIFT_create(nfeatures=max_features)  # type: ignore[attr-defined]
    keypoints, desc = sift.detectAndCompute(gray, None)
    if desc is None or len(keypoints) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
    # RootSIFT: Hellinger kernel instead of Euclidean; more distinct matches at no cost.
    desc = desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-7)
    return points, np.sqrt(desc).astype(np.float32)


def match_ratio(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> np.ndarray:
    """Nearest-neighbour matches that pass Lowe's ratio test in both directions.

    Returns
    -------
    (M, 2) int64 : index into ``desc_a``, index into ``desc_b``.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    forward = _ratio_one_way(desc_a, desc_b, ratio)
    backward = _ratio_one_way(desc_b, desc_a, ratio)
    back_map = dict(zip(backward[:, 0].tolist(), backward[:, 1].tolist(), strict=True))
    keep = [k for k, (a, b) in enumerate(forward.tolist()) if back_map.get(b) == a]
    return forward[keep]


def _ratio_one_way(desc_q: np.ndarray, desc_t: np.ndarray, ratio: float) -> np.ndarray:
    # FLANN kd-trees: the 2-NN search is approximate but ~10x faster than brute force at 6k features.
    cv2.setRNGSeed(len(desc_q))  # FLANN's randomised trees draw from OpenCV's RNG
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = flann.knnMatch(desc_q, desc_t, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def estimate_homography(points_a: np.ndarray, points_b: np.ndarray,
                        threshold_px: float) -> tuple[np.ndarray | None, np.ndarray]:
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
    H, mask = cv2.findHomography(points_a.astype(np.float64), points_b.astype(np.float64),
                                 cv2.USAC_MAGSAC, threshold_px, maxIters=10000, confidence=0.9999)
    if H is None or mask is None or abs(H[2, 2]) < 1e-12:
        return None, np.zeros(n, bool)
    return H / H[2, 2], mask.ravel().astype(bool)


def estimate_fundamental(points_a: np.ndarray, points_b: np.ndarray,
                         threshold_px: float) -> tuple[np.ndarray | None, np.ndarray]:
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
    F, mask = cv2.findFundamentalMat(points_a.astype(np.float64), points_b.astype(np.float64),
                                     cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000)
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
