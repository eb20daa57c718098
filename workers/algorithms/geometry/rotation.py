"""Rotations and poses: Rodrigues vectors to matrices and back, and the project's pose convention
``X_cam = R @ (X_world - C)`` (camera axes x right, y down, z forward, as OpenCV). NumPy only."""

from __future__ import annotations

import math

import numpy as np


def rotation_from_vector(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) (axis times angle in radians) -> (3, 3), like ``cv2.Rodrigues``."""
    return rotations_from_vectors(np.asarray(rvec, dtype=np.float64).reshape(1, 3))[0]


def rotations_from_vectors(rvecs: np.ndarray) -> np.ndarray:
    """Rodrigues for many vectors at once: (F, 3) -> (F, 3, 3), the one Rodrigues formula of the project."""
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    # sin(t)/t and (1 - cos t)/t^2 with their Taylor limits near 0
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def vector_from_rotation(R: np.ndarray) -> np.ndarray:
    """Inverse Rodrigues: (3, 3) rotation -> rotation vector (3,), stable near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    cos = min(max((np.trace(R) - 1.0) / 2.0, -1.0), 1.0)
    theta = math.acos(cos)
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if theta < 1e-6:
        return vee
    if math.pi - theta > 1e-4:
        return vee * (theta / math.sin(theta))
    # near pi: the axis is the column of (R + I) / 2 with the largest norm, its sign from vee
    sym = (R + np.eye(3)) / 2.0
    axis = sym[:, int(np.argmax(np.diag(sym)))]
    axis = axis / np.linalg.norm(axis)
    if axis @ vee < 0:
        axis = -axis
    return axis * theta


def world_to_camera(points: np.ndarray, R: np.ndarray, C: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> camera frame (N, 3) for the pose ``X_cam = R (X - C)``."""
    # einsum, not ``@ R.T``: BLAS takes ~10x longer on an (N, 3) x (3, 3) product with millions of rows
    return np.einsum(
        "ij,kj->ik",
        np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(C).ravel(),
        np.asarray(R, dtype=np.float64),
    )
