"""What every calibration solve shares: validated target views, a Levenberg-Marquardt solve with a
block Jacobian, parameter covariances, and the poses of target views.

All solves are MINPACK's LM (``scipy.optimize.least_squares(method="lm")``) with a central-difference
Jacobian that perturbs one pose parameter of every view at once (views do not share residuals), so a
Jacobian costs ``2 * (globals + 6)`` residual evaluations whatever the number of views. Parameter
covariances are ``sigma^2 (J^T J)^-1`` with ``sigma^2`` the residual variance per image coordinate.

Pixel convention: OpenCV's (integer coordinates at pixel centres). Poses: ``X_cam = R @ (X - C)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np
from scipy.optimize import least_squares

from workers.algorithms.calibration.limits import MIN_POINTS, MIN_VIEWS
from workers.algorithms.geometry import CONVENTIONS, DISTORTION_TERMS, Camera, rotation_from_vector

View = tuple[np.ndarray, np.ndarray]  # object points (N, 3), image points (N, 2)
StereoView = tuple[np.ndarray, np.ndarray, np.ndarray]  # object (N, 3), left (N, 2), right (N, 2)

POSE = 6  # rvec, tvec


def block_jacobian(
    fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, n_global: int, row_block: np.ndarray
) -> np.ndarray:
    """Central-difference Jacobian of ``fun`` at ``x``: ``n_global`` dense columns, then blocks of ``POSE``
    columns of which block ``b`` only touches the rows with ``row_block == b``."""
    n_blocks = (len(x) - n_global) // POSE
    rows = np.arange(len(row_block))
    jac = np.zeros((len(row_block), len(x)))
    groups = [np.array([c]) for c in range(n_global)]
    groups += [n_global + POSE * np.arange(n_blocks) + j for j in range(POSE)] if n_blocks else []
    for cols in groups:
        h = 1e-6 * np.maximum(1.0, np.abs(x[cols]))
        up, down = x.copy(), x.copy()
        up[cols] += h
        down[cols] -= h
        diff = fun(up) - fun(down)
        if cols[0] < n_global:
            jac[:, cols[0]] = diff / (2.0 * h[0])
        else:  # one column of every block at once: each row goes to its own block's column
            jac[rows, cols[row_block]] = diff / (2.0 * h[row_block])
    return jac


def solve_lm(
    fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, n_global: int, row_block: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt (MINPACK) from ``x0``; returns (x, residuals, Jacobian at x)."""

    def jac(x: np.ndarray) -> np.ndarray:
        return block_jacobian(fun, x, n_global, row_block)

    result = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12)
    return result.x, result.fun, result.jac  # scipy evaluates ``jac`` at the solution for method="lm"


def covariance(jac: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """``sigma^2 (J^T J)^-1``; the normal matrix is column-equilibrated first (fx ~ 1e3 px next to k3 ~ 1e-2
    would otherwise cost precision), and pseudo-inverted where a direction is not observable."""
    dof = max(len(residuals) - jac.shape[1], 1)
    sigma2 = float(residuals @ residuals) / dof
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    normal = (jac / scale).T @ (jac / scale)
    return np.linalg.pinv(normal, rcond=1e-12, hermitian=True) / np.outer(scale, scale) * sigma2


def check_points(obj: np.ndarray, pts: list[np.ndarray], index: int) -> None:
    if obj.ndim != 2 or obj.shape[1] != 3:
        raise ValueError(f"view {index}: object points must be (N, 3), got {obj.shape}")
    for p in pts:
        if p.shape != (len(obj), 2):
            raise ValueError(
                f"view {index}: image points must be (N, 2) with N = {len(obj)} object points, got {p.shape}"
            )
    if not all(np.all(np.isfinite(a)) for a in (obj, *pts)):
        raise ValueError(f"view {index}: points must be finite numbers")
    if len(obj) < MIN_POINTS:
        raise ValueError(f"view {index} has {len(obj)} points; each view needs at least {MIN_POINTS}")


def as_views(views: Sequence[Sequence[np.ndarray]], arity: int) -> list[list[np.ndarray]]:
    """Views as float64 arrays, validated; ``ValueError`` naming the first bad view."""
    if len(views) < MIN_VIEWS:
        raise ValueError(f"calibration needs at least {MIN_VIEWS} views of the target, got {len(views)}")
    out = []
    for index, view in enumerate(views):
        if len(view) != arity:
            raise ValueError(f"view {index}: expected {arity} arrays (object points and image points), got {len(view)}")
        arrays = [np.asarray(a, dtype=np.float64) for a in view]
        check_points(arrays[0], arrays[1:], index)
        out.append(arrays)
    return out


def split_by_counts(values: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    return np.split(values, np.cumsum(counts)[:-1])


def poses_from_params(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V * 6,) rvec/tvec pairs -> rotations (V, 3, 3) and translations (V, 3) (``X_cam = R X + t``)."""
    p = params.reshape(-1, POSE)
    return np.stack([rotation_from_vector(r) for r in p[:, :3]]), p[:, 3:]


def transform_points(rotations: np.ndarray, translations: np.ndarray, obj: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Every point through its own view's pose, (N, 3) -> (N, 3)."""
    return np.einsum("nij,nj->ni", rotations[view], obj) + translations[view]


def camera_centres(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Camera centres ``C = -R^T t`` of the project's pose convention, (V, 3)."""
    return -np.einsum("vji,vj->vi", rotations, translations)


def pose_from_target(camera: Camera, obj: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Pose (rvec, tvec) of a target seen by a calibrated camera (distortion removed first)."""
    ideal = camera.pixel_to_normalised(px) * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    ok, rvec, tvec = cv2.solvePnP(obj, ideal, camera.matrix(), None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("could not estimate the pose of a view; check its point correspondences")
    return np.concatenate([rvec.ravel(), tvec.ravel()])


def free_distortion_terms(terms: Sequence[str], convention: str) -> tuple[str, ...]:
    """The distortion terms to solve for, validated and in canonical order."""
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; known: {CONVENTIONS}")
    unknown = [t for t in terms if t not in DISTORTION_TERMS]
    if unknown or len(set(terms)) != len(terms):
        raise ValueError(f"terms must be distinct names from {DISTORTION_TERMS}, got {tuple(terms)}")
    return tuple(t for t in DISTORTION_TERMS if t in terms)
