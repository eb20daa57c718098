"""Feature detection and descriptor matching by feature type and device: OpenCV's SIFT on the CPU, the
``gpu_kernels`` SIFT on CUDA, OpenCV's ORB (binary, Hamming-matched) on the CPU for either device, and Harris
corners with NCC windows (the aerial-strip method) on either.

Arrays in and out are host NumPy arrays; data moves to the device and back inside each call.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import cv2
import numpy as np

from gpu_kernels.backend import Device, to_device, to_host
from gpu_kernels.bf_match import match_descriptors
from gpu_kernels.harris import harris_corners
from gpu_kernels.ncc import match_ncc, window_descriptors
from gpu_kernels.sift import sift
from workers.algorithms.mosaic.binary_features import detect_orb
from workers.algorithms.mosaic.homography import estimate_homography

FeatureType = Literal["sift", "orb", "harris_ncc"]


def uses_opencv(feature_type: FeatureType, device: Device) -> bool:
    """SIFT on the CPU and ORB anywhere are OpenCV's (ORB costs a GPU round trip more than it takes on the
    CPU); everything else runs on ``gpu_kernels``."""
    return feature_type == "orb" or (feature_type == "sift" and device == "cpu")


def detector_name(feature_type: FeatureType, device: Device) -> str:
    return f"opencv-{feature_type}" if uses_opencv(feature_type, device) else f"gpu_kernels-{feature_type}"


def detect(
    gray: np.ndarray,
    feature_type: FeatureType,
    device: Device,
    max_features: int,
    ncc_half_window: int = 7,
    cell_px: int = 64,
    per_cell: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``(N, 2) float32`` pixel (x, y) and descriptors ``(N, D)`` of a (H, W) uint8 image: float32,
    or uint8 bit strings for ORB."""
    if feature_type == "orb":
        return detect_orb(gray, max_features)
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
    indices: tuple[SearchIndex | None, SearchIndex | None] = (None, None),
    guide: OverlapGuide | None = None,
) -> np.ndarray:
    """(M, 2) int64 index pairs (row of ``desc_a``, row of ``desc_b``) of mutual matches.

    ``min_matches``: OpenCV SIFT and ORB give up early, empty, on a pair that cannot reach it
    (:func:`match_ratio`).
    ``indices``: OpenCV SIFT and ORB only, the :func:`match_index` of ``desc_a`` and ``desc_b`` built
    beforehand (a frame is in many pairs; its index is built once), None to build it here.
    ``guide``: OpenCV SIFT and ORB only, search only the overlap the first matches predict (:func:`match_ratio`).
    """
    if uses_opencv(feature_type, device):
        return match_ratio(desc_a, desc_b, ratio, min_matches, indices, guide)
    a, b = to_device(desc_a, device), to_device(desc_b, device)
    if feature_type == "sift":
        found = match_descriptors(a, b, ratio=ratio, mutual=True)
        return np.column_stack([to_host(found.index_a), to_host(found.index_b)]).astype(np.int64)
    ncc = match_ncc(a, b, threshold=ncc_threshold, mutual=True)
    return np.column_stack([to_host(ncc.index_a), to_host(ncc.index_b)]).astype(np.int64)


def match_index(desc: np.ndarray, feature_type: FeatureType, device: Device) -> SearchIndex | None:
    """What :func:`match` searches in a frame's (N, D) descriptors, built once per frame rather than once per
    pair and direction: OpenCV SIFT's :class:`FlannIndex`, ORB's :class:`HammingIndex`; None where ``match``
    needs none."""
    if not uses_opencv(feature_type, device) or len(desc) < 2:
        return None
    return HammingIndex(desc) if feature_type == "orb" else FlannIndex(desc)


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


