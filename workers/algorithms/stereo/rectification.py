"""Epipolar rectification of a stereo pair: resample both images so a scene point lies on the same row.

Three ways, by what is known of the pair:

- a calibrated rig (``rig_rectification``): OpenCV's ``cv2.stereoRectify`` (Bouguet's method) from the rig's
  cameras and relative pose, distortion removed by ``cv2.initUndistortRectifyMap``;
- a fundamental matrix from matched features (``uncalibrated_rectification``): Hartley's projective
  rectification (Hartley & Zisserman, algorithm 11.12.3), both homographies moved onto one canvas;
- correspondences generated from the images' camera models (``affine_rectification``, for RPC pairs): the
  affine fundamental matrix fitted to them (Hartley & Zisserman, algorithm 14.1), a rotation of each image that
  makes the epipolar lines rows, the right image's rows scaled and shifted onto the left's, and its columns
  sheared so a reference height has zero disparity (the affine rectification of satellite stereo pipelines
  such as S2P, de Franchis et al. 2014).

Pixel coordinates have (0, 0) at the first pixel's centre; a rectification maps original pixels to rectified
ones by a homography per image (for a rig the homography without the lens distortion, for the record).
Disparity is ``d = x_left - x_right`` in rectified pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from workers.algorithms.calibration import StereoRig

MAX_CANVAS_GROWTH = 4.0  # a rectified canvas this many times the left photo's area means a broken geometry


@dataclass(frozen=True, eq=False)
class Rectification:
    """How a pair maps onto its rectified frames.

    ``left``, ``right``: (3, 3) float64 homographies, original pixel -> rectified pixel; ``width``, ``height``:
    the rectified canvas (both images); ``fundamental``: (3, 3) F of the rectified pair, x_R^T F x_L = 0 (the
    ideal one, rows matching rows, unless the pair's measured F says otherwise); ``q``: (4, 4) OpenCV
    disparity-to-depth matrix of a calibrated rig, else None; ``method``: how it was found;
    ``residual_px``: the largest row misalignment left at the correspondences it was fitted to.
    """

    left: np.ndarray
    right: np.ndarray
    width: int
    height: int
    fundamental: np.ndarray
    method: str
    q: np.ndarray | None = None
    residual_px: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "left": self.left.tolist(),
            "right": self.right.tolist(),
            "width": self.width,
            "height": self.height,
            "fundamental": self.fundamental.tolist(),
            "q": None if self.q is None else self.q.tolist(),
            "residual_px": self.residual_px,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Rectification:
        q = data.get("q")
        return cls(
            np.array(data["left"], np.float64),
            np.array(data["right"], np.float64),
            int(data["width"]),
            int(data["height"]),
            np.array(data["fundamental"], np.float64),
            str(data["method"]),
            None if q is None else np.array(q, np.float64),
            float(data.get("residual_px", 0.0)),
        )

    def to_original(self, side: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified pixels of ``side`` ("left" or "right") -> its original pixels (homography methods)."""
        h = np.linalg.inv(self.left if side == "left" else self.right)
        return _apply(h, x, y)


def rectified_fundamental() -> np.ndarray:
    """F of an ideally rectified pair: x_R^T F x_L = 0 means y_R = y_L."""
    return np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _apply(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


def identity_rectification(width: int, height: int) -> Rectification:
    """An already rectified pair: nothing moves."""
    return Rectification(np.eye(3), np.eye(3), int(width), int(height), rectified_fundamental(), "rectified")


# -- A calibrated rig ------------------------------------------------------------------------------------


def rig_rectification(rig: StereoRig, alpha: float = 1.0) -> tuple[Rectification, tuple[np.ndarray, ...]]:
    """Rectify a rig's pair with ``cv2.stereoRectify``; returns the rectification and the ``cv2.remap`` maps
    ``(left_x, left_y, right_x, right_y)`` (float32, the canvas's shape) that resample the original photos.

    ``alpha`` is OpenCV's free scaling: 1 keeps every original pixel (black corners, masked), 0 only valid
    ones. The canvas has the left photo's size. ``ValueError`` for a rig whose baseline is mostly vertical
    (its rectified pair would differ by rows, not columns).
    """
    left, right = (c.with_convention("distort_ideal") for c in (rig.left, rig.right))
    size = (left.width, left.height)
    K1, K2 = left.matrix(), right.matrix()
    D1, D2 = left.opencv_distortion(), right.opencv_distortion()
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
        K1, D1, K2, D2, size, rig.R, rig.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha
    )
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        raise ValueError("the rig's baseline is vertical: its pair would be rectified along columns; turn the photos")
    maps_l = cv2.initUndistortRectifyMap(K1, D1, R1, P1, size, cv2.CV_32FC1)
    maps_r = cv2.initUndistortRectifyMap(K2, D2, R2, P2, size, cv2.CV_32FC1)
    h_l = P1[:, :3] @ R1 @ np.linalg.inv(K1)
    h_r = P2[:, :3] @ R2 @ np.linalg.inv(K2)
    rect = Rectification(h_l, h_r, size[0], size[1], rectified_fundamental(), "rig", q=np.asarray(Q, np.float64))
    return rect, (maps_l[0], maps_l[1], maps_r[0], maps_r[1])


def remap_pair(
    maps: tuple[np.ndarray, ...], left: np.ndarray, right: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Resample both photos through ``rig_rectification``'s maps: images and (H, W) bool validity masks."""
    out = []
    for (mx, my), image in (((maps[0], maps[1]), left), ((maps[2], maps[3]), right)):
        warped = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        ones = np.full(image.shape[:2], 255, np.uint8)
        valid = cv2.remap(ones, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
        out.append((warped, cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0))
    return out[0][0], out[1][0], out[0][1], out[1][1]


# -- Homographies on one canvas ---------------------------------------------------------------------------


def warp_pair(
    rect: Rectification, left: np.ndarray, right: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Resample both photos through the rectification's homographies onto its canvas.

    Returns the rectified left and right images (dtype kept) and (H, W) bool masks of the canvas pixels each
    photo covers (eroded by one pixel: the interpolation at a photo's edge mixes in the border).
    """
    size = (rect.width, rect.height)
    out = []
    for h, image in ((rect.left, left), (rect.right, right)):
        warped = cv2.warpPerspective(image, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        ones = np.full(image.shape[:2], 255, np.uint8)
        valid = cv2.warpPerspective(ones, h, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
        out.append((warped, cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def _on_canvas(h_l: np.ndarray, h_r: np.ndarray, size_l: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Shift both homographies by one translation so the left photo's rectified box starts at (0, 0)."""
    w, hgt = size_l
    x, y = _apply(h_l, np.array([0, w - 1, 0, w - 1.0]), np.array([0, 0, hgt - 1, hgt - 1.0]))
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("the rectification sends part of the left photo to infinity")
    width, height = int(np.ceil(np.ptp(x))) + 1, int(np.ceil(np.ptp(y))) + 1
    if width * height > MAX_CANVAS_GROWTH * w * hgt:
        raise ValueError(
            f"the rectified left photo would be {width}x{height} px, more than {MAX_CANVAS_GROWTH:g}x the photo: "
            "the pair's geometry could not be recovered"
        )
    shift = np.array([[1.0, 0.0, -x.min()], [0.0, 1.0, -y.min()], [0.0, 0.0, 1.0]])
    return shift @ h_l, shift @ h_r, width, height


# -- From a fundamental matrix ----------------------------------------------------------------------------


def fundamental_from_matches(
    left_px: np.ndarray, right_px: np.ndarray, threshold_px: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """F (x_R^T F x_L = 0) by MAGSAC++ (``cv2.findFundamentalMat``, USAC_MAGSAC) and the (N,) bool inliers.

    ``ValueError`` when there are too few matches or no F is found.
    """
    if len(left_px) < 15:
        raise ValueError(f"only {len(left_px)} features match between the photos; at least 15 are needed")
    F, inliers = cv2.findFundamentalMat(
        left_px.astype(np.float64), right_px.astype(np.float64), cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000
    )
    if F is None or F.shape != (3, 3) or inliers is None or int(inliers.sum()) < 15:
        raise ValueError("no fundamental matrix fits the matched features: are both photos of the same scene?")
    return np.asarray(F, np.float64), inliers.ravel() > 0


def uncalibrated_rectification(
    fundamental: np.ndarray,
    left_px: np.ndarray,
    right_px: np.ndarray,
    size_l: tuple[int, int],
    size_r: tuple[int, int] | None = None,
) -> Rectification:
    """Projective rectification from F and its inlier matches (Hartley & Zisserman, algorithm 11.12.3), on
    one canvas.

    The right photo's epipole is sent to infinity along x by a homography that is nearly rigid about the
    photo's centre; the left photo gets the matching homography (which makes the rows of corresponding points
    equal exactly where F holds) with the affine correction that brings the matches' columns closest. A pair
    mirrored by it is turned back, an upside-down one turned by 180 degrees. OpenCV's
    ``cv2.stereoRectifyUncalibrated`` left rows 0.6 px apart (2 px at the 95th percentile) on a pair whose F
    fitted its matches to 0.03 px; this leaves them within F's own error.
    """
    size_r = size_r or size_l
    h_r = _epipole_to_infinity(fundamental, size_r)
    e_r = _null(fundamental.T)  # the right epipole: F^T e' = 0
    skew = np.array([[0.0, -e_r[2], e_r[1]], [e_r[2], 0.0, -e_r[0]], [-e_r[1], e_r[0], 0.0]])
    m = skew @ fundamental + np.outer(e_r, np.ones(3))  # F = [e']x M with M invertible
    h0 = h_r @ m
    xl, yl = _apply(h0, left_px[:, 0], left_px[:, 1])
    xr, _ = _apply(h_r, right_px[:, 0], right_px[:, 1])
    coeffs, *_ = np.linalg.lstsq(np.column_stack([xl, yl, np.ones_like(xl)]), xr, rcond=None)
    h_l = np.array([coeffs, [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ h0
    h_l, h_r = _upright(h_l, h_r, size_l)
    h_l, h_r, width, height = _on_canvas(h_l, h_r, size_l)
    f_rect = np.linalg.inv(h_r).T @ fundamental @ np.linalg.inv(h_l)
    f_rect /= np.linalg.norm(f_rect)
    _, yl = _apply(h_l, left_px[:, 0], left_px[:, 1])
    _, yr = _apply(h_r, right_px[:, 0], right_px[:, 1])
    residual = float(np.percentile(np.abs(yl - yr), 95)) if len(yl) else 0.0
    return Rectification(h_l, h_r, width, height, f_rect, "uncalibrated", residual_px=residual)


def _null(matrix: np.ndarray) -> np.ndarray:
    """The unit vector the matrix sends to zero (its last right singular vector)."""
    return np.asarray(np.linalg.svd(matrix)[2][-1])


def _epipole_to_infinity(fundamental: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """H = G R T: the photo's centre to the origin, the epipole turned onto the x axis at (f, 0, w), then sent
    to infinity by G = [[1, 0, 0], [0, 1, 0], [-w / f, 0, 1]] (identity for an epipole already at infinity);
    the centre is brought back after."""
    e = _null(fundamental.T)
    cx, cy = (size[0] - 1) / 2.0, (size[1] - 1) / 2.0
    t = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    ex, ey, ew = t @ e
    angle = np.arctan2(ey, ex) if ew >= 0 else np.arctan2(-ey, -ex)  # e and -e are one point
    c, s = np.cos(angle), np.sin(angle)
    r = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    f, _, w = r @ t @ e
    g = np.eye(3)
    if abs(f) > 1e-12:
        g[2, 0] = -w / f
    back = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    return np.asarray(back @ g @ r @ t)


def _upright(h_l: np.ndarray, h_r: np.ndarray, size_l: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The homographies turned so that neither mirrors its photo nor turns it upside down (one that mirrors
    only one photo means inconsistent matches)."""
    centre = np.array([(size_l[0] - 1) / 2.0, (size_l[1] - 1) / 2.0])
    jl = _local_jacobian(h_l, centre)
    jr = _local_jacobian(h_r, centre)
    if (np.linalg.det(jl) < 0) != (np.linalg.det(jr) < 0):
        raise ValueError("the rectification mirrors one photo only: the matched features are not consistent")
    if np.linalg.det(jl) < 0:  # both mirrored: flip the columns back
        mirror = np.diag([-1.0, 1.0, 1.0])
        h_l, h_r, jl = mirror @ h_l, mirror @ h_r, np.diag([-1.0, 1.0]) @ jl
    if jl[1, 1] < 0:  # upside down: turn both by 180 degrees
        turn = np.diag([-1.0, -1.0, 1.0])
        h_l, h_r = turn @ h_l, turn @ h_r
    return h_l, h_r


def _local_jacobian(h: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(2, 2) derivative of the homography at ``point``."""
    eps = 0.5
    x0, y0 = _apply(h, point[0], point[1])
    x1, y1 = _apply(h, point[0] + eps, point[1])
    x2, y2 = _apply(h, point[0], point[1] + eps)
    return np.array([[x1 - x0, x2 - x0], [y1 - y0, y2 - y0]]) / eps


# -- Affine, from correspondences of known camera models ---------------------------------------------------


def affine_fundamental(left_px: np.ndarray, right_px: np.ndarray) -> np.ndarray:
    """The affine F = [[0, 0, a], [0, 0, b], [c, d, e]] best fitting the correspondences (Hartley & Zisserman,
    algorithm 14.1: the smallest singular vector of the centred (x_R, y_R, x_L, y_L)); |(a, b, c, d)| = 1 and
    d >= 0 (the left photo then turns by less than 90 degrees)."""
    points = np.column_stack([right_px, left_px]).astype(np.float64)
    mean = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - mean, full_matrices=False)
    a, b, c, d = vt[-1]
    if d < 0 or (d == 0 and c < 0):
        a, b, c, d = -a, -b, -c, -d
    e = -float(np.dot([a, b, c, d], mean))
    return np.array([[0.0, 0.0, a], [0.0, 0.0, b], [c, d, e]])


def affine_rectification(
    left_px: np.ndarray, right_px: np.ndarray, reference: np.ndarray, size_l: tuple[int, int]
) -> Rectification:
    """Affine rectification of a pair from correspondences its camera models generate.

    Parameters
    ----------
    left_px, right_px : (N, 2) float64, pixel (x, y) of the same ground points in each photo, spread over the
        left photo and over several heights
    reference : (N,) bool, the correspondences on the reference height; after rectification they have zero
        disparity (the right photo's columns are fitted to the left's there)
    size_l : the left photo's (width, height)

    The left photo is only turned (its scale is kept); the right one is turned, its rows scaled and shifted
    onto the left's, and its columns scaled and sheared. ``residual_px`` is the largest row difference left
    at the correspondences: the error of the affine approximation of the cameras over the photo.
    """
    F = affine_fundamental(left_px, right_px)
    a, b, e = F[0, 2], F[1, 2], F[2, 2]
    c, d = F[2, 0], F[2, 1]
    n_l = float(np.hypot(c, d))
    if n_l < 1e-12 or np.hypot(a, b) < 1e-12:
        raise ValueError("the correspondences do not define epipolar lines (identical views?)")
    h_l = np.array([[d / n_l, -c / n_l, 0.0], [c / n_l, d / n_l, 0.0], [0.0, 0.0, 1.0]])
    row_r = np.array([-a / n_l, -b / n_l, -e / n_l])  # y_R' = y_L' for corresponding points
    xl_rect, _ = _apply(h_l, left_px[:, 0], left_px[:, 1])
    design = np.column_stack([right_px[reference], np.ones(int(reference.sum()))])
    col_r, *_ = np.linalg.lstsq(design, xl_rect[reference], rcond=None)
    h_r = np.array([col_r, row_r, [0.0, 0.0, 1.0]])
    if np.linalg.det(h_r[:2, :2]) <= 0:
        raise ValueError("the right photo would be mirrored: the two camera models do not look the same way")
    h_l, h_r, width, height = _on_canvas(h_l, h_r, size_l)
    _, yl = _apply(h_l, left_px[:, 0], left_px[:, 1])
    _, yr = _apply(h_r, right_px[:, 0], right_px[:, 1])
    residual = float(np.abs(yl - yr).max())
    return Rectification(h_l, h_r, width, height, rectified_fundamental(), "rpc", residual_px=residual)


# -- Sparse matches and the disparity range --------------------------------------------------------------


def sparse_matches(
    left: np.ndarray, right: np.ndarray, max_features: int = 4000, ratio: float = 0.8
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints matched by Lowe's ratio test, mutual nearest neighbours: (N, 2), (N, 2) float64 px.

    ``left``, ``right`` (H, W) uint8 grey; the masks of rectified photos are not needed (black borders have
    no keypoints).
    """
    sift = cv2.SIFT_create(nfeatures=max_features)  # type: ignore[attr-defined]
    kl, dl = sift.detectAndCompute(left, None)
    kr, dr = sift.detectAndCompute(right, None)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(dl, dr, k=2)
    backward = {m.queryIdx: m.trainIdx for m in matcher.match(dr, dl)}
    good = [
        m[0]
        for m in forward
        if len(m) == 2 and m[0].distance < ratio * m[1].distance and backward.get(m[0].trainIdx) == m[0].queryIdx
    ]
    pl = np.array([kl[m.queryIdx].pt for m in good], np.float64).reshape(-1, 2)
    pr = np.array([kr[m.trainIdx].pt for m in good], np.float64).reshape(-1, 2)
    return pl, pr


def disparity_range(
    left_px: np.ndarray, right_px: np.ndarray, max_row_gap: float = 2.0, min_matches: int = 12
) -> tuple[int, int] | None:
    """``(min_disparity, num_disparities)`` covering rectified matches, or None with too few of them.

    Matches more than ``max_row_gap`` rows apart are wrong and left out; the range spans the 1st to 99th
    percentile of the rest, widened by a quarter of its width and at least 8 px on each side, and
    ``num_disparities`` is rounded up to a multiple of 16 (StereoSGBM's step).
    """
    on_row = np.abs(left_px[:, 1] - right_px[:, 1]) <= max_row_gap
    d = left_px[on_row, 0] - right_px[on_row, 0]
    if len(d) < min_matches:
        return None
    lo, hi = np.percentile(d, [1, 99])
    margin = max(8.0, 0.25 * (hi - lo))
    low = int(np.floor(lo - margin))
    count = int(np.ceil((hi + margin - low) / 16.0) * 16)
    return low, max(count, 16)
