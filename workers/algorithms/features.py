"""Feature detection and matching by feature type and device: OpenCV's SIFT on the CPU, the
``gpu_kernels`` SIFT on CUDA, and Harris corners with NCC windows (the aerial-strip method) on either.

Arrays in and out are host NumPy arrays; data moves to the device and back inside each call.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from gpu_kernels.backend import Device, to_device, to_host
from gpu_kernels.bf_match import match_descriptors
from gpu_kernels.harris import harris_corners
from gpu_kernels.ncc import match_ncc, window_descriptors
from gpu_kernels.sift import sift
from workers.algorithms.matching import detect_sift, match_ratio

FeatureType = Literal["sift", "harris_ncc"]


def uses_opencv(feature_type: FeatureType, device: Device) -> bool:
    """SIFT on the CPU is OpenCV's (the fast path there); everything else runs on ``gpu_kernels``."""
    return feature_type == "sift" and device == "cpu"


def detector_name(feature_type: FeatureType, device: Device) -> str:
    return "opencv-sift" if uses_opencv(feature_type, device) else f"gpu_kernels-{feature_type}"


def detect(gray: np.ndarray, feature_type: FeatureType, device: Device, max_features: int,
           ncc_half_window: int = 7, cell_px: int = 64, per_cell: int = 8) -> tuple[np.ndarray, np.ndarray]:
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


def match(desc_a: np.ndarray, desc_b: np.ndarray, feature_type: FeatureType, device: Device, ratio: float,
          ncc_threshold: float) -> np.ndarray:
    """(M, 2) int64 index pairs (row of ``desc_a``, row of ``desc_b``) of mutual matches."""
    if uses_opencv(feature_type, device):
        return match_ratio(desc_a, desc_b, ratio)
    a, b = to_device(desc_a, device), to_device(desc_b, device)
    if feature_type == "sift":
        found = match_descriptors(a, b, ratio=ratio, mutual=True)
        return np.column_stack([to_host(found.index_a), to_host(found.index_b)]).astype(np.int64)
    ncc = match_ncc(a, b, threshold=ncc_threshold, mutual=True)
    return np.column_stack([to_host(ncc.index_a), to_host(ncc.index_b)]).astype(np.int64)