def match_ratio(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    ratio: float,
    min_matches: int = 0,
    indices: tuple[SearchIndex | None, SearchIndex | None] = (None, None),
    guide: OverlapGuide | None = None,
) -> np.ndarray:
    """Nearest-neighbour matches that pass Lowe's ratio test in both directions.

    Parameters
    ----------
    desc_a, desc_b : (N, D), (M, D) descriptors: float32 (SIFT, searched by a :class:`FlannIndex`) or uint8
        bit strings (ORB, by a :class:`HammingIndex`).
    ratio : Lowe's nearest / second-nearest distance ratio.
    min_matches : a pair that cannot reach this many matches is not worth matching in full: every
        ``PROBE_SHARE``-th row of ``desc_a`` is searched first, and when they find fewer than
        ``min_matches / (2 PROBE_SHARE)`` (half the share of ``min_matches`` it would find in a pair just
        good enough) the pair is given up, empty. 0 searches every row.
    indices : the :func:`search_index` of ``desc_a`` and of ``desc_b``, or None to build one here. Built once
        per frame and shared by its pairs, they give the same matches as those built here (same seed, same
        trees).
    guide : the keypoints of both frames, for a planar scene: the probe's matches (``min_matches`` > 0)
        predict the overlap through a homography, and the other rows of ``desc_a`` are searched only where
        they fall in frame b (:func:`in_predicted_overlap`). A :class:`HammingIndex` is also searched only
        over the rows of ``desc_b`` that fall in frame a (a brute-force search costs the product of both
        sides; FLANN's trees cannot be cut), so its ratio test weighs the nearest against the second nearest
        in the overlap. Rows outside have no partner in the other frame.

    Returns
    -------
    (M, 2) int64 : index into ``desc_a``, index into ``desc_b``.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    index_a, index_b = indices
    index_b = search_index(desc_b) if index_b is None else index_b
    # every PROBE_SHARE-th row: detectors list keypoints by scale and place, so a prefix would be one
    # part of the frame, maybe one the other frame does not see
    probing = np.zeros(len(desc_a), bool)
    probing[:: PROBE_SHARE if min_matches > 0 else len(desc_a) + 1] = min_matches > 0
    rows = [np.flatnonzero(probing), np.flatnonzero(~probing)]
    probe = index_b.ratio_matches(desc_a[rows[0]], ratio)
    if min_matches > 0 and len(probe) * 2 * PROBE_SHARE < min_matches:
        return np.zeros((0, 2), np.int64)  # frames that do not overlap: 1/PROBE_SHARE of the work
    searched = index_b
    if guide is not None and min_matches > 0:
        H = predicted_homography(guide, rows[0][probe[:, 0]], probe[:, 1])
        if H is not None:
            rows[1] = rows[1][inside_frame(guide.points_a[rows[1]], H, guide.size_b)]
            searched = index_b.restricted(inside_frame(guide.points_b, np.linalg.inv(H), guide.size_a))
    rest = searched.ratio_matches(desc_a[rows[1]], ratio)
    forward = np.concatenate([probe, rest])
    forward[:, 0] = np.concatenate([rows[0][probe[:, 0]], rows[1][rest[:, 0]]])
    forward[len(probe) :, 1] = searched.rows[rest[:, 1]]
    forward = forward[np.argsort(forward[:, 0], kind="stable")]
    if not len(forward):
        return forward
    # Only the rows of b that some row of a chose can be mutual: search back from those alone (a
    # tenth of b on a typical pair, so the check costs a fraction of the forward search).
    chosen = np.unique(forward[:, 1])
    backward = (search_index(desc_a) if index_a is None else index_a).ratio_matches(desc_b[chosen], ratio)
    back = np.full(len(desc_b), -1, np.int64)  # row of b -> its mutual candidate in a, -1 for none
    back[chosen[backward[:, 0]]] = backward[:, 1]
    return forward[back[forward[:, 1]] == forward[:, 0]]


PROBE_SHARE = 8  # match_ratio: share of the query rows searched before deciding a pair is worth it
FLANN_CHECKS = 64  # leaves a FLANN search visits: more finds the true nearest neighbour more often, slower


class OverlapGuide(NamedTuple):
    """Where :func:`match_ratio` may look: both frames' keypoints and sizes."""

    points_a: np.ndarray  # (N, 2) float32 pixel (x, y) of the rows of desc_a
    points_b: np.ndarray  # (M, 2) float32 pixel (x, y) of the rows of desc_b
    size_b: tuple[int, int]  # frame b's width, height, px
    threshold_px: float  # USAC inlier threshold of the predicting homography, px
    size_a: tuple[int, int] = (0, 0)  # frame a's width, height, px; (0, 0): unknown, frame b is not cut


GUIDE_MIN_INLIERS = 20  # probe inliers a predicted overlap needs (a pair with fewer is searched in full)
GUIDE_MARGIN = 0.05  # the overlap is grown by this share of the other frame's longest side, for the model's error


def predicted_homography(guide: OverlapGuide, probe_a: np.ndarray, probe_b: np.ndarray) -> np.ndarray | None:
    """(3, 3) frame a px -> frame b px, the USAC homography of the (P,) int matched rows ``probe_a``,
    ``probe_b``; None when it has fewer than ``GUIDE_MIN_INLIERS`` inliers (a weak or non-overlapping pair:
    no prediction to trust)."""
    if len(probe_a) < GUIDE_MIN_INLIERS:
        return None
    H, inliers = estimate_homography(guide.points_a[probe_a], guide.points_b[probe_b], guide.threshold_px)
    return None if H is None or inliers.sum() < GUIDE_MIN_INLIERS else H


