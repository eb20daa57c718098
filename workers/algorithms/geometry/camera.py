"""Pinhole camera with Brown distortion, in the two conventions of our source documents.

* ``distort_ideal`` (OpenCV, Brown 1971): the ideal normalised projection ``(X/Z, Y/Z)`` is distorted
  by the Brown polynomial, then mapped to pixels by the camera matrix. Projection is closed-form;
  going from a pixel back to a ray needs the polynomial inverted (Newton).
* ``restore_ideal`` (the photogrammetric habit): the polynomial is a *correction* applied to the
  observed pixel offset from the principal point, normalised by the focal length, and restores the
  ideal projection. Going from a pixel to a ray is closed-form; projection needs the inversion.

The Brown polynomial is the same in both (radial k1..k3, tangential t1, t2 = OpenCV's p1, p2); only
the side it is applied on differs, so one camera can be converted to the other convention by a
linear least-squares refit (``Camera.with_convention``).

Pose convention of the whole project: ``X_cam = R @ (X_world - C)``; camera axes x right, y down,
z forward (OpenCV). NumPy only: the API imports this module to answer measurement requests.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

Convention = Literal["distort_ideal", "restore_ideal"]
CONVENTIONS: tuple[str, ...] = get_args(Convention)
DISTORTION_TERMS = ("k1", "k2", "k3", "t1", "t2")


def apply_brown(xy: np.ndarray, k: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The Brown polynomial on normalised coordinates, as ``cv2.projectPoints`` applies it.

    Parameters
    ----------
    xy : (N, 2) float64, normalised (x, y)
    k : (3,) radial k1, k2, k3
    t : (2,) tangential t1, t2 (OpenCV's p1, p2)

    Returns
    -------
    (N, 2) float64: ``xy * (1 + k1 r^2 + k2 r^4 + k3 r^6) + tangential(xy)``
    """
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    xd = x * radial + 2.0 * t[0] * x * y + t[1] * (r2 + 2.0 * x * x)
    yd = y * radial + t[0] * (r2 + 2.0 * y * y) + 2.0 * t[1] * x * y
    return np.stack([xd, yd], axis=1)


