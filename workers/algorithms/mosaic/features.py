"""Feature detection and descriptor matching by feature type and device: OpenCV's SIFT on the CPU, the
``gpu_kernels`` SIFT on CUDA, and Harris corners with NCC windows (the aerial-strip method) on either.

Arrays in and out are host NumPy arrays; data moves to the device and back inside each call.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

from gpu_kernels.backend import Device, to_device, to_host
from gpu_kernels.bf_match import match_descriptors
from gpu_kernels.harris import harris_corners
from gpu_kernels.ncc import match_ncc, window_descriptors
from gpu_kernels.sift import sift

FeatureType = Literal["sift", "harris_ncc"]


def uses_opencv(feature_type: FeatureType, device: Device) -> bool:
    """SIFT on the CPU is OpenCV's (the fast path there); everything else runs on ``gpu_kernels``."""
    return feature_type == "sift" and device == "cpu"


def detector_name(feature_type: FeatureType, device: Device) -> str:
    return "opencv-sift" if uses_opencv(feature_type, device) else f"gpu_kernels-{feature_type}"


def detect(
    gray: np.ndarray,
    feature_type: FeatureType,
    device: Device,
    max_features: int,
    ncc_half_window: int = 7,
    cell_px: int = 64,
    per_cell: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``(N, 2) float32`` pixel (x, y) and descriptors ``(N, D) float32`` of a (H, W) uint8 image."""
    if uses_opencv(feature_type, device):
        return detect_sift(gray, max_features)
    image = to_device(gray, device)
    if feature_type == "sift":
        found = sift(image, max_features=max_features)
        return to_host(found.xy).astype(np.float32), to_host(found.descriptors)
    corners = harris_corners(image, radius=3, threshold=1e-4, cell_px=cell_px, per_cell=per_cell)
    xy = corners.xy[:max_features]
    descriptors, kept = window_descriptors(image, xy, ncc_half_window)
    return to_host(xy[kept]).astype(np.float32), to_host(descriptors)


def match(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    feature_type: FeatureType,
    device: Device,
    ratio: float,
    ncc_threshold: float,
) -> np.ndarray:
    """(M, 2) int64 index pairs (row of ``desc_a``, row of ``desc_b``) of mutual matches."""
    if uses_opencv(feature_type, device):
        return match_ratio(desc_a, desc_b, ratio)
    a, b = to_device(desc_a, device), to_device(desc_b, device)
    if feature_type == "sift":
        found = match_descriptors(a, b, ratio=ratio, mutual=True)
        return np.column_stack([to_host(found.index_a), to_host(found.index_b)]).astype(np.int64)
    ncc = match_ncc(a, b, threshold=ncc_threshold, mutual=True)
    return np.column_stack([to_host(ncc.index_a), to_host(ncc.index_b)]).astype(np.int64)


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
