"""A camera's intrinsics and distortion from views of a planar target.

Zhang (2000) initialisation (``cv2.initCameraMatrix2D`` + ``cv2.solvePnP`` per view), then
Levenberg-Marquardt on the reprojection error over the intrinsics, the free distortion terms and every
view's pose, as ``cv2.calibrateCamera`` does, in either convention of ``geometry.camera``. RMS errors follow
``cv2.calibrateCamera``: ``sqrt(mean over points of |projected - observed|^2)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.algorithms.calibration.solver import (
    POSE,
    View,
    as_views,
    camera_centres,
    covariance,
    free_distortion_terms,
    pose_from_target,
    poses_from_params,
    solve_lm,
    split_by_counts,
    transform_points,
)
from workers.algorithms.geometry import Camera, Convention

INTRINSICS = ("fx", "fy", "cx", "cy")


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """A calibrated camera with the evidence for it.

    Attributes
    ----------
    camera : Camera, in the requested convention.
    rotations, centres : (V, 3, 3), (V, 3) float64; view v's camera pose in the target frame,
        ``X_cam = R @ (X_target - C)``.
    rms_px : overall RMS reprojection error (``cv2.calibrateCamera``'s definition).
    residuals : per view, (N_v, 2) float64 projected minus observed pixel.
    errors : per view, (N_v,) float64 pixel error of each point, ``|residual|``.
    parameter_names : names of the estimated camera parameters, in ``covariance`` order.
    std : parameter name -> standard deviation (px for fx..cy, unitless for distortion terms).
    covariance : (P, P) float64 over ``parameter_names``.
    pose_std : (V, 6) float64 standard deviations of (rvec [rad], tvec [target units]) per view.
    """

    camera: Camera
    rotations: np.ndarray
    centres: np.ndarray
    rms_px: float
    residuals: list[np.ndarray]
    errors: list[np.ndarray]
    parameter_names: tuple[str, ...]
    std: dict[str, float]
    covariance: np.ndarray
    pose_std: np.ndarray

    @property
    def view_rms_px(self) -> np.ndarray:
        """(V,) RMS error of each view."""
        return np.array([np.sqrt(np.mean(e**2)) for e in self.errors])

    def worst_points(self, n: int = 10) -> list[tuple[int, int, float]]:
        """The ``n`` largest point errors as (view, point index, error px), largest first."""
        flat = [(v, i, float(e)) for v, errs in enumerate(self.errors) for i, e in enumerate(errs)]
        return sorted(flat, key=lambda item: -item[2])[:n]


def calibrate_camera(
    views: Sequence[View],
    width: int,
    height: int,
    convention: Convention = "distort_ideal",
    terms: Sequence[str] = ("k1", "k2", "t1", "t2", "k3"),
    initial: Camera | None = None,
) -> CalibrationResult:
    """Intrinsics, distortion and view poses from several views of a known target (Zhang 2000).

    Follows ``cv2.calibrateCamera`` (no flags): ``cv2.initCameraMatrix2D`` and ``cv2.solvePnP`` per
    view give the start, then LM minimises the reprojection error of all points over fx, fy, cx, cy,
    the ``terms`` and every view's pose. A ``restore_ideal`` camera is solved in its own convention
    (its projection inverts the correction polynomial), not converted from an OpenCV fit.

    Parameters
    ----------
    views : sequence of (object points (N, 3) float64 target frame, image points (N, 2) float64
        pixel (x, y)); at least 3 views of at least 6 points. A non-planar target needs ``initial``
        (Zhang's start assumes Z = 0).
    width, height : image size, px.
    convention : "distort_ideal" (OpenCV) or "restore_ideal".
    terms : distortion terms to estimate, from k1, k2, k3, t1, t2; the others keep their ``initial``
        value (0 without one).
    initial : optional starting camera (e.g. a previous calibration); converted to ``convention``.

    Returns
    -------
    CalibrationResult
    """
    data = as_views(views, 2)
    free = free_distortion_terms(terms, convention)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width} x {height}")
    start = _initial_camera(data, width, height, convention, initial)
    names = INTRINSICS + free
    obj = np.concatenate([v[0] for v in data])
    img = np.concatenate([v[1] for v in data])
    counts = np.array([len(v[0]) for v in data])
    view = np.repeat(np.arange(len(data)), counts)
    if 2 * len(obj) <= len(names) + POSE * len(data):
        raise ValueError("too few points for the number of unknowns; add views or points")

    def residuals(x: np.ndarray) -> np.ndarray:
        camera = start.replace(**dict(zip(names, map(float, x[: len(names)]), strict=True)))
        rotations, translations = poses_from_params(x[len(names) :])
        return (camera.project(transform_points(rotations, translations, obj, view)) - img).ravel()

    x0 = np.concatenate([[getattr(start, n) for n in names], *[pose_from_target(start, v[0], v[1]) for v in data]])
    x, res, jac = solve_lm(residuals, x0, len(names), np.repeat(view, 2))
    return _calibration_result(start, names, x, res, jac, counts)


def _initial_camera(
    data: list[list[np.ndarray]], width: int, height: int, convention: Convention, initial: Camera | None
) -> Camera:
    """``initial`` in ``convention``, or Zhang's closed-form camera matrix without distortion.

    Zhang's start ignores distortion (f is 20-100 % off with 10-20 % barrel distortion at the frame
    corners), yet LM recovers from it on every synthetic lens tried (k1 down to -0.42 at f = 1000 px,
    3 to 15 views), as in OpenCV, so no distortion-aware start is added.
    """
    if initial is not None:
        return initial.with_convention(convention).replace(width=int(width), height=int(height))
    if any(np.abs(v[0][:, 2]).max() > 1e-9 * max(np.abs(v[0]).max(), 1.0) for v in data):
        raise ValueError("a non-planar target (Z != 0) needs an initial camera")
    K = cv2.initCameraMatrix2D(
        [v[0].astype(np.float32) for v in data], [v[1].astype(np.float32) for v in data], (int(width), int(height))
    )
    return Camera(
        int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), convention=convention
    )


def _calibration_result(
    start: Camera, names: tuple[str, ...], x: np.ndarray, res: np.ndarray, jac: np.ndarray, counts: np.ndarray
) -> CalibrationResult:
    m = len(names)
    camera = start.replace(**dict(zip(names, map(float, x[:m]), strict=True)))
    rotations, translations = poses_from_params(x[m:])
    residual = res.reshape(-1, 2)
    errors = np.linalg.norm(residual, axis=1)
    cov = covariance(jac, res)
    std = np.sqrt(np.diag(cov))
    return CalibrationResult(
        camera=camera,
        rotations=rotations,
        centres=camera_centres(rotations, translations),
        rms_px=float(np.sqrt(np.mean(errors**2))),
        residuals=split_by_counts(residual, counts),
        errors=split_by_counts(errors, counts),
        parameter_names=names,
        std=dict(zip(names, map(float, std[:m]), strict=True)),
        covariance=cov[:m, :m],
        pose_std=std[m:].reshape(-1, POSE),
    )