def brown_jacobian(xy: np.ndarray, k: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``d apply_brown / d xy`` as (N, 2, 2): rows output (x, y), columns input (x, y)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    g = k[0] + r2 * (2.0 * k[1] + 3.0 * r2 * k[2])  # d radial / d r2
    cross = 2.0 * g * x * y + 2.0 * t[0] * x + 2.0 * t[1] * y
    jac = np.empty((len(xy), 2, 2))
    jac[:, 0, 0] = radial + 2.0 * g * x * x + 2.0 * t[0] * y + 6.0 * t[1] * x
    jac[:, 0, 1] = cross
    jac[:, 1, 0] = cross
    jac[:, 1, 1] = radial + 2.0 * g * y * y + 6.0 * t[0] * y + 2.0 * t[1] * x
    return jac


def invert_brown(target: np.ndarray, k: np.ndarray, t: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Solve ``apply_brown(xy) == target`` for ``xy`` by Newton's method, (N, 2) -> (N, 2).

    Converges to machine precision within a few steps for any distortion a real lens has inside its
    frame; points where the polynomial folds over (far outside the frame) are left where Newton ends.
    """
    xy = np.array(target, dtype=np.float64, copy=True)
    if not np.any(k) and not np.any(t):
        return xy
    for _ in range(iterations):
        f = apply_brown(xy, k, t) - target
        jac = brown_jacobian(xy, k, t)
        det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step_x = (jac[:, 1, 1] * f[:, 0] - jac[:, 0, 1] * f[:, 1]) / det
        step_y = (jac[:, 0, 0] * f[:, 1] - jac[:, 1, 0] * f[:, 0]) / det
        xy[:, 0] -= step_x
        xy[:, 1] -= step_y
        if float(np.max(np.abs(f), initial=0.0)) < 1e-15:
            break
    return xy


def _brown_design(xy: np.ndarray) -> np.ndarray:
    """(2N, 5) matrix A with ``(apply_brown(xy) - xy).ravel() == A @ [k1, k2, k3, t1, t2]``."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    a = np.zeros((len(xy), 2, 5))
    a[:, 0, :3] = np.stack([x * r2, x * r2**2, x * r2**3], axis=1)
    a[:, 1, :3] = np.stack([y * r2, y * r2**2, y * r2**3], axis=1)
    a[:, 0, 3], a[:, 0, 4] = 2.0 * x * y, r2 + 2.0 * x * x
    a[:, 1, 3], a[:, 1, 4] = r2 + 2.0 * y * y, 2.0 * x * y
    return a.reshape(-1, 5)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with Brown distortion; pixel coordinates have (0, 0) at the first pixel's centre."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    t1: float = 0.0
    t2: float = 0.0
    convention: Convention = "distort_ideal"

    @property
    def k(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.k3])

    @property
    def t(self) -> np.ndarray:
        return np.array([self.t1, self.t2])

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def opencv_distortion(self) -> np.ndarray:
        """OpenCV's ``(k1, k2, p1, p2, k3)``; only a ``distort_ideal`` camera has one."""
        if self.convention != "distort_ideal":
            raise ValueError(
                "only a distort_ideal camera has OpenCV distortion coefficients; "
                "convert it with with_convention('distort_ideal') first"
            )
        return np.array([self.k1, self.k2, self.t1, self.t2, self.k3])

    @classmethod
    def from_opencv(cls, K: np.ndarray, dist: np.ndarray, width: int, height: int) -> Camera:
        """From OpenCV's camera matrix and ``(k1, k2, p1, p2[, k3])`` coefficients."""
        d = np.zeros(5)
        flat = np.asarray(dist, dtype=np.float64).ravel()
        if len(flat) not in (4, 5):
            raise ValueError(f"expected 4 or 5 OpenCV distortion coefficients, got {len(flat)}")
        d[: len(flat)] = flat
        return cls(
            width=int(width),
            height=int(height),
            fx=float(K[0, 0]),
            fy=float(K[1, 1]),
            cx=float(K[0, 2]),
            cy=float(K[1, 2]),
            k1=d[0],
            k2=d[1],
            t1=d[2],
            t2=d[3],
            k3=d[4],
        )

    def replace(self, **changes: Any) -> Camera:
        return dataclasses.replace(self, **changes)

    # -- mappings ---------------------------------------------------------------------------------
    def normalised_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Ideal normalised ``(N, 2)`` -> observed pixel ``(N, 2)`` (x, y)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.convention == "distort_ideal":
            observed = apply_brown(xy, self.k, self.t)
        else:
            observed = invert_brown(xy, self.k, self.t)
        return observed * [self.fx, self.fy] + [self.cx, self.cy]

    def pixel_to_normalised(self, uv: np.ndarray) -> np.ndarray:
        """Observed pixel ``(N, 2)`` (x, y) -> ideal normalised ``(N, 2)``."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        observed = (uv - [self.cx, self.cy]) / [self.fx, self.fy]
        if self.convention == "distort_ideal":
            return invert_brown(observed, self.k, self.t)
        return apply_brown(observed, self.k, self.t)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Points ``(N, 3)`` in the camera frame (z forward) -> pixels ``(N, 2)``."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        return self.normalised_to_pixel(p[:, :2] / p[:, 2:3])

    def in_frame(self, uv: np.ndarray) -> np.ndarray:
        """``(..., 2)`` pixels (x, y) -> ``(...)`` bool: on the photo (centres 0 .. width - 1, 0 .. height - 1)."""
        uv = np.asarray(uv)
        return np.asarray(
            (uv[..., 0] >= 0) & (uv[..., 0] <= self.width - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= self.height - 1)
        )

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` -> unit rays ``(N, 3)`` in the camera frame."""
        xy = self.pixel_to_normalised(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def project_jacobian(self, points_cam: np.ndarray) -> np.ndarray:
        """``d pixel / d point`` (N, 2, 3), analytic; for ``restore_ideal`` by the implicit function theorem."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        xy = p[:, :2] / z[:, None]
        d_xy = np.zeros((len(p), 2, 3))
        d_xy[:, 0, 0] = d_xy[:, 1, 1] = 1.0 / z
        d_xy[:, :, 2] = -xy / z[:, None]
        if self.convention == "distort_ideal":
            d_obs = brown_jacobian(xy, self.k, self.t)
        else:  # ideal = brown(observed): d observed / d ideal = inverse of brown's Jacobian at observed
            d_obs = np.linalg.inv(brown_jacobian(invert_brown(xy, self.k, self.t), self.k, self.t))
        return np.array([self.fx, self.fy])[None, :, None] * (d_obs @ d_xy)

    def undistort_maps(self, new: Camera | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps (H', W') float32 that render this camera's image as the distortion-free ``new``.

        ``new`` defaults to this camera without distortion (same size and matrix).
        """
        target = new or self.replace(k1=0.0, k2=0.0, k3=0.0, t1=0.0, t2=0.0)
        u, v = np.meshgrid(np.arange(target.width, dtype=np.float64), np.arange(target.height, dtype=np.float64))
        ideal = np.stack([(u.ravel() - target.cx) / target.fx, (v.ravel() - target.cy) / target.fy], axis=1)
        source = self.normalised_to_pixel(ideal).astype(np.float32)
        shape = (target.height, target.width)
        return source[:, 0].reshape(shape), source[:, 1].reshape(shape)

    def with_convention(self, convention: Convention, grid: int = 41) -> Camera:
        """The same pixel <-> ray mapping in the other convention, refitting the five coefficients.

        Samples a ``grid x grid`` lattice over the frame and solves the (linear) least-squares problem
        of the target polynomial; the inverse of a Brown polynomial is not exactly one, so the result
        agrees to a small fraction of a pixel for real lenses, not exactly.
        """
        if convention not in CONVENTIONS:
            raise ValueError(f"unknown convention {convention!r}; known: {CONVENTIONS}")
        if convention == self.convention:
            return self
        u, v = np.meshgrid(np.linspace(0, self.width - 1, grid), np.linspace(0, self.height - 1, grid))
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        ideal = self.pixel_to_normalised(uv)
        observed = (uv - [self.cx, self.cy]) / [self.fx, self.fy]
        # distort_ideal: observed = brown(ideal); restore_ideal: ideal = brown(observed)
        source, target = (ideal, observed) if convention == "distort_ideal" else (observed, ideal)
        coeffs, *_ = np.linalg.lstsq(_brown_design(source), (target - source).ravel(), rcond=None)
        return self.replace(convention=convention, **dict(zip(DISTORTION_TERMS, map(float, coeffs), strict=True)))

    # -- serialisation ----------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {"model": "pinhole_brown", **dataclasses.asdict(self)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Camera:
        """A camera from ``to_json`` output; ``ValueError`` naming the first bad field."""
        if not isinstance(data, dict):
            raise ValueError("a camera must be a JSON object")
        if data.get("model", "pinhole_brown") != "pinhole_brown":
            raise ValueError(f"unknown camera model {data.get('model')!r}; expected 'pinhole_brown'")
        convention = data.get("convention", "distort_ideal")
        if convention not in CONVENTIONS:
            raise ValueError(f"camera.convention must be one of {CONVENTIONS}, not {convention!r}")
        values: dict[str, Any] = {"convention": convention}
        for name in ("width", "height"):
            values[name] = _positive_int(data, name)
        for name in ("fx", "fy", "cx", "cy", *DISTORTION_TERMS):
            values[name] = _finite(data, name, required=name in ("fx", "fy", "cx", "cy"))
        if values["fx"] <= 0 or values["fy"] <= 0:
            raise ValueError("camera.fx and camera.fy must be positive (pixels)")
        return cls(**values)


def _positive_int(data: dict[str, Any], name: str) -> int:
    value = data.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"camera.{name} must be a positive integer (pixels)")
    return value


def _finite(data: dict[str, Any], name: str, required: bool) -> float:
    value = data.get(name, None if required else 0.0)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"camera.{name} must be a finite number")
    return float(value)
