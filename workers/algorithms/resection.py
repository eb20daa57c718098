"""A calibrated camera's pose from control points on a plane, and orthographic rectification onto that plane.

Model frame: the plane is Z = 0, X and Y in mm (a specimen: X right, Y down the plate). Poses follow the
project's convention ``X_cam = R (X - C)`` (see ``camera.py``).

The pose is first found by ``cv2.solvePnP`` (IPPE, Collins & Bartoli, IJCV 2014) on the undistorted,
normalised control points, then refined by Levenberg-Marquardt over the six pose parameters on the
pixel residuals of the full camera model (``scipy.optimize.least_squares``), so that the distortion
is honoured in either convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from workers.algorithms.camera import Camera, rotation_from_vector, vector_from_rotation, world_to_camera


@dataclass(frozen=True)
class Resection:
    """A photo's pose and how well its control points fit it."""

    R: np.ndarray  # (3, 3) world -> camera rotation
    C: np.ndarray  # (3,) projection centre, model mm
    residuals_px: np.ndarray  # (N, 2) projected minus marked pixel, px
    residuals_mm: np.ndarray  # (N, 2) marked pixel's ray on the plane minus the model point, (X, Y) mm

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
    ideal = camera.pixel_to_normalised(pixels)
    ok, rvec, tvec = cv2.solvePnP(model, ideal.reshape(-1, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("solvePnP found no pose for these control points")

    def residuals(params: np.ndarray) -> np.ndarray:
        R = rotation_from_vector(params[:3])
        return (camera.project(model @ R.T + params[3:]) - pixels).ravel()

    fit = least_squares(residuals, np.concatenate([rvec.ravel(), tvec.ravel()]), method="lm", x_scale="jac")
    R = rotation_from_vector(fit.x[:3])
    C = -R.T @ fit.x[3:]
    on_plane = plane_points(camera, R, C, pixels)
    return Resection(R, C, fit.fun.reshape(-1, 2), on_plane - model[:, :2])


def plane_points(camera: Camera, R: np.ndarray, C: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Where the rays of ``pixels`` (N, 2) meet the plane Z = 0: (N, 2) (X, Y) mm; NaN for rays that miss it."""
    rays = camera.unproject(pixels) @ R  # R.T @ ray per row: the rays in the model frame
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -C[2] / rays[:, 2]
    t = np.where(t > 0, t, np.nan)
    return C[:2] + t[:, None] * rays[:, :2]


def rectification_maps(camera: Camera, R: np.ndarray, C: np.ndarray, shape: tuple[int, int],
                       mm_per_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.remap`` maps that render a photo onto the plane, and how well the photo sees each point.

    Output pixel (col, row) is the model point (col * mm_per_px, row * mm_per_px, 0): its centre, as in
    ``crack_geometry``.

    Parameters
    ----------
    camera, R, C : the oriented camera that took the photo.
    shape : (rows, cols) of the output raster.
    mm_per_px : output resolution, mm per pixel.

    Returns
    -------
    map_x, map_y : (rows, cols) float32 photo pixel (x, y) of each output pixel, with distortion.
    density : (rows, cols) float32 photo pixels per mm^2 of plane at each output pixel
        (``f^2 cos(incidence) / distance^2``); 0 where the photo does not see the point.
    """
    rows, cols = shape
    X, Y = np.meshgrid(np.arange(cols, dtype=np.float64) * mm_per_px, np.arange(rows, dtype=np.float64) * mm_per_px)
    points = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    cam = world_to_camera(points, R, C)
    front = cam[:, 2] > 1e-9
    uv = np.full((len(points), 2), -1e6)
    uv[front] = camera.project(cam[front])
    seen = front & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)
    distance = np.linalg.norm(points - C, axis=1)
    cos_incidence = np.abs(C[2]) / distance  # the plane's normal is Z
    density = np.where(seen, camera.fx * camera.fy * cos_incidence / distance**2, 0.0)
    return (uv[:, 0].reshape(shape).astype(np.float32), uv[:, 1].reshape(shape).astype(np.float32),
            density.reshape(shape).astype(np.float32))


def pose_json(R: np.ndarray, C: np.ndarray) -> dict[str, list[float]]:
    """A pose as JSON: rotation vector (radians) and centre (mm)."""
    return {"rotation_vector": vector_from_rotation(R).tolist(), "centre_mm": np.asarray(C, float).tolist()}


def pose_from_json(data: dict[str, list[float]]) -> tuple[np.ndarray, np.ndarray]:
    return rotation_from_vector(np.array(data["rotation_vector"])), np.array(data["centre_mm"], dtype=np.float64)
