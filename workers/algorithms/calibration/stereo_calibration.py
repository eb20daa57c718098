"""The relative pose of two calibrated cameras with their intrinsics held fixed, like
``cv2.stereoCalibrate(..., flags=cv2.CALIB_FIX_INTRINSIC)``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.algorithms.calibration.solver import (
    POSE,
    StereoView,
    as_views,
    camera_centres,
    covariance,
    pose_from_target,
    poses_from_params,
    solve_lm,
    split_by_counts,
    transform_points,
)
from workers.algorithms.calibration.stereo_rig import StereoRig
from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation


@dataclass(frozen=True, eq=False)
class StereoCalibrationResult:
    """Relative pose of a calibrated camera pair.

    Attributes
    ----------
    rig : StereoRig with ``covariance`` of (rvec, T).
    R, T : (3, 3), (3,) float64, ``X_right = R @ X_left + T`` (OpenCV's convention).
    baseline, baseline_std : ``|T|`` and its standard deviation, target units.
    rms_px : RMS reprojection error over both images (``cv2.stereoCalibrate``'s definition).
    residuals_left, residuals_right : per view, (N_v, 2) projected minus observed pixel, in the order given.
    errors_left, errors_right : per view, (N_v,) pixel errors.
    rotations, centres : (V, 3, 3), (V, 3) pose of the left camera in each view's target frame.
    covariance : (6, 6) float64 over (rvec of R [rad], T).
    reversed_views : views whose right-image points were taken in reverse order, because a
        half-turn-symmetric board was detected in opposite orders in the two images.
    """

    rig: StereoRig
    rms_px: float
    residuals_left: list[np.ndarray]
    residuals_right: list[np.ndarray]
    errors_left: list[np.ndarray]
    errors_right: list[np.ndarray]
    rotations: np.ndarray
    centres: np.ndarray
    covariance: np.ndarray
    reversed_views: tuple[int, ...]

    @property
    def R(self) -> np.ndarray:
        return self.rig.R

    @property
    def T(self) -> np.ndarray:
        return self.rig.T

    @property
    def baseline(self) -> float:
        return self.rig.baseline

    @property
    def baseline_std(self) -> float:
        unit = self.T / self.baseline
        return float(np.sqrt(unit @ self.covariance[3:, 3:] @ unit))


def stereo_calibrate(left: Camera, right: Camera, views: Sequence[StereoView]) -> StereoCalibrationResult:
    """Relative pose of two calibrated cameras from views of a target seen by both.

    Like ``cv2.stereoCalibrate`` with ``cv2.CALIB_FIX_INTRINSIC``: both cameras are held fixed; LM
    estimates ``(R, T)`` and the target pose of every view (in the left camera) from the reprojection
    errors in both images. The start is the consensus of the per-view relative poses from
    ``cv2.solvePnP``; a view whose right points only agree with it in reverse order (a symmetric board
    detected the other way round) is used reversed and listed in ``reversed_views``.

    Parameters
    ----------
    left, right : calibrated cameras (either convention).
    views : sequence of (object points (N, 3), left pixels (N, 2), right pixels (N, 2)), the same
        target points in both images; at least 3 views of at least 6 points.

    Returns
    -------
    StereoCalibrationResult
    """
    data = as_views(views, 3)
    rig0, flipped = _initial_rig(left, right, data)
    for v in flipped:
        data[v][2] = data[v][2][::-1]
    obj = np.concatenate([v[0] for v in data])
    lpx, rpx = (np.concatenate([v[k] for v in data]) for k in (1, 2))
    counts = np.array([len(v[0]) for v in data])
    view = np.repeat(np.arange(len(data)), counts)

    def residuals(x: np.ndarray) -> np.ndarray:
        rotations, translations = poses_from_params(x[POSE:])
        in_left = transform_points(rotations, translations, obj, view)
        in_right = in_left @ rotation_from_vector(x[:3]).T + x[3:POSE]
        return np.concatenate([(left.project(in_left) - lpx).ravel(), (right.project(in_right) - rpx).ravel()])

    x0 = np.concatenate([rig0, *[pose_from_target(left, v[0], v[1]) for v in data]])
    x, res, jac = solve_lm(residuals, x0, POSE, np.tile(np.repeat(view, 2), 2))
    return _stereo_result(left, right, x, res, jac, counts, flipped)


def _initial_rig(left: Camera, right: Camera, data: list[list[np.ndarray]]) -> tuple[np.ndarray, list[int]]:
    """Starting (rvec, T) of the rig: the per-view relative pose most views agree with; and the views
    whose right points agree with it only when reversed."""
    poses = [_relative_pose(left, right, v[0], v[1], v[2]) for v in data]
    votes = [sum(_agree(p, q) for q in poses) for p in poses]
    best = poses[int(np.argmax(votes))]
    flipped = []
    for v, (obj, lpx, rpx) in enumerate(data):
        symmetric = np.allclose(obj[::-1], 2.0 * obj.mean(axis=0) - obj, atol=1e-9 * max(np.abs(obj).max(), 1.0))
        if not _agree(poses[v], best) and symmetric and _agree(_relative_pose(left, right, obj, lpx, rpx[::-1]), best):
            flipped.append(v)
    return best, flipped


def _relative_pose(left: Camera, right: Camera, obj: np.ndarray, lpx: np.ndarray, rpx: np.ndarray) -> np.ndarray:
    """(rvec, T) of ``X_right = R X_left + T`` from one view's two PnP poses."""
    pl, pr = pose_from_target(left, obj, lpx), pose_from_target(right, obj, rpx)
    Rl, Rr = rotation_from_vector(pl[:3]), rotation_from_vector(pr[:3])
    R = Rr @ Rl.T
    return np.concatenate([vector_from_rotation(R), pr[3:] - R @ pl[3:]])


def _agree(a: np.ndarray, b: np.ndarray, degrees: float = 5.0, fraction: float = 0.2) -> bool:
    """Whether two rig poses (rvec, T) are within ``degrees`` and ``fraction`` of the baseline."""
    rel = rotation_from_vector(a[:3]) @ rotation_from_vector(b[:3]).T
    angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(angle < degrees and np.linalg.norm(a[3:] - b[3:]) < fraction * np.linalg.norm(b[3:]))


def _stereo_result(
    left: Camera, right: Camera, x: np.ndarray, res: np.ndarray, jac: np.ndarray, counts: np.ndarray, flipped: list[int]
) -> StereoCalibrationResult:
    cov = covariance(jac, res)[:POSE, :POSE]
    rig = StereoRig(left, right, rotation_from_vector(x[:3]), x[3:POSE], 0.5 * (cov + cov.T))
    rotations, translations = poses_from_params(x[POSE:])
    both = res.reshape(2, -1, 2)
    res_left, res_right = split_by_counts(both[0], counts), split_by_counts(both[1], counts)
    for v in flipped:  # report in the order the caller gave the points
        res_right[v] = res_right[v][::-1]
    errors = np.linalg.norm(both, axis=2)
    return StereoCalibrationResult(
        rig=rig,
        rms_px=float(np.sqrt(np.mean(errors**2))),
        residuals_left=res_left,
        residuals_right=res_right,
        errors_left=[np.linalg.norm(r, axis=1) for r in res_left],
        errors_right=[np.linalg.norm(r, axis=1) for r in res_right],
        rotations=rotations,
        centres=camera_centres(rotations, translations),
        covariance=rig.covariance if rig.covariance is not None else cov,
        reversed_views=tuple(flipped),
    )
