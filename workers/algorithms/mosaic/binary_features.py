"""Binary features: ORB (Rublee et al. 2011; cv2.Stitcher's default), by OpenCV; matched by Hamming distance
with Lowe's ratio test both ways (:class:`~workers.algorithms.mosaic.features.HammingIndex`). (AKAZE is not in
OpenCV 5's main modules, which is what we install.)

ORB is far cheaper than SIFT to find (measured on a Brighton frame at 1024 px: 35 ms against about 200 ms)
and to match (a brute-force Hamming search is a popcount), at the price of coarser keypoint positions; in
planar mode tie points are refined on the working copies anyway
(:func:`workers.algorithms.mosaic.refine_tie_points`).
"""

from __future__ import annotations

import cv2
import numpy as np


def detect_orb(gray: np.ndarray, max_features: int) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``(N, 2) float32`` pixel (x, y) and descriptors ``(N, 32) uint8`` of a (H, W) uint8 image: the
    ``max_features`` best FAST corners over ORB's 8-level pyramid."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError("detect_orb expects a (H, W) uint8 image")
    # FAST threshold lowered from OpenCV's 20 so low-contrast ground (grass, tarmac) still yields corners
    detector = cv2.ORB_create(nfeatures=max_features, fastThreshold=10)  # type: ignore[attr-defined]
    keypoints, desc = detector.detectAndCompute(gray, None)
    if desc is None or not keypoints:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
    return points, np.ascontiguousarray(desc, np.uint8)
