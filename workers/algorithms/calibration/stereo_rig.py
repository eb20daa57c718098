"""Two-camera measurement: a calibrated stereo rig, midpoint triangulation and its uncertainty.

The rig follows OpenCV's ``cv2.stereoCalibrate`` convention, ``X_right = R @ X_left + T``; points are
returned in the left camera frame (x right, y down, z forward) in the unit of ``T`` (that of the
calibration target). Rays are unprojected through each camera's full model, so lens distortion is
removed before intersecting; the point is the midpoint of the common perpendicular of the two rays
(the classic "closest points" stereo intersection, e.g. Hartley & Sturm 1997, section 5.1).

NumPy only: the web API imports this module to answer measurement requests.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation

_RIG_PARAMS = 6  # (rvec of R in radians, T) in the rig covariance


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two calibrated cameras with ``X_right = R @ X_left + T``.

    Attributes
    ----------
    left, right : Camera
    R : (3, 3) float64 rotation, left camera frame -> right camera frame.
    T : (3,) float64 translation, in target units (e.g. mm); the baseline is ``|T|``.
    covariance : (6, 6) float64 or None
        Covariance of ``(rvec(R) [rad], T)``, e.g. from ``calibration.stereo_calibrate``.
    """

    left: Camera
    right: Camera
    R: np.ndarray
    T: np.ndarray
    covariance: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        R = _array(self.R, (3, 3), "R")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError("rig R must be a rotation matrix (orthonormal, determinant +1)")
        T = _array(self.T, (3,), "T")
        if np.linalg.norm(T) <= 0:
            raise ValueError("rig T must be non-zero: the two cameras need a baseline")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "T", T)
        if self.covariance is not None:
            cov = _array(self.covariance, (_RIG_PARAMS, _RIG_PARAMS), "covariance")
            if np.abs(cov - cov.T).max() > 1e-9 * max(np.abs(cov).max(), 1e-300) or np.any(np.diag(cov) < 0):
                raise ValueError("rig covariance must be symmetric with a non-negative diagonal")
            object.__setattr__(self, "covariance", cov)

    @property
    def baseline(self) -> float:
        """Distance between the two camera centres, in target units."""
        return float(np.linalg.norm(self.T))

    @property
    def right_centre(self) -> np.ndarray:
        """(3,) centre of the right camera in the left camera frame: ``-R.T @ T``."""
        return -self.R.T @ self.T

    def replace_pose(self, R: np.ndarray, T: np.ndarray) -> StereoRig:
        """The same cameras and covariance with another relative pose."""
        return StereoRig(self.left, self.right, R, T, self.covariance)

    def to_json(self) -> dict[str, Any]:
        cov = None if self.covariance is None else self.covariance.tolist()
        return {
            "left": self.left.to_json(),
            "right": self.right.to_json(),
            "R": self.R.tolist(),
            "T": self.T.tolist(),
            "covariance": cov,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> StereoRig:
        """A rig from ``to_json`` output; ``ValueError`` saying what is wrong."""
        if not isinstance(data, dict):
            raise ValueError("a stereo rig must be a JSON object")
        missing = [k for k in ("left", "right", "R", "T") if k not in data]
        if missing:
            raise ValueError(f"stereo rig is missing {', '.join(missing)}")
        return cls(
            Camera.from_json(data["left"]),
            Camera.from_json(data["right"]),
            data["R"],
            data["T"],
            data.get("covariance"),
        )


def _array(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"rig {name} must be numbers of shape {shape}") from exc
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise ValueError(f"rig {name} must be finite numbers of shape {shape}, got shape {arr.shape}")
    return arr


def _pixels(px: Any, name: str) -> np.ndarray:
    arr = np.asarray(px, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (N, 2) pixel (x, y) coordinates, got shape {arr.shape}")
    return arr


def triangulate_midpoint(rig: StereoRig, left_px: np.ndarray, right_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersect corresponding rays of the two cameras at the midpoint of their common perpendicular.

    Parameters
    ----------
    rig : StereoRig
    left_px, right_px : (N, 2) float64, observed pixel (x, y) of the same N points in each image.

    Returns
    -------
    points : (N, 3) float64, left camera frame, target units; NaN where the rays are parallel.
    ray_gap : (N,) float64, length of the common perpendicular (how far the rays miss each other),
        target units; a large gap relative to the depth flags a mismatched pair.
    """
    left_px, right_px = _pixels(left_px, "left_px"), _pixels(right_px, "right_px")
    if len(left_px) != len(right_px):
        raise ValueError(f"left_px has {len(left_px)} points but right_px has {len(right_px)}")
    d1 = rig.left.unproject(left_px)
    d2 = rig.right.unproject(right_px) @ rig.R  # rows R.T @ d: right rays in the left frame
    c2 = rig.right_centre
    # minimise |s d1 - (c2 + u d2)|^2 over s, u (normal equations of the two ray parameters)
    b = np.sum(d1 * d2, axis=1)
    d, e = d1 @ c2, d2 @ c2
    denom = 1.0 - b * b  # unit rays: a = c = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-15, (d - b * e) / denom, np.nan)
        u = np.where(denom > 1e-15, (b * d - e) / denom, np.nan)
    p1 = s[:, None] * d1
    p2 = c2 + u[:, None] * d2
    return 0.5 * (p1 + p2), np.linalg.norm(p1 - p2, axis=1)


@dataclass(frozen=True, eq=False)
class Measurement:
    """Triangulated points, the distances between them, and their uncertainties.

    Attributes
    ----------
    points : (N, 3) float64, left camera frame, target units.
    ray_gap : (N,) float64, see ``triangulate_midpoint``.
    distances : (N, N) float64, distance between every pair of points (symmetric, zero diagonal);
        consecutive distances along a polyline are ``np.diagonal(distances, 1)``.
    point_covariance : (N, 3, 3) float64, covariance of each point from the pixel perturbation.
    point_sigma_px, distance_sigma_px : (N,), (N, N) float64; the part from pixel errors.
    point_sigma_rig, distance_sigma_rig : (N,), (N, N) float64; the part from the rig's calibration
        covariance (zeros when the rig carries none). Point sigmas are ``sqrt(trace(covariance))``.
    point_sigma, distance_sigma : the two parts combined as root sum of squares (independent sources).
    """

    points: np.ndarray
    ray_gap: np.ndarray
    distances: np.ndarray
    point_covariance: np.ndarray
    point_sigma_px: np.ndarray
    distance_sigma_px: np.ndarray
    point_sigma_rig: np.ndarray
    distance_sigma_rig: np.ndarray

    @property
    def point_sigma(self) -> np.ndarray:
        return np.hypot(self.point_sigma_px, self.point_sigma_rig)

    @property
    def distance_sigma(self) -> np.ndarray:
        return np.hypot(self.distance_sigma_px, self.distance_sigma_rig)


def measure(rig: StereoRig, left_px: np.ndarray, right_px: np.ndarray, perturb_px: float = 0.5) -> Measurement:
    """Triangulate N marked points, the distances between all pairs, and how far they can be trusted.

    Pixel part: each of the four image coordinates of a point is moved by ``+-perturb_px`` (central
    difference); the changes of the point, taken as independent, give its covariance, and the changes
    projected on the direction between two points give the distance's variance (first-order
    propagation of a ``perturb_px`` standard error per coordinate). Rig part: the same propagation of
    ``rig.covariance`` over ``(rvec, T)``; it is shared by all points, so it is correlated between them
    and propagated through each distance as a whole.

    Parameters
    ----------
    rig : StereoRig
    left_px, right_px : (N, 2) float64, pixel (x, y) of the same points in each image.
    perturb_px : the pixel standard error assumed for each marked coordinate, > 0.

    Returns
    -------
    Measurement
    """
    if not np.isfinite(perturb_px) or perturb_px <= 0:
        raise ValueError(f"perturb_px must be a positive number of pixels, got {perturb_px}")
    points, gap = triangulate_midpoint(rig, left_px, right_px)
    diff = points[:, None, :] - points[None, :, :]
    distances = np.linalg.norm(diff, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.where(distances[..., None] > 0, diff / distances[..., None], 0.0)  # (N, N, 3) from j to i
    deltas = _pixel_deltas(rig, np.asarray(left_px, float), np.asarray(right_px, float), perturb_px)  # (4, N, 3)
    cov = np.einsum("cni,cnj->nij", deltas, deltas)
    along = np.einsum("ijk,cik->cij", unit, deltas)  # (4, N, N): change of d_ij from point i's coordinates
    dist_var_px = np.sum(along**2, axis=0) + np.sum(along.transpose(0, 2, 1) ** 2, axis=0)
    point_rig, dist_rig = _rig_sigmas(rig, np.asarray(left_px, float), np.asarray(right_px, float), unit)
    return Measurement(
        points, gap, distances, cov, np.sqrt(np.trace(cov, axis1=1, axis2=2)), np.sqrt(dist_var_px), point_rig, dist_rig
    )


def _pixel_deltas(rig: StereoRig, left_px: np.ndarray, right_px: np.ndarray, h: float) -> np.ndarray:
    """(4, N, 3): half the change of each point when one of its 4 coordinates moves from -h to +h."""
    both = np.concatenate([left_px, right_px], axis=1)
    out = np.empty((4, len(both), 3))
    for c in range(4):  # all points at once, one coordinate at a time
        step = np.zeros(4)
        step[c] = h
        plus, _ = triangulate_midpoint(rig, (both + step)[:, :2], (both + step)[:, 2:])
        minus, _ = triangulate_midpoint(rig, (both - step)[:, :2], (both - step)[:, 2:])
        out[c] = 0.5 * (plus - minus)
    return out


def _rig_sigmas(
    rig: StereoRig, left_px: np.ndarray, right_px: np.ndarray, unit: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Point and distance standard deviations from ``rig.covariance``, by central differences."""
    n = len(left_px)
    if rig.covariance is None:
        return np.zeros(n), np.zeros((n, n))
    rvec = vector_from_rotation(rig.R)
    steps = np.concatenate([np.full(3, 1e-6), np.full(3, 1e-6 * rig.baseline)])
    jac = np.empty((_RIG_PARAMS, n, 3))
    for a in range(_RIG_PARAMS):
        shifted = []
        for sign in (1.0, -1.0):
            p = np.concatenate([rvec, rig.T])
            p[a] += sign * steps[a]
            shifted.append(
                triangulate_midpoint(rig.replace_pose(rotation_from_vector(p[:3]), p[3:]), left_px, right_px)[0]
            )
        jac[a] = (shifted[0] - shifted[1]) / (2.0 * steps[a])
    cov = rig.covariance
    point_var = np.einsum("ani,ab,bni->n", jac, cov, jac)
    grad = np.einsum("ijk,aik->aij", unit, jac) - np.einsum("ijk,ajk->aij", unit, jac)  # d d_ij / d param
    dist_var = np.einsum("aij,ab,bij->ij", grad, cov, grad)
    return np.sqrt(np.maximum(point_var, 0.0)), np.sqrt(np.maximum(dist_var, 0.0))
