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


def registration_copy(gray: np.ndarray, max_px: int) -> tuple[np.ndarray, tuple[float, float]]:
    """``gray`` (H, W) shrunk (INTER_AREA) so its longest side is at most ``max_px``, and the (x, y) factors
    small / full; (1.0, 1.0) and the image itself when it is already that small.

    Features are found on this copy (cv2.Stitcher's ``registration_resol``): SIFT's cost grows with the
    pixels, and a few hundred well-spread tie points per pair need no more than about 0.6 MP per frame.
    """
    if max_px < 1:
        raise ValueError("max_px must be positive")
    height, width = gray.shape[:2]
    scale = max_px / max(width, height)
    if scale >= 1.0:
        return gray, (1.0, 1.0)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    return small, (size[0] / width, size[1] / height)


def to_full_pixels(points: np.ndarray, factors: tuple[float, float]) -> np.ndarray:
    """(N, 2) float32 pixel (x, y) on a :func:`registration_copy` -> the same points on the full image.

    Pixel centres sit at integers on both (OpenCV's convention), so the map is ``(x + 0.5) / s - 0.5``.
    """
    f = np.asarray(factors, dtype=np.float64)
    return ((points.astype(np.float64) + 0.5) / f - 0.5).astype(np.float32)


def match(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    feature_type: FeatureType,
    device: Device,
    ratio: float,
    ncc_threshold: float,
    min_matches: int = 0,
) -> np.ndarray:
    """(M, 2) int64 index pairs (row of ``desc_a``, row of ``desc_b``) of mutual matches.

    ``min_matches``: OpenCV SIFT gives up early, empty, on a pair that cannot reach it (:func:`match_ratio`).
    """
    if uses_opencv(feature_type, device):
        return match_ratio(desc_a, desc_b, ratio, min_matches)
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


def match_ratio(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float, min_matches: int = 0) -> np.ndarray:
    """Nearest-neighbour matches that pass Lowe's ratio test in both directions.

    Parameters
    ----------
    desc_a, desc_b : (N, D), (M, D) float32 descriptors.
    ratio : Lowe's nearest / second-nearest distance ratio.
    min_matches : a pair that cannot reach this many matches is not worth matching in full: every
        ``PROBE_SHARE``-th row of ``desc_a`` is searched first, and when they find fewer than
        ``min_matches / (2 PROBE_SHARE)`` (half the share of ``min_matches`` it would find in a pair just
        good enough) the pair is given up, empty. 0 searches every row.

    Returns
    -------
    (M, 2) int64 : index into ``desc_a``, index into ``desc_b``.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    index_b = _flann_index(desc_b)
    # every PROBE_SHARE-th row: detectors list keypoints by scale and place, so a prefix would be one
    # part of the frame, maybe one the other frame does not see
    probing = np.zeros(len(desc_a), bool)
    probing[:: PROBE_SHARE if min_matches > 0 else len(desc_a) + 1] = min_matches > 0
    rows = [np.flatnonzero(probing), np.flatnonzero(~probing)]
    probe = _ratio_one_way(desc_a[rows[0]], index_b, ratio)
    if min_matches > 0 and len(probe) * 2 * PROBE_SHARE < min_matches:
        return np.zeros((0, 2), np.int64)  # frames that do not overlap: 1/PROBE_SHARE of the work
    rest = _ratio_one_way(desc_a[rows[1]], index_b, ratio)
    forward = np.concatenate([probe, rest])
    forward[:, 0] = np.concatenate([rows[0][probe[:, 0]], rows[1][rest[:, 0]]])
    forward = forward[np.argsort(forward[:, 0], kind="stable")]
    if not len(forward):
        return forward
    # Only the rows of b that some row of a chose can be mutual: search back from those alone (a
    # tenth of b on a typical pair, so the check costs a fraction of the forward search).
    chosen = np.unique(forward[:, 1])
    backward = _ratio_one_way(desc_b[chosen], _flann_index(desc_a), ratio)
    back_map = dict(zip(chosen[backward[:, 0]].tolist(), backward[:, 1].tolist(), strict=True))
    keep = [k for k, (a, b) in enumerate(forward.tolist()) if back_map.get(b) == a]
    return forward[keep]


PROBE_SHARE = 8  # match_ratio: share of the query rows searched before deciding a pair is worth it


def _flann_index(desc: np.ndarray) -> tuple[cv2.flann.Index, np.ndarray]:
    """A FLANN kd-forest over ``desc``, with the array it searches (the index reads it, so it must live)."""
    # FLANN kd-trees: the 2-NN search is approximate but ~10x faster than brute force at 6k features.
    data = np.ascontiguousarray(desc, np.float32)
    cv2.setRNGSeed(len(data))  # FLANN's randomised trees draw from OpenCV's RNG: same input, same trees
    return cv2.flann.Index(data, {"algorithm": 1, "trees": 4}), data


def _ratio_one_way(desc_q: np.ndarray, index_t: tuple[cv2.flann.Index, np.ndarray], ratio: float) -> np.ndarray:
    """(K, 2) int64 (query row, target row) of the queries whose nearest target passes the ratio test."""
    if not len(desc_q):
        return np.zeros((0, 2), np.int64)
    nearest, dist2 = index_t[0].knnSearch(np.ascontiguousarray(desc_q, np.float32), 2, params={"checks": 64})
    good = dist2[:, 0] < ratio**2 * dist2[:, 1]  # FLANN's L2 distances are squared
    return np.column_stack([np.flatnonzero(good), nearest[good, 0]]).astype(np.int64)