def inside_frame(points: np.ndarray, H: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(K,) bool: which (K, 2) pixel (x, y) ``points`` ``H`` maps into a frame of ``size`` (width, height)
    grown by ``GUIDE_MARGIN``; all True for an unknown size (0, 0)."""
    if min(size) <= 0:
        return np.ones(len(points), bool)
    q = np.asarray(points, np.float64) @ H[:, :2].T + H[:, 2]
    ahead = q[:, 2] > 1e-12  # points the model maps behind the other camera are in no overlap
    xy = q[:, :2] / np.where(ahead, q[:, 2], 1.0)[:, None]
    margin = GUIDE_MARGIN * max(size)
    lo, hi = -0.5 - margin, np.asarray(size, np.float64) - 0.5 + margin
    return ahead & np.all((xy >= lo) & (xy <= hi), axis=1)


def in_predicted_overlap(guide: OverlapGuide, probe_a: np.ndarray, probe_b: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(K,) bool: which ``rows`` of frame a fall in frame b through :func:`predicted_homography`; all True
    when there is none."""
    H = predicted_homography(guide, probe_a, probe_b)
    return np.ones(len(rows), bool) if H is None else inside_frame(guide.points_a[rows], H, guide.size_b)


class FlannIndex:
    """A FLANN kd-forest over (N, D) float32 descriptors, with the array it searches (the index reads it
    in place, so it must live as long as the index).

    Searching is read-only: pairs on several threads may share one frame's index.
    """

    def __init__(self, desc: np.ndarray) -> None:
        # FLANN kd-trees: the 2-NN search is approximate but ~10x faster than brute force at 6k features.
        self.data = np.ascontiguousarray(desc, np.float32)
        self.rows = np.arange(len(self.data))  # row of the descriptors given, per row searched
        cv2.setRNGSeed(len(self.data))  # FLANN's randomised trees draw from OpenCV's RNG: same input, same trees
        self.index = cv2.flann.Index(self.data, {"algorithm": 1, "trees": 4})

    def ratio_matches(self, desc_q: np.ndarray, ratio: float) -> np.ndarray:
        """(K, 2) int64 (query row, row searched) of the queries whose nearest neighbour passes the ratio test."""
        if not len(desc_q):
            return np.zeros((0, 2), np.int64)
        nearest, dist2 = self.index.knnSearch(
            np.ascontiguousarray(desc_q, np.float32), 2, params={"checks": FLANN_CHECKS}
        )
        good = dist2[:, 0] < ratio**2 * dist2[:, 1]  # FLANN's L2 distances are squared
        return np.column_stack([np.flatnonzero(good), nearest[good, 0]]).astype(np.int64)

    def restricted(self, keep: np.ndarray) -> FlannIndex:
        """The index itself: its trees cannot be cut to some rows (a rebuild costs more than the search saves)."""
        return self


class HammingIndex:
    """Brute-force nearest neighbours by Hamming distance over (N, 32) uint8 binary descriptors (ORB):
    ``cv2.batchDistance``, a popcount per pair of rows, exact."""

    def __init__(self, desc: np.ndarray, rows: np.ndarray | None = None) -> None:
        self.data = np.ascontiguousarray(desc, np.uint8)
        self.rows = np.arange(len(self.data)) if rows is None else rows

    def ratio_matches(self, desc_q: np.ndarray, ratio: float) -> np.ndarray:
        """(K, 2) int64 (query row, row searched) of the queries whose nearest neighbour passes the ratio test
        (none when fewer than 2 rows are searched: no second neighbour to weigh it against)."""
        if not len(desc_q) or len(self.data) < 2:
            return np.zeros((0, 2), np.int64)
        dist, nearest = cv2.batchDistance(
            np.ascontiguousarray(desc_q, np.uint8), self.data, -1, normType=cv2.NORM_HAMMING, K=2
        )
        good = dist[:, 0] < ratio * dist[:, 1]
        return np.column_stack([np.flatnonzero(good), nearest[good, 0]]).astype(np.int64)

    def restricted(self, keep: np.ndarray) -> HammingIndex:
        """The index over the rows where the (N,) bool ``keep`` is True (``rows`` maps them back)."""
        return HammingIndex(self.data[keep], self.rows[keep])


SearchIndex = FlannIndex | HammingIndex


def search_index(desc: np.ndarray) -> SearchIndex:
    """The index a frame's descriptors are searched by: Hamming for uint8 bit strings, FLANN for floats."""
    return HammingIndex(desc) if desc.dtype == np.uint8 else FlannIndex(desc)
