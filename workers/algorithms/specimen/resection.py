"""A calibrated camera's pose from control points on a plate or on a curved specimen.

Model frame: mm; a plate is Z = 0 with X right and Y down. Poses follow the project's convention
``X_cam = R (X - C)`` (see ``camera.py``).

The pose is first found by ``cv2.solvePnP`` (IPPE for a plate, Collins & Bartoli, IJCV 2014; SQPnP for
points in space) on the undistorted,
normalised control points, then refined by Levenberg-Marquardt over the six pose parameters on the
pixel residuals of the full camera model (``scipy.optimize.least_squares``), so that the distortion
is honoured in either convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation


@dataclass(frozen=True)
class Resection:
    """A photo's pose and how well its control points fit it."""

    R: np.ndarray  # (3, 3) world -> camera rotation
    C: np.ndarray  # (3,) projection centre, model mm
    residuals_px: np.ndarray  # (N, 2) projected minus marked pixel, px
    # (N, 2) on a plate: the marked pixel's ray on the plane minus the model point, (X, Y) mm;
    # (N, 3) otherwise: the ray's nearest point to the model point minus the model point, (X, Y, Z) mm
    residuals_mm: np.ndarray

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals_px**2, axis=1))))

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals_mm**2, axis=1))))


def resect_plane(camera: Camera, model: np.ndarray, pixels: np.ndarray) -> Resection:
    """The pose of ``camera`` from control points on the plane Z = 0.

    Parameters
    ----------
    camera : the calibrated camera (distortion in either convention).
    model : (N, 3) float64 model (X, Y, Z) mm with Z = 0, N >= 4, not all on one line.
    pixels : (N, 2) float64 observed pixel (x, y) of the same points.

    Returns
    -------
    The refined pose and the per-point residuals in px and on the plane in mm.
    """
    model = np.asarray(model, dtype=np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(model) < 4 or len(model) != len(pixels):
        raise ValueError(f"need at least 4 model/pixel pairs of equal count, got {len(model)} and {len(pixels)}")
    R, C, residuals_px = _refined_pose(camera, model, pixels, cv2.SOLVEPNP_IPPE)
    on_plane = plane_points(camera, R, C, pixels)
    return Resection(R, C, residuals_px, on_plane - model[:, :2])


def resect_points(camera: Camera, model: np.ndarray, pixels: np.ndarray) -> Resection:
    """The pose of ``camera`` from control points anywhere in space (on a curved specimen).

    As :func:`resect_plane`, with the start from SQPnP (Terzakis & Lourakis, ECCV 2020), which needs no
    plane. ``residuals_mm`` is (N, 3): from the model point to the nearest point of the marked pixel's ray.
    """
    model = np.asarray(model, dtype=np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(model) < 4 or len(model) != len(pixels):
        raise ValueError(f"need at least 4 model/pixel pairs of equal count, got {len(model)} and {len(pixels)}")
    R, C, residuals_px = _refined_pose(camera, model, pixels, cv2.SOLVEPNP_SQPNP)
    rays = camera.unproject(pixels) @ R  # R.T @ ray per row: unit rays in the model frame
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", model - C, rays)
    return Resection(R, C, residuals_px, C + along[:, None] * rays - model)


def _refined_pose(
    camera: Camera, model: np.ndarray, pixels: np.ndarray, method: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A first pose by ``cv2.solvePnP(method)`` on normalised points, refined by LM on the pixel residuals
    of the full camera model. Returns R, C and the (N, 2) residuals, px."""
    ideal = camera.pixel_to_normalised(pixels)
    ok, rvec, tvec = cv2.solvePnP(model, ideal.reshape(-1, 1, 2), np.eye(3), None, flags=method)
    if not ok:
        raise ValueError("solvePnP found no pose for these control points")

    def residuals(params: np.ndarray) -> np.ndarray:
        R = rotation_from_vector(params[:3])
        return (camera.project(model @ R.T + params[3:]) - pixels).ravel()

    fit = least_squares(residuals, np.concatenate([rvec.ravel(), tvec.ravel()]), method="lm", x_scale="jac")
    R = rotation_from_vector(fit.x[:3])
    return R, -R.T @ fit.x[3:], fit.fun.reshape(-1, 2)


def plane_points(camera: Camera, R: np.ndarray, C: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Where the rays of ``pixels`` (N, 2) meet the plane Z = 0: (N, 2) (X, Y) mm; NaN for rays that miss it."""
    rays = camera.unproject(pixels) @ R  # R.T @ ray per row: the rays in the model frame
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -C[2] / rays[:, 2]
    t = np.where(t > 0, t, np.nan)
    return C[:2] + t[:, None] * rays[:, :2]


def pose_json(R: np.ndarray, C: np.ndarray) -> dict[str, list[float]]:
    """A pose as JSON: rotation vector (radians) and centre (mm)."""
    return {"rotation_vector": vector_from_rotation(R).tolist(), "centre_mm": np.asarray(C, float).tolist()}


def pose_from_json(data: dict[str, list[float]]) -> tuple[np.ndarray, np.ndarray]:
    return rotation_from_vector(np.array(data["rotation_vector"])), np.array(data["centre_mm"], dtype=np.float64)
