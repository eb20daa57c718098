"""Camera and stereo-rig calibration from a planar target, and distortion from straight lines.

* ``calibrate_camera``: Zhang (2000) initialisation (``cv2.initCameraMatrix2D`` + ``cv2.solvePnP`` per
  view), then Levenberg-Marquardt on the reprojection error over the intrinsics, the free distortion
  terms and every view's pose, as ``cv2.calibrateCamera`` does, in either convention of ``camera.py``.
* ``stereo_calibrate``: the relative pose of two calibrated cameras with their intrinsics held fixed,
  like ``cv2.stereoCalibrate(..., flags=cv2.CALIB_FIX_INTRINSIC)``.
* ``plumb_line``: distortion alone from images of straight lines (Brown 1971, "Close-range camera
  calibration"), independent of any target geometry.

All solves are MINPACK's LM (``scipy.optimize.least_squares(method="lm")``) with a central-difference
Jacobian that perturbs one pose parameter of every view at once (views do not share residuals), so a
Jacobian costs ``2 * (globals + 6)`` residual evaluations whatever the number of views. Parameter
covariances are ``sigma^2 (J^T J)^-1`` with ``sigma^2`` the residual variance per image coordinate.

Pixel convention: OpenCV's (integer coordinates at pixel centres). Poses: ``X_cam = R @ (X - C)``.
RMS errors follow ``cv2.calibrateCamera``: ``sqrt(mean over points of |projected - observed|^2)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from workers.algorithms.camera import (
    CONVENTIONS,
    DISTORTION_TERMS,
    Camera,
    Convention,
    rotation_from_vector,
    vector_from_rotation,
)
from workers.algorithms.stereo import StereoRig

View = tuple[np.ndarray, np.ndarray]  # object points (N, 3), image points (N, 2)
StereoView = tuple[np.ndarray, np.ndarray, np.ndarray]  # object (N, 3), left (N, 2), right (N, 2)
INTRINSICS = ("fx", "fy", "cx", "cy")
MIN_VIEWS = 3
MIN_POINTS = 6  # per view: a pose has 6 unknowns
POSE = 6  # rvec, tvec


# -- chessboards -------------------------------------------------------------------------------------
def board_points(pattern: tuple[int, int], square: float) -> np.ndarray:
    """Inner corners of a chessboard in its own frame, in OpenCV's corner order.

    Parameters
    ----------
    pattern : (columns, rows) of inner corners, as given to ``cv2.findChessboardCorners``.
    square : side of one square, in the unit wanted for poses and baselines (e.g. mm).

    Returns
    -------
    (columns * rows, 3) float64: ``(i * square, j * square, 0)``, row by row (i fastest).
    """
    cols, rows = _pattern(pattern)
    if not np.isfinite(square) or square <= 0:
        raise ValueError(f"square must be a positive length, got {square}")
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel() * square, j.ravel() * square, np.zeros(cols * rows)], axis=1).astype(np.float64)


def _pattern(pattern: tuple[int, int]) -> tuple[int, int]:
    if len(pattern) != 2 or min(pattern) < 2:
        raise ValueError(f"pattern must be (columns, rows) of inner corners, each >= 2, got {pattern}")
    return int(pattern[0]), int(pattern[1])


def find_chessboard(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Inner chessboard corners to sub-pixel accuracy, or None if the whole board is not found.

    ``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix`` (window half-size 40 % of the
    smallest corner spacing, at most 11 px, so a window never reaches the next corner); where that
    fails, ``cv2.findChessboardCornersSB`` (already sub-pixel). The order is OpenCV's, matching
    ``board_points``; a board symmetric under a half turn may come back in reverse order.

    Parameters
    ----------
    gray : (H, W) uint8 image.
    pattern : (columns, rows) of inner corners.

    Returns
    -------
    (columns * rows, 2) float64 pixel (x, y), or None.
    """
    cols, rows = _pattern(pattern)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"find_chessboard needs a (H, W) uint8 grey image, got {gray.shape} {gray.dtype}")
    # FAST_CHECK answers "no board" in ~0.05 s instead of ~0.5 s on a 1 MP photo; SB below catches its misses
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
    if found:
        grid = corners.reshape(rows, cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
        half = int(np.clip(0.4 * spacing, 2, 11))
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), criteria)
        return corners.reshape(-1, 2).astype(np.float64)
    found, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_EXHAUSTIVE)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


# -- shared solver machinery ---------------------------------------------------------------------------
def _block_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, n_global: int,
                    row_block: np.ndarray) -> np.ndarray:
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


def _solve(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, n_global: int,
           row_block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt (MINPACK) from ``x0``; returns (x, residuals, Jacobian at x)."""
    def jac(x: np.ndarray) -> np.ndarray:
        return _block_jacobian(fun, x, n_global, row_block)

    result = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12)
    return result.x, result.fun, result.jac  # scipy evaluates ``jac`` at the solution for method="lm"


def _covariance(jac: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """``sigma^2 (J^T J)^-1``; the normal matrix is column-equilibrated first (fx ~ 1e3 px next to k3 ~ 1e-2
    would otherwise cost precision), and pseudo-inverted where a direction is not observable."""
    dof = max(len(residuals) - jac.shape[1], 1)
    sigma2 = float(residuals @ residuals) / dof
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    normal = (jac / scale).T @ (jac / scale)
    return np.linalg.pinv(normal, rcond=1e-12, hermitian=True) / np.outer(scale, scale) * sigma2


def _check_points(obj: np.ndarray, pts: list[np.ndarray], index: int) -> None:
    if obj.ndim != 2 or obj.shape[1] != 3:
        raise ValueError(f"view {index}: object points must be (N, 3), got {obj.shape}")
    for p in pts:
        if p.shape != (len(obj), 2):
            raise ValueError(f"view {index}: image points must be (N, 2) with N = {len(obj)} object points, "
                             f"got {p.shape}")
    if not all(np.all(np.isfinite(a)) for a in (obj, *pts)):
        raise ValueError(f"view {index}: points must be finite numbers")
    if len(obj) < MIN_POINTS:
        raise ValueError(f"view {index} has {len(obj)} points; each view needs at least {MIN_POINTS}")


def _as_views(views: Sequence[Sequence[np.ndarray]], arity: int) -> list[list[np.ndarray]]:
    """Views as float64 arrays, validated; ``ValueError`` naming the first bad view."""
    if len(views) < MIN_VIEWS:
        raise ValueError(f"calibration needs at least {MIN_VIEWS} views of the target, got {len(views)}")
    out = []
    for index, view in enumerate(views):
        if len(view) != arity:
            raise ValueError(f"view {index}: expected {arity} arrays (object points and image points), "
                             f"got {len(view)}")
        arrays = [np.asarray(a, dtype=np.float64) for a in view]
        _check_points(arrays[0], arrays[1:], index)
        out.append(arrays)
    return out


def _split(values: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    return np.split(values, np.cumsum(counts)[:-1])


def _poses_from_params(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V * 6,) rvec/tvec pairs -> rotations (V, 3, 3) and translations (V, 3) (``X_cam = R X + t``)."""
    p = params.reshape(-1, POSE)
    return np.stack([rotation_from_vector(r) for r in p[:, :3]]), p[:, 3:]


def _transform(rotations: np.ndarray, translations: np.ndarray, obj: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Every point through its own view's pose, (N, 3) -> (N, 3)."""
    return np.einsum("nij,nj->ni", rotations[view], obj) + translations[view]


def _centres(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Camera centres ``C = -R^T t`` of the project's pose convention, (V, 3)."""
    return -np.einsum("vji,vj->vi", rotations, translations)


def _pnp(camera: Camera, obj: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Pose (rvec, tvec) of a target seen by a calibrated camera (distortion removed first)."""
    ideal = camera.pixel_to_normalised(px) * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    ok, rvec, tvec = cv2.solvePnP(obj, ideal, camera.matrix(), None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("could not estimate the pose of a view; check its point correspondences")
    return np.concatenate([rvec.ravel(), tvec.ravel()])


# -- single camera ----------------------------------------------------------------------------------
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


def calibrate_camera(views: Sequence[View], width: int, height: int, convention: Convention = "distort_ideal",
                     terms: Sequence[str] = ("k1", "k2", "t1", "t2", "k3"),
                     initial: Camera | None = None) -> CalibrationResult:
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
    data = _as_views(views, 2)
    free = _free_terms(terms, convention)
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
        rotations, translations = _poses_from_params(x[len(names):])
        return (camera.project(_transform(rotations, translations, obj, view)) - img).ravel()

    x0 = np.concatenate([[getattr(start, n) for n in names], *[_pnp(start, v[0], v[1]) for v in data]])
    x, res, jac = _solve(residuals, x0, len(names), np.repeat(view, 2))
    return _calibration_result(start, names, x, res, jac, counts)


def _free_terms(terms: Sequence[str], convention: str) -> tuple[str, ...]:
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; known: {CONVENTIONS}")
    unknown = [t for t in terms if t not in DISTORTION_TERMS]
    if unknown or len(set(terms)) != len(terms):
        raise ValueError(f"terms must be distinct names from {DISTORTION_TERMS}, got {tuple(terms)}")
    return tuple(t for t in DISTORTION_TERMS if t in terms)


def _initial_camera(data: list[list[np.ndarray]], width: int, height: int, convention: Convention,
                    initial: Camera | None) -> Camera:
    """``initial`` in ``convention``, or Zhang's closed-form camera matrix without distortion.

    Zhang's start ignores distortion (f is 20-100 % off with 10-20 % barrel distortion at the frame
    corners), yet LM recovers from it on every synthetic lens tried (k1 down to -0.42 at f = 1000 px,
    3 to 15 views), as in OpenCV, so no distortion-aware start is added.
    """
    if initial is not None:
        return initial.with_convention(convention).replace(width=int(width), height=int(height))
    if any(np.abs(v[0][:, 2]).max() > 1e-9 * max(np.abs(v[0]).max(), 1.0) for v in data):
        raise ValueError("a non-planar target (Z != 0) needs an initial camera")
    K = cv2.initCameraMatrix2D([v[0].astype(np.float32) for v in data], [v[1].astype(np.float32) for v in data],
                               (int(width), int(height)))
    return Camera(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  convention=convention)


def _calibration_result(start: Camera, names: tuple[str, ...], x: np.ndarray, res: np.ndarray, jac: np.ndarray,
                        counts: np.ndarray) -> CalibrationResult:
    m = len(names)
    camera = start.replace(**dict(zip(names, map(float, x[:m]), strict=True)))
    rotations, translations = _poses_from_params(x[m:])
    residual = res.reshape(-1, 2)
    errors = np.linalg.norm(residual, axis=1)
    cov = _covariance(jac, res)
    std = np.sqrt(np.diag(cov))
    return CalibrationResult(camera=camera, rotations=rotations, centres=_centres(rotations, translations),
                             rms_px=float(np.sqrt(np.mean(errors**2))), residuals=_split(residual, counts),
                             errors=_split(errors, counts), parameter_names=names,
                             std=dict(zip(names, map(float, std[:m]), strict=True)), covariance=cov[:m, :m],
                             pose_std=std[m:].reshape(-1, POSE))


# -- plumb line ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PlumbLineResult:
    """Distortion fitted to straight lines.

    Attributes
    ----------
    camera : the input camera with the fitted terms (same convention and intrinsics).
    line_rms_px : (L,) float64 RMS distance of each line's corrected points to its fitted line.
    rms_px : overall RMS over all points.
    residuals : per line, (N_l,) float64 signed distances, px.
    std : term -> standard deviation.
    """

    camera: Camera
    line_rms_px: np.ndarray
    rms_px: float
    residuals: list[np.ndarray]
    std: dict[str, float]


def plumb_line(lines: Sequence[np.ndarray], camera: Camera,
               terms: Sequence[str] = ("k1", "k2", "t1", "t2")) -> PlumbLineResult:
    """Distortion terms that make images of straight lines straight (Brown 1971's plumb-line method).

    Each point is corrected to ideal coordinates with the trial terms (``Camera.pixel_to_normalised``,
    scaled back to pixels by fx, fy), every line gets its total-least-squares straight line, and LM
    minimises the perpendicular distances. The intrinsics of ``camera`` only normalise and are not
    estimated: the distortion centre is the principal point. Distances are in ideal (corrected) pixels.

    Parameters
    ----------
    lines : sequence of (N_l, 2) float64 pixel (x, y) points along one straight line each; at least 3
        points per line and 2 lines, spread over the frame to constrain the outer field.
    camera : starting camera; its fixed terms keep their values.
    terms : the distortion terms to estimate, from k1, k2, k3, t1, t2.

    Returns
    -------
    PlumbLineResult
    """
    free = _free_terms(terms, camera.convention)
    pts, line_id, counts = _as_lines(lines)
    if not free or len(pts) - 2 * len(counts) < len(free):
        raise ValueError("plumb_line needs at least one term and more points beyond 2 per line than terms")

    def residuals(x: np.ndarray) -> np.ndarray:
        trial = camera.replace(**dict(zip(free, map(float, x), strict=True)))
        ideal = trial.pixel_to_normalised(pts) * [camera.fx, camera.fy]
        return _line_distances(ideal, line_id, len(counts))

    x0 = np.array([getattr(camera, t) for t in free])
    x, res, jac = _solve(residuals, x0, len(free), np.zeros(len(pts), dtype=int))
    std = np.sqrt(np.diag(_covariance(jac, res)))
    per_line = _split(res, counts)
    return PlumbLineResult(camera=camera.replace(**dict(zip(free, map(float, x), strict=True))),
                           line_rms_px=np.array([np.sqrt(np.mean(r**2)) for r in per_line]),
                           rms_px=float(np.sqrt(np.mean(res**2))), residuals=per_line,
                           std=dict(zip(free, map(float, std), strict=True)))


def _as_lines(lines: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stacked points (N, 2), their line index (N,) and points per line (L,)."""
    if len(lines) < 2:
        raise ValueError(f"plumb_line needs at least 2 lines, got {len(lines)}")
    arrays = [np.asarray(line, dtype=np.float64) for line in lines]
    for index, a in enumerate(arrays):
        if a.ndim != 2 or a.shape[1] != 2 or len(a) < 3 or not np.all(np.isfinite(a)):
            raise ValueError(f"line {index} must be finite (N, 2) pixel points with N >= 3, got {a.shape}")
    counts = np.array([len(a) for a in arrays])
    return np.concatenate(arrays), np.repeat(np.arange(len(arrays)), counts), counts


def _line_distances(pts: np.ndarray, line_id: np.ndarray, n_lines: int) -> np.ndarray:
    """Signed distance of every point to its line's total-least-squares line, (N, 2) -> (N,)."""
    count = np.bincount(line_id, minlength=n_lines)
    mean = np.stack([np.bincount(line_id, pts[:, k], n_lines) / count for k in (0, 1)], axis=1)
    d = pts - mean[line_id]
    sxx, syy, sxy = (np.bincount(line_id, w, n_lines) for w in (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]))
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of largest spread (the line)
    normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    # theta wraps at +-90 degrees (a vertical line), which would flip the sign of a whole line's
    # distances between two evaluations: orient each normal by its line's first-to-last direction.
    ends = np.cumsum(count) - 1  # lines are contiguous runs of points (``_as_lines``)
    chord = pts[ends] - pts[ends - count + 1]
    side = np.sign(normal[:, 0] * -chord[:, 1] + normal[:, 1] * chord[:, 0])
    normal *= np.where(side == 0, 1.0, side)[:, None]
    return np.sum(d * normal[line_id], axis=1)


# -- stereo rig -----------------------------------------------------------------------------------------
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
    data = _as_views(views, 3)
    rig0, flipped = _initial_rig(left, right, data)
    for v in flipped:
        data[v][2] = data[v][2][::-1]
    obj = np.concatenate([v[0] for v in data])
    lpx, rpx = (np.concatenate([v[k] for v in data]) for k in (1, 2))
    counts = np.array([len(v[0]) for v in data])
    view = np.repeat(np.arange(len(data)), counts)

    def residuals(x: np.ndarray) -> np.ndarray:
        rotations, translations = _poses_from_params(x[POSE:])
        in_left = _transform(rotations, translations, obj, view)
        in_right = in_left @ rotation_from_vector(x[:3]).T + x[3:POSE]
        return np.concatenate([(left.project(in_left) - lpx).ravel(), (right.project(in_right) - rpx).ravel()])

    x0 = np.concatenate([rig0, *[_pnp(left, v[0], v[1]) for v in data]])
    x, res, jac = _solve(residuals, x0, POSE, np.tile(np.repeat(view, 2), 2))
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
    pl, pr = _pnp(left, obj, lpx), _pnp(right, obj, rpx)
    Rl, Rr = rotation_from_vector(pl[:3]), rotation_from_vector(pr[:3])
    R = Rr @ Rl.T
    return np.concatenate([vector_from_rotation(R), pr[3:] - R @ pl[3:]])


def _agree(a: np.ndarray, b: np.ndarray, degrees: float = 5.0, fraction: float = 0.2) -> bool:
    """Whether two rig poses (rvec, T) are within ``degrees`` and ``fraction`` of the baseline."""
    rel = rotation_from_vector(a[:3]) @ rotation_from_vector(b[:3]).T
    angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(angle < degrees and np.linalg.norm(a[3:] - b[3:]) < fraction * np.linalg.norm(b[3:]))


def _stereo_result(left: Camera, right: Camera, x: np.ndarray, res: np.ndarray, jac: np.ndarray,
                   counts: np.ndarray, flipped: list[int]) -> StereoCalibrationResult:
    cov = _covariance(jac, res)[:POSE, :POSE]
    rig = StereoRig(left, right, rotation_from_vector(x[:3]), x[3:POSE], 0.5 * (cov + cov.T))
    rotations, translations = _poses_from_params(x[POSE:])
    both = res.reshape(2, -1, 2)
    res_left, res_right = _split(both[0], counts), _split(both[1], counts)
    for v in flipped:  # report in the order the caller gave the points
        res_right[v] = res_right[v][::-1]
    errors = np.linalg.norm(both, axis=2)
    return StereoCalibrationResult(rig=rig, rms_px=float(np.sqrt(np.mean(errors**2))), residuals_left=res_left,
                                   residuals_right=res_right,
                                   errors_left=[np.linalg.norm(r, axis=1) for r in res_left],
                                   errors_right=[np.linalg.norm(r, axis=1) for r in res_right],
                                   rotations=rotations, centres=_centres(rotations, translations),
                                   covariance=rig.covariance if rig.covariance is not None else cov,
                                   reversed_views=tuple(flipped))
